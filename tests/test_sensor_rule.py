"""The simulator reduces a sector's readings by the robot side's rule (`sector_nearest`): a few
stray near readings are outvoted where a sector has many readings, and with the default rays
(fewer than `readings_per_stray` a sector) the rule is the plain minimum, bit for bit."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxnav.core.sensors import SensorConfig, reduce_sectors
from jaxnav.robot_side.observation import sector_nearest


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
