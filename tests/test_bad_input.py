"""Bad input everywhere: every user mistake exits 2 with one `error:` line naming the file, field or
flag, and no traceback (DESIGN.md, command-line contract).

Most cases call the CLIs' `main(argv)` in-process, since a subprocess costs a JAX import (3-5 s);
`test_in_a_process` runs four of them as real processes, started together before the other tests
so that their imports overlap.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnav
import jaxnav.cli.evaluate as evaluate_cli
import jaxnav.cli.export as export_cli
import jaxnav.cli.train as train_cli
import jaxnav.export
from jaxnav import evaluation
from jaxnav.core.scene import SceneConfig
from jaxnav.io import checkpoint
from jaxnav.io.layouts import Box, Cylinder, RoomLayout, save_layouts
from jaxnav.ppo.config import preset
from jaxnav.ppo.networks import init_stats
from jaxnav.ppo.train import TrainState, make_network
from jaxnav.runconfig import RunConfig
from jaxnav.tasks.avoid import AvoidConfig

# A valid room; each bad layout breaks one thing in a copy of it (tests/test_layouts.py checks the
# messages of the parser itself; here they go through the command lines).
GOOD_ROOM = {
    "name": "office",
    "room": {"size": [4.0, 4.0]},
    "robot": {"pos": [0.0, 0.0]},
    "obstacles": [{"type": "box", "pos": [1.2, 0.5], "size": [0.6, 0.4]}],
}
BAD_LAYOUTS = {  # file name: (change to GOOD_ROOM's first obstacle or room, what the message names)
    "unknown_type.json": ({"type": "cone"}, "obstacles[0].type"),
    "negative_size.json": ({"size": [-0.6, 0.4]}, "obstacles[0].size"),
    "outside_room.json": ({"pos": [3.0, 0.5]}, "obstacles[0]"),
    "spawn_overlap.json": ({"pos": [0.2, 0.0]}, "robot.pos"),
    "unknown_key.json": ({"colour": "red"}, "obstacles[0].colour"),
    "wrong_type.json": ({"room": {"size": "4x4"}}, "room.size"),
    "no_free_spawn.json": (
        {"room": {"size": [2.0, 2.0]}, "robot": None, "obstacles": [
            {"type": "box", "pos": [x, y], "size": [1.0, 1.0]} for x in (-.5, .5) for y in (-.5, .5)
        ]},
        "no free spawn",
    ),
    "huge_room.json": ({"room": {"size": [1e30, 1e30]}}, "room.size"),
}  # fmt: skip
# Files that are not JSON rooms at all: (content, what the message says).
BAD_FILES = {
    "deep.json": ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    "digits.json": ('{"room": {"size": [' + "9" * 5000 + ", 4]}}", "invalid JSON"),
}
# Reached by a training run whose config passed every check: these tests must never get there.
PASSED = "the config passed validation"


def _bad_room(change: dict) -> dict:
    room = json.loads(json.dumps(GOOD_ROOM))
    if "room" in change:
        room.update(change)
        room = {k: v for k, v in room.items() if v is not None}
    else:
        room["obstacles"][0].update(change)
    return room


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("layouts")
    for name, (change, _) in BAD_LAYOUTS.items():
        (root / name).write_text(json.dumps(_bad_room(change)))
    for name, (content, _) in BAD_FILES.items():
        (root / name).write_text(content)
    os.mkfifo(root / "fifo.json")
    return root


def _make_run(run: Path) -> Path:
    """A run folder with one checkpoint of an untrained tiny network (no env, no training)."""
    ppo = preset("cpu", num_envs=2, rollout_length=4, minibatch_size=8, total_steps=8, hidden=(8,))
    params = make_network(ppo, AvoidConfig().action_spec).init(
        jax.random.PRNGKey(0), jnp.zeros((1, 8))
    )
    ts = TrainState(params, (), init_stats(8), (), jax.random.PRNGKey(0), jnp.int32(1))
    return checkpoint.save(run, ts, RunConfig(ppo=ppo), {})


def _edit_config(ckpt: Path, **changes) -> None:
    config = json.loads((ckpt / "config.json").read_text())
    for group, fields in changes.items():
        config[group].update(fields)
    (ckpt / "config.json").write_text(json.dumps(config))


# Broken copies of a good run: (what is done to its checkpoint, what the message names).
BROKEN_RUNS = {
    "missing": (None, "missing"),
    "empty": (None, "empty"),
    "corrupt_msgpack": (
        lambda c: (c / "policy.msgpack").write_bytes(b"\x93not msgpack\xff"),
        "policy.msgpack",
    ),
    "truncated_msgpack": (
        lambda c: (c / "policy.msgpack").write_bytes((c / "policy.msgpack").read_bytes()[:40]),
        "policy.msgpack",
    ),
    "no_msgpack": (lambda c: (c / "policy.msgpack").unlink(), "policy.msgpack"),
    "garbage_config": (lambda c: (c / "config.json").write_text("{ppo: ???"), "config.json"),
    "config_wrong_type": (lambda c: _edit_config(c, ppo={"num_envs": "many"}), "ppo.num_envs"),
    "config_mismatch": (lambda c: _edit_config(c, ppo={"hidden": [64, 64]}), "policy.msgpack"),
    "random_msgpack": (
        lambda c: (c / "policy.msgpack").write_bytes(np.random.default_rng(0).bytes(64)),
        "policy.msgpack",
    ),
    "truncated_state": (
        lambda c: (c / "train_state.npz").write_bytes((c / "train_state.npz").read_bytes()[:300]),
        "train_state.npz",
    ),
    "garbled_state": (lambda c: _garble(c / "train_state.npz"), "train_state.npz"),
    "truncated_meta": (
        lambda c: (c / "meta.json").write_text((c / "meta.json").read_text()[:15]),
        "meta.json",
    ),
}


def _garble(file: Path) -> None:
    data = bytearray(file.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = np.random.default_rng(1).bytes(64)
    file.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("runs")
    good = _make_run(root / "good")
    (root / "empty").mkdir()
    for name, (damage, _) in BROKEN_RUNS.items():
        if damage is not None:
            shutil.copytree(root / "good", root / name)
            damage(root / name / good.relative_to(root / "good"))
    return root


def _call(main, argv, capsys) -> tuple[int, str]:
    """(exit code, stderr) of an in-process CLI call; argparse's SystemExit counts as an exit."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as stop:
        code = stop.code
    return code, capsys.readouterr().err


