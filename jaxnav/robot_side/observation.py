"""On the robot: depth image or laser scan -> the policy's sector minima -> velocity command.

numpy only (no jax). The sensor's settings and the action table are the ones the policy was trained
with; they come from the exported .npz (`NumpyPolicy.sensor`, `NumpyPolicy.commands`), never from
constants here. Sectors are ordered right to left (obs[0] is the rightmost slice), and every reading
is camera depth (distance along the optical axis: range * cos(angle), what a depth image holds).

Both paths end in `reduce_sectors`, the one sector reduction, whose docstring states the rule the
simulator mirrors. Its point is the Orbbec Astra's blind zone: the camera reports 0 both for
surfaces nearer than its ~0.6 m minimum and for no return, so a sector the camera cannot read is
taken as near (range_min, the reading that makes the policy turn), never as far (range_max, the
reading the reward pays most for driving into).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np


@dataclasses.dataclass(frozen=True)
class Sensor:
    """The simulated depth sensor a policy was trained with (stored in the exported .npz)."""

    fov: float
    """Horizontal field of view, rad, split into `num_sectors` equal sectors, right to left."""
    num_sectors: int
    """Length of the observation: one minimum distance per sector."""
    range_min: float
    """m; nearer readings, and sectors the camera cannot read, read range_min (`reduce_sectors`)."""
    range_max: float
    """m; farther readings, and no return within range, read range_max."""

    def __post_init__(self):
        if not 0 < self.fov < 2 * math.pi:
            raise ValueError(f"Sensor.fov: must be in (0, 2 pi) rad, got {self.fov}")
        if self.num_sectors < 1:
            raise ValueError(f"Sensor.num_sectors: must be >= 1, got {self.num_sectors}")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError(
                f"Sensor.range_min/range_max: need 0 <= range_min < range_max, "
                f"got {self.range_min}, {self.range_max}"
            )


class Twist(NamedTuple):
    """A velocity command: forward speed (m/s) and yaw rate (rad/s, positive = left)."""

    linear: float
    angular: float


BLIND_FRACTION = 0.5
"""Default share of unknown readings from which a sector reads near (see `reduce_sectors`).

