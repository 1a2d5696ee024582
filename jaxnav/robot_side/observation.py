"""On the robot: depth image or laser scan -> the policy's sector minima -> velocity command.

numpy only (no jax), like `numpy_policy.py`: copy both files (and `ros_node.py` for ROS 2) with the
exported .npz onto the robot. The conversions reproduce `jaxnav.core.sensors` exactly:

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

import math
from typing import NamedTuple

import numpy as np

FOV = math.radians(60.0)  # rad; Astra horizontal field of view (jaxnav.core.robot.CAMERA_FOV)
NUM_SECTORS = 8
RANGE_MIN, RANGE_MAX = 0.6, 8.0  # m; Astra usable depth range (jaxnav.core.robot.CAMERA_RANGE)
ASTRA_VFOV = math.radians(49.5)  # rad; Astra vertical field of view
# (forward-speed fraction, yaw-rate fraction) per action: 0 forward, 1 left (+yaw), 2 right.
# A copy of jaxnav.core.robot.ACTIONS (importing jaxnav would import jax); the tests keep them equal.
ACTIONS = ((1.0, 0.0), (0.0, 1.0), (0.0, -1.0))


class Twist(NamedTuple):
    """A velocity command: forward speed (m/s) and yaw rate (rad/s, positive = left)."""

    linear: float
    angular: float


def _valid(x: np.ndarray) -> np.ndarray:
    """Readings that are real distances: finite and positive (0 is the Astra's "no data")."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(x) & (x > 0)


def _finish(minima: np.ndarray, range_min: float, range_max: float) -> np.ndarray:
    """Sector minima (inf = no valid reading) -> float32 observation clipped to the range."""
    return np.clip(np.where(np.isinf(minima), range_max, minima), range_min, range_max).astype(
        np.float32
    )


def _bin_by_angle(depth, angles, fov: float, num_sectors: int) -> np.ndarray:
    """[num_sectors] minimum depth per angle bin of width fov/num_sectors from -fov/2 (inf if none)."""
    half = 0.5 * fov
    keep = np.abs(angles) <= half
    # The simulator's bins: ray i of R lies at (i + 0.5) / R * fov - fov/2, sector i // (R / n).
    idx = np.floor((angles[keep] + half) / (fov / num_sectors)).astype(np.int64)
    idx = np.clip(idx, 0, num_sectors - 1)  # a beam exactly at +fov/2 belongs to the last sector
    out = np.full(num_sectors, np.inf)
    np.minimum.at(out, idx, depth[keep])
    return out


def scan_to_sectors(
    ranges,
    angles,
    fov: float = FOV,
    num_sectors: int = NUM_SECTORS,
    range_min: float = RANGE_MIN,
    range_max: float = RANGE_MAX,
) -> np.ndarray:
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
    return _finish(_bin_by_angle(depth, angles[ok], fov, num_sectors), range_min, range_max)


def depth_image_to_sectors(
    depth,
    fov: float = FOV,
    num_sectors: int = NUM_SECTORS,
    range_min: float = RANGE_MIN,
    range_max: float = RANGE_MAX,
    rows=None,
    column_angles=None,
) -> np.ndarray:
    """[num_sectors] float32 observation from a depth image [H, W] in metres (camera depth, z).

    Column 0 is the LEFT of the image of a forward-looking camera, so sector 0 holds the rightmost
    columns: the columns are split into num_sectors equal slices right to left (the image is taken
    to span exactly `fov`), and each sector reads its minimum valid depth over `rows`.

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
        minima = _bin_by_angle(column_min.astype(np.float64), angles, fov, num_sectors)
        return _finish(minima, range_min, range_max)
    width = column_min.size
    if width < num_sectors:
        raise ValueError(f"depth image has {width} columns, fewer than {num_sectors} sectors")
    starts = np.arange(num_sectors) * width // num_sectors  # slices differ by at most one column
    minima = np.minimum.reduceat(column_min[::-1], starts)
    return _finish(minima, range_min, range_max)


def pinhole_column_angles(width: int, hfov: float = FOV) -> np.ndarray:
    """[W] angle (rad, positive = left) of each pixel column's centre for a pinhole camera."""
    focal = 0.5 * width / math.tan(0.5 * hfov)
    return np.arctan((0.5 * (width - 1) - np.arange(width)) / focal)


def horizon_rows(
    height: int, vfov: float = ASTRA_VFOV, half_width_deg: float = 2.0, tilt: float = 0.0
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


def action_to_twist(
    action, forward_speed: float = 0.5, turn_rate: float = 1.5, speed_calibration: float = 1.0
) -> Twist:
    """The command of action 0 (forward), 1 (turn left in place) or 2 (right), as trained.

    speed_calibration multiplies both speeds: set it so that the real robot moves at the speeds the
    simulator assumed (the paper had to recalibrate its robot's speed commands).
    """
    a = int(action)
    if not 0 <= a < len(ACTIONS):
        raise ValueError(f"action must be 0, 1 or 2, got {action}")
    fwd, yaw = ACTIONS[a]
    return Twist(fwd * forward_speed * speed_calibration, yaw * turn_rate * speed_calibration)


class Controller:
    """Sensor reading -> observation -> policy -> Twist, in one call.

    policy: any callable obs [num_sectors] float32 -> action int (e.g. `NumpyPolicy`). Settings left
    None are taken from the policy when it carries them (a NumpyPolicy knows its training's speeds
    and sensor), else the module defaults. `rows` / `column_angles` go to `depth_image_to_sectors`.
    """

    def __init__(
        self,
        policy,
        *,
        fov=None,
        num_sectors=None,
        range_min=None,
        range_max=None,
        forward_speed=None,
        turn_rate=None,
        speed_calibration: float = 1.0,
        rows=None,
        column_angles=None,
    ):
        pick = lambda value, name, default: (  # noqa: E731
            value if value is not None else getattr(policy, name, default)
        )
        self.policy = policy
        self.sensor = dict(
            fov=pick(fov, "fov", FOV),
            num_sectors=pick(num_sectors, "num_sectors", NUM_SECTORS),
            range_min=pick(range_min, "range_min", RANGE_MIN),
            range_max=pick(range_max, "range_max", RANGE_MAX),
        )
        self.forward_speed = pick(forward_speed, "forward_speed", 0.5)
        self.turn_rate = pick(turn_rate, "turn_rate", 1.5)
        if not speed_calibration > 0:
            raise ValueError(f"speed_calibration must be > 0, got {speed_calibration}")
        self.speed_calibration = speed_calibration
        self.rows, self.column_angles = rows, column_angles
        self.last_obs, self.last_action = None, None  # for logging

    @classmethod
    def from_npz(cls, path, **kwargs) -> Controller:
        """A controller around the NumpyPolicy exported to `path`."""
        if __package__:
            from jaxnav.robot_side.policy import NumpyPolicy
        else:  # copied flat onto the robot, beside numpy_policy.py: no jaxnav (and no jax) needed
            from numpy_policy import NumpyPolicy
        return cls(NumpyPolicy.from_npz(path), **kwargs)

    def act(self, obs) -> Twist:
        """The command for an observation [num_sectors] (metres, right to left)."""
        self.last_obs = obs
        self.last_action = int(self.policy(obs))
        return action_to_twist(
            self.last_action, self.forward_speed, self.turn_rate, self.speed_calibration
        )

    def image_to_twist(self, depth) -> Twist:
        """The command for a depth image [H, W] in metres."""
        obs = depth_image_to_sectors(
            depth, rows=self.rows, column_angles=self.column_angles, **self.sensor
        )
        return self.act(obs)

    def scan_to_twist(self, ranges, angles) -> Twist:
        """The command for a laser scan: ranges [N] m at angles [N] rad (0 ahead, positive left)."""
        return self.act(scan_to_sectors(ranges, angles, **self.sensor))