def assert_one_error_line(code, err: str, *names: str) -> None:
    assert code == 2, f"exit code {code}: {err}"
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for name in names:
        assert name in lines[0], f"{name!r} not named in: {lines[0]}"


@pytest.fixture
def train_main(monkeypatch, tmp_path):
    """`jaxnav.cli.train.main` (with --out in tmp_path unless `out=False`); a config that passes
    validation fails the test at once instead of starting to train."""

    def refuse(config, *args, **kwargs):
        raise AssertionError(f"{PASSED}: {config}")

    monkeypatch.setattr(train_cli, "run", refuse)
    monkeypatch.chdir(tmp_path)

    def main(argv, out=True):
        argv = ["--out", tmp_path / "run", *argv] if out else argv
        return train_cli.main([str(a) for a in argv])

    return main


# ------------------------------------------------------------------------------
# Four real processes: one `error:` line, no traceback, exit code 2


def _start(module: str, *args, cwd) -> subprocess.Popen:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    cmd = [sys.executable, "-m", module, *map(str, args)]
    return subprocess.Popen(
        cmd, cwd=cwd, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )


@pytest.fixture(scope="module", autouse=True)
def processes(files, runs, tmp_path_factory):
    """{name: (process, names its message must hold)}, started before the in-process tests."""
    cwd = tmp_path_factory.mktemp("cwd")
    bad = files / "unknown_type.json"
    procs = {
        "train_layout": (
            _start("jaxnav.train", "--out", cwd / "a", "--layouts", bad, cwd=cwd),
            (str(bad), "obstacles[0].type"),
        ),
        "train_flag": (
            _start("jaxnav.train", "--out", cwd / "b", "--task.forward-speed", "3", cwd=cwd),
            ("AvoidConfig.forward_speed",),
        ),
        "evaluate_layout": (
            _start("jaxnav.evaluate", "--policy", "forward", "--layouts", bad, cwd=cwd),
            ("--layouts", str(bad), "obstacles[0].type"),
        ),
        "export_corrupt": (
            _start("jaxnav.export", runs / "corrupt_msgpack", cwd=cwd),
            ("policy.msgpack",),
        ),
    }
    yield procs
    for proc, _ in procs.values():
        if proc.poll() is None:  # a test failed before waiting for it
            proc.kill()
            proc.communicate()


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["train_layout", "train_flag", "evaluate_layout", "export_corrupt"]
)
def test_in_a_process(processes, name):
    """Exit status 2 and one line from the command lines themselves. Slow: four processes, each
    importing jax (the process boundary is what is tested)."""
    proc, names = processes[name]
    _, stderr = proc.communicate(timeout=180)
    assert_one_error_line(proc.returncode, stderr, *names)