Why one half: a surface inside the blind zone (nearer than range_min = 0.6 m) spanning at least one
sector's angle (7.5 deg: 8 cm at 0.6 m, 4 cm at 0.3 m) covers at least half of some sector however
it is aligned, so that sector reads near. A lower share would also catch thinner close objects but
would turn a sector near whenever part of it looks at a black, shiny or sunlit surface that returns
nothing; a higher one would need a close object about two sectors wide before anything reads near.
"""


def reduce_sectors(depth, sector, sensor: Sensor, blind_fraction=BLIND_FRACTION) -> np.ndarray:
    """[num_sectors] float32 observation from readings depth [N] (m) lying in sectors sector [N].

    The one reduction from readings to the observation, for depth images and scans alike; the
    simulator applies the same rule to its rays. A reading is a camera depth in metres, or NaN for
    "unknown" (the camera returned nothing: too close or no return, it cannot tell which).
    For each sector s (0 = rightmost), with n(s) readings of which u(s) are unknown:

    1. Blind: if u(s) >= blind_fraction * n(s) (so also when n(s) = 0) it reads range_min (near).
    2. Otherwise it reads the minimum of its known readings clipped to [range_min, range_max]: a
       reading below range_min (0 and -inf included) reads range_min, one above range_max (+inf: no
       hit within range) reads range_max.

    The simulator (`jaxnav.core.sensors`) applies the same rule to its rays, with the camera's
    unknowns: rays nearer than range_min, rays at dark obstacles, dropped rays and (with
    `far_invalid`) rays beyond range_max; rays that meet the floor are left out on both sides
    (`tests/test_fidelity.py` checks the two agree). blind_fraction must be in (0, 1]; 1 means only
    a sector whose readings are all unknown reads near.
    """
    if not 0 < blind_fraction <= 1:
        raise ValueError(f"blind_fraction: must be in (0, 1], got {blind_fraction}")
    depth = np.asarray(depth, np.float64).ravel()
    sector = np.asarray(sector, np.int64).ravel()
    n = sensor.num_sectors
    unknown = np.isnan(depth)
    count = np.bincount(sector, minlength=n)
    blind = np.bincount(sector[unknown], minlength=n) >= blind_fraction * count
    minima = np.full(n, np.inf)
    np.minimum.at(minima, sector[~unknown], depth[~unknown])
    near = np.clip(minima, sensor.range_min, sensor.range_max)
    return np.where(blind, sensor.range_min, near).astype(np.float32)


def _angle_sectors(angles, sensor: Sensor) -> tuple[np.ndarray, np.ndarray]:
    """(keep [N] bool: within +-fov/2, sector [K] of each kept angle), bins of fov/num_sectors."""
    half, n = 0.5 * sensor.fov, sensor.num_sectors
    keep = np.abs(angles) <= half
    # The simulator's bins: ray i of R lies at (i + 0.5) / R * fov - fov/2, sector i // (R / n).
    idx = np.floor((angles[keep] + half) / (sensor.fov / n)).astype(np.int64)
    return keep, np.clip(idx, 0, n - 1)  # a beam exactly at +fov/2 belongs to the last sector


def scan_to_sectors(ranges, angles, sensor: Sensor) -> np.ndarray:
    """[num_sectors] float32 observation from a laser scan, as the simulator computes it.

    ranges [N] m and angles [N] rad as in a ROS LaserScan (0 ahead, positive to the left). Beams
    within +-fov/2 are kept and turned into camera depth (range * cos(angle)). A range of 0 or below
    (-inf included: nearer than the scanner measures) reads range_min; +inf and NaN (no return) read
    range_max. Then `reduce_sectors` (a scan has no unknown readings: its minimum, clipped).
    """
    ranges = np.asarray(ranges, np.float64).ravel()
    angles = np.asarray(angles, np.float64).ravel()
    if ranges.shape != angles.shape:
        raise ValueError(f"ranges {ranges.shape} and angles {angles.shape} differ in length")
    keep, sector = _angle_sectors(angles, sensor)
    r = ranges[keep]
    with np.errstate(invalid="ignore"):
        depth = np.where(r > 0, r * np.cos(angles[keep]), 0.0)  # 0: reads range_min
    depth[np.isnan(r) | np.isposinf(r)] = np.inf  # no return: reads range_max
    return reduce_sectors(depth, sector, sensor)


def depth_image_to_sectors(
    depth, sensor: Sensor, rows=None, column_angles=None, blind_fraction=BLIND_FRACTION
) -> np.ndarray:
    """[num_sectors] float32 observation from a depth image [H, W] in metres (camera depth, z).

    Column 0 is the LEFT of the image of a forward-looking camera, so sector 0 holds the rightmost
    columns: the columns are split into num_sectors equal slices right to left (the image is taken
    to span exactly `sensor.fov`). The pixels of a sector's columns in `rows` go to
    `reduce_sectors`: 0, NaN and negative pixels are unknown (the Astra's 0 means too close or no
    return), +inf reads range_max; so a sector at least `blind_fraction` unknown reads range_min.

    rows: row indices or a slice; None = all rows. On the robot pass the rows around the horizon
        (`horizon_rows`): the simulator sees a horizontal fan only, and lower rows see the floor,
        which is no obstacle but would read as one ~0.65 m ahead.
    column_angles: [W] angle of each column (rad, positive = left, e.g. `pinhole_column_angles`);
        when given, columns are binned by angle like `scan_to_sectors` instead of equal slices
        (columns beyond +-fov/2 are dropped). Equal slices of a pinhole image are up to ~1.5 deg
        off the simulator's equal-angle bins.
    """
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth image must be [H, W], got shape {depth.shape}")
    band = depth if rows is None else depth[rows]
    if band.ndim != 2 or band.shape[0] == 0:
        raise ValueError(f"rows {rows!r} select no image rows")
    width, n = band.shape[1], sensor.num_sectors
    if column_angles is not None:
        keep, sector = _angle_sectors(np.asarray(column_angles, np.float64), sensor)
        band = band[:, keep]
    elif width < n:
        raise ValueError(f"depth image has {width} columns, fewer than {n} sectors")
    else:  # equal slices, right to left, differing by at most one column
        starts = np.arange(n) * width // n
        sector = np.searchsorted(starts, np.arange(width)[::-1], side="right") - 1
    with np.errstate(invalid="ignore"):
        readings = np.where(band > 0, band, np.nan)  # 0, NaN, negative: unknown
    sector = np.broadcast_to(sector, readings.shape)
    return reduce_sectors(readings, sector, sensor, blind_fraction)


def pinhole_column_angles(width: int, hfov: float) -> np.ndarray:
    """[W] angle (rad, positive = left) of each pixel column's centre for a pinhole camera."""
    focal = 0.5 * width / math.tan(0.5 * hfov)
    return np.arctan((0.5 * (width - 1) - np.arange(width)) / focal)


