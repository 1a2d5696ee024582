"""The drive and the contacts: no sideways sliding, commanded speeds reached, no tunnelling."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, KOBUKI, corridor, start_in

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


@pytest.mark.slow
def test_velocity_smoother_and_latency():
    """From rest, speed ramps at the smoother's 0.3 m/s^2 after `latency` steps of delay, and
    braking from 0.5 m/s takes about 1.7 s. Slow: two envs (with and without latency) compile."""
    # Without latency (the Kobuki's own pipeline) both checks share one env: the board's room is
    # layout 0, a room clear for 3.5 m ahead is layout 1.
    clear = corridor(Box(pos=(3.8, 0.0), size=(0.1, 0.1)), size=(8.0, 3.0))
    kobuki = jaxnav.make_env("avoid", [BOARD, clear], randomize=KOBUKI, max_steps=200)
    kobuki_jitted = jax.jit(kobuki.reset), jax.jit(kobuki.step)
    for latency in (0, 2):
        if latency == 0:
            env, (reset, step) = kobuki, kobuki_jitted
        else:
            cfg = dataclasses.replace(KOBUKI, latency_steps=(latency, latency))
            env = jaxnav.make_env("avoid", [BOARD], randomize=cfg, max_steps=100)
            reset, step = jax.jit(env.reset), jax.jit(env.step)
        state = start_in(env, reset, 0)
        speeds = []
        for _ in range(6):
            state = step(state, jnp.int32(0))
            speeds.append(body_velocity(state)[0])
        expected = [0.03 * max(0, k + 1 - latency) for k in range(6)]  # 0.3 m/s^2 x 0.1 s
        np.testing.assert_allclose(speeds, expected, atol=2e-3)
    env, (reset, step) = kobuki, kobuki_jitted
    state = start_in(env, reset, 1)
    for _ in range(20):  # up to 0.5 m/s
        state = step(state, jnp.int32(0))
    assert body_velocity(state)[0] == pytest.approx(0.5, abs=0.01)
    path, turns = 0.0, 0
    while body_velocity(state)[0] > 1e-3:  # "turn" commands zero forward speed: the base brakes
        before = np.asarray(state.data.qpos[:2])
        state = step(state, jnp.int32(1))
        path += float(np.linalg.norm(np.asarray(state.data.qpos[:2]) - before))
        turns += 1
    assert turns == pytest.approx(17, abs=1)  # 0.5 m/s / 0.3 m/s^2 = 1.7 s
    assert path == pytest.approx(0.5**2 / (2 * 0.3), abs=0.05)  # about the whole blind zone


def test_wheel_asymmetry_curves_a_straight_command():
    cfg = dataclasses.replace(EXACT, wheel_asymmetry=(0.05, 0.05))
    env = jaxnav.make_env("avoid", [BOARD], randomize=cfg)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    state = jax.jit(env.step)(state, jnp.int32(0))
    gain = np.asarray(state.info["params"].wheel_gain)
    assert abs(gain[1] - gain[0]) == pytest.approx(0.05, abs=1e-6)
    yaw_rate = (gain[1] - gain[0]) * 0.5 / TURTLEBOT2I.wheelbase  # forward 0.5 m/s
    assert float(state.data.qvel[2]) == pytest.approx(yaw_rate, rel=0.02)


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


def _products(jaxpr) -> list:
    """The precision of every matrix product in `jaxpr` (a Jaxpr), inner programs included."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for value in eqn.params.values():
            for inner in value if isinstance(value, (list, tuple)) else [value]:
                if isinstance(inner, (jax.extend.core.ClosedJaxpr, jax.extend.core.Jaxpr)):
                    found += _products(getattr(inner, "jaxpr", inner))
    return found


def test_the_simulation_s_matrix_products_are_float32():
    """MuJoCo's step and the room draws compute their matrix products in float32, also where
    JAX's default would not: on a GPU it rounds their inputs to TF32 (10 bits of mantissa), and
    the same wheeled physics then differed between two programs by 4e-4 within 30 steps. Every
    product of the env's step and reset asks for the highest precision."""
    env = jaxnav.make_env("goal")  # its reset draws the room families, tables and chairs too
    reset, state = jax.make_jaxpr(env.reset, return_shape=True)(jax.random.PRNGKey(0))
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    step = _products(jax.make_jaxpr(env.step)(state, jnp.int32(0)).jaxpr)  # traced, not compiled
    reset = _products(reset.jaxpr)
    assert len(step) > 10 and reset  # MuJoCo's step has products, and the tables' chairs
    assert set(step + reset) == {highest}