# ------------------------------------------------------------------------------
# Layouts through both command lines


@pytest.mark.parametrize("file", sorted(BAD_LAYOUTS))
def test_train_bad_layout(files, train_main, capsys, file):
    code, err = _call(train_main, ["--layouts", files / file], capsys)
    assert_one_error_line(code, err, file, BAD_LAYOUTS[file][1])


@pytest.mark.parametrize("file", sorted(BAD_LAYOUTS))
def test_evaluate_bad_layout(files, capsys, file):
    argv = ["--policy", "forward", "--layouts", files / file]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--layouts", file, BAD_LAYOUTS[file][1])


SPECIAL = {"deep.json": "nested too deeply", "digits.json": "invalid JSON"}
SPECIAL |= {"fifo.json": "FIFO", "/dev/zero": "character device", "/dev/urandom": "device"}


@pytest.mark.parametrize("file", sorted(SPECIAL))
def test_layouts_that_are_not_json_rooms(files, capsys, file):
    """Deep nesting, 5000-digit numbers, a FIFO (blocked forever) and devices (4 GB read)."""
    path = file if file.startswith("/") else files / file
    argv = ["--policy", "forward", "--layouts", path]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--layouts", str(path), SPECIAL[file])


@pytest.mark.parametrize("flag", ["--plots", "--json", "--video"])
def test_evaluate_unwritable_output_before_evaluating(capsys, monkeypatch, flag):
    def never(*args, **kwargs):
        raise AssertionError("evaluated before checking where the results go")

    monkeypatch.setattr(evaluate_cli, "evaluate", never)
    path = "/proc/results.json" if flag == "--json" else "/proc"
    code, err = _call(evaluate_cli.main, ["--policy", "forward", flag, path], capsys)
    assert_one_error_line(code, err, flag, "/proc", "cannot write")


@pytest.mark.slow
def test_evaluate_never_reports_nan(tmp_path, capsys, monkeypatch):
    """A room whose metrics are not finite is an error, and no JSON is written. Slow: an
    evaluation compiled for this check."""
    real = evaluation.evaluate_rooms

    def diverged(*args, **kwargs):
        return [{**r, "distance": r["distance"] * np.nan} for r in real(*args, **kwargs)]

    monkeypatch.setattr(evaluation, "evaluate_rooms", diverged)
    out = tmp_path / "eval.json"
    argv = ["--policy", "forward", "--episodes", "2", "--steps", "2", "--json", out]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert "room 'inference-room'" in err and "mean_speed is nan" in err
    assert not out.exists()


def test_more_obstacles_than_slots_grows_the_slots(tmp_path, train_main, capsys):
    """Not an error: `--scene.num-boxes` is a minimum, every layout gets the slots it needs."""
    boxes = [Box(pos=(-2.0 + 0.5 * i, 1.5), size=(0.3, 0.3)) for i in range(9)]
    cylinders = [Cylinder(pos=(-2.0 + 0.8 * i, -1.5), radius=0.15) for i in range(5)]
    room = RoomLayout(name="crowded", size=(5.0, 4.0), obstacles=(*boxes, *cylinders))
    save_layouts(tmp_path / "crowded.json", room)
    argv = ["--scene.num-boxes", "1", "--scene.num-cylinders", "0", "--layouts"]
    with pytest.raises(AssertionError, match=PASSED):  # the CLI accepts it...
        train_main([*argv, tmp_path / "crowded.json"])
    assert capsys.readouterr().err == ""
    scene = SceneConfig(num_boxes=1, num_cylinders=0)  # ...and the env grows its slots to fit
    env = jaxnav.make_env("avoid", layouts=[room], scene=scene)
    assert (env.scene.cfg.num_boxes, env.scene.cfg.num_cylinders) == (9, 5)
    assert env.bank.rooms.box_pos.shape == (1, 9, 2)
    assert int(env.bank.rooms.box_active.sum()) == 9
    assert int(env.bank.rooms.cyl_active.sum()) == 5


