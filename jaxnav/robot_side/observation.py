"""On the robot: depth image or laser scan -> the policy's sector minima -> velocity command.

numpy only (no jax). The sensor's settings and the action table are the ones the policy was trained
with; they come from the exported .npz (`NumpyPolicy.sensor`, `NumpyPolicy.commands`), never from
constants here. Sectors are ordered right to left (obs[0] is the rightmost slice), and every reading
is camera depth (distance along the optical axis: range * cos(angle), what a depth image holds).

Both paths end in `reduce_sectors`, the one sector reduction, whose docstring states the rule the
simulator mirrors. Its point is the Orbbec Astra's blind zone: the camera reports 0 both for
surfaces nearer than its ~0.6 m minimum and for no return, so a sector the camera cannot read is
taken as near (range_min, the reading that makes the policy turn), never as far (range_max, the
reading the reward pays most for driving into). A sector reads its nearest reading that enough of
its readings confirm (`sector_nearest`), so a few stray pixels do not make a phantom obstacle. A
frame that is almost all unknown (a covered lens, sunlight) carries no observation at all: with
`max_unknown` set it is refused (`BlindFrame`) rather than read as "everything near".

A depth image is read where the simulator casts its rays (`ray_pixels`: for each image column, one
pixel per ray row of the sensor, at that row's elevation), and pixels that see the floor are left
out (`floor_mask`: the same function the simulator applies to its rays), so a policy trained with
rows below the horizon (`--sensor.rows 5`, which sees obstacles from 0.05 m tall) is deployed on the
pixels it was trained on: `depth_image_to_sectors(depth, sensor, vfov=...)`, or with the camera's
calibration (`Intrinsics`, a CameraInfo's K) `depth_image_to_sectors(depth, sensor, camera=...)`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

FLOOR_MARGIN = 0.02
"""m: a reading whose point lies this close to the floor plane (plus `FLOOR_MARGIN_SLOPE` per metre
of depth), or below it, is floor (`floor_mask`); the default of `Sensor` and `SensorConfig`.

