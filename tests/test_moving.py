"""Moving obstacles: layout motions and the sampler's movers move, are seen, collide, keep off the
robot's spawn and the goal, and change without recompiling."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, traced_once

import jaxnav
from jaxnav.core import motion
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import FIDELITY, RandomizeConfig, make_bank
from jaxnav.io.layouts import (
    Box,
    Cylinder,
    LayoutError,
    Motion,
    RoomLayout,
    layout_to_dict,
    parse_layouts,
)

DT = 0.1  # s, the control period


def _room(*obstacles, size=(6.0, 4.0), **kw) -> RoomLayout:
    return RoomLayout(name="m", size=size, robot_pos=(-2.5, -1.5), obstacles=obstacles, **kw)


def _bank_params(layout: RoomLayout):
    """The layout's SceneParams as `sample` starts them (one room, no batch axis)."""
    bank = make_bank([layout], 2, 2)
    return jax.tree_util.tree_map(lambda x: x[0], bank.rooms)


def test_velocity_mover_moves_v_dt_and_reflects_at_walls():
    # A cylinder of radius 0.2 at x = 2.5 heading east at 0.4 m/s: the wall at x = 3 stops its
    # centre at 2.8, so after 1 s it has gone 0.3 m out and 0.1 m back (mirrored at 2.8).
    layout = _room(Cylinder(pos=(2.5, 0.0), radius=0.2, motion=Motion(velocity=(0.4, 0.1))))
    params = _bank_params(layout)
    advance = jax.jit(motion.advance, static_argnums=1)
    one = advance(params, DT)
    np.testing.assert_allclose(one.cyl_pos[0], [2.54, 0.01], atol=1e-6)
    params = one
    for _ in range(9):
        params = advance(params, DT)
    np.testing.assert_allclose(params.cyl_pos[0], [2.8 - 0.1, 0.1], atol=1e-5)
    np.testing.assert_allclose(params.motion.velocity[2], [-0.4, 0.1], atol=1e-6)  # slot nb + 0
    np.testing.assert_array_equal(params.box_pos, one.box_pos)  # nothing else moved


def test_velocity_mover_bounces_off_an_obstacle():
    # Heading east at a box whose west face is at x = 1: the cylinder (radius 0.2) turns back
    # where its edge would pass the face, and never overlaps the box.
    layout = _room(
        Box(pos=(1.5, 0.0), size=(1.0, 1.0)),
        Cylinder(pos=(0.0, 0.0), radius=0.2, motion=Motion(velocity=(0.5, 0.0))),
    )
    params = _bank_params(layout)
    advance = jax.jit(motion.advance, static_argnums=1)
    xs = []
    for _ in range(40):
        params = advance(params, DT)
        xs.append(float(params.cyl_pos[0, 0]))
    assert max(xs) <= 1.0 - 0.2 + 1e-6 and max(xs) >= 0.75
    assert float(params.motion.velocity[2, 0]) == pytest.approx(-0.5)
    assert xs[-1] < 0.0  # on its way back west


def test_path_mover_goes_back_and_forth():
    # From (0, 0) to (1, 0) to (1, 1) at 0.5 m/s: 2 m out, 2 m back, a 4 s cycle.
    path = Motion(path=((1.0, 0.0), (1.0, 1.0)), speed=0.5)
    layout = _room(Box(pos=(0.0, 0.0), size=(0.2, 0.2), motion=path))
    params = _bank_params(layout)
    advance = jax.jit(motion.advance, static_argnums=1)
    expected = {5: (0.25, 0.0), 20: (1.0, 0.0), 30: (1.0, 0.5), 40: (1.0, 1.0), 50: (1.0, 0.5)}
    expected |= {70: (0.5, 0.0), 80: (0.0, 0.0), 90: (0.5, 0.0)}
    for k in range(1, 91):
        params = advance(params, DT)
        if k in expected:
            np.testing.assert_allclose(params.box_pos[0], expected[k], atol=1e-4, err_msg=k)