# ------------------------------------------------------------------------------
# Config fields through `python -m jaxnav.train` (PPO flags are named as flags, the other groups
# as Class.field, each group consistently)

CONFIG_CASES = [
    (["--num-envs", "0"], "--num-envs"),
    (["--learning-rate", "-1"], "--learning-rate"),
    (["--learning-rate", "nan"], "--learning-rate"),
    (["--minibatch-size", "3"], "--minibatch-size"),
    (["--gamma", "2"], "--gamma"),
    (["--critic-output", "sigmoid"], "--critic-output"),
    (["--hidden", "0"], "--hidden"),
    (["--total-steps", "100"], "--total-steps"),
    (["--preset", "turbo"], "--preset"),
    (["--task.forward-speed", "3"], "AvoidConfig.forward_speed"),
    (["--task.max-steps", "0"], "AvoidConfig.max_steps"),
    (["--task.near-threshold", "inf"], "AvoidConfig.near_threshold"),
    (["--randomize.friction", "1", "0.5"], "RandomizeConfig.friction"),
    (["--randomize.friction", "nan", "1"], "RandomizeConfig.friction"),
    (["--randomize.sampled-room-prob", "1.5"], "RandomizeConfig.sampled_room_prob"),
    (["--randomize.spawn-clearance", "-1"], "RandomizeConfig.spawn_clearance"),
    (["--randomize.collision-margin", "0", "0.4"], "RandomizeConfig.collision_margin"),
    (["--sensor.range-min", "9"], "SensorConfig.range_min"),
    (["--sensor.fov", "4"], "SensorConfig.fov"),
    (["--sensor.rays-per-sector", "0"], "SensorConfig.rays_per_sector"),
    (["--scene.substeps", "0"], "SceneConfig.substeps"),
    (["--scene.timestep", "nan"], "SceneConfig.timestep"),
    (["--anneal-lr", "maybe"], "--anneal-lr"),
    (["--privileged-critic", "true"], "--privileged-critic"),  # avoid has no critic-only inputs
    (["--num-envs", "many"], "--num-envs"),
    (["--num-robots", "8"], "--num-robots"),
]


@pytest.mark.parametrize("argv, name", CONFIG_CASES)
def test_train_bad_config(train_main, capsys, argv, name):
    code, err = _call(train_main, argv, capsys)
    assert_one_error_line(code, err, name)


