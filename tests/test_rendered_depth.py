"""An independent check of the simulated depth camera: MuJoCo's own renderer draws depth images of
the same rooms from the same camera pose, the robot side turns them into sectors as it would the
Orbbec Astra's images, and the result must be the simulator's observation.

The simulator casts analytic rays (`jaxnav.core.sensors`); the renderer rasterises the scene's
geoms (`jaxnav.viz.render.episode_model`) with OpenGL. The camera is placed here from the robot's
pose and the `RobotSpec` mount (with the episode's mount error), not from the simulator's code;
the rendered metric depth (distance along the optical axis) is zeroed below range_min and above
range_max, as the Astra reports it; and the robot side reads the pixels nearest the simulator's
rays (`ray_pixels`), leaves out the floor (`floor_mask`) and reduces (`rays_to_sectors`).

Tolerance: for each ray the robot side reads the nearest pixel, within half a pixel per axis
(0.055 deg: 640 x 480 over 49.5 deg is a focal length of 520 px). On a surface at depth z seen at
incidence a that moves the reading by about z * 0.00096 * tan(a): 2 mm at 2 m facing the camera,
8 mm at 3 m and 60 deg, 3 cm at 8 m and 75 deg; the depth buffer and the capsules' tessellation add
under a millimetre. A sector's value is the minimum over its rays and moves no more than they do:
sectors agree to TOL = 3 cm, at least 95 % of them (measured: median 0.2 mm, 90 % within 2 mm).
A sector may differ by more where a ray grazes an edge (the ray and the pixel half a pixel away see
different surfaces) or meets a horizontal surface edge-on (a shelf's underside near the camera's
height: tan(a) ~ 20); every sector must then read what the simulator reads with its camera turned
by at most one pixel (`SHIFTS`), which bounds the pixel's ray. A wrong camera pose, blind-zone
rule or floor rule on either side fails these tests.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import EXACT, corridor

import jaxnav
from jaxnav.core.geometry import signed_distance
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.core.sensors import SensorConfig, observe
from jaxnav.io.layouts import Box, RoomLayout
from jaxnav.robot_side.observation import Sensor, floor_mask, ray_pixels, rays_to_sectors
from jaxnav.viz import render

WIDTH, HEIGHT = 640, 480  # the Astra's depth image
VFOV = math.radians(49.5)  # its vertical field of view: 63.3 deg across, wider than the 60 deg used
SCENES = 40  # sampled rooms, half of them with an obstacle in the blind zone
PIXEL = 2 * math.tan(VFOV / 2) / HEIGHT  # rad: one pixel's angle at the image centre
TOL = 0.03  # m; see the module docstring
# The camera turned by up to one pixel (pitch, yaw): the rays of a pixel's neighbourhood.
SHIFTS = [(0.0, 0.0)] + [(a * PIXEL, b * PIXEL) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
# A horizontal fan; far_invalid: beyond 8 m reads 0.
ONE_ROW = SensorConfig(rows=1, far_invalid=True)
FIVE_ROWS = SensorConfig(rows=5, far_invalid=True)
# Sampled rooms with low obstacles and overhangs, the camera mount off by its full error range;
# no noise, dropout or dark obstacles (the renderer has none).
ROOMS = dataclasses.replace(
    EXACT,
    sampled_room_prob=0.8,
    low_prob=0.3,
    overhang_prob=0.15,
    camera_height_error=0.02,
    camera_pitch_error=0.052,
    camera_yaw_error=0.035,
)
LOW_BOX = corridor(Box(pos=(1.5, 0.0), size=(0.3, 1.0), height=0.1))  # face 1.35 m ahead
BLIND_WALL = RoomLayout(
    name="blind", size=(3.0, 3.0), robot_pos=(0.0, 0.0), robot_yaw=0.0,
    obstacles=(Box(pos=(0.5, 0.0), size=(0.2, 2.0)),),  # face 0.4 m ahead: inside 0.6 m
)  # fmt: skip


def _place_near_obstacle(params, rng):
    """(x, y, yaw) of a base whose camera stands 0.1-0.5 m from an obstacle, looking 17-34 deg
    to one side of its centre, at least 0.2 m from the walls; None if no candidate does."""
    centres = np.concatenate([np.asarray(params.box_pos), np.asarray(params.cyl_pos)])
    active = np.concatenate([np.asarray(params.box_active), np.asarray(params.cyl_active)])
    target = rng.choice(np.flatnonzero(active), 200)
    bearing, reach = rng.uniform(0, 2 * np.pi, 200), rng.uniform(0.2, 1.0, 200)
    cams = centres[target] + reach[:, None] * np.column_stack([np.cos(bearing), np.sin(bearing)])
    gap = np.asarray(signed_distance(params, cams))  # to the nearest obstacle or wall
    inside = (np.asarray(params.room_half) - np.abs(cams)).min(-1)
    fit = np.flatnonzero((gap >= 0.1) & (gap <= 0.5) & (inside >= 0.2))
    if fit.size == 0:
        return None
    i = fit[0]
    # Off to one side: part of the view is blind, the rest is not.
    look = bearing[i] + np.pi + rng.choice([-1, 1]) * rng.uniform(0.3, 0.6)
    yaw = look - float(params.camera[2])  # the camera's yaw error turns the image
    fwd = TURTLEBOT2I.camera_forward
    return np.array([*(cams[i] - fwd * np.array([np.cos(yaw), np.sin(yaw)])), yaw])


@pytest.fixture(scope="module")
def scenes(needs_gl):
    """(env, params [N], data [N], qpos [N, 3], kinds [N]): the two probe rooms, then SCENES
    sampled rooms, every other one with the robot placed by an obstacle (kind "blind")."""
    env = jaxnav.make_env("avoid", [LOW_BOX, BLIND_WALL], randomize=ROOMS, sensor=FIVE_ROWS)
    new_episode = jax.jit(env.new_episode)  # one compile; a vmapped one compiles 3x longer
    rng = np.random.default_rng(0)
    found: dict[str, list] = {"low box": [], "blind wall": [], "room": []}
    for seed in range(4 * SCENES):
        params, data = new_episode(jax.random.PRNGKey(seed))
        kind = ("room", "low box", "blind wall")[int(params.layout_id) + 1]
        found[kind].append((params, data, np.asarray(data.qpos), kind))
        if len(found["room"]) >= SCENES and found["low box"] and found["blind wall"]:
            break
    # The low box with a stated mount error (2 cm low, 1.1 deg down, within ROOMS' ranges): the
    # 5 rows' lowest is below the box's 0.1 m top at its face, 1.35 m ahead; as mounted it passes
    # over the box. The sampled rooms cover the whole error range.
    params, data, qpos, kind = found["low box"][0]
    mount = jnp.array([-0.02, 0.02, 0.0, 0.0, 0.0])  # height m, pitch rad (+ down), yaw, floor rule
    low = (params.replace(camera=mount), data, qpos, kind)
    episodes = [low, found["blind wall"][0]]
    for i, (params, data, qpos, _) in enumerate(found["room"][:SCENES]):
        near = _place_near_obstacle(params, rng) if i % 2 else None
        episodes.append(
            (params, data, qpos, "room") if near is None else (params, data, near, "blind")
        )
    params, data, qpos, kinds = zip(*episodes, strict=True)
    stack = lambda *x: jnp.stack(x)  # noqa: E731
    params, data = jax.tree_util.tree_map(stack, *params), jax.tree_util.tree_map(stack, *data)
    return env, params, data, np.array(qpos, np.float32), list(kinds)


def _simulated(env, cfg, params, data, qpos):
    """[len(SHIFTS), N, num_sectors] noiseless observations of sensor `cfg` at the poses qpos
    [N, 3], with the camera turned by each of `SHIFTS` (pitch, yaw rad; the first: none)."""

    def one(p, d, q, shift):  # the rays need only the room and the pose
        p = p.replace(camera=p.camera.at[1:3].add(shift))
        return observe(p, q, jax.random.PRNGKey(0), cfg, env.robot)

    n, k = len(qpos), len(SHIFTS)
    tile = lambda x: jnp.concatenate([x] * k)  # noqa: E731
    shifts = jnp.repeat(jnp.asarray(SHIFTS, jnp.float32), n, axis=0)
    args = (jax.tree_util.tree_map(tile, params), jax.tree_util.tree_map(tile, data))
    obs = jax.jit(jax.vmap(one))(*args, tile(jnp.asarray(qpos)), shifts)
    return np.asarray(obs).reshape(k, n, -1)


def _camera_quat(pitch: float, yaw: float) -> np.ndarray:
    """MuJoCo camera orientation in the base's frame: looking along +x turned by `yaw` (left +)
    and tilted down by `pitch`; MuJoCo cameras look along their -z with +y up."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    up = np.array([np.sin(pitch) * np.cos(yaw), np.sin(pitch) * np.sin(yaw), np.cos(pitch)])
    right = np.cross(forward, up)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([right, up, -forward]).ravel())
    return quat


