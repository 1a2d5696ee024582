"""Evaluation: metrics of the baselines in the inference room, the CLI and its errors, the plots.

Each `evaluate` call compiles one rollout (~10 s on a 2-core CPU), so the module shares two of them.
"""

import dataclasses
import json
import math
import os
import string
import subprocess
import sys
from subprocess import PIPE

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnav
import jaxnav.cli.evaluate as evaluate_module
from jaxnav.cli.evaluate import main
from jaxnav.core import goals
from jaxnav.core.scene import SCENES_DIR
from jaxnav.core.types import ContinuousActions
from jaxnav.evaluation import (
    MAX_FILE_STEM,
    METRIC_KEYS,
    default_steps,
    eval_randomize,
    evaluate,
    file_stems,
    format_table,
    load_suite,
    make_recorder,
    make_rollout,
    metrics,
    strip_private,
    suite_meta,
)
from jaxnav.io.layouts import Grid
from jaxnav.policy import Policy, forward_policy, random_policy, stand_policy
from jaxnav.tasks.avoid import AvoidEnv
from jaxnav.tasks.base import EvalMetric
from jaxnav.tasks.goal import GoalConfig
from jaxnav.tasks.registry import TASKS
from jaxnav.viz.plots import METRICS_HEADER, plot_reward_curve

EPISODES, STEPS = 8, 150  # 150 steps: enough for the forward baseline to reach an obstacle
ROOM = SCENES_DIR / "inference_room.json"


@pytest.fixture(scope="module")
def room():
    return jaxnav.load_layout(ROOM)


@pytest.fixture(scope="module")
def forward_results(room):
    return evaluate(forward_policy(), room, episodes=EPISODES, steps=STEPS, seed=0)


@pytest.fixture(scope="module")
def random_results(room):
    return evaluate(random_policy(), room, episodes=EPISODES, steps=STEPS, seed=0)


def test_results_schema_and_ranges(forward_results, room):
    r = forward_results
    keys = {"layouts", "overall", "policy", "physics", "steps", "seed", "smoother"}
    assert set(strip_private(r)) == keys and r["smoother"] == "per-axis"
    assert r["physics"] == "fast"  # the policy's own (SceneConfig default)
    assert r["policy"] == "forward" and r["steps"] == STEPS and r["seed"] == 0
    assert list(r["layouts"]) == [room[0].name]
    for m in [*r["layouts"].values(), r["overall"]]:
        assert set(m) == set(METRIC_KEYS)
        assert m["episodes"] == EPISODES and isinstance(m["episodes"], int)
        assert all(isinstance(m[k], float) and math.isfinite(m[k]) for k in METRIC_KEYS[1:])
        assert 0.0 <= m["collision_free_rate"] <= 1.0
        assert 1.0 <= m["mean_steps"] <= STEPS
        assert m["mean_speed"] >= 0.0 and m["mean_distance"] >= 0.0
    json.dumps(strip_private(r))  # JSON-ready as is
    traj = r["_trajectories"][room[0].name]
    assert len(traj["paths"]) == len(traj["collided"]) == EPISODES
    assert all(p.ndim == 2 and p.shape[1] == 2 and 2 <= len(p) <= STEPS + 1 for p in traj["paths"])


def test_forward_baseline_drives_straight_into_obstacles(forward_results):
    m = forward_results["overall"]
    # The layout spawn faces a cylinder 1.6 m ahead: every episode should end there.
    assert m["collision_free_rate"] <= 0.5
    assert m["mean_steps"] < STEPS
    # Speed over the steps actually run: from rest, the Kobuki's velocity smoother (0.25-0.35
    # m/s^2) needs 1.4-2 s of the ~4 s to the cylinder to reach the commanded speed, and the
    # latency 0-0.2 s more, so the mean is 65-90 % of it (speed gain 0.8-1.2 averages out).
    speed = jaxnav.tasks.registry.AvoidConfig().forward_speed
    assert 0.6 * speed < m["mean_speed"] < 0.95 * speed
    # Frozen after the collision: distance is speed x time up to then, not over all STEPS steps.
    assert m["mean_distance"] == pytest.approx(m["mean_speed"] * m["mean_steps"] * 0.1, rel=0.15)


