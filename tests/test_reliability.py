"""Nothing lost, nothing silent: what a killed, interrupted, crowded or starved run leaves behind.

Most tests drive `jaxnav.train.main` in-process with a stand-in trainer (numpy-sized state, no
compile), so the loop's files, locks and errors are tested in seconds. The signal tests start real
processes (tiny flags, the session's shared XLA cache).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TINY_FLAGS

from jaxnav import train as train_module
from jaxnav.io import checkpoint, files, runlog
from jaxnav.ppo.networks import init_stats
from jaxnav.ppo.train import Trainer, TrainState, make_network
from jaxnav.tasks.avoid import AvoidConfig

UPDATES = 6  # TINY_FLAGS: 6 updates in chunks of 2, a checkpoint after each chunk


# ------------------------------------------------------------------------------
# A stand-in trainer: the real loop, files and errors around a state of a few numbers


class FakeEnv:
    observation_size = 8
    metric_names = ("collision",)


def fake_trainer(cfg, env, fail_at=None):
    """A Trainer whose chunk adds `updates_per_chunk` updates; `fail_at(update)` may raise."""
    params = make_network(cfg, AvoidConfig().action_spec).init(
        jax.random.PRNGKey(0), jnp.zeros((1, 8))
    )

    def init(key):
        env_state = jnp.zeros((cfg.num_envs, 4))  # [N, 4]: sized like robots for memory_check
        return TrainState(params, (), init_stats(8), env_state, key, jnp.int32(0))

    def run_chunk(ts):
        n = cfg.updates_per_chunk
        if fail_at is not None:
            fail_at(int(ts.update) + n)
        one = np.ones(n)
        metrics = {"live": one > 0, "obs_finite": one > 0, "total": one, "collision": 0 * one}
        for key in ("episode_reward", "episode_length", *runlog.LOSSES[1:]):
            metrics[key] = one
        return ts.replace(update=ts.update + n), metrics

    return Trainer(None, init, run_chunk, None)


@pytest.fixture
def fake(monkeypatch, tmp_path):
    """`main(argv) -> (code, stdout, stderr)` of jaxnav.train with the stand-in trainer; set
    `fake.fail_at` to make a chunk raise."""
    monkeypatch.setattr(train_module, "make_run_env", lambda config: FakeEnv())
    state = {"fail_at": None}
    monkeypatch.setattr(
        train_module, "make_train", lambda cfg, env: fake_trainer(cfg, env, state["fail_at"])
    )
    monkeypatch.chdir(tmp_path)

    def main(*argv):
        return train_module.main([str(a) for a in argv])

    main.state = state
    return main


def one_error_line(err: str, *names: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if not line.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for name in names:
        assert name in lines[0], f"{name!r} not named in: {lines[0]}"
    return lines[0]


def rows(out: Path) -> list[int]:
    return [r["update"] for r in runlog.read_rows(out / "metrics.csv")]


# ------------------------------------------------------------------------------
# 1. metrics.csv and the budget survive a kill during a resume's start-up


def test_metrics_never_truncated_before_the_kept_rows_are_on_disk(tmp_path, monkeypatch):
    fields = runlog.columns(("collision",))
    ints = ("update", "env_steps", "steps_per_second")
    full = [{k: (i if k in ints else 0.5) for k in fields} for i in range(1, 7)]
    with runlog.MetricsLog(tmp_path, fields, full):
        pass
    before = (tmp_path / "metrics.csv").read_text()

    def killed(*args):  # the rename that would replace the file never happens
        raise KeyboardInterrupt

    monkeypatch.setattr(files.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt), runlog.MetricsLog(tmp_path, fields, full[:4]):
        pass
    assert (tmp_path / "metrics.csv").read_text() == before  # all six rows still there
    monkeypatch.undo()
    with runlog.MetricsLog(tmp_path, fields, full[:4]):  # a resume from update 4
        assert rows(tmp_path) == [1, 2, 3, 4]  # on disk before the first chunk runs
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_resume_budget_comes_from_the_run_config(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    run = tmp_path / "run"
    config = checkpoint.load_config(run)
    more = config.ppo.total_steps * 2
    extended = train_module._with_budget(config, more)
    files.write_atomic(run / "config.json", json.dumps(extended.to_dict()))
    # As after a kill right after a resume wrote the new budget: the checkpoint's copy is older.
    assert fake("--resume", "run", "--no-progress") == 0
    assert checkpoint.load_meta(checkpoint.resolve(run))["update"] == 2 * UPDATES
    assert rows(run) == list(range(1, 2 * UPDATES + 1))


def test_kill_during_resume_start_up_loses_nothing(tiny_run, tmp_path):
    """kill -9 while a resume compiles: every row and the new budget are still there."""
    out = tmp_path / "run"
    shutil.copytree(tiny_run[0], out)
    before = (out / "metrics.csv").read_text()
    total = 16 * 16 * (UPDATES + 2)
    cmd = [sys.executable, "-m", "jaxnav.train", "--resume", str(out), "--total-steps", str(total)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("jaxnav: compiling"):
            break
    proc.kill()
    proc.communicate(timeout=60)
    assert (out / "metrics.csv").read_text() == before
    ckpt = checkpoint.resolve(out)
    assert train_module._run_config(out, ckpt).ppo.total_steps == total


# ------------------------------------------------------------------------------
# 3. One line, not a traceback: a full disk, a read-only folder, not enough memory


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EACCES])
def test_failed_checkpoint_write_is_one_line_naming_what_was_saved(
    fake, tmp_path, monkeypatch, capsys, code
):
    real = checkpoint.save

    def save(run_dir, ts, *args, **kwargs):
        if int(ts.update) > 2:
            target = Path(run_dir) / "checkpoints" / f"update_{int(ts.update):06d}"
            raise OSError(code, os.strerror(code), str(target))
        return real(run_dir, ts, *args, **kwargs)

    monkeypatch.setattr(checkpoint, "save", save)
    assert fake("--out", "run", *TINY_FLAGS) == 1
    line = one_error_line(capsys.readouterr().err, "update_000004", os.strerror(code))
    assert "saved: checkpoint" in line and "update_000002" in line
    assert [c.name for c in checkpoint.list_checkpoints(tmp_path / "run")] == ["update_000002"]


def test_out_of_memory_is_one_line_and_removes_the_unstarted_folder(fake, tmp_path, capsys):
    def oom(update):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 9 GB")

    fake.state["fail_at"] = oom
    assert fake("--out", "run", *TINY_FLAGS) == 1
    one_error_line(capsys.readouterr().err, "out of memory", "--num-envs")
    assert not (tmp_path / "run").exists()


def test_too_many_robots_refused_before_anything_is_written(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    flags = ["--num-envs", "10000000", "--rollout-length", "16", "--total-steps", "160000000"]
    code = train_module.main(["--out", "run", *flags, "--no-progress"])
    assert code == 2
    line = one_error_line(capsys.readouterr().err, "--num-envs 10000000", "largest --num-envs")
    fits = int(line.rsplit("about ", 1)[1].replace(",", ""))
    assert 256 <= fits < 10_000_000  # the cpu preset's robots fit this machine
    assert not (tmp_path / "run").exists()


def test_unwritable_run_folder_is_one_line(tmp_path):
    folder = train_module._NewRunFolder(Path("/proc"), train_module.build_config())
    with pytest.raises(ValueError, match="--out /proc: cannot write"):
        folder.create()


# ------------------------------------------------------------------------------
# 4. Ctrl-C from the first instant


def _launch(out: Path, *flags):
    cmd = [sys.executable, "-m", "jaxnav.train", "--out", str(out), *TINY_FLAGS, *flags]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("delay", [1.0, 2.5])
def test_sigint_while_importing_exits_at_once(tmp_path, delay):
    proc = _launch(tmp_path / "run")
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    tick = time.perf_counter()
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stderr
    assert time.perf_counter() - tick < 5
    assert one_error_line(stderr.replace("interrupted", "error: interrupted"), "SIGINT")
    assert not (tmp_path / "run").exists()


def test_an_interrupt_ends_the_children_a_library_started():
    """`import mujoco` starts pyGLFW's version probe, a Python that prints to a pipe back to its
    parent: ended with its parent, it would print a BrokenPipeError traceback (`cli.end_children`)."""
    script = (
        "import subprocess, sys; from jaxnav import cli\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        "cli.end_children()\n"
        "print(child.wait(timeout=10))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(-signal.SIGKILL)


def test_sigint_while_compiling_exits_at_once_and_removes_the_folder(tmp_path):
    out = tmp_path / "run"
    proc = _launch(out)
    for line in proc.stdout:
        if line.startswith("jaxnav: compiling"):
            break
    assert out.is_dir()
    proc.send_signal(signal.SIGINT)
    tick = time.perf_counter()
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert time.perf_counter() - tick < 10  # not after the compile
    assert "removed the unfinished run folder" in stderr and not out.exists()


# ------------------------------------------------------------------------------
# 7, 8. Messages name the file; locks; stale writes; budgets and flags on resume


def test_garbage_metrics_row_names_the_file(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    with open(tmp_path / "run" / "metrics.csv", "a") as fh:
        fh.write("7,1792,abc\n")
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 2
    one_error_line(capsys.readouterr().err, "metrics.csv", "line 8")


def test_truncated_meta_json_names_the_file(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    for ckpt in checkpoint.list_checkpoints(tmp_path / "run"):
        meta = ckpt / "meta.json"
        meta.write_text(meta.read_text()[:20])
    assert fake("--resume", "run", "--no-progress") == 2
    one_error_line(capsys.readouterr().err, "meta.json")


def test_resume_cleans_stale_writes_and_refuses_a_smaller_budget(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    run = tmp_path / "run"
    (run / "checkpoints" / ".tmp-killed").mkdir()
    assert fake("--resume", "run", "--total-steps", "512", "--no-progress") == 2
    one_error_line(capsys.readouterr().err, "--total-steps 512", "below the run's progress")
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0
    assert not (run / "checkpoints" / ".tmp-killed").exists()


@pytest.mark.parametrize("flags", [["--learning-rate", "0.1"], ["--seed", "0"]])
def test_resume_names_changed_flags_as_typed(fake, tmp_path, capsys, flags):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    assert fake("--resume", "run", *flags) == 2
    one_error_line(capsys.readouterr().err, f"drop {flags[0]}")


def test_lock_refuses_a_second_writer_and_takes_over_a_dead_one(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    lock = tmp_path / "run" / files.LOCK
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock.write_text(f"{live.pid}\n")
        assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8)) == 2
        one_error_line(capsys.readouterr().err, str(live.pid), "in use")
        assert fake("--out", "run2", *TINY_FLAGS) == 0  # another folder is not locked
    finally:
        live.kill()
        live.wait()
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0
    assert f"process {live.pid} is gone" in capsys.readouterr().err
    assert not lock.exists()  # released at the end


def test_resume_starts_a_run_killed_before_its_first_checkpoint(fake, tmp_path, capsys):
    """kill -9 before the first checkpoint leaves config.json and a stale lock: resume starts it."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    run = tmp_path / "run"
    shutil.rmtree(run / "checkpoints")
    (run / files.LOCK).write_text("999999999\n")  # no such process
    assert fake("--resume", "run", "--no-progress") == 0
    assert "no checkpoint yet" in capsys.readouterr().out
    assert checkpoint.load_meta(checkpoint.resolve(run))["update"] == UPDATES
    assert rows(run) == list(range(1, UPDATES + 1))
