"""The wheeled validation model (`SceneConfig(physics="wheeled")`): it tracks the commanded speeds
on its wheels, stays upright on the floor, collides like the fast model and never recompiles.

Slow, all of it: the wheeled model's MJX program (contacts, the constraint solver) and an
`evaluate --physics wheeled` process compile for these tests alone.
"""

import json
import os
import subprocess
import sys
from subprocess import PIPE

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, corridor, start_in, traced_once

import jaxnav
from jaxnav.cli import Parser
from jaxnav.core.scene import SceneConfig
from jaxnav.io.layouts import Box, RoomLayout
from jaxnav.runconfig import add_flags, overrides_from_args

WHEELED = SceneConfig(physics="wheeled")
BOX_FACE = 2.8  # x of the box's near face in ROOM
ROOM = corridor(Box(pos=(3.0, 0.0), size=(0.4, 0.8)))
OPEN = RoomLayout(name="open", size=(6.0, 6.0), robot_pos=(0.0, 0.0), robot_yaw=0.0)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", autouse=True)
def cli_run(tmp_path_factory):
    """`evaluate --physics wheeled`, started first so that its compile overlaps the tests'."""
    out = tmp_path_factory.mktemp("wheeled") / "out.json"
    args = ("--policy", "forward", "--physics", "wheeled", "--episodes", "2", "--steps", "10")
    env = {**os.environ, "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", "jaxnav.evaluate", *args, "--json", str(out)]
    proc = subprocess.Popen(cmd, cwd=out.parent, env=env, text=True, stdout=PIPE, stderr=PIPE)
    yield proc, out
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def wheeled():
    """The wheeled env in ROOM and OPEN, its reset and step each allowed one trace."""
    env = jaxnav.make_env("avoid", [ROOM, OPEN], randomize=EXACT, scene=WHEELED, max_steps=100)

    return env, *traced_once(env)


def drive(step, state, action, n):
    """`n` steps of `action`: the state and the [n + 1, nq] positions along the way."""
    qpos = [np.asarray(state.data.qpos)]
    for _ in range(n):
        state = step(state, jnp.int32(action))
        qpos.append(np.asarray(state.data.qpos))
    return state, np.array(qpos)


def with_gain(state, gain):
    """The episode's speed gain (traced data) set to `gain`: commands scale by it."""
    params = state.info["params"].replace(speed_gain=jnp.float32(gain))
    return state.replace(info={**state.info, "params": params})


def assert_upright_on_floor(qpos):
    """z (m), pitch and roll (rad) of the base, qpos[3:6], stay near rest."""
    z, pitch, roll = qpos[:, 3], qpos[:, 4], qpos[:, 5]
    assert np.abs(z).max() < 0.003, "left the floor or sank into it"
    assert np.abs(pitch).max() < 0.05 and np.abs(roll).max() < 0.05, "tipped over"  # 3 deg


@pytest.mark.parametrize("speed", [0.3, 0.5])
def test_tracks_commanded_forward_speed(wheeled, speed):
    env, reset, step = wheeled
    state = with_gain(start_in(env, reset, 1), speed / 0.5)  # forward is 0.5 m/s at gain 1
    state, qpos = drive(step, state, 0, 20)
    # After 1 s of spin-up, the speed over the next second, along the x axis it faces.
    assert (qpos[20, 0] - qpos[10, 0]) / 1.0 == pytest.approx(speed, rel=0.05)
    assert np.abs(qpos[:, 1]).max() < 0.005 and np.abs(qpos[:, 2]).max() < 0.01  # straight
    assert_upright_on_floor(qpos)


@pytest.mark.parametrize("action, yaw_rate", [(1, 1.5), (2, -1.5)])
def test_tracks_commanded_yaw_rate_in_place(wheeled, action, yaw_rate):
    env, reset, step = wheeled
    state, qpos = drive(step, start_in(env, reset, 1), action, 15)
    yaw = np.unwrap(qpos[:, 2])
    assert (yaw[15] - yaw[5]) / 1.0 == pytest.approx(yaw_rate, rel=0.05)
    assert np.linalg.norm(qpos[:, :2], axis=-1).max() < 0.01  # turns in place
    assert_upright_on_floor(qpos)


def test_driving_into_a_box_ends_with_a_collision(wheeled):
    env, reset, step = wheeled
    state = start_in(env, reset, 0)
    for _ in range(80):  # 2.6 m to go at 0.5 m/s: about 53 steps
        state = step(state, jnp.int32(0))
        if bool(state.done):
            break
    assert bool(state.metrics["collision"]) and float(state.reward) == -100.0
    x = float(state.data.qpos[0])  # stopped at the box by the analytic test, as the fast model
    assert x == pytest.approx(BOX_FACE - jaxnav.core.robot.TURTLEBOT2I.radius, abs=0.06)


def test_episodes_reuse_the_compiled_step(wheeled):
    env, reset, step = wheeled
    rooms = set()
    for seed in range(6):  # chex fails the step or reset if either traces again
        state = reset(jax.random.PRNGKey(seed))
        rooms.add(int(state.info["params"].layout_id))
        state = step(with_gain(state, 0.8 + 0.1 * (seed % 3)), jnp.int32(seed % 3))
    assert rooms == {0, 1}


def test_sensor_reads_the_same_pose_in_both_physics(wheeled):
    env, reset, _ = wheeled
    fast = jaxnav.make_env("avoid", [ROOM, OPEN], randomize=EXACT, max_steps=100)
    key = jax.random.PRNGKey(0)
    a, b = reset(key), jax.jit(fast.reset)(key)
    np.testing.assert_array_equal(np.asarray(a.data.qpos[:3]), np.asarray(b.data.qpos))
    np.testing.assert_allclose(np.asarray(a.obs), np.asarray(b.obs), atol=1e-5)


def test_physics_flags():
    parser = Parser()
    add_flags(parser)
    for flag in ("--physics", "--scene.physics"):
        overrides = overrides_from_args(parser.parse_args([flag, "wheeled"]))
        assert overrides["scene"] == {"physics": "wheeled"}
    with pytest.raises(ValueError, match="SceneConfig.physics"):
        SceneConfig(physics="legs")


def test_evaluate_cli_accepts_physics_wheeled(cli_run):
    proc, out = cli_run
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    data = json.loads(out.read_text())
    assert data["physics"] == "wheeled"
    assert data["overall"]["episodes"] == 2 and 0 < data["overall"]["mean_speed"] < 0.7
    assert "collision-free" in stdout