Why these: the height of a floor point is known to about +-1 cm from the camera's mount, and depth
noise moves it by noise * camera_height / depth (the Astra's ~1 cm at 1 m: 3 mm), hence 2 cm at
the camera. Farther out a pitch error dominates: it moves a point by depth * error, and 0.01 m/m
is 0.57 deg of pitch calibration (structured-light noise, ~0.0016 depth^2, adds only
0.0016 * 0.295 * depth = 0.0005 m/m). What this costs: an obstacle is told from the floor where
it stands taller than the margin, 5 cm tall out to 3 m, 10 cm tall over the whole 8 m range.
"""
FLOOR_MARGIN_SLOPE = 0.01
"""m of floor margin per m of depth (see `FLOOR_MARGIN`)."""


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
    elevations: tuple[float, ...] = (0.0,)
    """Elevation of each ray row from the optical axis, rad, bottom to top (the simulator's
    `SensorConfig.elevations`; (0,): the horizontal fan, and policy files that do not say)."""
    camera_height: float | None = None
    """Height of the camera's optical centre above the floor, m (the mount the policy was trained
    with; set the robot's measured one). None: no pixel is taken for floor (`floor_mask`)."""
    camera_pitch: float = 0.0
    """Downward tilt of the optical axis, rad (positive = looking down)."""
    floor_margin: float = FLOOR_MARGIN
    """A pixel within floor_margin + floor_margin_slope * depth (m) of the floor plane, or below
    it, is floor (`floor_mask`)."""
    floor_margin_slope: float = FLOOR_MARGIN_SLOPE
    """Growth of the floor margin per metre of depth, m/m (see `floor_mask`)."""
    far_reads_max: bool = False
    """An unknown pixel at or above the horizon, in a column whose farthest-reaching floor pixel
    returned, is no return from beyond range and reads range_max (`far_mask`); False: unknown."""

    def __post_init__(self):
        if not 0 < self.fov < 2 * math.pi:
            raise ValueError(f"Sensor.fov: must be in (0, 2 pi) rad, got {self.fov}")
        if self.num_sectors < 1:
            raise ValueError(f"Sensor.num_sectors: must be >= 1, got {self.num_sectors}")
        if not 0 <= self.range_min < self.range_max < math.inf:
            raise ValueError(
                f"Sensor.range_min/range_max: need 0 <= range_min < range_max < inf, "
                f"got {self.range_min}, {self.range_max}"
            )
        object.__setattr__(self, "elevations", tuple(float(e) for e in self.elevations))
        if not self.elevations or not all(abs(e) < math.pi / 2 for e in self.elevations):
            raise ValueError(
                f"Sensor.elevations: need at least one, each in (-pi/2, pi/2), got {self.elevations}"
            )
        if self.camera_height is not None and not 0 < self.camera_height < math.inf:
            raise ValueError(
                f"Sensor.camera_height: must be finite and > 0 m, got {self.camera_height}"
            )
        if not abs(self.camera_pitch) < math.pi / 2:
            raise ValueError(
                f"Sensor.camera_pitch: must be in (-pi/2, pi/2), got {self.camera_pitch}"
            )
        for name in ("floor_margin", "floor_margin_slope"):
            if not 0 <= getattr(self, name) < math.inf:
                raise ValueError(
                    f"Sensor.{name}: must be finite and >= 0, got {getattr(self, name)}"
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


READINGS_PER_STRAY = 50
"""Default count of a sector's known readings per extra reading that must confirm what it reads
(`sector_nearest`: the k-th nearest, k = 1 + known // 50).

Why 50 (measured on 640x480 frames in `test_robot_side.py::test_stray_pixels_make_no_phantom`): a
5-row policy reads ~150 known pixels per sector (its lower rows see floor), a one-row policy's
+-2 deg band ~3000, so k is 4 and 61. Then 0.1 % stray pixels no longer make phantom obstacles
(the plain minimum put one into over half the frames), while a 2 cm table leg at 1 m (11 columns,
45 pixels of 5 rows) stays seen. 100 let 0.1 % strays through in ~3 % of the frames; 25 lost a
2 cm leg from 2.5 m on the 5 rows.
"""

MAX_UNKNOWN = 0.9
"""Default largest share of a frame's readings that may be unknown (`check_frame`); above it the
frame is refused (`BlindFrame`), not read as everything near.

Why 0.9: a sector is readable only when over half of its readings are known (`BLIND_FRACTION`),
so at most 16 * (1 - share) of the 8 sectors can hold a reading: above 0.9 at most one, and the
policy sees "everything at range_min", on which it spins. Real scenes stay well below (measured
in `tests/test_ros_node.py::test_broken_frames_stop_the_robot`: a black surface over half the
view 50 %, sunlight over 80 % of it 80 %); a covered lens or a sunlit view is 98-100 %. So is a
surface nearer than range_min across the whole view: the robot stops there instead of turning.
"""


class BlindFrame(ValueError):
    """A frame whose readings are almost all unknown (`check_frame`): no observation to act on."""

    def __init__(self, share: float, max_unknown: float):
        super().__init__(
            f"over {max_unknown:.0%} of its readings unknown (lens covered, sunlight, or a "
            "surface in the blind zone across the whole view)"
        )
        self.share = share
        """The share of the frame's readings that were unknown."""


def check_frame(depth, max_unknown: float | None) -> None:
    """Raises `BlindFrame` when more than `max_unknown` of the readings depth [N] (NaN: unknown)
    are unknown, or there are none; max_unknown None: no check."""
    if max_unknown is None:
        return
    depth = np.asarray(depth)
    share = float(np.isnan(depth).mean()) if depth.size else 1.0
    if share > max_unknown:
        raise BlindFrame(share, max_unknown)


def sector_nearest(reading, readings_per_stray=READINGS_PER_STRAY, xp=np):
    """[S] the nearest reading of each sector that enough of its readings confirm.

    reading [S, N]: each sector's known readings (m; +inf: no return within range), NaN in the
    other slots (unknown readings, floor, padding). With n(s) known readings, a sector reads its
    k-th nearest one, k = 1 + n(s) // readings_per_stray: the nearest distance that at least k of
    its readings reach. Up to k - 1 stray readings nearer than the scene are outvoted, while an
    object covering k readings is seen. readings_per_stray 0: k = 1, the plain minimum; a sector
    of fewer known readings than readings_per_stray also reads its minimum (the simulator's
    3 x 5 rays per sector). NaN where n(s) = 0. `xp` is the array module (numpy here; jax.numpy
    where the simulator applies the same rule).
    """
    known = (~xp.isnan(reading)).sum(-1)
    k = 1 + known // readings_per_stray if readings_per_stray else xp.ones_like(known)
    nearest = xp.sort(reading, axis=-1)  # NaN last
    return xp.take_along_axis(nearest, (k - 1)[..., None], axis=-1)[..., 0]


def _by_sector(depth: np.ndarray, sector: np.ndarray, n: int) -> np.ndarray:
    """[n, M] the readings depth [N] of each sector (sector [N]), NaN-padded to the longest."""
    order = np.argsort(sector, kind="stable")
    count = np.bincount(sector, minlength=n)
    slot = np.arange(sector.size) - np.repeat(np.cumsum(count) - count, count)
    grouped = np.full((n, max(1, int(count.max(initial=0)))), np.nan)
    grouped[sector[order], slot] = depth[order]
    return grouped


def reduce_sectors(
    depth,
    sector,
    sensor: Sensor,
    blind_fraction=BLIND_FRACTION,
    readings_per_stray=READINGS_PER_STRAY,
) -> np.ndarray:
    """[num_sectors] float32 observation from readings depth [N] (m) lying in sectors sector [N].

    The one reduction from readings to the observation, for depth images and scans alike; the
    simulator applies the same rule to its rays. A reading is a camera depth in metres, or NaN for
    "unknown" (the camera returned nothing: too close or no return, it cannot tell which).
    For each sector s (0 = rightmost), with n(s) readings of which u(s) are unknown:

    1. Blind: if u(s) >= blind_fraction * n(s) (so also when n(s) = 0) it reads range_min (near).
    2. Otherwise it reads its nearest known reading that enough of them confirm (`sector_nearest`:
       the k-th nearest, k = 1 + known // readings_per_stray; 0: the minimum), clipped to
       [range_min, range_max]: a reading below range_min (0 and -inf included) reads range_min,
       one above range_max (+inf: no hit within range) reads range_max.

    The simulator (`jaxnav.core.sensors`) applies the same rule to its rays, with the camera's
    unknowns: rays nearer than range_min, rays at dark obstacles, dropped rays and (with
    `far_invalid`) rays beyond range_max, of which `far_mask` turns those from beyond range
    into +inf where `far_reads_max` is set; rays that meet the floor are left out on both sides
    (`tests/test_fidelity.py` checks the two agree). blind_fraction must be in (0, 1]; 1 means only
    a sector whose readings are all unknown reads near.
    """
    if not 0 < blind_fraction <= 1:
        raise ValueError(f"blind_fraction: must be in (0, 1], got {blind_fraction}")
    _check_readings_per_stray(readings_per_stray)
    depth = np.asarray(depth, np.float64).ravel()
    sector = np.asarray(sector, np.int64).ravel()
    n = sensor.num_sectors
    count = np.bincount(sector, minlength=n)
    blind = np.bincount(sector[np.isnan(depth)], minlength=n) >= blind_fraction * count
    # NaN only in sectors without known readings, which are blind
    nearest = sector_nearest(_by_sector(depth, sector, n), readings_per_stray)
    near = np.clip(nearest, sensor.range_min, sensor.range_max)
    return np.where(blind, sensor.range_min, near).astype(np.float32)


def _check_readings_per_stray(value, owner: str = "") -> None:
    """A ValueError naming the field unless value is 0 or a whole number >= 2."""
    if not (value == 0 or (value >= 2 and value == int(value))):
        raise ValueError(
            f"{owner}readings_per_stray: must be 0 (the plain minimum) or a whole number >= 2, "
            f"got {value}"
        )


def floor_mask(reading, known, rise, camera_height, sensor, xp=np):
    """[...] bool: the readings that are the floor, which `reduce_sectors` must not see.

    The one floor rule, applied by the simulator to its rays (`jaxnav.core.sensors.observe`, with
    `xp` = jax.numpy) and here to depth-image pixels. reading [...] is camera depth (a lidar:
    range), m; known [...] bool marks the readings the camera returned; rise [...] is the height
    the ray gains per metre of reading (negative: towards the floor); camera_height is the
    camera's height above the floor, m; `sensor` gives range_min, range_max, floor_margin and
    floor_margin_slope (a `Sensor` or the simulator's `SensorConfig`).

    - A known reading is floor when the point it measures, camera_height + reading * rise above
      the floor, is at most floor_margin + floor_margin_slope * min(reading, range_max) (its
      noise and the mount's calibration error, see `FLOOR_MARGIN`); below the floor counts too.
    - An unknown reading (the camera's 0) is floor when its ray meets the floor where the camera
      cannot read it: nearer than range_min or beyond range_max. The floor would have read 0 there
      too; elsewhere the floor would have been read, so a 0 means something else (a surface in the
      blind zone, or one that returns no depth).
    """
    down = rise < 0
    finite = known & xp.isfinite(reading)
    r = xp.where(finite, reading, 0.0)
    margin = sensor.floor_margin + sensor.floor_margin_slope * xp.minimum(r, sensor.range_max)
    seen = xp.where(finite, camera_height + r * rise <= margin, down)  # +inf down: through it
    meets = camera_height / xp.where(down, -rise, 1.0)  # reading at which the ray meets the floor
    unreadable = down & ((meets < sensor.range_min) | (meets > sensor.range_max))
    return xp.where(known, seen, unreadable)


def far_mask(known, rise, camera_height, sensor, xp=np):
    """[R, K] bool: the unknown readings that are no return from beyond range, not a surface in
    the blind zone; they read range_max (+inf to `reduce_sectors`) where `far_reads_max` is set.

    The one far rule, applied by the simulator to its rays (`jaxnav.core.sensors.observe`, `xp` =
    jax.numpy) and here to depth-image pixels. known [R, K] bool marks the readings the camera
    returned, rise [R, K] the height each ray gains per metre of reading, for R rows (bottom to
    top or any order) in each of K columns; camera_height and `sensor` (range_min, range_max) as
    for `floor_mask`.

    An unknown reading is far when its ray points at or above the horizon (it meets no floor)
    and its column's witness returned: of the column's rays that meet the floor within
    [range_min, range_max], the one that meets it farthest out. Anything standing in front of
    the camera nearer than that floor point blocks it, so a surface in the blind zone (which
    blocks every ray of its columns) still reads near, as does a dark obstacle; one dropped pixel
    elsewhere in the column does not matter. A column without witnesses (a one-row sensor at the
    horizon) keeps every unknown unknown. What one frame cannot tell apart: an overhang nearer
    than range_min that the witness passes under reads far (docs/simulation.md).
    """
    down = rise < 0
    meets = camera_height / xp.where(down, -rise, 1.0)  # reading at which the ray meets the floor
    witness = down & (meets >= sensor.range_min) & (meets <= sensor.range_max)  # [R, K]
    reach = xp.where(witness, meets, -1.0)
    farthest = witness & (reach == reach.max(-2, keepdims=True))  # [R, K] one per column
    clear = (farthest & known).any(-2)  # [K] the column's witness returned
    return ~known & ~down & clear[..., None, :]


def _angle_sectors(angles, sensor: Sensor) -> tuple[np.ndarray, np.ndarray]:
    """(keep [N] bool: within +-fov/2, sector [K] of each kept angle), bins of fov/num_sectors."""
    half, n = 0.5 * sensor.fov, sensor.num_sectors
    keep = np.abs(angles) <= half
    # The simulator's bins: ray i of R lies at (i + 0.5) / R * fov - fov/2, sector i // (R / n).
    idx = np.floor((angles[keep] + half) / (sensor.fov / n)).astype(np.int64)
    return keep, np.clip(idx, 0, n - 1)  # a beam exactly at +fov/2 belongs to the last sector


def scan_to_sectors(
    ranges,
    angles,
    sensor: Sensor,
    blind_fraction=BLIND_FRACTION,
    *,
    readings_per_stray=READINGS_PER_STRAY,
    max_unknown=None,
) -> np.ndarray:
    """[num_sectors] float32 observation from a laser scan, as the simulator computes it.

    ranges [N] m and angles [N] rad as in a ROS LaserScan (0 ahead, positive to the left). Beams
    within +-fov/2 are kept and turned into camera depth (range * cos(angle)), read as REP 117
    defines them: NaN is unknown (no valid measurement; `depthimage_to_laserscan` writes it for
    columns the camera returned nothing in), like a depth image's 0; -inf (too close) and ranges
    of 0 or below read range_min; +inf (no return within range) reads range_max. Then
    `reduce_sectors`, and with `max_unknown` the frame check (`check_frame`).
    """
    ranges = np.asarray(ranges, np.float64).ravel()
    angles = np.asarray(angles, np.float64).ravel()
    if ranges.shape != angles.shape:
        raise ValueError(f"ranges {ranges.shape} and angles {angles.shape} differ in length")
    keep, sector = _angle_sectors(angles, sensor)
    r = ranges[keep]
    with np.errstate(invalid="ignore"):
        depth = np.where(r > 0, r * np.cos(angles[keep]), 0.0)  # 0: reads range_min
    depth[np.isposinf(r)] = np.inf  # no return within range: reads range_max
    depth[np.isnan(r)] = np.nan  # unknown: counts towards the blind share
    check_frame(depth, max_unknown)
    return reduce_sectors(depth, sector, sensor, blind_fraction, readings_per_stray)


def depth_image_to_sectors(
    depth,
    sensor: Sensor,
    rows=None,
    column_angles=None,
    blind_fraction=BLIND_FRACTION,
    vfov=None,
    *,
    camera: Intrinsics | None = None,
    readings_per_stray=READINGS_PER_STRAY,
    max_unknown=None,
) -> np.ndarray:
    """[num_sectors] float32 observation from a depth image [H, W] in metres (camera depth, z).

    Column 0 is the LEFT of the image of a forward-looking camera, so sector 0 holds the rightmost
    columns. 0, NaN and negative pixels are unknown (the Astra's 0 means too close or no return),
    +inf reads range_max; a sector at least `blind_fraction` unknown reads range_min, the others
    their nearest reading confirmed by 1 + known // readings_per_stray pixels (`reduce_sectors`).
    With `max_unknown`, a frame more unknown than that is refused (`check_frame`: `BlindFrame`).
    Two ways to pick the pixels:

    vfov or camera: the image's vertical field of view, rad (a pinhole camera with square pixels
        centred: the Astra's 49.5 deg is 0.864), or its calibration (`Intrinsics`, a CameraInfo's
        K). The pixels where the simulator casts its rays are read (`ray_pixels`: every column
        within +-fov/2, binned by angle, one pixel per row of `sensor.elevations`) and those that
        see the floor are left out (`floor_mask`, given `sensor.camera_height`): the simulator's
        observation, for one row or several. rows and column_angles must be None.
    Otherwise the pixels of `rows` are read in every column, none taken for floor:
    rows: row indices or a slice; None = all rows. On the robot pass the rows around the horizon
        (`horizon_rows`, `Intrinsics.horizon_rows`) for a one-row sensor: lower rows see the
        floor, which is no obstacle but would read as one ~0.65 m ahead.
    column_angles: [W] angle of each column (rad, positive = left, e.g.
        `Intrinsics.column_angles`); when given, columns are binned by angle like
        `scan_to_sectors` instead of equal slices (columns beyond +-fov/2 are dropped; the image
        is otherwise taken to span exactly `sensor.fov`). Equal slices of a pinhole image are up
        to ~1.5 deg off the simulator's equal-angle bins.
    """
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth image must be [H, W], got shape {depth.shape}")
    rules = dict(readings_per_stray=readings_per_stray, max_unknown=max_unknown)
    if vfov is not None or camera is not None:
        if rows is not None or column_angles is not None:
            raise ValueError("depth image: give vfov, or rows and column_angles, not both")
        pixels = ray_pixels(sensor, depth.shape[0], depth.shape[1], vfov, camera=camera)
        return rays_to_sectors(depth, pixels, sensor, blind_fraction, **rules)
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
    check_frame(readings, max_unknown)
    sector = np.broadcast_to(sector, readings.shape)
    return reduce_sectors(readings, sector, sensor, blind_fraction, readings_per_stray)


class Intrinsics(NamedTuple):
    """A pinhole depth camera's calibration, pixels (a CameraInfo's K: fx, fy, cx, cy), for images
    of width x height; pixel centres lie at whole numbers (column 0 on the left, row 0 at the top).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov: float) -> Intrinsics:
        """Square pixels, the principal point at the image's centre, `hfov` rad across the width."""
        if not 0 < hfov < math.pi:
            raise ValueError(f"hfov: must be in (0, pi) rad, got {hfov}")
        focal = 0.5 * width / math.tan(0.5 * hfov)
        return cls(focal, focal, 0.5 * (width - 1), 0.5 * (height - 1), width, height)

    @classmethod
    def from_vfov(cls, width: int, height: int, vfov: float) -> Intrinsics:
        """Square pixels, the principal point at the image's centre, `vfov` rad over the height."""
        if not 0 < vfov < math.pi:
            raise ValueError(f"vfov: must be in (0, pi) rad, got {vfov}")
        focal = 0.5 * height / math.tan(0.5 * vfov)
        return cls(focal, focal, 0.5 * (width - 1), 0.5 * (height - 1), width, height)

    def fits(self, height: int, width: int) -> None:
        """A ValueError unless the calibration is for images of this size."""
        if (self.height, self.width) != (height, width):
            raise ValueError(
                f"camera calibration is for {self.width}x{self.height} images, "
                f"the image is {width}x{height}"
            )

    def across(self, cols=None) -> np.ndarray:
        """[C] how far left of the optical axis each column's ray runs per metre of depth (the
        tangent of its angle; `cols` default: every column)."""
        cols = np.arange(self.width) if cols is None else np.asarray(cols)
        return (self.cx - cols) / self.fx

    def up(self, rows=None) -> np.ndarray:
        """[R] how far above the optical axis each row's ray runs per metre of depth."""
        rows = np.arange(self.height) if rows is None else np.asarray(rows)
        return (self.cy - rows) / self.fy

    def back_project(self, depth, rows, cols) -> np.ndarray:
        """[N, 3] the points (forward, left, up; m, the camera's frame: forward along the optical
        axis) that pixels (rows [N], cols [N]) of depth [N] (camera depth, m) see."""
        depth = np.asarray(depth, np.float64)
        return depth[:, None] * np.stack(
            [np.ones_like(depth), self.across(cols), self.up(rows)], axis=-1
        )

    def column_angles(self) -> np.ndarray:
        """[width] angle (rad, positive = left) of each column's centre from the optical axis."""
        return np.arctan(self.across())

    def horizon_rows(self, half_width_deg: float = 2.0, tilt: float = 0.0) -> np.ndarray:
        """Row indices within +-half_width_deg of the horizontal through the camera, tilted
        `tilt` rad down (the horizon then moves up the image); always at least one row."""
        centre = self.cy - self.fy * math.tan(tilt)
        half = self.fy * math.tan(math.radians(half_width_deg))
        lo = max(0, math.ceil(centre - half))
        hi = min(self.height - 1, math.floor(centre + half))
        if lo > hi:  # band thinner than a row: the row nearest the horizon
            lo = hi = min(self.height - 1, max(0, round(centre)))
        return np.arange(lo, hi + 1)


class RayPixels(NamedTuple):
    """Where a depth image holds the simulator's rays (`ray_pixels`), K columns by R rows."""

    rows: np.ndarray  # [R, K] int image row of each ray (row 0 at the top)
    cols: np.ndarray  # [K] int image column (column 0 on the left)
    sector: np.ndarray  # [K] int sector of each column (0 = rightmost)
    rise: np.ndarray  # [R, K] height gained per metre of depth along each pixel's ray, m/m


def ray_pixels(
    sensor: Sensor, height: int, width: int, vfov=None, azimuths=None, camera=None
) -> RayPixels:
    """The pixels of a depth image [height, width] that see along the simulator's rays.

    The camera is a pinhole: `camera` (`Intrinsics`, its calibration), or with square pixels, its
    principal point at the image centre and a vertical field of view `vfov` (rad); give one.
    Columns: every column whose angle lies within +-fov/2, binned into sectors by angle as the
    simulator's rays are; or, with `azimuths` [K] (rad, positive = left, e.g.
    `SensorConfig.ray_angles`), the column nearest each. Rows: in each column, for each of
    `sensor.elevations`, the pixel whose ray's elevation from the optical axis is nearest (a row of
    rays at one elevation is a curve on the image, not an image row). A ray beyond the top or
    bottom of the image (rows wider than the camera's vertical field of view at the image's
    sides) reads the edge row.
    """
    if (vfov is None) == (camera is None):
        raise ValueError("ray_pixels: give the camera's vfov or its Intrinsics, one of them")
    camera = camera or Intrinsics.from_vfov(width, height, vfov)
    camera.fits(height, width)
    across = camera.across()  # tan of each column's angle
    angles = np.arctan(across)
    if azimuths is None:
        keep, sector = _angle_sectors(angles, sensor)
        cols = np.flatnonzero(keep)
    else:
        azimuths = np.asarray(azimuths, np.float64).ravel()
        if np.abs(azimuths).max() > np.abs(angles).max():
            raise ValueError(f"azimuths: beyond the image's +-{np.abs(angles).max():.3f} rad")
        cols = np.abs(angles[None, :] - azimuths[:, None]).argmin(-1)
        sector = _angle_sectors(angles[cols], sensor)[1]
    if cols.size == 0:
        raise ValueError(f"depth image of {width} columns has none within the sensor's fov")
    # The pixel ray (1, t, y) (forward, left, up, per metre of depth) has elevation
    # atan(y / sqrt(1 + t^2)): y = tan(e) * sqrt(1 + t^2) puts it at elevation e.
    up = np.tan(np.asarray(sensor.elevations))[:, None] * np.hypot(1.0, across[cols])[None, :]
    rows = np.clip(np.rint(camera.cy - camera.fy * up), 0, height - 1).astype(np.int64)
    y = camera.up(rows)  # the chosen pixels' own rays
    pitch = sensor.camera_pitch
    return RayPixels(rows, cols, sector, math.cos(pitch) * y - math.sin(pitch))


def rays_to_sectors(
    depth,
    pixels: RayPixels,
    sensor: Sensor,
    blind_fraction=BLIND_FRACTION,
    *,
    readings_per_stray=READINGS_PER_STRAY,
    max_unknown=None,
):
    """[num_sectors] float32 observation from a depth image [H, W] (m) read at `pixels`
    (`ray_pixels`): 0, NaN and negative pixels are unknown, floor pixels are left out
    (`floor_mask`; none without `sensor.camera_height`), with `sensor.far_reads_max` unknown
    pixels from beyond range read range_max (`far_mask`), the rest go to `reduce_sectors`; with
    `max_unknown`, all of them, floor included, to `check_frame` first."""
    reading = np.asarray(depth, np.float64)[pixels.rows, pixels.cols[None, :]]  # [R, K]
    with np.errstate(invalid="ignore"):
        known = reading > 0
    if sensor.camera_height is None:
        floor = np.zeros(reading.shape, bool)
    else:
        with np.errstate(invalid="ignore"):
            floor = floor_mask(reading, known, pixels.rise, sensor.camera_height, sensor)
    readings = np.where(known, reading, np.nan)
    if sensor.far_reads_max and sensor.camera_height is not None:
        far = far_mask(known, pixels.rise, sensor.camera_height, sensor)
        readings = np.where(far, np.inf, readings)  # no return within range: range_max
    check_frame(
        readings, max_unknown
    )  # floor included: a pixel that sees it shows the camera works
    sector = np.broadcast_to(pixels.sector, reading.shape)
    return reduce_sectors(
        readings[~floor], sector[~floor], sensor, blind_fraction, readings_per_stray
    )


def pinhole_column_angles(width: int, hfov: float) -> np.ndarray:
    """[W] angle (rad, positive = left) of each pixel column's centre for a pinhole camera."""
    return Intrinsics.from_hfov(width, 1, hfov).column_angles()


def horizon_rows(
    height: int, vfov: float, half_width_deg: float = 2.0, tilt: float = 0.0
) -> np.ndarray:
    """Row indices within +-half_width_deg of the horizontal through the camera (pinhole model).

    vfov: vertical field of view, rad. tilt: camera pitch, rad, positive = looking down (the
    horizon then moves up the image). Always at least one row (`Intrinsics.horizon_rows`).
    """
    return Intrinsics.from_vfov(1, height, vfov).horizon_rows(half_width_deg, tilt)


def action_to_twist(action, commands: np.ndarray, speed_calibration: float = 1.0) -> Twist:
    """The command of `action` from the trained table `commands` [A, 2] (forward m/s, yaw rad/s).

    speed_calibration multiplies both speeds: set it so that the real robot moves at the speeds the
    simulator assumed (the paper had to recalibrate its robot's speed commands).
    """
    a = int(action)
    if not 0 <= a < len(commands):
        raise ValueError(f"action must be in 0..{len(commands) - 1}, got {action}")
    return finite_twist(commands[a], speed_calibration)


def finite_twist(command, speed_calibration: float = 1.0) -> Twist:
    """The Twist of command (forward m/s, yaw rad/s) times speed_calibration; a ValueError if
    either is NaN or infinite, so that no such value ever reaches the robot."""
    forward, yaw = (float(x) * speed_calibration for x in command)
    if not (math.isfinite(forward) and math.isfinite(yaw)):
        raise ValueError(f"command ({forward}, {yaw}) is not finite")
    return Twist(forward, yaw)


@dataclasses.dataclass(frozen=True)
class Controller:
    """Sensor reading -> observation -> policy -> Twist, in one call."""

    policy: object
    """A `NumpyPolicy`: callable obs [D] -> action int, with `.sensor` and `.commands` (D: the
    sectors, or what the control loop builds of them: stacked frames, the goal's inputs)."""
    speed_calibration: float = 1.0
    """Multiplies both speeds of every command (see `action_to_twist`)."""
    blind_fraction: float = BLIND_FRACTION
    """A sector at least this share unknown (0/NaN) reads near (`reduce_sectors`)."""
    readings_per_stray: int = READINGS_PER_STRAY
    """A sector reads its nearest reading confirmed by 1 + known // this readings
    (`sector_nearest`); 0: the plain minimum."""
    max_unknown: float | None = MAX_UNKNOWN
    """A frame more than this share unknown is refused (`check_frame`: BlindFrame); None: never."""

    def __post_init__(self):
        if not 0 < self.speed_calibration < math.inf:
            raise ValueError(
                f"Controller.speed_calibration: must be finite and > 0, got {self.speed_calibration}"
            )
        if not 0 < self.blind_fraction <= 1:
            raise ValueError(
                f"Controller.blind_fraction: must be in (0, 1], got {self.blind_fraction}"
            )
        _check_readings_per_stray(self.readings_per_stray, "Controller.")
        if self.max_unknown is not None and not 0 <= self.max_unknown <= 1:
            raise ValueError(f"Controller.max_unknown: must be in [0, 1], got {self.max_unknown}")

    def act(self, obs) -> Twist:
        """The command for an observation [D] (sectors in metres, right to left; the goal task's
        entries after them, see `policy.goal_observation`). A ValueError where the observation or
        the command is not finite (NaN would otherwise pick the first action: forward)."""
        obs = np.asarray(obs, np.float32)
        if not np.isfinite(obs).all():
            bad = np.flatnonzero(~np.isfinite(obs)).tolist()
            raise ValueError(f"observation entries {bad} are NaN or infinite")
        if getattr(self.policy, "continuous", False):
            return finite_twist(self.policy(obs), self.speed_calibration)
        return action_to_twist(self.policy(obs), self.policy.commands, self.speed_calibration)

    def image_obs(
        self, depth, rows=None, column_angles=None, vfov=None, camera=None, sensor=None
    ) -> np.ndarray:
        """The observation of a depth image [H, W] in metres (see `depth_image_to_sectors`);
        `sensor` replaces the policy's (e.g. its mount set to the robot's)."""
        return depth_image_to_sectors(
            depth,
            sensor or self.policy.sensor,
            rows,
            column_angles,
            self.blind_fraction,
            vfov,
            camera=camera,
            readings_per_stray=self.readings_per_stray,
            max_unknown=self.max_unknown,
        )

    def scan_obs(self, ranges, angles) -> np.ndarray:
        """The observation of a laser scan: ranges [N] m at angles [N] rad (0 ahead, + left)."""
        return scan_to_sectors(
            ranges,
            angles,
            self.policy.sensor,
            self.blind_fraction,
            readings_per_stray=self.readings_per_stray,
            max_unknown=self.max_unknown,
        )

    def image_to_twist(self, depth, rows=None, column_angles=None, vfov=None) -> Twist:
        """The command for a depth image [H, W] in metres (see `depth_image_to_sectors`)."""
        return self.act(self.image_obs(depth, rows, column_angles, vfov))

    def scan_to_twist(self, ranges, angles) -> Twist:
        """The command for a laser scan: ranges [N] m at angles [N] rad (0 ahead, positive left)."""
        return self.act(self.scan_obs(ranges, angles))