def _rendered(env, params, qpos, cfg):
    """[N, H, W] depth images as the Astra reports them (0 outside [range_min, range_max])."""
    robot, scene = env.robot, env.scene
    first = jax.tree_util.tree_map(lambda x: x[0], params)
    model = render.episode_model(scene, first, WIDTH, HEIGHT)
    model.vis.map.znear = 0.01 / model.stat.extent  # nothing is nearer the camera than 0.1 m
    camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "depth")
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0
    option.geomgroup[[1, 2, render.WALL_GROUP]] = 1  # obstacles, floor, walls; not the robot
    data = mujoco.MjData(model)
    images = []
    with mujoco.Renderer(model, HEIGHT, WIDTH) as renderer:
        renderer.enable_depth_rendering()
        for i in range(len(qpos)):
            one = jax.tree_util.tree_map(lambda x, i=i: x[i], params)
            render.set_room(model, scene, one)
            error = np.asarray(one.camera, np.float64)  # height m, pitch rad, yaw rad
            model.cam_pos[camera] = (robot.camera_forward, 0.0, robot.camera_height + error[0])
            model.cam_quat[camera] = _camera_quat(robot.camera_pitch + error[1], error[2])
            model.cam_fovy[camera] = math.degrees(VFOV)
            data.qpos[:] = qpos[i]
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera, option)
            depth = renderer.render().copy()
            depth[(depth < cfg.range_min) | (depth > cfg.range_max)] = 0.0  # the Astra's "none"
            images.append(depth)
    return np.stack(images)


