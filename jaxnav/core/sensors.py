"""The paper's observation: the 8 shortest depth-camera distances, one per slice of the field of view.

Rays leave the sensor, mounted where the `RobotSpec` says (with the episode's mount error), over the
horizontal field of view in `rows` rows spanning `row_angles` of the vertical field of view, so
obstacles lower than the camera (from 0.05 m) and overhangs are seen. For a depth camera each hit is
turned into camera depth (distance along the optical axis, what a depth image holds); a lidar reports
the range itself. Sectors are ordered right to left (increasing angle, as in a ROS LaserScan): obs[0]
is the rightmost slice, obs[7] the leftmost.

Each ray reads the first surface it meets, floor included, as the Orbbec Astra reports it:
- invalid (the camera reports 0): the surface is nearer than `range_min` (the blind zone), the
  obstacle returns no depth (dark, glossy, glass), the pixel drops out, or (with `far_invalid`)
  the surface is farther than `range_max` or absent.
- valid: a depth in [range_min, range_max], with noise of std `noise_std + noise_quad * depth^2`.
Then rays that see the floor are told apart from obstacle hits by the robot side's own rule,
`jaxnav.robot_side.observation.floor_mask` (the same code): a reading whose point lies within
`floor_margin + floor_margin_slope * depth` of the floor plane, or an invalid one whose ray meets
the floor outside the camera's range. Floor is not an obstacle; it is left out of the sector.
With `far_reads_max`, an invalid ray at or above the horizon whose column's farthest-reaching
floor ray returned is no return from beyond range and reads range_max (the robot side's
`far_mask`: the same code).
The simulator classifies with the episode's true camera mount off by a calibration error
(`RandomizeConfig.calibration_height_error`, `calibration_pitch_error`; 0 by default): the robot
side classifies with its calibrated mount (`jaxnav.robot_side.calibrate`).

One reduction per sector, the same rule as on the robot (`jaxnav.robot_side.observation`): if at
least `blind_fraction` of its non-floor rays are invalid (a sector of floor only included), the
sector reads `range_min` (near: the camera cannot tell "too close" from "nothing", and near is the
safe reading); otherwise its nearest valid reading that 1 + n // readings_per_stray of its n valid
readings reach (the robot side's `sector_nearest`: a few stray readings are outvoted), clipped to
the range. With the default 3 x 5 rays a sector has fewer than `readings_per_stray` readings, so
that is the minimum.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnav.core.checks import require_finite
from jaxnav.core.draws import hashed_uniform, normal_of
from jaxnav.core.geometry import ray_cast
from jaxnav.core.robot import RobotSpec
from jaxnav.robot_side.observation import (
    FLOOR_MARGIN,
    FLOOR_MARGIN_SLOPE,
    READINGS_PER_STRAY,
    far_mask,
    floor_mask,
    sector_nearest,
)

SENSOR_MODELS = ("camera", "lidar")


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """The sensor's geometry, limits and reduction to sectors (default: the Orbbec Astra)."""

    model: str = "camera"
    """'camera': readings are depth along the optical axis (fov < pi); 'lidar': ranges (fov <= 2 pi)."""
    num_sectors: int = 8
    """Slices of the field of view, one observation each (the paper: 8)."""
    rays_per_sector: int = 3
    """Ray columns per slice; more see thinner obstacles further away."""
    fov: float = float(np.deg2rad(60.0))
    """Horizontal field of view, rad (Astra: 60 deg)."""
    rows: int = 5
    """Ray rows, evenly spread over `row_angles`. 5 (default) sees obstacles from 0.05 m tall and
    overhangs: trained with 1 (a horizontal fan at the camera's height, 1/5 of the ray cost) or 3
    rows, a policy collides with most low obstacles (docs/results.md)."""
    row_angles: tuple[float, float] = (-0.38, 0.17)
    """Elevation of the lowest and highest row from the optical axis, rad (up +). The Astra's
    vertical field of view is 49.5 deg (+-0.43 rad) at the image's centre but only +-0.38 rad at
    its sides (+-30 deg: a pinhole image's edge rows curve towards the axis), so lower rows would
    see what the camera cannot (tests/test_rendered_depth.py)."""
    range_min: float = 0.6
    """Nearest readable depth, m; nearer surfaces are invalid (Astra: 0.6)."""
    range_max: float = 8.0
    """Farthest readable depth, m; farther surfaces are invalid (Astra: 8)."""
    blind_fraction: float = 0.5
    """A sector whose non-floor rays are invalid in at least this share reads range_min."""
    readings_per_stray: int = READINGS_PER_STRAY
    """A sector of n valid readings reads its (1 + n // this)-th nearest, as the robot side does
    (`sector_nearest`); 0: the minimum. Below this many rays per sector it is the minimum."""
    far_invalid: bool = False
    """Surfaces beyond range_max (and rays meeting nothing) are invalid, as the Astra reports them
    (0); False (default): they read range_max, as a LaserScan's inf does."""
    far_reads_max: bool = False
    """An invalid ray at or above the horizon whose column's farthest-reaching floor ray returned
    is no return from beyond range and reads range_max (`far_mask`, shared with the robot side,
    which reads the flag from the policy file); False (default): it stays invalid."""
    floor_margin: float = FLOOR_MARGIN
    """A reading within floor_margin + floor_margin_slope * depth (m) of the floor plane, or
    below it, is floor, not an obstacle (`floor_mask`, shared with the robot side)."""
    floor_margin_slope: float = FLOOR_MARGIN_SLOPE
    """Growth of the floor margin per metre of depth, m/m."""

    def __post_init__(self):
        require_finite(self)
        for name in ("num_sectors", "rays_per_sector", "rows"):
            if getattr(self, name) < 1:
                raise ValueError(f"SensorConfig.{name}: must be >= 1, got {getattr(self, name)}")
        if self.model not in SENSOR_MODELS:
            raise ValueError(
                f"SensorConfig.model: must be one of {', '.join(SENSOR_MODELS)}, got {self.model!r}"
            )
        top, label = (
            (np.pi, "(0, pi)") if self.model == "camera" else (2 * np.pi + 1e-6, "(0, 2 pi]")
        )
        if not 0 < self.fov < top:
            raise ValueError(
                f"SensorConfig.fov: must be in {label} rad for a {self.model}, got {self.fov}"
            )
        low, high = self.row_angles
        if not -np.pi / 2 < low <= high < np.pi / 2:
            raise ValueError(
                f"SensorConfig.row_angles: need -pi/2 < low <= high < pi/2, got {self.row_angles}"
            )
        if self.range_max <= 0:
            raise ValueError(f"SensorConfig.range_max: must be > 0 m, got {self.range_max}")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError(
                f"SensorConfig.range_min: must be in [0, range_max = {self.range_max}) m, "
                f"got {self.range_min}"
            )
        if self.readings_per_stray < 0 or self.readings_per_stray == 1:
            raise ValueError(
                "SensorConfig.readings_per_stray: must be 0 (the minimum) or >= 2, "
                f"got {self.readings_per_stray}"
            )
        if not 0 <= self.blind_fraction <= 1:
            raise ValueError(
                f"SensorConfig.blind_fraction: must be in [0, 1], got {self.blind_fraction}"
            )
        for name in ("floor_margin", "floor_margin_slope"):
            if getattr(self, name) < 0:
                raise ValueError(f"SensorConfig.{name}: must be >= 0, got {getattr(self, name)}")

    @property
    def ray_angles(self) -> np.ndarray:
        """[num_sectors * rays_per_sector] column angles from the optical axis, right to left, rad."""
        n = self.num_sectors * self.rays_per_sector
        return (np.arange(n) + 0.5) / n * self.fov - 0.5 * self.fov

    @property
    def elevations(self) -> np.ndarray:
        """[rows] row elevations from the optical axis, bottom to top, rad (one row: 0)."""
        if self.rows == 1:
            return np.zeros(1)
        return np.linspace(*self.row_angles, self.rows)