def test_train_out_is_a_file(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken").write_text("")
    tiny = ["--num-envs", "1", "--rollout-length", "2", "--minibatch-size", "2"]  # if it did train
    argv = ["--out", "taken", *tiny, "--total-steps", "2", "--no-progress"]
    code, err = _call(train_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--out", "taken")


# ------------------------------------------------------------------------------
# Checkpoints: train --resume, evaluate and export


RESUME_BROKEN = ["missing", "empty", "garbage_config", "config_wrong_type", "truncated_state"]
RESUME_BROKEN += ["garbled_state", "truncated_meta", "random_msgpack"]


@pytest.mark.parametrize("run", RESUME_BROKEN)
def test_train_resume_broken_run(runs, train_main, capsys, run):
    code, err = _call(lambda a: train_main(a, out=False), ["--resume", runs / run], capsys)
    assert_one_error_line(code, err, str(runs / run), BROKEN_RUNS[run][1])


@pytest.mark.parametrize("run", sorted(BROKEN_RUNS))
def test_evaluate_broken_checkpoint(runs, capsys, run):
    argv = ["--checkpoint", runs / run, "--episodes", "1", "--steps", "1"]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--checkpoint", str(runs / run), BROKEN_RUNS[run][1])


@pytest.mark.parametrize("run", sorted(BROKEN_RUNS))
def test_export_broken_checkpoint(runs, tmp_path, capsys, run):
    argv = [runs / run, "--out", tmp_path / "policy.npz"]
    code, err = _call(export_cli.main, argv, capsys)
    assert_one_error_line(code, err, str(runs / run), BROKEN_RUNS[run][1])


def test_export_writes_nothing_that_fails_its_check(runs, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(jaxnav.export, "verify", lambda *a, **k: (0.5, 0))
    code, err = _call(export_cli.main, [runs / "good", "--out", tmp_path / "p.npz"], capsys)
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "p.npz: not written" in err
    assert list(tmp_path.iterdir()) == []  # neither the file nor its temporary


def test_export_unknown_format(runs, tmp_path, capsys):
    argv = [runs / "good", "--format", "tflite", "--out", tmp_path / "p.tflite"]
    code, err = _call(export_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--format", "tflite")
    assert not (tmp_path / "p.tflite").exists()


def test_export_out_is_not_writable(runs, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    argv = [runs / "good", "--out", tmp_path / "file" / "policy.npz"]
    code, err = _call(export_cli.main, argv, capsys)
    assert_one_error_line(code, err, "--out", "policy.npz")


# ------------------------------------------------------------------------------
# Evaluate's own flags


@pytest.mark.parametrize(
    "argv, names",
    [
        (["--policy", "forward", "--episodes", "0"], ("--episodes",)),
        (["--policy", "forward", "--steps", "-5"], ("--steps",)),
        (["--policy", "forward", "--episodes", "ten"], ("--episodes", "ten")),
        (["--policy", "forward", "--checkpoint", "."], ("--checkpoint", "--policy")),
        (["--policy", "straight"], ("--policy", "straight")),
        (["--episodes", "4"], ("--policy", "--checkpoint")),
        (["--policy", "forward", "--video", "a_file"], ("--video", "a_file")),
        (["--policy", "forward", "--plots", "a_file"], ("--plots", "a_file")),
        # A JAX OverflowError once, after the layouts and the policy were loaded.
        (["--policy", "forward", "--steps", str(10**12)], ("--steps", "at most 2,147,483,647")),
        (["--policy", "forward", "--episodes", str(2**31)], ("--episodes", "at most 2,147,")),
        (
            ["--policy", "forward", "--coupled-smoother", "--deterministic-env"],
            ("--coupled-smoother", "--deterministic-env"),
        ),
    ],
)
def test_evaluate_bad_flags(tmp_path, monkeypatch, capsys, argv, names):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(evaluate_cli, "evaluate", _never)
    (tmp_path / "a_file").write_text("")
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, *names)


def _never(*args, **kwargs):
    raise AssertionError("evaluated (or compiled) before the mistake was found")


def test_evaluate_batch_beyond_memory_before_compiling(monkeypatch, capsys):
    """100 million episodes aborted inside XLA; the need is now weighed before compiling."""
    monkeypatch.setattr(evaluation, "make_rollout", _never)
    monkeypatch.setattr(evaluation, "_available_memory", lambda: (2**30, "memory"))
    argv = ["--policy", "forward", "--episodes", "100000000", "--steps", "5"]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, "episodes 100,000,000 x 1 room(s) x steps 5: needs about")
    assert "but the memory is 1.1 GB; at 5 steps about " in err
    argv = ["--policy", "forward", "--episodes", "1", "--steps", "200000000"]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, "not even 1 episode per room of 200,000,000 steps fits")


def test_evaluate_full_disk_before_evaluating(tmp_path, monkeypatch, capsys):
    """A full disk failed the JSON's write after the whole evaluation."""
    monkeypatch.setattr(evaluate_cli, "evaluate", _never)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(1, 1, 0))
    argv = ["--policy", "forward", "--json", tmp_path / "out" / "eval.json"]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, f"--json {tmp_path / 'out'}: 0.0 kB free, the results need")
    assert not list((tmp_path / "out").iterdir())


def _layout_files(root: Path, **rooms) -> list[Path]:
    """{file stem: room object or list} written as root/<stem>.json."""
    for stem, content in rooms.items():
        (root / f"{stem}.json").write_text(json.dumps(content))
    return [root / f"{stem}.json" for stem in rooms]


