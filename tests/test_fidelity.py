"""Sim-to-real fidelity: a camera with rows sees low obstacles and overhangs, the floor is not an
obstacle, the blind zone reads near and beyond range far exactly as on the robot, and the 2i's
body collides up to its top deck."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, LOW_BOX_HEIGHTS, ONE_ROW_ROOMS, corridor, low_box, start_in

import jaxnav
from jaxnav.core import families
from jaxnav.core.randomize import FIDELITY, RandomizeConfig
from jaxnav.core.robot import RobotSpec
from jaxnav.core.sensors import SensorConfig, camera_readings, ray_readings, sectors
from jaxnav.io.layouts import Box, Cylinder, RoomLayout
from jaxnav.robot_side.observation import (
    RayPixels,
    Sensor,
    floor_mask,
    rays_to_sectors,
    reduce_sectors,
)

CAMERA = SensorConfig(rows=5, far_invalid=True)
SHELF = Box(pos=(1.5, 0.0), size=(0.4, 1.2), bottom=0.4, height=0.6)
HIGH_SHELF = Box(pos=(1.5, 0.0), size=(0.4, 1.2), bottom=0.5, height=0.6)
FLOOR_POLE = Cylinder(pos=(3.5, 1.2), radius=0.05)
NEAR_WALL = Box(pos=(0.55, 0.0), size=(0.2, 2.8))  # face 0.45 m ahead: inside the 0.6 m blind zone
# Every camera probe room of this module in one layout bank: the env compiles once and a test
# starts in its room by its index here.
ROOMS = [corridor(o) for o in (*map(low_box, LOW_BOX_HEIGHTS), SHELF, HIGH_SHELF, FLOOR_POLE)]
ROOMS.append(corridor(NEAR_WALL))


@pytest.fixture(scope="module")
def camera_env():
    """`avoid` with the camera's rows in ROOMS: (env, jitted reset, jitted step)."""
    env = jaxnav.make_env("avoid", ROOMS, randomize=EXACT, sensor=CAMERA)
    return env, jax.jit(env.reset), jax.jit(env.step)


def first_obs(compiled, obstacle, rooms=ROOMS):
    """(env, jitted step, first state, its observation) in the corridor of `obstacle`."""
    env, reset, step = compiled
    state = start_in(env, reset, rooms.index(corridor(obstacle)))
    return env, step, state, np.asarray(state.obs)


@pytest.mark.parametrize("height", LOW_BOX_HEIGHTS)
def test_low_obstacles_are_seen_only_with_rows(one_row_env, camera_env, height):
    box = low_box(height)
    *_, fan = first_obs(one_row_env, box, ONE_ROW_ROOMS)
    *_, camera = first_obs(camera_env, box)
    assert fan[3:5].min() > 2.0  # the horizontal fan at 0.295 m looks over it
    assert camera[3:5].min() == pytest.approx(0.85 + 0.05, abs=0.12)  # camera 0.05 m behind


def test_overhang_is_seen_and_collides(camera_env):
    _, step, state, obs = first_obs(camera_env, SHELF)
    assert obs[3:5].min() < 2.0  # the upper rows see the shelf's underside and face
    for _ in range(30):
        state = step(state, jnp.int32(0))
        if bool(state.done):
            break
    assert bool(state.metrics["collision"])  # the top deck (0.47 m) hits a 0.4 m underside
    assert float(state.data.qpos[0]) < 1.3 - 0.177 + 0.08
    _, step, state, _ = first_obs(camera_env, HIGH_SHELF)
    for _ in range(45):  # 2.25 m at 0.5 m/s: through under the shelf
        state = step(state, jnp.int32(0))
    assert not bool(state.metrics["collision"]) and float(state.data.qpos[0]) > 2.0  # under it


def test_floor_is_not_an_obstacle(camera_env):
    *_, obs = first_obs(camera_env, FLOOR_POLE)
    assert obs.min() > 1.0  # the lowest row meets the floor 0.74 m out: not an obstacle