@pytest.mark.slow
def test_random_baseline_moves_less_per_step_than_forward(forward_results, random_results):
    """Slow: the random baseline's evaluation compiles a program of its own (9 s)."""
    fwd, rnd = forward_results["overall"], random_results["overall"]
    # Over the same steps run, random turns two thirds of the time: it covers less ground per step.
    assert rnd["mean_speed"] < 0.7 * fwd["mean_speed"]
    assert rnd["mean_steps"] > fwd["mean_steps"]  # and it survives longer in this room


@pytest.mark.parametrize("actions", ["discrete", "discrete_stop", "discrete_back", "continuous"])
def test_stand_baseline_never_drives(actions):
    """`stand` commands no forward speed whatever the actions: stop where there is one, else the
    first turn in place (never backing away), and (0, 0) for continuous commands."""
    spec = GoalConfig(actions=actions).action_spec
    act = stand_policy(spec).act(jnp.zeros((4, 7)), jax.random.PRNGKey(0))
    if isinstance(spec, ContinuousActions):
        np.testing.assert_array_equal(act, np.zeros((4, 2)))
        return
    command = spec.table()[np.asarray(act)]  # [4, 2] forward m/s, yaw rad/s
    assert act.shape == (4,) and (command[:, 0] == 0).all()
    want = 0.0 if actions == "discrete_stop" else GoalConfig().turn_rate
    np.testing.assert_allclose(command[:, 1], want)


def _start_cli(*args, cwd) -> subprocess.Popen:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", "jaxnav.evaluate", *args]
    return subprocess.Popen(cmd, cwd=cwd, env=env, text=True, stdout=PIPE, stderr=PIPE)


def _cli(*args, cwd) -> subprocess.CompletedProcess:
    proc = _start_cli(*args, cwd=cwd)
    stdout, stderr = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.fixture(scope="module", autouse=True)
def cli_run(tmp_path_factory):
    """The CLI run, started before the other tests so its JAX compile overlaps theirs."""
    cwd = tmp_path_factory.mktemp("cli")
    out = cwd / "eval" / "out.json"
    args = ("--policy", "forward", "--episodes", "4", "--steps", "30", "--json", str(out))
    proc = _start_cli(*args, cwd=cwd)
    yield proc, out
    if proc.poll() is None:  # a test failed before waiting for it
        proc.kill()
        proc.communicate()


def test_cli_writes_json_and_pngs(cli_run):
    proc, out = cli_run
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    data = json.loads(out.read_text())
    assert set(data["layouts"]) == {"inference-room"}
    for m in [*data["layouts"].values(), data["overall"]]:
        assert set(m) == set(METRIC_KEYS)
        assert m["episodes"] == 4
    assert "_trajectories" not in data
    png = out.parent / "inference-room.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "inference-room" in stdout and "collision-free" in stdout
    assert f"plots: {out.parent}/ (1 PNG: inference-room.png)" in stdout