class Accepted(Exception):
    """Raised by a stand-in for the work of a command: the command line accepted its input."""


def test_layouts_of_several_files_in_both_command_lines(tmp_path, monkeypatch, train_main, capsys):
    """Unnamed rooms of two files were `room-0` twice: train refused them naming no file while
    evaluate renamed one. Now both name them by file and index, and refuse a name given twice
    naming both files."""
    unnamed = {"room": {"size": [4.0, 4.0]}}
    a, b = _layout_files(tmp_path, a=unnamed, b=[unnamed, unnamed])

    def evaluated(policy, layouts, **kwargs):
        raise Accepted([room.name for room in layouts])

    monkeypatch.setattr(evaluate_cli, "evaluate", evaluated)
    with pytest.raises(Accepted) as names:
        evaluate_cli.main(["--policy", "forward", "--layouts", str(a), str(b)])
    assert names.value.args[0] == ["a-0", "b-0", "b-1"]

    def trained(config, *args, **kwargs):
        raise Accepted([room["name"] for room in config.layouts])

    monkeypatch.setattr(train_cli, "run", trained)
    with pytest.raises(Accepted) as names:
        train_main(["--layouts", a, b])
    assert names.value.args[0] == ["a-0", "b-0", "b-1"]
    office = {**unnamed, "name": "office"}
    one, two = _layout_files(tmp_path, one=office, two=[unnamed, office])
    code, err = _call(evaluate_cli.main, ["--policy", "forward", "--layouts", one, two], capsys)
    assert_one_error_line(
        code, err, f"--layouts: {two}: room 'office' (#1): name: duplicate room name, also used "
        f"by room #0 of {one}"
    )  # fmt: skip
    code, err = _call(evaluate_cli.main, ["--policy", "forward", "--layouts", a, a], capsys)
    assert_one_error_line(code, err, f"--layouts: {a}: given twice")


def test_evaluate_goal_on_the_spawn(tmp_path, monkeypatch, capsys):
    """A goal on the spawn reported 100 % success and SPL 0: the goal task refuses it."""
    monkeypatch.setattr(evaluate_cli, "evaluate", _never)
    room = {**GOOD_ROOM, "goal": {"pos": [0.0, 0.1]}}
    (path,) = _layout_files(tmp_path, on_spawn=room)
    argv = ["--policy", "forward", "--env", "goal", "--layouts", path]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(
        code, err, f"--layouts: {path}: room 'office' (#0): goal.pos: 0.100 m from robot.pos "
        "[0.0, 0.0], within the goal task's success radius (0.3 m)"
    )  # fmt: skip


