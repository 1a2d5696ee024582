"""Shared fixtures: environments are compiled once per session and reused."""

import jax
import pytest

import jaxnav
from jaxnav.layouts import Box, Cylinder, RoomLayout
from jaxnav.randomize import RandomizeConfig

# Deterministic physics and sensing: no randomisation of gain, traction or noise.
EXACT = RandomizeConfig(
    sampled_room_prob=0.0,
    random_spawn_prob=0.0,
    friction=(1.0, 1.0),
    speed_gain=(1.0, 1.0),
    sensor_noise=(0.0, 0.0),
    sensor_dropout=(0.0, 0.0),
)


def corridor(obstacle, size=(8.0, 3.0)) -> RoomLayout:
    """A room with the robot at the origin facing +x and one obstacle ahead of it."""
    return RoomLayout(
        name="probe", size=size, robot_pos=(0.0, 0.0), robot_yaw=0.0, obstacles=(obstacle,)
    )


@pytest.fixture(scope="session")
def probe_env():
    """An env whose layout bank holds the probe rooms used by the sensor and collision tests."""
    layouts = [
        corridor(Box(pos=(2.0, 0.0), size=(0.4, 0.8))),  # face at x = 1.8
        corridor(Cylinder(pos=(1.5, 0.0), radius=0.2)),  # surface at x = 1.3
        RoomLayout(name="wall", size=(3.0, 3.0), robot_pos=(0.0, 0.0), robot_yaw=0.0),
    ]
    env = jaxnav.make_env("avoid", layouts=layouts, randomize=EXACT, auto_reset=False)
    return env, jax.jit(env.reset), jax.jit(env.step)


def start_in(env, reset, layout_id):
    """Resets until the bank's layout `layout_id` is drawn (layouts are drawn uniformly)."""
    for seed in range(200):
        state = reset(jax.random.PRNGKey(seed))
        if int(state.params.layout_id) == layout_id:
            return state
    raise AssertionError(f"layout {layout_id} never drawn")