def test_blind_zone_reads_near(camera_env):
    *_, obs = first_obs(camera_env, NEAR_WALL)
    np.testing.assert_allclose(obs[2:6], 0.6)


def test_simulator_and_robot_reduce_alike():
    """The robot side's floor rule and reduction over the simulator's own rays (unknown -> NaN,
    floor readings left out by the numpy `floor_mask`) give the simulator's observation, in rooms
    with low, near and dark obstacles and camera mount errors."""
    sensor = dataclasses.replace(CAMERA, rays_per_sector=4)
    cfg = RandomizeConfig(sampled_room_prob=1.0, **{**FIDELITY, "sensor_noise": (0.0, 0.0)})
    cfg = dataclasses.replace(cfg, sensor_noise_quadratic=(0.0, 0.0), sensor_dropout=(0.0, 0.0))
    env = jaxnav.make_env("avoid", layouts=[], randomize=cfg, sensor=sensor)
    robot = Sensor(sensor.fov, sensor.num_sectors, sensor.range_min, sensor.range_max)
    columns = np.arange(sensor.num_sectors * sensor.rays_per_sector) // sensor.rays_per_sector

    @jax.jit
    def sim(key):
        state = env.reset(key)
        params = state.info["params"]
        rays = ray_readings(params, state.data.qpos, sensor, env.robot)
        dark = (rays.slot >= 0) & params.dark[jnp.maximum(rays.slot, 0)]
        return state.obs, rays.reading, dark, rays.rise, rays.height

    near_seen = floor_seen = 0
    for seed in range(96):  # a reset reads near (an obstacle inside 0.6 m) in a few in 100
        obs, reading, dark, rise, height = (np.asarray(x) for x in sim(jax.random.PRNGKey(seed)))
        unknown = dark | (reading < sensor.range_min) | (reading > sensor.range_max)
        floor = floor_mask(reading, ~unknown, rise, float(height), robot)
        depth = np.where(unknown, np.nan, reading)
        sector = np.broadcast_to(columns, reading.shape)
        expected = reduce_sectors(depth[~floor], sector[~floor], robot, sensor.blind_fraction)
        np.testing.assert_allclose(obs, expected, rtol=1e-6)
        near_seen += int((obs == sensor.range_min).any())
        floor_seen += int(floor.any())
    assert near_seen >= 3 and floor_seen >= 80  # the blind-zone and floor rules were exercised


def test_fidelity_ranges_are_drawn_per_episode_without_recompiling():
    cfg = RandomizeConfig(**FIDELITY, collision_margin=(0.02, 0.08))
    env = jaxnav.make_env("avoid", layouts=[], randomize=cfg)
    reset = jax.jit(jax.vmap(env.reset))
    params = reset(jax.random.split(jax.random.PRNGKey(0), 256)).info["params"]
    margin = np.asarray(params.margin)
    assert margin.min() >= 0.02 and margin.max() <= 0.08 and margin.std() > 0.01
    # The margin grows the collision test by its size: a robot `gap` m from the nearest surface
    # touches with a margin above the gap, not below it.
    one = jax.tree_util.tree_map(lambda x: x[0], params)
    data = env.place(one)
    gap = float(env.gap(one, data))
    assert gap > 0.05 and not bool(env.touching(one.replace(margin=0.0), data))
    assert bool(env.touching(one.replace(margin=gap + 0.01), data))
    assert not bool(env.touching(one.replace(margin=gap - 0.01), data))
    assert set(np.unique(np.asarray(params.latency)).tolist()) == {0, 1, 2}
    accel = np.asarray(params.accel)
    assert (accel[:, 0] >= 0.25).all() and (accel[:, 0] <= 0.35).all()
    gain = np.asarray(params.wheel_gain)
    assert np.abs(gain[:, 1] - gain[:, 0]).max() <= 0.05 + 1e-6
    assert 0 < np.asarray(params.dark).mean() < 0.2
    low = (np.asarray(params.box_height) <= 0.25) & np.asarray(params.box_active)
    hang = np.asarray(params.box_bottom) > 0
    assert low.any() and hang.any()


