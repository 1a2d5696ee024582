"""The `long_hall` family: halls and open floors beyond the camera's 8 m, passable end to end,
drawn by name only (not by 'all'), and refused by the goal task, whose grid covers 10.5 m."""

import jax
import numpy as np
import pytest

import jaxnav
from jaxnav.core import families
from jaxnav.core.assets import scenes_dir
from jaxnav.core.randomize import RandomizeConfig, family_weights
from jaxnav.io.layouts import load_layout

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
    with pytest.raises(ValueError, match="RandomizeConfig.families: long_hall rooms are larger"):
        jaxnav.make_env("goal", randomize=RandomizeConfig(families="long_hall"))


def test_the_25m_hall_layout_loads():
    (hall,) = load_layout(scenes_dir() / "halls" / "hall_25m.json")
    assert hall.size == (25.0, 2.4) and hall.robot_pos == (-11.5, 0.0)
