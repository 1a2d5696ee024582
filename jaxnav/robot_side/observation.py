"""On the robot: depth image or laser scan -> the policy's sector minima -> velocity command.

numpy only (no jax). The sensor's settings and the action table are the ones the policy was trained
with; they come from the exported .npz (`NumpyPolicy.sensor`, `NumpyPolicy.commands`), never from
constants here. The conversions reproduce `jaxnav.core.sensors` exactly:

- The simulator casts a horizontal fan of rays, turns each hit distance into camera depth (distance along
  the optical axis: range * cos(angle), what a depth image holds), clips it to [range_min, range_max]
  and takes the minimum per sector. Sectors are ordered right to left: obs[0] is the rightmost slice.
- A ray with no return reads range_max. Here, invalid readings as the Orbbec Astra and ROS drivers
  report them (0, NaN, +-inf, negative) are ignored; a sector with no valid reading reads range_max,
  and valid readings below range_min read range_min.

Caveat: the Astra cannot see closer than ~0.6 m and reports 0 there, which reads as "nothing" here,
whereas the simulator reports range_min for such close surfaces.
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
    """m; valid readings nearer than this read range_min."""
    range_max: float
    """m; farther readings, and sectors without a valid reading, read range_max."""

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


def _valid(x: np.ndarray) -> np.ndarray:
    """Readings that are real distances: finite and positive (0 is the Astra's "no data")."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(x) & (x > 0)


def _finish(minima: np.ndarray, sensor: Sensor) -> np.ndarray:
    """Sector minima [n] (inf = no valid reading) -> float32 observation clipped to the range."""
    full = np.where(np.isinf(minima), sensor.range_max, minima)
    return np.clip(full, sensor.range_min, sensor.range_max).astype(np.float32)


def _bin_by_angle(depth, angles, sensor: Sensor) -> np.ndarray:
    """[num_sectors] minimum depth per angle bin of width fov/num_sectors from -fov/2 (inf if none)."""
    half, n = 0.5 * sensor.fov, sensor.num_sectors
    keep = np.abs(angles) <= half
    # The simulator's bins: ray i of R lies at (i + 0.5) / R * fov - fov/2, sector i // (R / n).
    idx = np.floor((angles[keep] + half) / (sensor.fov / n)).astype(np.int64)
    idx = np.clip(idx, 0, n - 1)  # a beam exactly at +fov/2 belongs to the last sector
    out = np.full(n, np.inf)
    np.minimum.at(out, idx, depth[keep])
    return out


def scan_to_sectors(ranges, angles, sensor: Sensor) -> np.ndarray:
    """[num_sectors] float32 observation from a laser scan, as the simulator computes it.

    ranges [N] m and angles [N] rad as in a ROS LaserScan (0 ahead, positive to the left). Beams
    within +-fov/2 are kept, turned into camera depth (range * cos(angle)) and binned by angle into
    sectors of width fov/num_sectors from -fov/2 (right to left); invalid ranges are ignored.
    """
    ranges = np.asarray(ranges, np.float64).ravel()
    angles = np.asarray(angles, np.float64).ravel()
    if ranges.shape != angles.shape:
        raise ValueError(f"ranges {ranges.shape} and angles {angles.shape} differ in length")
    ok = _valid(ranges)
    depth = ranges[ok] * np.cos(angles[ok])
    return _finish(_bin_by_angle(depth, angles[ok], sensor), sensor)


def depth_image_to_sectors(depth, sensor: Sensor, rows=None, column_angles=None) -> np.ndarray:
    """[num_sectors] float32 observation from a depth image [H, W] in metres (camera depth, z).

    Column 0 is the LEFT of the image of a forward-looking camera, so sector 0 holds the rightmost
    columns: the columns are split into num_sectors equal slices right to left (the image is taken
    to span exactly `sensor.fov`), and each sector reads its minimum valid depth over `rows`.

    rows: row indices or a slice; None = all rows. On the robot pass the rows around the horizon
        (`horizon_rows`): the simulator sees a horizontal fan only, and lower rows see the floor,
        which would read as an obstacle ~0.65 m ahead.
    column_angles: [W] angle of each column (rad, positive = left, e.g. `pinhole_column_angles`);
        when given, columns are binned by angle like `scan_to_sectors` instead of equal slices.
        Equal slices of a pinhole image are up to ~1.5 deg off the simulator's equal-angle bins.
    """
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth image must be [H, W], got shape {depth.shape}")
    band = depth if rows is None else depth[rows]
    if band.ndim != 2 or band.shape[0] == 0:
        raise ValueError(f"rows {rows!r} select no image rows")
    column_min = np.where(_valid(band), band, np.inf).min(axis=0)  # [W], left to right
    if column_angles is not None:
        angles = np.asarray(column_angles, np.float64)
        return _finish(_bin_by_angle(column_min.astype(np.float64), angles, sensor), sensor)
    width, n = column_min.size, sensor.num_sectors
    if width < n:
        raise ValueError(f"depth image has {width} columns, fewer than {n} sectors")
    starts = np.arange(n) * width // n  # slices differ by at most one column
    return _finish(np.minimum.reduceat(column_min[::-1], starts), sensor)


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

    def __post_init__(self):
        if not self.speed_calibration > 0:
            raise ValueError(
                f"Controller.speed_calibration: must be > 0, got {self.speed_calibration}"
            )

    def act(self, obs) -> Twist:
        """The command for an observation [num_sectors] (metres, right to left)."""
        return action_to_twist(self.policy(obs), self.policy.commands, self.speed_calibration)

    def image_to_twist(self, depth, rows=None, column_angles=None) -> Twist:
        """The command for a depth image [H, W] in metres (see `depth_image_to_sectors`)."""
        return self.act(depth_image_to_sectors(depth, self.policy.sensor, rows, column_angles))

    def scan_to_twist(self, ranges, angles) -> Twist:
        """The command for a laser scan: ranges [N] m at angles [N] rad (0 ahead, positive left)."""
        return self.act(scan_to_sectors(ranges, angles, self.policy.sensor))
