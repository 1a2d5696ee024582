"""The simulator reduces a sector's readings by the robot side's rule (`sector_nearest`): a few
stray near readings are outvoted where a sector has many readings, and with the default rays
(fewer than `readings_per_stray` a sector) the rule is the plain minimum, bit for bit. Beyond the
camera's range, both sides read a sector by one rule (`far_mask`): far where the floor rays saw
the floor, near where a surface in the blind zone blocked them."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxnav.core.sensors import Rays, Readings, SensorConfig, reduce_sectors, sectors
from jaxnav.robot_side.observation import (
    RayPixels,
    Sensor,
    floor_mask,
    rays_to_sectors,
    sector_nearest,
)


def readings(cfg: SensorConfig, strays: int, seed: int = 0):
    """[rows, sectors * rays] a wall at 5 m, `strays` readings at 0.9 m in sector 0."""
    rng = np.random.default_rng(seed)
    reading = np.full((cfg.rows, cfg.num_sectors * cfg.rays_per_sector), 5.0, np.float32)
    sector0 = rng.choice(cfg.rows * cfg.rays_per_sector, strays, replace=False)
    rows, cols = np.unravel_index(sector0, (cfg.rows, cfg.rays_per_sector))
    reading[rows, cols] = 0.9  # sector 0 is the rightmost columns
    valid, floor = np.ones_like(reading, bool), np.zeros_like(reading, bool)
    return reading, valid, floor


@pytest.mark.parametrize("strays, want", [(1, 5.0), (2, 0.9), (3, 0.9)])
def test_many_rays_outvote_strays_as_the_robot_does(strays, want):
    cfg = dataclasses.replace(SensorConfig(), rays_per_sector=12)  # 60 readings: k = 2
    reading, valid, floor = readings(cfg, strays)
    sim = np.asarray(reduce_sectors(jnp.asarray(reading), valid, floor, cfg))
    robot = sector_nearest(reading[:, :12].reshape(1, -1).astype(np.float64), 50)
    assert sim[0] == pytest.approx(want) and robot[0] == pytest.approx(want)
    assert np.allclose(sim[1:], 5.0)


def test_default_rays_read_the_minimum():
    cfg = SensorConfig()  # 5 rows x 3 rays = 15 < 50 readings a sector
    reading, valid, floor = readings(cfg, 1)
    sim = np.asarray(reduce_sectors(jnp.asarray(reading), valid, floor, cfg))
    off = dataclasses.replace(cfg, readings_per_stray=0)
    assert sim[0] == pytest.approx(0.9)
    np.testing.assert_array_equal(sim, reduce_sectors(jnp.asarray(reading), valid, floor, off))
    with pytest.raises(ValueError, match="readings_per_stray: must be 0"):
        SensorConfig(readings_per_stray=1)


# ------------------------------------------------------------------------------
# Beyond range: the Astra's 0 for no return, told from the blind zone by `far_mask`

FAR = SensorConfig(far_invalid=True, far_reads_max=True)  # the Astra's 5 rows x 24 columns
HEIGHT = 0.295  # m, the camera above the floor (RobotSpec)


def rise(cfg: SensorConfig = FAR) -> np.ndarray:
    """[rows, C] height each ray gains per metre of camera depth (optical axis level)."""
    return np.tan(cfg.elevations)[:, None] / np.cos(cfg.ray_angles)[None, :]


def hall(cfg: SensorConfig = FAR) -> np.ndarray:
    """[rows, C] camera depths in an empty hall whose walls lie beyond range: the rows below the
    horizon read the floor, the others nothing (0)."""
    up = rise(cfg)
    floor = HEIGHT / np.where(up < 0, -up, 1.0)
    return np.where((up < 0) & (floor <= cfg.range_max), floor, 0.0)


def both_sides(depth, cfg: SensorConfig = FAR) -> tuple[np.ndarray, np.ndarray]:
    """(simulator, robot) observations of one frame [rows, C] (0: no reading): the simulator's
    `sectors` and the robot side's `rays_to_sectors`, each rays' own pixel."""
    k = cfg.rays_per_sector
    valid = depth > 0
    up = rise(cfg)
    rays = Rays(jnp.asarray(depth), jnp.full(depth.shape, -1), jnp.asarray(up), jnp.asarray(HEIGHT))
    floor = floor_mask(depth, valid, up, HEIGHT, cfg)
    sim = sectors(Readings(rays, jnp.asarray(depth), jnp.asarray(valid), jnp.asarray(floor)), cfg)
    rows, cols = np.indices(depth.shape)
    pixels = RayPixels(rows, cols[0], cols[0] // k, up)
    sensor = Sensor(cfg.fov, cfg.num_sectors, cfg.range_min, cfg.range_max, cfg.elevations,
                    HEIGHT, far_reads_max=cfg.far_reads_max)  # fmt: skip
    return np.asarray(sim), rays_to_sectors(depth, pixels, sensor, cfg.blind_fraction)


def test_beyond_range_reads_far_and_the_blind_zone_near():
    depth = hall()
    depth[:, 9:15] = 0.0  # sectors 3 and 4: a wall 0.45 m ahead, inside the blind zone
    for cfg, far in ((FAR, 8.0), (dataclasses.replace(FAR, far_reads_max=False), 0.6)):
        sim, robot = both_sides(depth, cfg)
        np.testing.assert_array_equal(sim, robot)
        np.testing.assert_allclose(sim, [far] * 3 + [0.6] * 2 + [far] * 3)


def test_a_dark_obstacle_blocks_the_witness():
    """A surface that returns nothing 2 m ahead hides the floor beyond it (the middle row meets
    the floor at 2.8 m): near, not far."""
    depth = hall()
    blocked = HEIGHT / np.maximum(-rise(), 1e-9) > 2.0  # [rows, C] the floor behind it, and up
    depth[:, :3] = np.where(blocked[:, :3], 0.0, depth[:, :3])
    sim, robot = both_sides(depth)
    assert sim[0] == robot[0] == pytest.approx(0.6) and (sim[1:] == 8.0).all()


def test_a_dropped_pixel_does_not_turn_a_far_sector_near():
    depth = hall()
    depth[0, 0] = depth[1, 4] = 0.0  # dropouts of floor pixels that are not a column's farthest
    depth[2, 7] = 0.0  # and the farthest of one column: its two upper rays stay unknown
    sim, robot = both_sides(depth)
    np.testing.assert_array_equal(sim, robot)
    assert (sim == 8.0).all()


def test_one_row_has_no_witness():
    """A horizontal fan has no floor ray to tell far from the blind zone: unknown reads near."""
    cfg = dataclasses.replace(FAR, rows=1)
    sim, robot = both_sides(np.zeros((1, 24)), cfg)
    assert (sim == 0.6).all() and (robot == 0.6).all()


def test_the_policy_file_carries_the_far_rule(tmp_path):
    from test_robot_side import write_policy_npz

    from jaxnav.robot_side.policy import NumpyPolicy

    old = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "old.npz")).sensor
    new = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "new.npz", far_reads_max=np.int32(1)))
    assert not old.far_reads_max and new.sensor.far_reads_max