HALL_CAMERA = SensorConfig(rows=5, far_invalid=True, far_reads_max=True)


@jax.jit
def _hall_readings(key):
    """The simulator's observation [8] and what its camera returned (`Readings` [5, 24]) at a
    random pose in a `long_hall` room, with depth noise, 2 % dropout and a mount error."""
    k_room, k_pose, k_mount, k_obs = jax.random.split(key, 4)
    room = families.long_hall(k_room, 16, 4, RobotSpec().radius)
    mount = jax.random.uniform(k_mount, (3,), minval=-1.0, maxval=1.0) * jnp.array(
        [0.02, 0.05, 0.03]
    )
    room = room.replace(noise_std=0.01, noise_quad=0.0016, dropout=0.02, camera=mount)
    # Pose: the spawn, heading along the hall to its farther end, +-0.3 rad uniform.
    axis = jnp.argmax(room.room_half)
    along = 0.5 * jnp.pi * axis + jnp.pi * (room.spawn[axis] > 0)
    yaw = along + jax.random.uniform(k_pose, (), minval=-0.3, maxval=0.3)
    qpos = jnp.append(room.spawn[:2], yaw)
    readings = camera_readings(room, qpos, k_obs, HALL_CAMERA, RobotSpec())
    return sectors(readings, HALL_CAMERA), readings


def test_beyond_range_reads_alike_in_the_simulator_and_on_the_robot():
    """In long halls, where sectors are unknown because the wall lies beyond 8 m, the robot
    side (`rays_to_sectors` over the simulator's rays as pixels: unknown -> 0, its own floor and
    far rules) reads every sector as the simulator does, and far sectors read range_max."""
    cfg = HALL_CAMERA
    cols = np.arange(cfg.num_sectors * cfg.rays_per_sector)
    far = near = 0
    for seed in range(16):
        obs, (rays, reading, valid, _) = jax.device_get(_hall_readings(jax.random.PRNGKey(seed)))
        depth = np.where(valid, reading, 0.0)  # the camera's 0: too near, too far, dropped
        pixels = RayPixels(np.indices(depth.shape)[0], cols, cols // cfg.rays_per_sector, rays.rise)
        robot = Sensor(cfg.fov, cfg.num_sectors, cfg.range_min, cfg.range_max, cfg.elevations,
                       float(rays.height), far_reads_max=True)  # fmt: skip
        np.testing.assert_allclose(obs, rays_to_sectors(depth, pixels, robot), rtol=1e-6)
        far += int((obs == cfg.range_max).sum())
        near += int((obs == cfg.range_min).sum())
    assert far >= 32 and near < far  # beyond-range sectors were met, and read far


@pytest.mark.slow
def test_floor_rule_with_a_calibration_error_reads_the_floor_as_the_robot_would():
    """The floor rule uses the true mount off by the episode's calibration error: a floor rule
    2 deg or more less pitched down than the camera (what an uncalibrated, tilted Astra gives the
    robot) reads the open floor as obstacles within 1.5 m, as the robot side does (2 deg: 0.93 m
    in `tests/test_calibrate.py`'s frames); within 0.5 deg the hall reads its walls. Slow: an env of its own (the error range is compiled in)."""
    hall = RoomLayout(name="hall", size=(8.0, 4.0), robot_pos=(-2.0, 0.0), robot_yaw=0.0)
    cfg = dataclasses.replace(EXACT, calibration_pitch_error=np.deg2rad(3.0))
    env = jaxnav.make_env("avoid", layouts=[hall], randomize=cfg, sensor=CAMERA)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 64))
    error = np.rad2deg(np.asarray(states.info["params"].camera[:, 4]))  # [64] deg, down +
    nearest = np.asarray(states.obs).min(-1)  # [64] m
    assert error.min() < -2.0 and np.abs(error).min() < 0.5  # both kinds were drawn
    assert (nearest[error < -2.0] < 1.5).all()
    assert (nearest[np.abs(error) < 0.5] > 2.5).all()
    np.testing.assert_array_equal(np.asarray(states.info["params"].camera[:, :3]), 0.0)