def camera_pose(
    qpos: jax.Array, robot: RobotSpec, error=None
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """World position [3], yaw [] and pitch [] (down +) of the sensor for base pose qpos = (x, y,
    yaw), with the episode's mount `error` [3] (height m, pitch rad, yaw rad) if given."""
    error = jnp.zeros(3) if error is None else error
    x, y, yaw = qpos[0], qpos[1], qpos[2]
    fwd = robot.camera_forward
    z = jnp.asarray(robot.camera_height) + error[0]
    pos = jnp.stack([x + fwd * jnp.cos(yaw), y + fwd * jnp.sin(yaw), z])
    return pos, yaw + error[2], jnp.asarray(robot.camera_pitch) + error[1]


def _camera_frame(cfg: SensorConfig) -> jax.Array:
    """[rows, C, 3] unit directions of the rays in the camera frame (x optical axis, y left, z up);
    x is the cosine between each ray and the optical axis (the factor from range to depth)."""
    h = jnp.asarray(cfg.ray_angles, jnp.float32)[None, :]  # [1, C]
    v = jnp.asarray(cfg.elevations, jnp.float32)[:, None]  # [rows, 1]
    return jnp.stack(
        jnp.broadcast_arrays(jnp.cos(v) * jnp.cos(h), jnp.cos(v) * jnp.sin(h), jnp.sin(v)), -1
    )


def _pitched(cam: jax.Array, pitch) -> tuple[jax.Array, jax.Array]:
    """(forward, up) [rows, C] components of the camera-frame rays `cam` pitched down by `pitch`."""
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    return cp * cam[..., 0] + sp * cam[..., 2], -sp * cam[..., 0] + cp * cam[..., 2]


def _directions(cfg: SensorConfig, yaw, pitch) -> tuple[jax.Array, jax.Array]:
    """World unit directions [rows, C, 3] of the rays and the cosine [rows, C] between each ray and
    the optical axis (the factor from range to camera depth)."""
    cam = _camera_frame(cfg)  # pitched down by `pitch`, then yawed
    fx, fz = _pitched(cam, pitch)
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    world = jnp.stack([cy * fx - sy * cam[..., 1], sy * fx + cy * cam[..., 1], fz], -1)
    return world, cam[..., 0]


class Rays(NamedTuple):
    """Noiseless readings of the sensor's rays [rows, C] (`ray_readings`)."""

    reading: jax.Array  # [rows, C] camera depth (lidar: range) of the first surface, m; inf: none
    slot: jax.Array  # [rows, C] int32 obstacle hit first (boxes, then cylinders); -1: wall, floor
    rise: jax.Array  # [rows, C] height the ray gains per metre of reading, m/m (< 0: downwards)
    height: jax.Array  # [] the camera's height above the floor, m (with the mount error)
    # rise and height are those the floor rule uses: the true mount's off by the episode's
    # calibration error (`RandomizeConfig.calibration_*_error`; 0: the true mount's).


def ray_readings(params, qpos: jax.Array, cfg: SensorConfig, robot: RobotSpec) -> Rays:
    """The noiseless `Rays` of a robot at qpos = (x, y, yaw) with the mount error of `params` (the
    episode's `SceneParams`): what each ray meets first, the floor included. The rays are cast
    analytically on the room's shapes (`geometry.ray_cast`, which agrees with `mjx.ray` on the MJX
    scene: tested); the floor plane z = 0 is intersected here."""
    pos, yaw, pitch = camera_pose(qpos, robot, params.camera)
    dirs, cosine = _directions(cfg, yaw, pitch)
    dist, slot = ray_cast(params, pos, dirs)  # [rows, C]
    hit = jnp.isfinite(dist)
    floor_dist = jnp.where(dirs[..., 2] < 0, pos[2] / jnp.maximum(-dirs[..., 2], 1e-9), jnp.inf)
    floor = jnp.where(hit, floor_dist < dist, jnp.isfinite(floor_dist))
    dist = jnp.where(floor, floor_dist, dist)
    scale = cosine if cfg.model == "camera" else jnp.ones_like(cosine)
    slot = jnp.where(floor, -1, slot)
    # The floor rule's mount: the true one off by the episode's calibration error (the robot's
    # rule uses its calibrated mount).
    _, believed_up = _pitched(_camera_frame(cfg), pitch + params.camera[4])
    return Rays(dist * scale, slot, believed_up / scale, pos[2] + params.camera[3])


def _floor(rays: Rays, reading, valid, cfg: SensorConfig):
    """[rows, C] bool: the rays whose readings (`reading`, `valid` [rows, C]) are the floor."""
    return floor_mask(reading, valid, rays.rise, rays.height, cfg, xp=jnp)


def ray_depths(params, qpos: jax.Array, cfg: SensorConfig, robot: RobotSpec):
    """[rows * C] noiseless readings of the rays, inf where a ray meets nothing or the floor."""
    rays = ray_readings(params, qpos, cfg, robot)
    in_range = (rays.reading <= cfg.range_max) | (not cfg.far_invalid)
    floor = _floor(rays, rays.reading, (rays.reading >= cfg.range_min) & in_range, cfg)
    return jnp.where(floor, jnp.inf, rays.reading).reshape(-1)


def reduce_sectors(reading, valid, floor, cfg: SensorConfig, xp=jnp):
    """[num_sectors] observation from per-ray readings [R, num_sectors * k] (columns right to left):
    `valid` [R, C] bool, `floor` [R, C] bool. The one reduction of the module docstring; `xp` is
    the array module (jax.numpy here, numpy on the robot), so both compute it the same way."""
    rows = reading.shape[0]
    split = lambda x: x.reshape(rows, cfg.num_sectors, -1)  # noqa: E731  [R, S, k]
    reading, valid, floor = split(reading), split(valid), split(floor)
    per_sector = rows * reading.shape[-1]  # static: below readings_per_stray, k is always 1
    # Both counts in one sum (not floor, + `base` x not floor and unknown): XLA's CPU backend
    # computes the readings anew inside each reduction of them, so one fewer is one fewer pass.
    base = per_sector + 1
    counts = ((~floor).astype(xp.int32) + (~floor & ~valid).astype(xp.int32) * base).sum((0, 2))
    counted, invalid = counts % base, counts // base  # [S] each
    if cfg.readings_per_stray and per_sector >= cfg.readings_per_stray:
        known = xp.where(valid & ~floor, reading, xp.nan).transpose(1, 0, 2)
        nearest = sector_nearest(known.reshape(cfg.num_sectors, -1), cfg.readings_per_stray, xp=xp)
        nearest = xp.where(xp.isnan(nearest), xp.inf, nearest)
    else:
        nearest = xp.where(valid & ~floor, reading, xp.inf).min((0, 2))
    near = invalid >= cfg.blind_fraction * counted  # as the robot side: at least that share
    out = xp.where(near, cfg.range_min, xp.where(xp.isinf(nearest), cfg.range_max, nearest))
    return xp.clip(out, cfg.range_min, cfg.range_max)


class Readings(NamedTuple):
    """What the camera returns for each ray [rows, C] (`camera_readings`)."""

    rays: Rays  # the noiseless rays
    reading: jax.Array  # [rows, C] camera depth with noise, m
    valid: jax.Array  # [rows, C] bool: the camera returned it (else it reads 0)
    floor: jax.Array  # [rows, C] bool: it is the floor (`floor_mask`)


def camera_readings(params, qpos, key, cfg: SensorConfig, robot: RobotSpec) -> Readings:
    """The `Readings` of a robot at qpos = (x, y, yaw) with the episode's noise, dropout, dark
    obstacles and camera mount error (`params`: its `SceneParams`), before `far_mask`."""
    rays = ray_readings(params, qpos, cfg, robot)
    reading = rays.reading
    u = hashed_uniform(key, (2, *reading.shape))  # noise and dropout
    std = params.noise_std + params.noise_quad * jnp.square(jnp.minimum(reading, cfg.range_max))
    reading = reading + std * normal_of(u[0])
    dropped = u[1] < params.dropout
    dark = (rays.slot >= 0) & params.dark[jnp.maximum(rays.slot, 0)]  # no return
    in_range = (reading <= cfg.range_max) | (not cfg.far_invalid)
    valid = (reading >= cfg.range_min) & in_range & ~dropped & ~dark
    return Readings(rays, reading, valid, _floor(rays, reading, valid, cfg))


def sectors(readings: Readings, cfg: SensorConfig) -> jax.Array:
    """[num_sectors] float32 observation of the camera's `readings`: with `far_reads_max`, no
    return from beyond range reads range_max (`far_mask`), then `reduce_sectors`."""
    rays, reading, valid, floor = readings
    if cfg.far_reads_max:
        far = far_mask(valid, rays.rise, rays.height, cfg, xp=jnp)  # [rows, C]
        reading, valid = jnp.where(far, jnp.inf, reading), valid | far
    return reduce_sectors(reading, valid, floor, cfg).astype(jnp.float32)


def observe(params, qpos, key, cfg: SensorConfig, robot: RobotSpec) -> jax.Array:
    """[num_sectors] float32 observation of a robot at qpos = (x, y, yaw) with the episode's
    noise, dropout, dark obstacles and camera mount error (`params`: its `SceneParams`)."""
    return sectors(camera_readings(params, qpos, key, cfg, robot), cfg)