def test_evaluate_layouts_too_big_to_compile(tmp_path, monkeypatch, capsys):
    """10,000 obstacles (with a free spawn or not) and 5,000 rooms compiled for minutes."""
    monkeypatch.setattr(evaluate_cli, "evaluate", _never)
    boxes = [
        {"type": "box", "pos": [-49.5 + i % 100, -49.5 + i // 100], "size": [0.3 + 0.7 * full] * 2}
        for full in (False, True)
        for i in range(10_000)
    ]
    many, full, rooms = _layout_files(
        tmp_path,
        many={"room": {"size": [100, 100]}, "obstacles": boxes[:10_000]},
        full={"room": {"size": [100, 100]}, "obstacles": boxes[10_000:]},
        rooms=[{"room": {"size": [4, 4]}}] * 5000,
    )
    for path, fragment in [(many, "obstacles: 10000 obstacles: at most 256 per room")] + [
        (full, "obstacles: 10000 obstacles: at most 256 per room"),
        (rooms, "5000 rooms: at most 1024"),
    ]:
        code, err = _call(evaluate_cli.main, ["--policy", "forward", "--layouts", path], capsys)
        assert_one_error_line(code, err, f"--layouts: {path}: ", fragment)


def _refuse_stat(monkeypatch, folder: Path) -> None:
    """Looking into `folder` is refused as for a folder without permission (root reads all)."""
    real = os.stat

    def stat(path, *args, **kwargs):
        if os.fspath(path).startswith(str(folder)):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", stat)


def test_unreadable_checkpoint_folder(runs, tmp_path, monkeypatch, capsys):
    """A run inside a folder without permission: evaluate said `cannot write` (exit 1) and
    export printed a PermissionError traceback."""
    closed = tmp_path / "closed"
    shutil.copytree(runs / "good", closed / "run")
    _refuse_stat(monkeypatch, closed)
    argv = ["--checkpoint", closed / "run"]
    code, err = _call(evaluate_cli.main, argv, capsys)
    assert_one_error_line(code, err, f"--checkpoint {closed / 'run'}: cannot access (Permission")
    code, err = _call(export_cli.main, [closed / "run"], capsys)
    assert_one_error_line(code, err, f"{closed / 'run'}: cannot read (Permission denied)")


def test_unreadable_layout_file(tmp_path, monkeypatch, capsys):
    (path,) = _layout_files(tmp_path, locked=GOOD_ROOM)
    real = os.open

    def refuse(file, *args, **kwargs):
        if os.fspath(file) == str(path):
            raise PermissionError(13, "Permission denied", os.fspath(file))
        return real(file, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    code, err = _call(evaluate_cli.main, ["--policy", "forward", "--layouts", path], capsys)
    assert_one_error_line(code, err, f"--layouts: {path}: cannot read (Permission denied)")


def test_export_unknown_flag(capsys):
    code, err = _call(export_cli.main, ["run", "--bogus"], capsys)
    assert_one_error_line(code, err, "--bogus")


def test_export_outputs_are_checked_before_the_checkpoint_is_read(
    runs, tmp_path, monkeypatch, capsys
):
    """--out naming a folder raised IsADirectoryError after the export; a bundle folder whose
    jaxnav_robot is a file raised FileExistsError and left half a bundle."""
    monkeypatch.setattr(jaxnav.export, "read_policy", _never)
    code, err = _call(export_cli.main, [runs / "good", "--out", tmp_path], capsys)
    assert_one_error_line(code, err, f"--out {tmp_path}: is a folder; give a file name")
    bundle = tmp_path / "robot"
    bundle.mkdir()
    (bundle / "jaxnav_robot").write_text("not a package")
    code, err = _call(export_cli.main, [runs / "good", "--bundle", bundle], capsys)
    assert_one_error_line(code, err, f"--bundle {bundle}: its jaxnav_robot is not a folder")
    (bundle / "notes.txt").write_text("mine")
    code, err = _call(export_cli.main, [runs / "good", "--bundle", bundle], capsys)
    assert_one_error_line(code, err, f"--bundle {bundle}: holds notes.txt, not part of a bundle")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot"]
    assert sorted(p.name for p in bundle.iterdir()) == ["jaxnav_robot", "notes.txt"]


# ------------------------------------------------------------------------------
# The Python API names fields as the dataclasses do


def test_config_json_errors_name_the_field():
    raw = RunConfig().to_dict()
    cases = {
        "ppo.num_envs": {"ppo": {"num_envs": "8"}},
        "randomize.friction": {"randomize": {"friction": [0.5]}},
        "ppo.hidden": {"ppo": {"hidden": [64, "wide"]}},
        "unknown keys in 'task'": {"task": {"speed": 1.0}},
        "seed": {"seed": 0.5},
    }
    for name, change in cases.items():
        with pytest.raises(ValueError, match=name.replace(".", r"\.").replace("(", r"\(")):
            RunConfig.from_dict({**raw, **change})


def test_make_env_unknown_override():
    with pytest.raises(ValueError, match="near_treshold.*valid: .*near_threshold"):
        jaxnav.make_env("avoid", near_treshold=0.8)


def test_config_classes_reject_nan():
    from jaxnav.core.randomize import RandomizeConfig
    from jaxnav.core.sensors import SensorConfig
    from jaxnav.tasks.avoid import AvoidConfig

    nan = float("nan")
    for cls, field, value in [
        (AvoidConfig, "collision_reward", nan),
        (RandomizeConfig, "sensor_noise", (0.0, nan)),
        (SensorConfig, "range_max", nan),
        (SceneConfig, "timestep", nan),
    ]:
        with pytest.raises(ValueError, match=f"{cls.__name__}.{field}"):
            dataclasses.replace(cls(), **{field: value})