def test_layout_motion_parsing_round_trip_and_errors():
    room = {
        "room": {"size": [6, 4]},
        "obstacles": [
            {"type": "cylinder", "pos": [-1, 1], "radius": 0.2, "motion": {"velocity": [0.3, 0]}},
            {"type": "box", "pos": [1, 1], "size": [0.4, 0.4], "motion": {"path": [[2, 1]], "speed": 0.4}},
            {"type": "box", "pos": [0, -1], "size": [0.4, 0.4]},
        ],
    }  # fmt: skip
    layout = parse_layouts(room)[0]
    assert layout.obstacles[0].motion == Motion(velocity=(0.3, 0.0))
    assert layout.obstacles[1].motion == Motion(path=((2.0, 1.0),), speed=0.4)
    assert layout.obstacles[2].motion is None
    written = layout_to_dict(layout)
    assert "motion" not in written["obstacles"][2]  # still obstacles are written as before
    assert parse_layouts(written)[0] == layout
    bad = {
        "obstacles[1].motion.speed: must be > 0": {"path": [[2, 1]], "speed": 0},
        "obstacles[1].motion.speed: missing required field": {"path": [[2, 1]]},
        "obstacles[1].motion: must have either": {"speed": 0.3},
        "obstacles[1].motion.velocity: its speed (length) must be > 0": {"velocity": [0, 0]},
        "obstacles[1].motion.velocity: its speed (length) must be > 0 and <= 1": {
            "velocity": [2, 0]
        },
        "obstacles[1].motion.path: must be a list of 1 to 8": {"path": [[2, 1]] * 9, "speed": 1},
        "obstacles[1].motion.path[1]: box at [3.0, 0.0] reaches 0.200 m beyond the east": {
            "path": [[2, 1], [3, 0]],
            "speed": 1,
        },
        "obstacles[1].motion.velocty: unknown key; did you mean 'velocity'": {"velocty": [1, 0]},
    }
    for message, value in bad.items():
        room["obstacles"][1]["motion"] = value
        with pytest.raises(LayoutError, match="^f.json: room #0: " + re.escape(message)):
            parse_layouts(room, "f.json")


@pytest.fixture(scope="module")
def approach():
    """A robot standing at the origin facing +x and a cylinder (radius 0.2) coming at it from
    x = 3 at 0.5 m/s: per step the observation and whether the episode ended in a collision."""
    mover = Cylinder(pos=(3.0, 0.0), radius=0.2, height=1.0, motion=Motion(velocity=(-0.5, 0.0)))
    layout = RoomLayout(name="approach", size=(8.0, 3.0), robot_pos=(0.0, 0.0), obstacles=(mover,))
    env = jaxnav.make_env("avoid", layouts=[layout], randomize=EXACT, actions="continuous")
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))

    def body(state, _):
        state = env.step(state, jnp.zeros(2))  # stand still
        return state, (state.obs, state.done, state.metrics["collision"], state.data.qpos[:2])

    _, out = jax.jit(lambda s: jax.lax.scan(body, s, None, 60))(state)
    return env, state, jax.device_get(out)


def test_sensor_sees_an_approaching_mover(approach):
    env, start, (obs, _, _, _) = approach
    # The central sectors read the cylinder's front as camera depth: centre - radius - the
    # camera's offset (0.05 m behind the robot's centre), within the ray spacing's curvature.
    front = np.asarray(start.obs)[3:5].min()
    assert front == pytest.approx(3.0 - 0.2 + 0.05, abs=0.01)
    for k in (5, 20, 35):  # after k + 1 steps
        expected = 3.0 - 0.05 * (k + 1) - 0.2 + 0.05
        assert obs[k, 3:5].min() == pytest.approx(expected, abs=0.01)
    assert (obs[:40, 0] == obs[0, 0]).all()  # the rightmost sector sees the wall only


def test_a_mover_driving_into_the_robot_ends_the_episode(approach):
    env, _, (_, done, collision, xy) = approach
    # Contact when the gap centre - radius - bumper radius closes: 3 - 0.05 k - 0.2 < 0.177.
    first = int(np.ceil((3.0 - 0.2 - env.scene.bumper_radius) / 0.05))
    hit = int(np.argmax(done)) + 1  # steps run
    assert collision[hit - 1] == 1 and hit in (first, first + 1)
    assert np.abs(xy[: hit - 1]).max() < 1e-6  # the robot stood still until the contact