def _robot_side(images, params, cfg, robot):
    """([N, num_sectors] observations, [N] floor pixels) of the images through the robot side,
    at the pixels of the simulator's rays, with each episode's camera mount (a calibrated robot)."""
    obs, floor = [], []
    for image, error in zip(images, np.asarray(params.camera), strict=True):
        sensor = Sensor(
            cfg.fov,
            cfg.num_sectors,
            cfg.range_min,
            cfg.range_max,
            elevations=tuple(cfg.elevations),
            camera_height=robot.camera_height + float(error[0]),
            camera_pitch=robot.camera_pitch + float(error[1]),
            floor_margin=cfg.floor_margin,
            floor_margin_slope=cfg.floor_margin_slope,
        )
        pixels = ray_pixels(sensor, HEIGHT, WIDTH, VFOV, azimuths=cfg.ray_angles)
        obs.append(rays_to_sectors(image, pixels, sensor, cfg.blind_fraction))
        reading = image[pixels.rows, pixels.cols]
        floor.append(floor_mask(reading, reading > 0, pixels.rise, sensor.camera_height, sensor))
    return np.stack(obs), np.array([f.sum() for f in floor])


@pytest.fixture(
    scope="module",
    params=[pytest.param(ONE_ROW, marks=pytest.mark.slow), FIVE_ROWS],
    ids=["one-row", "five-rows"],
)
def observed(request, scenes):
    """The simulator's observations (unshifted, and the least and most over `SHIFTS`), the robot
    side's of the rendered images, and its floor pixels per scene, for one sensor. The one-row
    sensor's cases are slow: its env compiles for this module alone (13 s on 2 cores); the
    quick tier checks the default five-row sensor."""
    cfg = request.param
    env, params, data, qpos, kinds = scenes
    sims = _simulated(env, cfg, params, data, qpos)
    got, floor = _robot_side(_rendered(env, params, qpos, cfg), params, cfg, env.robot)
    return dict(cfg=cfg, sim=sims[0], low=sims.min(0), high=sims.max(0), got=got, floor=floor)


def test_rendered_depth_gives_the_simulated_observation(observed, scenes):
    sim, got, cfg = observed["sim"], observed["got"], observed["cfg"]
    close = np.abs(got - sim) <= TOL
    assert close.mean() >= 0.95, f"{(~close).sum()} of {close.size} sectors differ by > {TOL} m"
    # The rest lie where a ray grazes an edge: the simulator reads the same with its rays
    # turned by up to one pixel.
    within = (got >= observed["low"] - TOL) & (got <= observed["high"] + TOL)
    bad = np.argwhere(~within)
    assert not bad.size, f"sectors (scene, sector) {bad.tolist()}: {got[~within]} vs {sim[~within]}"
    if cfg.rows > 1:  # the floor rule ran on the images: below-horizon rows see floor
        assert (observed["floor"] > 0).mean() > 0.8


def test_blind_zone_reads_near_in_both(observed, scenes):
    sim, got, cfg = observed["sim"], observed["got"], observed["cfg"]
    kinds, near_value = np.array(scenes[-1]), np.float32(cfg.range_min)
    np.testing.assert_array_equal(got[kinds == "blind wall"], near_value)
    np.testing.assert_array_equal(sim[kinds == "blind wall"], near_value)
    near = (sim == near_value)[kinds == "blind"]
    assert near.sum() >= 40  # obstacles inside 0.6 m, in most of the placed scenes
    agree = near == (got == near_value)[kinds == "blind"]
    assert agree.mean() >= 0.97


def test_low_box_is_seen_only_with_rows(observed, scenes):
    kinds, cfg = scenes[-1], observed["cfg"]
    ahead = slice(3, 5)  # the two sectors straight ahead
    for obs in (observed["sim"][kinds.index("low box")], observed["got"][kinds.index("low box")]):
        if cfg.rows == 1:
            assert obs[ahead].min() > 2.0  # the fan at 0.295 m looks over a 0.1 m box
        else:
            np.testing.assert_allclose(obs[ahead], 1.40, atol=0.08)  # face 1.35 m + 0.05 m
