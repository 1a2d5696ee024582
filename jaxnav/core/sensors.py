"""The paper's observation: the 8 shortest depth-camera distances, one per slice of the field of view.

Rays leave the sensor, mounted where the `RobotSpec` says (with the episode's mount error), over the
horizontal field of view in `rows` rows spanning `row_angles` of the vertical field of view, so
obstacles lower than the camera (from 0.05 m) and overhangs are seen. For a depth camera each hit is
turned into camera depth (distance along the optical axis, what a depth image holds); a lidar reports
the range itself. Sectors are ordered right to left (increasing angle, as in a ROS LaserScan): obs[0]
is the rightmost slice, obs[7] the leftmost.

Each ray reads one of three things, as the Orbbec Astra reports them:
- floor: the ray meets the floor before any obstacle. Not an obstacle; left out of the sector.
- invalid (the camera reports 0): the surface is nearer than `range_min` (the blind zone), the
  obstacle returns no depth (dark, glossy, glass), the pixel drops out, or (with `far_invalid`)
  the surface is farther than `range_max` or absent.
- valid: a depth in [range_min, range_max], with noise of std `noise_std + noise_quad * depth^2`.

One reduction per sector, the same rule as on the robot (`jaxnav.robot_side.observation`): if at
least `blind_fraction` of its non-floor rays are invalid (a sector of floor only included), the
sector reads `range_min` (near: the camera cannot tell "too close" from "nothing", and near is the
safe reading); otherwise the minimum of its valid readings, clipped to the range.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnav.core.checks import require_finite
from jaxnav.core.geometry import ray_cast
from jaxnav.core.robot import RobotSpec

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
    rows, a policy collides with most low obstacles (benchmarks/RESULTS.md)."""
    row_angles: tuple[float, float] = (-0.40, 0.17)
    """Elevation of the lowest and highest row from the optical axis, rad (up +); the Astra's
    vertical field of view is 49.5 deg (+-0.43 rad)."""
    range_min: float = 0.6
    """Nearest readable depth, m; nearer surfaces are invalid (Astra: 0.6)."""
    range_max: float = 8.0
    """Farthest readable depth, m; farther surfaces are invalid (Astra: 8)."""
    blind_fraction: float = 0.5
    """A sector whose non-floor rays are invalid in at least this share reads range_min."""
    far_invalid: bool = False
    """Surfaces beyond range_max (and rays meeting nothing) are invalid, as the Astra reports them
    (0); False (default): they read range_max, as a LaserScan's inf does."""

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
        if not 0 <= self.blind_fraction <= 1:
            raise ValueError(
                f"SensorConfig.blind_fraction: must be in [0, 1], got {self.blind_fraction}"
            )

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


def _directions(cfg: SensorConfig, yaw, pitch) -> tuple[jax.Array, jax.Array]:
    """World unit directions [rows, C, 3] of the rays and the cosine [rows, C] between each ray and
    the optical axis (the factor from range to camera depth)."""
    h = jnp.asarray(cfg.ray_angles, jnp.float32)[None, :]  # [1, C]
    v = jnp.asarray(cfg.elevations, jnp.float32)[:, None]  # [rows, 1]
    # Camera frame (x optical axis, y left, z up), then pitched down by `pitch`, then yawed.
    cam = jnp.stack(
        jnp.broadcast_arrays(jnp.cos(v) * jnp.cos(h), jnp.cos(v) * jnp.sin(h), jnp.sin(v)), -1
    )
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    fx, fz = cp * cam[..., 0] + sp * cam[..., 2], -sp * cam[..., 0] + cp * cam[..., 2]
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    world = jnp.stack([cy * fx - sy * cam[..., 1], sy * fx + cy * cam[..., 1], fz], -1)
    return world, cam[..., 0]


def ray_readings(params, qpos: jax.Array, cfg: SensorConfig, robot: RobotSpec):
    """Noiseless per-ray readings [rows, C]: (reading m, hit slot, floor bool), for a robot at
    qpos = (x, y, yaw) with the mount error of `params` (the episode's `SceneParams`).

    reading is camera depth (lidar: range), inf where the ray meets nothing; slot is the obstacle
    hit (boxes then cylinders, as in `SceneParams`; -1 for a wall or nothing); floor marks rays
    that meet the floor before any obstacle. The rays are cast analytically on the room's shapes
    (`geometry.ray_cast`, which agrees with `mjx.ray` on the MJX scene: tested).
    """
    pos, yaw, pitch = camera_pose(qpos, robot, params.camera)
    dirs, cosine = _directions(cfg, yaw, pitch)
    dist, slot = ray_cast(params, pos, dirs)  # [rows, C]
    hit = jnp.isfinite(dist)
    floor_dist = jnp.where(dirs[..., 2] < 0, pos[2] / jnp.maximum(-dirs[..., 2], 1e-9), jnp.inf)
    floor = jnp.where(hit, floor_dist < dist, jnp.isfinite(floor_dist))
    scale = cosine if cfg.model == "camera" else jnp.ones_like(cosine)
    reading = jnp.where(hit, dist * scale, jnp.inf)
    return reading, slot, floor


def ray_depths(params, qpos: jax.Array, cfg: SensorConfig, robot: RobotSpec):
    """[rows * C] noiseless readings of the rays, inf where a ray meets nothing or the floor."""
    reading, _, floor = ray_readings(params, qpos, cfg, robot)
    return jnp.where(floor, jnp.inf, reading).reshape(-1)


def reduce_sectors(reading, valid, floor, cfg: SensorConfig, xp=jnp):
    """[num_sectors] observation from per-ray readings [R, num_sectors * k] (columns right to left):
    `valid` [R, C] bool, `floor` [R, C] bool. The one reduction of the module docstring; `xp` is
    the array module (jax.numpy here, numpy on the robot), so both compute it the same way."""
    rows = reading.shape[0]
    group = lambda x: (
        x.reshape(rows, cfg.num_sectors, -1).transpose(1, 0, 2).reshape(cfg.num_sectors, -1)
    )  # noqa: E731
    reading, valid, floor = group(reading), group(valid), group(floor)
    counted = (~floor).sum(-1)
    invalid = (~floor & ~valid).sum(-1)
    nearest = xp.where(valid & ~floor, reading, xp.inf).min(-1)
    near = invalid >= cfg.blind_fraction * counted  # as the robot side: at least that share
    out = xp.where(near, cfg.range_min, xp.where(xp.isinf(nearest), cfg.range_max, nearest))
    return xp.clip(out, cfg.range_min, cfg.range_max)


def observe(params, qpos, key, cfg: SensorConfig, robot: RobotSpec) -> jax.Array:
    """[num_sectors] float32 observation of a robot at qpos = (x, y, yaw) with the episode's
    noise, dropout, dark obstacles and camera mount error (`params`: its `SceneParams`)."""
    reading, slot, floor = ray_readings(params, qpos, cfg, robot)
    k_noise, k_drop = jax.random.split(key)
    std = params.noise_std + params.noise_quad * jnp.square(jnp.minimum(reading, cfg.range_max))
    reading = reading + std * jax.random.normal(k_noise, reading.shape)
    dropped = jax.random.bernoulli(k_drop, params.dropout, reading.shape)
    dark = (slot >= 0) & params.dark[jnp.maximum(slot, 0)]  # an obstacle with no return
    in_range = (reading <= cfg.range_max) | (not cfg.far_invalid)
    valid = (reading >= cfg.range_min) & in_range & ~dropped & ~dark
    return reduce_sectors(reading, valid, floor, cfg).astype(jnp.float32)
