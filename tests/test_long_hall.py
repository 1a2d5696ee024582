"""The `long_hall` family: halls and open floors beyond the camera's 8 m, passable end to end,
drawn by name only (not by 'all'); the goal task's traced grid grows to cover them, laid along
each hall whichever its direction."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnav
from jaxnav.core import families, goals
from jaxnav.core.assets import scenes_dir
from jaxnav.core.randomize import LARGE_FAMILIES, RandomizeConfig, family_weights
from jaxnav.io.layouts import Box, RoomLayout, load_layout

RADIUS = 0.177


@pytest.fixture(scope="module")
def halls():
    """32 `long_hall` rooms, drawn in one compiled call."""
    keys = jax.random.split(jax.random.PRNGKey(0), 32)
    draw = jax.jit(jax.vmap(lambda k: families.long_hall(k, 16, 4, RADIUS)))
    batch = jax.device_get(draw(keys))
    return [jax.tree_util.tree_map(lambda x, i=i: x[i], batch) for i in range(32)]


def test_halls_reach_beyond_the_camera(halls):
    size = np.array([2 * np.asarray(h.room_half) for h in halls])  # [32, 2]
    length, width = size.max(-1), size.min(-1)
    assert (length >= 8.0 - 1e-4).all() and (length <= 30.0 + 1e-4).all()
    assert (width >= families.MIN_CORRIDOR - 1e-4).all() and (width <= 12.0 + 1e-4).all()
    assert (length > 16.0).mean() > 0.4  # most halls hold more than two camera ranges
    assert ((width > 4.0) & (width < 6.0)).sum() == 0  # halls to 4 m, open floors from 6 m


def test_halls_are_passable_end_to_end(halls):
    """The free space the robot reaches from its spawn spans the hall's whole length."""
    for i, hall in enumerate(halls[:8]):
        layout = families.to_layout(hall, f"hall-{i}")  # validates the spawn and the walls
        reach, centres = families.reachable(layout)
        axis = int(np.argmax(layout.size))
        span = centres[..., axis][reach]
        assert span.max() - span.min() >= layout.size[axis] - 2 * RADIUS - 0.3, layout.size


def test_long_hall_is_drawn_by_name_only():
    assert "long_hall" not in family_weights("all")
    assert family_weights("random:3,long_hall:1")["long_hall"] == pytest.approx(0.25)
    assert set(LARGE_FAMILIES) == set(families.LARGE_EXTENTS)  # the goal grid covers each


@pytest.mark.slow
def test_goal_task_draws_goals_down_long_halls():
    """With `long_hall` in the mix the goal grid covers 30 x 12 m, laid along each hall: goals
    beyond 10.8 m occur, and the flood from each goal reaches its spawn along the hall. Slow: it
    compiles a goal env's reset."""
    mix = RandomizeConfig(sampled_room_prob=1.0, families="long_hall")
    env = jaxnav.make_env("goal", randomize=mix)
    assert env._grid_extent == families.LARGE_EXTENTS["long_hall"] == (15.0, 6.0)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), 32))
    field, goal, params = states.info["field"], states.info["goal"], states.info["params"]
    assert field.shape == (32, 60, 150)
    spawn = states.data.qpos[:, :2]
    straight = np.linalg.norm(np.asarray(goal - spawn), axis=-1)
    to_go = jax.vmap(lambda f, g, x, h: goals.geodesic(f, g, x, jnp.inf, h))
    geo = np.asarray(to_go(field, goal, spawn, params.room_half))
    along_y = np.asarray(params.room_half[:, 1] > params.room_half[:, 0])
    assert 0 < along_y.mean() < 1  # halls of both directions
    assert straight.max() > 12.0  # beyond the square grid of the other families
    assert np.isfinite(geo).all() and (geo >= straight - goals.GRID_CELL).all()
    assert np.median(geo / straight) < 1.1  # along the hall, not round it


def _hall(transposed: bool) -> RoomLayout:
    """A 20 x 2 m hall with a cabinet, spawn at one end and the goal at the other."""
    t = (lambda xy: (xy[1], xy[0])) if transposed else (lambda xy: xy)
    cabinet = Box(pos=t((0.0, 0.7)), size=t((1.0, 0.6)), height=0.8)
    return RoomLayout(
        name=f"hall-{int(transposed)}",
        size=t((20.0, 2.0)),
        robot_pos=t((-9.0, 0.0)),
        goal_pos=t((9.0, -0.3)),
        obstacles=(cabinet,),
    )


@pytest.mark.slow
def test_a_hall_and_its_transpose_have_one_geodesic():
    """The grid lies on a hall along y transposed: the distance to go from the spawn is the
    same in a hall and in the hall turned a quarter, and about the 18 m between the ends; drawn
    as sampled rooms, neither spawn is taken for one the flood missed (and moved). Slow: it
    compiles a goal env's reset."""
    halls = [_hall(False), _hall(True)]
    env = jaxnav.make_env("goal", layouts=halls)
    assert env._grid_extent == (10.0, goals.GRID_HALF)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 8))
    ids = np.asarray(states.info["params"].layout_id)
    assert set(ids) == {0, 1}
    info = states.info
    to_go = jax.vmap(lambda f, g, x, h: goals.geodesic(f, g, x, None, h))
    geo = np.asarray(
        to_go(info["field"], info["goal"], states.data.qpos[:, :2], info["params"].room_half)
    )
    assert np.ptp(geo) < 1e-4 and np.hypot(18.0, 0.3) <= geo[0] < 18.6
    sampled = env.bank.rooms.replace(layout_id=jnp.array([-1, -1]))
    draw = lambda k, p: goals.sample_goal(
        k, p, env._grid_extent, env.bank.goals, RADIUS, 0.3, 1.5, 0.15
    )  # noqa: E731
    rooms, _, _ = jax.vmap(draw)(jax.random.split(jax.random.PRNGKey(1), 2), sampled)
    np.testing.assert_array_equal(rooms.spawn, sampled.spawn)


def test_the_25m_hall_layout_loads():
    (hall,) = load_layout(scenes_dir() / "halls" / "hall_25m.json")
    assert hall.size == (25.0, 2.4) and hall.robot_pos == (-11.5, 0.0)
    assert hall.goal_pos == (8.5, 0.0)  # the goal task's goal 20 m down the hall