def test_cli_error_in_a_process_is_one_line(tmp_path):
    proc = _cli("--policy", "forward", "--layouts", "no_such_rooms.json", cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "no_such_rooms.json" in lines[0]


@pytest.mark.parametrize(
    "args, names",
    [
        (["--policy", "forward", "--episodes", "0"], "--episodes"),
        (["--policy", "forward", "--steps", "-1"], "--steps"),
        (["--episodes", "4"], "--policy"),
        (["--policy", "forward", "--checkpoint", "."], "--checkpoint"),
        (["--checkpoint", "no_such_run"], "no_such_run"),
        (["--policy", "forward", "--layouts", "bad.json"], "bad.json"),
        (["--policy", "forward", "--suite", "no_such_suite"], "--suite"),
    ],
)
def test_cli_errors_are_one_line(tmp_path, monkeypatch, capsys, args, names):
    # In-process (a subprocess costs a JAX import each); an uncaught exception would fail the test.
    monkeypatch.chdir(tmp_path)
    bad = {"name": "x", "room": {"size": [4, 4]}, "obstacles": [{"type": "cone"}]}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    assert main(args) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and names in lines[0], err


def test_plot_reward_curve(tmp_path):
    csv_path, png = tmp_path / "metrics.csv", tmp_path / "reward.png"
    rows = [",".join(METRICS_HEADER)]
    for i in range(6):
        reward = "" if i == 0 else ("nan" if i == 1 else f"{-50 + 10 * i}")
        rows.append(f"{i},{1000 * (i + 1)},{reward},40,{0.9 - 0.1 * i},1,0.5,0.5,1.0,0.01,5000,{i}")
    csv_path.write_text("\n".join(rows) + "\n")
    plot_reward_curve(csv_path, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_coupled_smoother_reaches_the_evaluation_env(room):
    """--coupled-smoother: the sim-to-real ranges with the Kobuki's smoother rule; exact physics
    has no smoother to couple."""
    coupled = eval_randomize(coupled_smoother=True)
    assert coupled == dataclasses.replace(eval_randomize(), coupled_smoother=True)
    assert coupled.accel_limit[1] > 0  # the smoother it couples is on
    with pytest.raises(ValueError, match="coupled_smoother"):
        eval_randomize(stochastic_env=False, coupled_smoother=True)


def test_evaluate_rejects_bad_arguments(room):
    with pytest.raises(ValueError, match="episodes"):
        evaluate(forward_policy(), room, episodes=0)
    with pytest.raises(ValueError, match="spawn"):
        evaluate(forward_policy(), room, episodes=1, spawn="nowhere")


def test_benchmark_suite_loads():
    suite = load_suite("benchmark")
    assert len(suite) >= 8 and sum(len(rooms) for rooms in suite.values()) >= 30
    for family, rooms in suite.items():
        assert all(r.name.startswith(family) and r.robot_pos is not None for r in rooms)


def test_hard_suite_holds_the_families_all_leaves_out():
    """`--suite hard`: BARN-like fields on a grid, halls beyond the camera's range and rooms
    people cross, some giving way to the robot; every spawn on its room's main free component,
    and the default 60 s an episode, in which the robot's 0.5 m/s covers the longest hall."""
    suite = load_suite("hard")
    assert list(suite) == ["crowd", "dense_field", "long_hall"]
    for family, rooms in suite.items():
        assert len(rooms) == 4 and all(r.name.startswith(family) for r in rooms)
        for room in rooms:
            main, _ = goals.main_component(room)  # [rows, cols] the spawn's free component
            span = max(np.ptp(np.nonzero(main)[axis]) / main.shape[axis] for axis in (0, 1))
            assert span > 0.7, room.name  # it reaches across the room
    assert all(any(isinstance(o, Grid) for o in r.obstacles) for r in suite["dense_field"])
    assert max(max(r.size) for r in suite["long_hall"]) > 16.0  # twice the camera's range
    walkers = [o.motion for r in suite["crowd"] for o in r.cylinders if o.motion is not None]
    assert all(len([o for o in r.cylinders if o.motion]) >= 3 for r in suite["crowd"])
    assert {m.reactive for m in walkers} == {True, False}
    assert all(0.3 <= m.speed <= 1.4 and m.goal is not None and m.repeat for m in walkers)
    assert suite_meta("hard") == {} and default_steps("hard", forward_policy()) == 600
    assert max(max(r.size) for r in suite["long_hall"]) / 0.5 < 0.8 * 60.0


def _cautious():
    """Deterministic: forward unless something is nearer than 0.7 m, then turn left."""
    return Policy("cautious", lambda obs, key: jnp.where(obs.min(-1) < 0.7, 1, 0).astype(jnp.int32))


@pytest.mark.slow
def test_one_batch_matches_per_room_rollouts():
    """Two rooms of different families in one compiled batch give each room the metrics of its
    own env's rollout. Slow: it compiles a rollout per room besides the batch's."""
    suite = load_suite("benchmark")
    rooms = [suite["corridor"][0], suite["clutter"][1]]
    episodes, steps = 3, 120
    batch = evaluate(
        _cautious(), rooms, episodes=episodes, steps=steps, seed=1, stochastic_env=False
    )
    randomize = eval_randomize("layout", stochastic_env=False)
    for room in rooms:
        env = jaxnav.make_env("avoid", [room], randomize=randomize, max_steps=steps)
        track, _ = make_rollout(env, _cautious().act, episodes, steps)(jax.random.PRNGKey(5))
        alone = metrics(track.collided, track.steps, track.distance, env.control_period)
        got = batch["layouts"][room.name]
        assert got["collision_free_rate"] == alone["collision_free_rate"], room.name
        assert got["mean_speed"] == pytest.approx(alone["mean_speed"], rel=1e-3), room.name
        assert got["mean_steps"] == alone["mean_steps"], room.name
        assert 0.0 < got["coverage"] <= 1.0


@pytest.mark.slow
def test_recorder_records_the_rollouts_episodes():
    """`make_recorder` steps the episodes of a pinned `make_rollout` with the same key: the steps
    it records as running and the collisions add up to the rollout's counts, from the same
    starts. Slow: it compiles both."""
    suite = load_suite("benchmark")
    rooms = [suite["corridor"][0], suite["clutter"][1]]
    env = jaxnav.make_env("avoid", rooms, randomize=eval_randomize("layout"), max_steps=150)

    def act(obs, key):  # forward 4 steps in 5, else left: drawn with the step's key
        return jnp.where(jax.random.uniform(key, obs.shape[:1]) < 0.8, 0, 1).astype(jnp.int32)

    key = jax.random.PRNGKey(3)
    track, _ = make_rollout(env, act, 4, 150, pinned=True)(key)

    def record(state, action, nxt, running):
        return running, (nxt.metrics["collision"] > 0) & running, state.data.qpos[:, :2]

    running, hit, xy = map(np.asarray, make_recorder(env, act, 4, 150, record)(key))
    np.testing.assert_array_equal(running.sum(0), track.steps)
    np.testing.assert_array_equal(hit.any(0), track.collided)
    np.testing.assert_array_equal(xy[0], track.start)
    assert hit.any() and len(set(running.sum(0))) > 2  # collisions, at steps the keys drew


class _CleanEnv(AvoidEnv):
    """`avoid` with one more evaluation metric, declared on the task alone: the mean distance
    driven by the episodes that did not collide."""

    eval_metrics = (
        EvalMetric(
            "clean_distance",
            value=lambda room: np.asarray(room["distance"], np.float64),
            over=lambda room: ~np.asarray(room["collided"], bool),
            column="clean m",
            width=7,
        ),
    )


def test_evaluate_reports_what_the_task_declares(room, monkeypatch):
    """A new task's metric reaches the results, their JSON and the table with no change in
    evaluation."""
    monkeypatch.setitem(TASKS, "avoid_clean", TASKS["avoid"]._replace(env_cls=_CleanEnv))
    policy = dataclasses.replace(forward_policy(), env="avoid_clean")
    results = evaluate(policy, room, episodes=2, steps=5, seed=0)  # too short to collide
    for m in [*results["layouts"].values(), results["overall"]]:
        assert set(m) == {*METRIC_KEYS, "clean_distance"}
        assert m["clean_distance"] == pytest.approx(m["mean_distance"])
    assert "clean_distance" in json.loads(json.dumps(strip_private(results)))["overall"]
    head, _, row, _ = format_table(results).splitlines()
    assert head.endswith(" clean m") and row.endswith(f"{results['overall']['mean_distance']:7.2f}")


@pytest.mark.slow
def test_cli_suite_writes_families_and_one_picture_each(tmp_path):
    """Slow: the command line evaluates every room of the benchmark suite and draws a picture per
    family, compiling the suite's batched rollout."""
    out = tmp_path / "suite.json"
    args = ["--policy", "forward", "--suite", "benchmark", "--episodes", "1", "--steps", "5"]
    assert main([*args, "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    families = load_suite("benchmark")
    assert set(data["families"]) == set(families) and data["suite"] == "benchmark"
    assert len(data["layouts"]) == sum(len(r) for r in families.values())
    for m in data["families"].values():
        assert set(m) == set(METRIC_KEYS) and 0.0 <= m["coverage"] <= 1.0
    assert sorted(p.stem for p in tmp_path.glob("*.png")) == sorted(families)


def test_file_stems_are_safe_distinct_and_bounded(tmp_path):
    """Rooms "a b" and "a/b" both made a_b.png (two rooms, one picture), and a 300-character
    name a file name too long to write."""
    names = ["a b", "a/b", "A_B", "x" * 300, "x" * 299 + "y", "..", "", "\n\x1b[31m", "ok-1"]
    stems = file_stems(names)
    assert stems[0] == "a_b" and stems[-1] == "ok-1"  # plain names stay as they were
    assert stems[1].startswith("a_b-") and stems[2].startswith("A_B-")
    assert len({s.lower() for s in stems}) == len(names)  # distinct, case aside
    assert all(0 < len(s) <= MAX_FILE_STEM + 9 and not s.startswith(".") for s in stems)
    assert all(set(s) <= set(string.ascii_letters + string.digits + "._-") for s in stems)
    assert file_stems(names) == stems  # the same rooms, the same files
    for stem in stems:
        (tmp_path / f"{stem}.png").write_bytes(b"")
    assert len(list(tmp_path.iterdir())) == len(names)


def test_table_escapes_control_characters_in_names():
    """A newline or a terminal escape in a room's name is printed escaped, never raw."""
    m = dict.fromkeys(METRIC_KEYS, 0.5) | {"episodes": 4}
    table = format_table({"layouts": {"evil\nroom\x1b[31m": m}, "overall": m})
    assert "\x1b" not in table and len(table.splitlines()) == 4  # head, rule, the room, overall
    assert table.splitlines()[2].startswith("evil\\nroom\\x1b[31m ")


def test_a_baseline_writes_nothing_where_it_was_not_asked(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = ["--policy", "forward", "--episodes", "1", "--steps", "5"]
    assert evaluate_module.main(argv) == 0
    assert "plots: none" in capsys.readouterr().out and list(tmp_path.iterdir()) == []


def test_picture_titles_fit_their_figure(tmp_path, monkeypatch):
    """A long title is broken into lines that stay inside the figure."""
    from matplotlib.figure import Figure

    from jaxnav.viz import plots

    saved = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: saved.append(fig))
    room = jaxnav.load_layout(evaluate_module.DEFAULT_LAYOUTS)[0]
    title = "inference_room_with_a_long_name: checkpoint runs/avoid-cpu, 100% collision-free, "
    plots.plot_trajectories(room, [np.zeros((3, 2))], [False], tmp_path / "x.png", title * 2)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = saved[0]
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    box = fig.axes[0].title.get_window_extent(renderer)
    assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1, (box, fig.bbox)
    assert fig.axes[0].title.get_text().count("\n") >= 1


@pytest.mark.slow
def test_time_to_solve_evaluator_runs_the_suite_under_its_own_jit(monkeypatch):
    """`benchmarks/time_to_solve.py`'s evaluator: the benchmark suite in one batch, under one jit
    of its own with jaxnav's compiler options around `rollout_program` (JAX takes those at the top
    level only), the policy's parameters an argument: a policy that turns in place stays put and
    never collides, and the same program driving forward moves. Compiler options as on a CPU
    outside the tests (here XLA_FLAGS sets the level, so jaxnav passes none), at the tests' level.
    Slow: it compiles a rollout of the whole suite."""
    from conftest import benchmark_script

    from jaxnav import evaluation
    from jaxnav.training import build_config

    tts = benchmark_script("time_to_solve")
    options = lambda backend=None: {"xla_backend_optimization_level": 0}  # noqa: E731
    for module in (tts, evaluation):
        monkeypatch.setattr(module, "compiler_options", options)
    act = lambda action, obs, key: jnp.full(obs.shape[:1], action, jnp.int32)  # noqa: E731
    evaluate, family = tts.make_evaluator(act, build_config("cpu"), episodes=2, steps=40)
    turning = evaluate(1, jax.random.PRNGKey(0))  # 1: left, in place
    assert turning["collided"].shape == turning["speed"].shape == family.shape == (64,)
    assert not turning["collided"].any() and (turning["speed"] < 0.05).all()
    forward = evaluate(0, jax.random.PRNGKey(0))
    assert forward["speed"].mean() > 0.2, forward["speed"]