@pytest.mark.slow
def test_goal_task_movers_keep_clear_and_change_without_recompiling():
    """Goal-task movers start clear of the spawn and goal and change per episode without
    recompiling. Slow: the goal env with movers compiles for this test alone."""
    cfg = RandomizeConfig(sampled_room_prob=1.0, moving_count=(1, 3), **FIDELITY)
    env = jaxnav.make_env("goal", layouts=[], randomize=cfg)
    reset, step = traced_once(env)
    reset_b, step_b = jax.jit(jax.vmap(reset)), jax.jit(jax.vmap(step))
    actions = jnp.zeros(64, jnp.int32)
    for seed in (0, 1):  # new rooms, movers and goals: nothing is traced again
        states = reset_b(jax.random.split(jax.random.PRNGKey(seed), 64))
        start = jax.device_get(states.info["params"])
        for _ in range(2):
            states = step_b(states, actions)
    p, movers = start, slice(-3, None)  # the reserved cylinder slots
    on, r = p.cyl_active[:, movers], p.cyl_radius[:, movers]  # [E, 3]
    speed = np.linalg.norm(p.motion.velocity[:, movers], axis=-1)
    assert 0.4 < on.mean() < 0.9  # 1-3 movers of 3 slots (a crowded room may fit fewer)
    assert ((speed[on] >= 0.2 - 1e-6) & (speed[on] <= 0.5 + 1e-6)).all() and (speed[~on] == 0).all()
    # At least moving_clearance from the robot's edge, off the goal, clear of everything else.
    centre = p.cyl_pos[:, movers]  # [E, 3, 2]
    gap = np.linalg.norm(centre - p.spawn[:, None, :2], axis=-1) - r - env.robot.radius
    assert gap[on].min() >= cfg.moving_clearance
    goal = np.asarray(states.info["goal"])[:, None]
    assert (np.linalg.norm(centre - goal, axis=-1) - r)[on].min() > env.robot.radius
    static = p.cyl_active.copy()
    static[:, movers] = False
    clear = np.asarray(jax.jit(jax.vmap(signed_distance))(p.replace(cyl_active=static), centre))
    assert (clear[on] > r[on]).all()
    # Two steps later each has moved 2 v dt (less where it bounced and waited).
    after = np.asarray(states.info["params"].cyl_pos)[:, movers]
    moved = np.linalg.norm(after - centre, axis=-1)
    assert np.median(moved[on] / (2 * DT * speed[on])) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.slow
def test_movers_that_cannot_be_placed_change_nothing():
    """Slow: two rollout programs (with and without the mover machinery) compile."""
    # The mover machinery on (a reserved slot, a motion state, advance every step) with no mover
    # placed (moving_clearance beyond any room): the rollout is the static one, to float32
    # round-off (the two programs differ, so XLA may fuse them differently). Over a minute here.
    base = RandomizeConfig(sampled_room_prob=1.0, **{**FIDELITY, "dark_prob": 0.0})
    none = dataclasses.replace(base, moving_count=(1, 1), moving_clearance=100.0)
    keys = jax.random.split(jax.random.PRNGKey(3), 8)
    runs = []
    for cfg in (base, none):
        env = jaxnav.make_env("avoid", layouts=[], randomize=cfg)

        def rollout(keys, env=env):
            state = jax.vmap(env.reset)(keys)
            body = lambda s, a: (jax.vmap(env.step)(s, a), (s.obs, s.data.qpos, s.reward))  # noqa: E731
            actions = jax.random.randint(jax.random.PRNGKey(0), (10, 8), 0, 3)
            return jax.lax.scan(body, state, actions)[1]

        runs.append(jax.device_get(jax.jit(rollout)(keys)))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_pictures_draw_the_movers(tmp_path):
    from matplotlib.figure import Figure

    from jaxnav.viz.plots import draw_movers, plot_trajectories

    layout = _room(
        Cylinder(pos=(1.0, 0.0), radius=0.25, motion=Motion(velocity=(0.0, 0.4))),
        Box(pos=(-2.0, 1.5), size=(0.6, 0.4), motion=Motion(path=((2.0, 1.5),), speed=0.3)),
        Box(pos=(0.0, -1.0), size=(0.5, 0.5)),
    )
    ax = Figure().add_subplot()
    assert draw_movers(ax, _bank_params(layout))
    outlines = [p for p in ax.patches if p.get_linestyle() == "--"]
    assert len(outlines) == 2  # the two movers, not the still box
    assert len(ax.lines) == 1  # the path (the arrow is a patch)
    assert not draw_movers(Figure().add_subplot(), _bank_params(_room(Box((0, 0), (1, 1)))))
    plot_trajectories(layout, [], [], tmp_path / "m.png", movers=_bank_params(layout))
    assert (tmp_path / "m.png").stat().st_size > 0
