"""`python -m jaxnav.twin`: the robot's control loop in classic MuJoCo, rendered depth, no JAX.

The episodes here are short (a few seconds of robot time) and render small depth images
(160 x 120, the Astra's calibration scaled): each control step renders one frame in software
OpenGL, which is what the twin's time goes to.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip(
    "rosbags", reason="the twin's messages need rosbags (pip install 'jaxnav[ros]')"
)
from test_replay import write_goal_policy_npz  # noqa: E402
from test_robot_side import ROOT, write_policy_npz  # noqa: E402

from jaxnav import twin  # noqa: E402
from jaxnav.cli import twin as twin_cli  # noqa: E402
from jaxnav.core.randomize import FIDELITY, RandomizeConfig  # noqa: E402
from jaxnav.evaluation import METRIC_KEYS  # noqa: E402
from jaxnav.io.layouts import Box, RoomLayout, save_layouts  # noqa: E402
from jaxnav.tasks.base import NavTask  # noqa: E402
from jaxnav.tasks.goal import GoalEnv  # noqa: E402

SMALL = dict(width=160, height=120)  # px; fx = 142.6, the Astra's 570.3 at 640 wide, scaled
ROOM = RoomLayout(
    name="small", size=(5.0, 3.0), robot_pos=(-1.8, 0.0), robot_yaw=0.0,
    obstacles=(Box(pos=(0.2, 0.0), size=(0.3, 0.3)),),  # 2 m ahead: a post, not a wall
)  # fmt: skip


@pytest.fixture
def forward_npz(tmp_path):
    """A policy that always drives forward (0.4 m/s): its first action wins by 10 whatever it
    sees."""
    return write_policy_npz(
        tmp_path / "forward.npz", W1=np.zeros((16, 3), np.float32),
        b1=np.array([10.0, 0.0, 0.0], np.float32),
    )  # fmt: skip


def test_config_is_the_simulators_nominal_robot():
    """The smoother limits are the centre of the simulator's sim-to-real ranges; latency and
    mount error are drawn from the same ranges."""
    cfg = twin.TwinConfig()
    assert cfg.accel_limit == pytest.approx(np.mean(FIDELITY["accel_limit"]))
    assert cfg.angular_accel_limit == pytest.approx(np.mean(FIDELITY["angular_accel_limit"]))
    assert cfg.latency_steps == FIDELITY["latency_steps"]
    for name in ("camera_height_error", "camera_pitch_error", "camera_yaw_error"):
        assert getattr(cfg, name) == pytest.approx(FIDELITY[name], abs=1e-3)
    with pytest.raises(ValueError, match="episodes: must be >= 1"):
        twin.TwinConfig(episodes=0)


def test_smoother_ramps_and_keeps_the_direction():
    step = twin.smoother_step
    np.testing.assert_allclose(step([0, 0], [0.5, 0], (0.3, 3.5), 0.05), [0.015, 0.0])
    np.testing.assert_allclose(step([0.49, 0], [0.5, 0], (0.3, 3.5), 0.05), [0.5, 0.0])
    # Forward to turning: both change by the same share, limited by the linear bound.
    out = step([0.5, 0.0], [0.0, 1.5], (0.3, 3.5), 0.05)
    np.testing.assert_allclose(out, [0.5 - 0.015, 0.045])
    # The simulator's drive: each on its own.
    out = step([0.5, 0.0], [0.0, 1.5], (0.3, 3.5), 0.05, coupled=False)
    np.testing.assert_allclose(out, [0.5 - 0.015, 0.175])


@pytest.mark.parametrize("coupled", [True, False])
def test_simulator_smoother_is_the_twins(coupled):
    """The simulator's smoother over one 0.1 s control period (`NavTask._smoothed`) moves the
    command as the twin's kobuki_velocity_smoother does in its two 20 Hz cycles, by the rule
    `RandomizeConfig.coupled_smoother` picks; a limit of 0 is none in the simulator."""
    cfg = RandomizeConfig(coupled_smoother=coupled)
    env = types.SimpleNamespace(control_period=0.1, randomize=cfg)
    rng = np.random.default_rng(0)
    for _ in range(50):
        last, target = rng.uniform(-0.7, 0.7, 2), rng.uniform(-3.0, 3.0, 2)
        target[0] = rng.choice([target[0], last[0]])  # some with one component unchanged
        accel = rng.uniform([0.1, 1.0], [0.5, 6.0])
        sim = last + np.asarray(NavTask._smoothed(env, jnp.asarray(target - last), accel))
        twice = last
        for _ in range(2):
            twice = twin.smoother_step(twice, target, accel, 0.05, coupled=coupled)
        np.testing.assert_allclose(sim, twice, atol=1e-6)
    free = NavTask._smoothed(env, jnp.asarray([0.4, 2.0]), jnp.asarray([0.0, 3.5]))
    np.testing.assert_allclose(free, [0.4, 0.35] if coupled is False else [0.07, 0.35])


def test_drive_latency_silence_and_driver_timeout():
    """A command reaches the smoother after the latency and ramps; once the node falls silent the
    smoother ramps down; once the smoother stops publishing the driver holds its last command for
    the 0.6 s timeout, then stops the wheels."""
    drive = twin.Drive(latency=0.2, accel=(0.3, 3.5), period=0.05, silence=0.3, timeout=0.6)
    drive.command(0.0, (0.4, 0.0))
    for k in range(4):  # 0, 0.05, 0.1, 0.15 s: still on its way
        drive.cycle(0.05 * k)
        np.testing.assert_array_equal(drive.wheels(0.05 * k), [0.0, 0.0])
    drive.cycle(0.2)
    np.testing.assert_allclose(drive.wheels(0.2), [0.015, 0.0])
    drive.cycle(0.25)
    np.testing.assert_allclose(drive.wheels(0.25), [0.03, 0.0])
    drive.cycle(0.55)  # 0.35 s after the command arrived: silent, the target is zero
    np.testing.assert_allclose(drive.wheels(0.55), [0.015, 0.0])
    drive.cycle(0.6)
    np.testing.assert_allclose(drive.wheels(0.6), [0.0, 0.0])
    # The smoother publishes at every cycle while its input is active; without it (stopped),
    # the driver holds the last command for its timeout.
    drive = twin.Drive(latency=0.0, accel=(10.0, 10.0), period=0.05, silence=0.3, timeout=0.6)
    drive.command(1.0, (0.4, 0.5))
    drive.cycle(1.0)
    np.testing.assert_allclose(drive.wheels(1.5), [0.4, 0.5])
    np.testing.assert_allclose(drive.wheels(1.6), [0.4, 0.5])
    np.testing.assert_array_equal(drive.wheels(1.61), [0.0, 0.0])


def test_forward_into_a_post_collides(needs_gl, forward_npz):
    cfg = twin.TwinConfig(episodes=1, steps=80, **SMALL)
    room = twin.run_room(forward_npz, ROOM, 0, cfg)
    assert room["collided"].tolist() == [True]
    # 2 m less the post's half and the robot's radius (1.67 m) at 0.4 m/s after the smoother's
    # ramp (0.3 m/s^2: 1.3 s, 0.27 m), the first frame (0.1 s) and 0-0.2 s of latency: 5-5.2 s.
    assert 50 <= room["steps"][0] <= 53
    touch = 0.2 - 0.15 - twin.TURTLEBOT2I.radius  # x of the base at the first touch
    assert touch <= room["paths"][0][-1][0] <= touch + 0.04  # within the control step's 4 cm
    assert room["states"]["policy"] >= room["steps"][0] - 5  # blind in the last few: too near


def test_every_frame_changes_nothing(needs_gl, tmp_path):
    """The loop keeps only the newest frame: rendering the frames no tick reads changes no step."""
    npz = write_policy_npz(tmp_path / "p.npz")
    paths = []
    for every in (False, True):
        cfg = twin.TwinConfig(episodes=1, steps=20, every_frame=every, **SMALL)
        paths.append(twin.run_room(npz, ROOM, 0, cfg)["paths"][0])
    np.testing.assert_array_equal(paths[0], paths[1])


def test_cli_writes_evaluates_keys(needs_gl, forward_npz, tmp_path, capsys):
    save_layouts(tmp_path / "room.json", [ROOM])
    out = tmp_path / "twin.json"
    args = ["--policy", str(forward_npz), "--layouts", str(tmp_path / "room.json")]
    size = ["--width", "160", "--height", "120"]
    assert (
        twin_cli.main([*args, "--episodes", "2", "--steps", "15", *size, "--json", str(out)]) == 0
    )
    results = json.loads(out.read_text())
    assert set(results["layouts"]["small"]) == set(METRIC_KEYS)
    assert set(results["overall"]) == set(METRIC_KEYS)
    assert results["overall"]["episodes"] == 2
    assert results["overall"]["collision_free_rate"] == 1.0  # 1.5 s: not at the post yet
    assert 0.05 < results["overall"]["mean_speed"] < 0.4
    assert results["twin"]["width"] == 160 and results["control_steps_per_s"] > 0
    assert "control steps/s" in capsys.readouterr().out


def test_goal_policies_get_goals_and_odometry(needs_gl, tmp_path):
    """A goal policy drives to the layout's goal, or to one drawn on the reachable free cells at
    least `goal_min_distance` away; the results add evaluate's goal metrics."""
    npz = write_goal_policy_npz(tmp_path / "goal.npz")
    rooms = [dataclasses.replace(ROOM, goal_pos=(1.5, 1.0)), dataclasses.replace(ROOM, name="b")]
    cfg = twin.TwinConfig(episodes=2, steps=10, **SMALL)
    results = twin.run_twin(npz, rooms, cfg=cfg)
    goal_keys = [m.name for m in GoalEnv.eval_metrics]  # success_rate, spl, time_to_goal
    assert set(results["overall"]) == {*METRIC_KEYS, *goal_keys, "success", "path_length"}
    goals = results["_rooms"]["b"]["goal"]
    np.testing.assert_array_equal(results["_rooms"]["small"]["goal"], [[1.5, 1.0]] * 2)
    assert (np.linalg.norm(goals - ROOM.robot_pos, axis=-1) >= cfg.goal_min_distance).all()
    assert results["loop_states"]["policy"] >= 4 * 10 - 4  # odometry and goal reached the loop


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--policy", "nowhere.npz", "--layouts", "scenes/inference_room.json"], "--policy: "),
        (["--policy", "{npz}", "--suite", "nosuchsuite"], "--suite: no suite 'nosuchsuite'"),
        (["--policy", "{npz}", "--layouts", "nowhere.json"], "--layouts: "),
        (["--policy", "{npz}", "--suite", "benchmark", "--episodes", "0"], "--episodes: must be"),
    ],
)
def test_mistakes_are_one_line(flags, message, forward_npz, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    assert twin_cli.main([f.format(npz=forward_npz) for f in flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and err.count("\n") == 1


def test_the_loop_runs_no_jax(needs_gl, forward_npz, monkeypatch):
    """A twin room's episodes with every JAX operation failing: the loop, the physics and the
    rendering run none. (The process imports jax: `jaxnav.core`, home of the layout model and
    `is_free`, imports MJX.)"""
    from jax._src import core

    def bind(self, *args, **kwargs):
        raise AssertionError(f"a JAX operation ran in the twin's loop: {self.name}")

    cfg = twin.TwinConfig(episodes=2, steps=10, **SMALL)
    monkeypatch.setattr(core.Primitive, "bind", bind)
    room = twin.run_room(forward_npz, ROOM, 0, cfg)
    monkeypatch.undo()
    assert room["steps"].tolist() == [10, 10]


def test_camera_quat_looks_along_the_mount():
    """The rendering camera looks along +x of the base, pitched down and turned left as drawn."""
    import mujoco

    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, twin.camera_quat(0.1, 0.2))
    forward = -mat.reshape(3, 3)[:, 2]  # MuJoCo cameras look along their -z
    assert math.atan2(forward[1], forward[0]) == pytest.approx(0.2)
    assert -math.asin(forward[2]) == pytest.approx(0.1)


def test_the_node_calibrates_the_mount_in_the_twin(needs_gl, tmp_path):
    """The camera pitched 2 deg down from a 5-row policy's mount: the node's default start-up
    check refuses to drive; with calibration:=use it drives after its first frames."""
    rows = dict(elevations=np.linspace(-0.38, 0.17, 5).astype(np.float32))
    npz = write_policy_npz(
        tmp_path / "rows.npz", W1=np.zeros((16, 3), np.float32),
        b1=np.array([10.0, 0.0, 0.0], np.float32), camera_height=np.float32(0.295), **rows,
    )  # fmt: skip
    bias = dict(camera_pitch_error=0.0, camera_pitch_bias=math.radians(2.0))
    moved = {}
    for mount in ("check", "calibrate"):
        cfg = twin.TwinConfig(episodes=1, steps=20, mount=mount, **bias, **SMALL)
        room = twin.run_room(npz, ROOM, 0, cfg)
        moved[mount] = room["distance"][0]
        refused = sum(n for s, n in room["states"].items() if s.startswith("camera mount refused"))
        assert (refused >= 6) == (mount == "check"), room["states"]
    assert moved["check"] < 0.01 and moved["calibrate"] > 0.1
    with pytest.raises(ValueError, match="mount: must be one of true, calibrate, check, policy"):
        twin.TwinConfig(mount="guess")
