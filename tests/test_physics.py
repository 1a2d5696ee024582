"""The drive and the contacts: no sideways sliding, commanded speeds reached, no tunnelling."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, corridor

import jaxnav
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.core.scene import SceneConfig
from jaxnav.io.layouts import Box

BOARD = corridor(Box(pos=(1.5, 0.0), size=(0.05, 1.0)))  # a 5 cm thin board 1.5 m ahead


@pytest.fixture(scope="module")
def fast_env():
    """The robot at its top speeds in front of the board."""
    return jaxnav.make_env(
        "avoid",
        [BOARD],
        randomize=EXACT,
        forward_speed=TURTLEBOT2I.max_linear_speed,
        turn_rate=TURTLEBOT2I.max_angular_speed,
    )


def body_velocity(state):
    """(forward, sideways) velocity in the robot frame, m/s."""
    yaw = state.data.qpos[2]
    vx, vy = state.data.qvel[0], state.data.qvel[1]
    return (
        float(jnp.cos(yaw) * vx + jnp.sin(yaw) * vy),
        float(-jnp.sin(yaw) * vx + jnp.cos(yaw) * vy),
    )


def test_speeds_reached_without_sideways_sliding(fast_env):
    reset, step = jax.jit(fast_env.reset), jax.jit(fast_env.step)
    state = reset(jax.random.PRNGKey(0))
    state = step(state, jnp.int32(1))  # turn left in place
    assert float(state.data.qvel[2]) == pytest.approx(TURTLEBOT2I.max_angular_speed, rel=0.02)
    assert float(jnp.linalg.norm(state.data.qvel[:2])) < 1e-3
    state = step(state, jnp.int32(0))  # then forward along the new heading
    forward, sideways = body_velocity(state)
    assert forward == pytest.approx(TURTLEBOT2I.max_linear_speed, rel=0.02)
    assert abs(sideways) < 1e-3


@pytest.mark.parametrize("substeps", [1, 2])
def test_no_tunnelling_at_top_speed(substeps):
    scene = dataclasses.replace(SceneConfig(), timestep=0.1 / substeps, substeps=substeps)
    env = jaxnav.make_env(
        "avoid",
        [BOARD],
        randomize=EXACT,
        forward_speed=TURTLEBOT2I.max_linear_speed,
        scene=scene,
    )
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = reset(jax.random.PRNGKey(0))
    xs = []
    for _ in range(40):
        state = step(state, jnp.int32(0))
        xs.append(float(state.data.qpos[0]))
        if bool(state.done):
            break
    assert bool(state.metrics["collision"]), "drove through the board"
    face = 1.5 - 0.025
    assert max(xs) < face  # the centre never passes the board's near face
    assert max(xs) == pytest.approx(face - TURTLEBOT2I.radius, abs=0.08)


def test_speed_limits_are_the_robot_s():
    with pytest.raises(ValueError, match="forward_speed"):
        jaxnav.make_env("avoid", forward_speed=TURTLEBOT2I.max_linear_speed + 0.1)
    with pytest.raises(ValueError, match="turn_rate"):
        jaxnav.make_env("avoid", turn_rate=4.0)
    assert np.isclose(TURTLEBOT2I.radius * 2, 0.354) and jaxnav.make_env("avoid").scene.mass == 2.35
