"""The paper's observation: the 8 shortest depth-camera distances, one per slice of the field of view.

A horizontal fan of rays leaves the sensor, mounted where the `RobotSpec` says. For a depth camera each
ray's hit distance is turned into camera depth (distance along the optical axis, what a depth image
holds); a lidar reports the range itself and may see all around. Readings are noised, dropped out,
clipped to the sensor's range, and the minimum is taken per sector. Sectors are ordered right to left (increasing angle, as in a ROS
LaserScan): obs[0] is the rightmost slice, obs[7] the leftmost.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from jaxnav.core.checks import require_finite
from jaxnav.core.robot import RobotSpec
from jaxnav.core.scene import OBSTACLE_GROUP

SENSOR_MODELS = ("camera", "lidar")


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """The sensor's geometry, limits and reduction to sectors (default: the Orbbec Astra)."""

    model: str = "camera"
    """'camera': readings are depth along the optical axis (fov < pi); 'lidar': ranges (fov <= 2 pi)."""
    num_sectors: int = 8
    """Slices of the field of view, one observation each (the paper: 8)."""
    rays_per_sector: int = 3
    """Rays cast per slice; more rays see thinner obstacles further away."""
    fov: float = float(np.deg2rad(60.0))
    """Horizontal field of view, rad (Astra: 60 deg)."""
    range_min: float = 0.6
    """Nearest readable depth, m; closer surfaces read this value (Astra: 0.6)."""
    range_max: float = 8.0
    """Farthest readable depth, m; no return reads this value (Astra: 8)."""

    def __post_init__(self):
        require_finite(self)
        for name in ("num_sectors", "rays_per_sector"):
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
        if self.range_max <= 0:
            raise ValueError(f"SensorConfig.range_max: must be > 0 m, got {self.range_max}")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError(
                f"SensorConfig.range_min: must be in [0, range_max = {self.range_max}) m, "
                f"got {self.range_min}"
            )

    @property
    def ray_angles(self) -> np.ndarray:
        """[num_sectors * rays_per_sector] ray angles from the optical axis, right to left, rad."""
        n = self.num_sectors * self.rays_per_sector
        return (np.arange(n) + 0.5) / n * self.fov - 0.5 * self.fov


def camera_pose(qpos: jax.Array, robot: RobotSpec) -> tuple[jax.Array, jax.Array]:
    """World position [3] and yaw [] of the sensor for base pose qpos = (x, y, yaw)."""
    x, y, yaw = qpos[0], qpos[1], qpos[2]
    fwd = robot.camera_forward
    pos = jnp.stack(
        [x + fwd * jnp.cos(yaw), y + fwd * jnp.sin(yaw), jnp.asarray(robot.camera_height)]
    )
    return pos, yaw


def ray_depths(m: mjx.Model, d: mjx.Data, cfg: SensorConfig, robot: RobotSpec, robot_body: int):
    """[R] noiseless reading of each ray (camera depth or lidar range), inf where it hits nothing."""
    pos, yaw = camera_pose(d.qpos, robot)
    angles = jnp.asarray(cfg.ray_angles, jnp.float32)
    vecs = jnp.stack([jnp.cos(yaw + angles), jnp.sin(yaw + angles), jnp.zeros_like(angles)], -1)
    groups = tuple(int(g == OBSTACLE_GROUP) for g in range(6))
    dist, _ = jax.vmap(lambda v: mjx.ray(m, d, pos, v, geomgroup=groups, bodyexclude=robot_body))(
        vecs
    )
    reading = dist * jnp.cos(angles) if cfg.model == "camera" else dist
    return jnp.where(dist < 0, jnp.inf, reading)


def sector_minima(depths: jax.Array, cfg: SensorConfig) -> jax.Array:
    """[num_sectors] clipped minimum of each sector's ray depths [R] (inf = no return)."""
    per_sector = depths.reshape(cfg.num_sectors, cfg.rays_per_sector)
    return jnp.clip(per_sector.min(axis=1), cfg.range_min, cfg.range_max)


def observe(m, d, params, key, cfg: SensorConfig, robot: RobotSpec, robot_body: int) -> jax.Array:
    """[num_sectors] float32 observation with the episode's noise std and dropout rate."""
    depths = ray_depths(m, d, cfg, robot, robot_body)
    k_noise, k_drop = jax.random.split(key)
    depths = depths + params.noise_std * jax.random.normal(k_noise, depths.shape)
    dropped = jax.random.bernoulli(k_drop, params.dropout, depths.shape)
    return sector_minima(jnp.where(dropped, jnp.inf, depths), cfg).astype(jnp.float32)