def horizon_rows(
    height: int, vfov: float, half_width_deg: float = 2.0, tilt: float = 0.0
) -> np.ndarray:
    """Row indices within +-half_width_deg of the horizontal through the camera (pinhole model).

    vfov: vertical field of view, rad. tilt: camera pitch, rad, positive = looking down (the
    horizon then moves up the image). Always at least one row.
    """
    focal = 0.5 * height / math.tan(0.5 * vfov)
    centre = 0.5 * (height - 1) - focal * math.tan(tilt)
    half = focal * math.tan(math.radians(half_width_deg))
    lo = max(0, math.ceil(centre - half))
    hi = min(height - 1, math.floor(centre + half))
    if lo > hi:  # band thinner than a row: the row nearest the horizon
        lo = hi = min(height - 1, max(0, round(centre)))
    return np.arange(lo, hi + 1)


def action_to_twist(action, commands: np.ndarray, speed_calibration: float = 1.0) -> Twist:
    """The command of `action` from the trained table `commands` [A, 2] (forward m/s, yaw rad/s).

    speed_calibration multiplies both speeds: set it so that the real robot moves at the speeds the
    simulator assumed (the paper had to recalibrate its robot's speed commands).
    """
    a = int(action)
    if not 0 <= a < len(commands):
        raise ValueError(f"action must be in 0..{len(commands) - 1}, got {action}")
    forward, yaw = commands[a]
    return Twist(float(forward) * speed_calibration, float(yaw) * speed_calibration)


@dataclasses.dataclass(frozen=True)
class Controller:
    """Sensor reading -> observation -> policy -> Twist, in one call."""

    policy: object
    """A `NumpyPolicy`: callable obs [num_sectors] -> action int, with `.sensor` and `.commands`."""
    speed_calibration: float = 1.0
    """Multiplies both speeds of every command (see `action_to_twist`)."""
    blind_fraction: float = BLIND_FRACTION
    """A depth-image sector at least this share unknown (0/NaN) reads near (`reduce_sectors`)."""

    def __post_init__(self):
        if not self.speed_calibration > 0:
            raise ValueError(
                f"Controller.speed_calibration: must be > 0, got {self.speed_calibration}"
            )
        if not 0 < self.blind_fraction <= 1:
            raise ValueError(
                f"Controller.blind_fraction: must be in (0, 1], got {self.blind_fraction}"
            )

    def act(self, obs) -> Twist:
        """The command for an observation [D] (sectors in metres, right to left; the goal task's
        entries after them, see `policy.goal_observation`)."""
        if getattr(self.policy, "continuous", False):
            forward, yaw = self.policy(obs)
            return Twist(
                float(forward) * self.speed_calibration, float(yaw) * self.speed_calibration
            )
        return action_to_twist(self.policy(obs), self.policy.commands, self.speed_calibration)

    def image_obs(self, depth, rows=None, column_angles=None) -> np.ndarray:
        """The observation of a depth image [H, W] in metres (see `depth_image_to_sectors`)."""
        sensor = self.policy.sensor
        return depth_image_to_sectors(depth, sensor, rows, column_angles, self.blind_fraction)

    def scan_obs(self, ranges, angles) -> np.ndarray:
        """The observation of a laser scan: ranges [N] m at angles [N] rad (0 ahead, + left)."""
        return scan_to_sectors(ranges, angles, self.policy.sensor)

    def image_to_twist(self, depth, rows=None, column_angles=None) -> Twist:
        """The command for a depth image [H, W] in metres (see `depth_image_to_sectors`)."""
        return self.act(self.image_obs(depth, rows, column_angles))

    def scan_to_twist(self, ranges, angles) -> Twist:
        """The command for a laser scan: ranges [N] m at angles [N] rad (0 ahead, positive left)."""
        return self.act(self.scan_obs(ranges, angles))
