"""Nothing lost, nothing silent: what a killed, interrupted, crowded or starved run leaves behind.

Most tests drive `jaxnav.cli.train.main` in-process with a stand-in trainer (numpy-sized state, no
compile), so the loop's files, locks and errors are tested in seconds. The signal tests start real
processes (tiny flags, the session's shared XLA cache).
"""

from __future__ import annotations

import contextlib
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

import jaxnav.cli.train as train_cli
from jaxnav import process, runs
from jaxnav import training as train_module
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
        return train_cli.main([str(a) for a in argv])

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
    config = runs.load_config(run)
    more = config.ppo.total_steps * 2
    extended = train_module._with_budget(config, more)
    files.write_atomic(run / "config.json", json.dumps(extended.to_dict()))
    # As after a kill right after a resume wrote the new budget: the checkpoint's copy is older.
    assert fake("--resume", "run", "--no-progress") == 0
    assert checkpoint.load_meta(checkpoint.resolve(run))["update"] == 2 * UPDATES
    assert rows(run) == list(range(1, 2 * UPDATES + 1))


@pytest.mark.slow
def test_kill_during_resume_start_up_loses_nothing(tiny_run, tmp_path):
    """kill -9 while a resume compiles: every row and the new budget are still there. Slow: a
    training run (the CLI's) and a resume in a process of its own, killed mid-compile."""
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
    code = train_cli.main(["--out", "run", *flags, "--no-progress"])
    assert code == 2
    line = one_error_line(capsys.readouterr().err, "--num-envs 10000000", "largest --num-envs")
    fits = int(line.rsplit("about ", 1)[1].replace(",", ""))
    assert 256 <= fits < 10_000_000  # the cpu preset's robots fit this machine
    assert not (tmp_path / "run").exists()


def test_the_memory_check_counts_a_rollouts_episodes_drawn_ahead(tmp_path, monkeypatch, capsys):
    """Drawn ahead (`--reset-ahead`, the default), a rollout's new episodes are held at once: with
    a new episode a robot a step, 16 steps of them, a robot needs more memory than with one step's
    drawn at a time, and fewer robots fit."""
    monkeypatch.chdir(tmp_path)
    # 100 M robots: more than any host holds either way (about 1.8 TB drawn per step).
    flags = ["--num-envs", "100000000", "--rollout-length", "16", "--total-steps", "1600000000"]
    flags += ["--reset-share", "1"]
    need = {}
    for ahead in ("true", "false"):
        code = train_cli.main(["--out", f"run-{ahead}", *flags, "--reset-ahead", ahead])
        assert code == 2
        line = one_error_line(capsys.readouterr().err, "--num-envs 100000000", "kB per robot")
        kb = float(line.split(" kB per robot")[0].rsplit("(", 1)[1])
        need[ahead] = (kb, int(line.rsplit("about ", 1)[1].replace(",", "")))
        assert not (tmp_path / f"run-{ahead}").exists()
    assert need["true"][0] > need["false"][0] and need["true"][1] < need["false"][1], need


def test_unwritable_run_folder_is_one_line(tmp_path):
    folder = train_module._RunFolder(Path("/proc"), train_module.build_config())
    with pytest.raises(ValueError, match="--out /proc: cannot write"):
        folder.create()


# ------------------------------------------------------------------------------
# 4. Ctrl-C from the first instant


def _launch(out: Path, *flags):
    cmd = [sys.executable, "-m", "jaxnav.train", "--out", str(out), *TINY_FLAGS, *flags]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
@pytest.mark.parametrize("delay", [1.0, 2.5])
def test_sigint_while_importing_exits_at_once(tmp_path, delay):
    """Slow: a training process per case, signalled while it imports or traces and compiles
    (without the compilation cache: with a warm one the tiny run trains within 2.5 s)."""
    proc = _launch(tmp_path / "run", "--no-compile-cache")
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    tick = time.perf_counter()
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stderr
    assert time.perf_counter() - tick < 5
    assert one_error_line(stderr.replace("interrupted", "error: interrupted"), "SIGINT")
    assert not (tmp_path / "run").exists()


def exits_noting(monkeypatch, noted) -> list:
    """The signal handler's end of the process (`os._exit`; the children's end a no-op) made a
    SystemExit, after appending `noted()` to the list returned: what the signal left behind."""
    seen = []

    def exit_now(code):
        seen.append(noted())
        raise SystemExit(code)

    monkeypatch.setattr(process.os, "_exit", exit_now)
    monkeypatch.setattr(process, "end_children", lambda: None)
    return seen


def test_a_signal_from_the_run_folders_first_instant_takes_it_back(fake, tmp_path, monkeypatch):
    """The run folder is made once the memory check has passed, while the programs are still
    traced; a signal from that instant ends the start as one while compiling does: the folder
    removed, the line saying so (not "nothing was written" over a folder holding config.json and
    a lock, which the next `--out` of it refused)."""
    out, stop = tmp_path / "run", process.Interrupts()
    left = exits_noting(monkeypatch, out.exists)
    find = train_module.find_programs

    def find_programs(trainer, config, env, key, check=None):
        def checked(state):  # the folder is made here; the signal comes right after
            check(state)
            assert out.is_dir()
            stop._handle(signal.SIGINT, None)

        return find(trainer, config, env, key, check=checked)

    monkeypatch.setattr(train_module, "find_programs", find_programs)
    config = train_module.build_config(
        "cpu", 0, None, train_cli.overrides_from_args(train_cli.parse_args(TINY_FLAGS))
    )
    with pytest.raises(SystemExit, match="130"):
        train_module.run(config, out, progress=False, stop=stop)
    assert left == [False]
    assert stop.note == f"removed the unfinished run folder {out}"


def test_a_signal_while_a_resume_holds_the_lock_releases_it(fake, tmp_path, monkeypatch):
    """A resume takes the run's lock, then cleans stale writes, writes config.json and waits for
    the other processes; a signal once the lock is taken (here, while stale writes are cleaned)
    releases it and says nothing was lost (not the start's "nothing was written" over a lock left
    behind)."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    out, stop = tmp_path / "run", process.Interrupts()
    held = exits_noting(monkeypatch, (out / files.LOCK).exists)
    clean = checkpoint.remove_stale_writes

    def signalled(folder):  # right after the lock is taken
        assert (out / files.LOCK).exists()
        clean(folder)
        stop._handle(signal.SIGINT, None)

    monkeypatch.setattr(checkpoint, "remove_stale_writes", signalled)
    with pytest.raises(SystemExit, match="130"):
        train_module.resume(out, progress=False, stop=stop)
    assert held == [False]
    assert stop.note == f"nothing was lost; continue with: python -m jaxnav.train --resume {out}"


def test_an_interrupt_ends_the_children_a_library_started():
    """`import mujoco` starts pyGLFW's version probe, a Python that prints to a pipe back to its
    parent: ended with its parent, it would print a BrokenPipeError traceback (`process.end_children`)."""
    script = (
        "import subprocess, sys; from jaxnav import process\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        "process.end_children()\n"
        "print(child.wait(timeout=10))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(-signal.SIGKILL)


@pytest.mark.slow
def test_sigint_while_compiling_exits_at_once_and_removes_the_folder(tmp_path):
    """SIGINT while the first chunk compiles: the process ends at once and its new folder goes.
    Slow: a training process, signalled mid-compile (the process boundary is what is tested);
    without the compilation cache, whose programs other tests' tiny runs may have kept."""
    out = tmp_path / "run"
    proc = _launch(out, "--no-compile-cache")
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
    """A damaged row up to the checkpoint is the user's to see, named by file and line."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    log = tmp_path / "run" / "metrics.csv"
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:3] + ["3,768,abc\n"] + lines[4:]))
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 2
    one_error_line(capsys.readouterr().err, "metrics.csv", "line 4")


@pytest.mark.parametrize("tail", ["7,1792,0.1234,0", "7,1792,abc\n", "\x00\x00", "7,17"])
def test_rows_past_the_checkpoint_are_dropped_whatever_they_hold(fake, tmp_path, tail):
    """A full disk stops a run mid-row (`MetricsLog.add`): its resume rewrites those updates."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    with open(tmp_path / "run" / "metrics.csv", "a") as fh:
        fh.write(tail)
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0
    assert rows(tmp_path / "run") == list(range(1, 9))


@pytest.mark.slow
def test_a_metrics_log_over_16_mib_resumes(tmp_path):
    """A metrics log larger than 16 MiB is read back up to a row and resumed from it. Slow:
    about 10 s on 2 cores, its 130,000 rows written and read back twice."""
    fields = runlog.columns(("collision",))
    ints = ("update", "env_steps", "steps_per_second")
    many = [{k: (i if k in ints else 0.123456789 * i) for k in fields} for i in range(1, 130_001)]
    with runlog.MetricsLog(tmp_path, fields, many, write=True):
        pass
    log = tmp_path / "metrics.csv"
    assert log.stat().st_size > 16 * 2**20
    kept = runlog.read_rows(log, upto=120_000)
    assert len(kept) == 120_000 and kept[-1] == many[119_999]
    with runlog.MetricsLog(tmp_path, fields, kept):
        pass
    assert runlog.read_rows(log)[-1]["update"] == 120_000


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


def test_a_lock_released_again_while_it_is_released_lets_go_once(tmp_path, monkeypatch):
    """A signal's cleanup may release the run's lock while the run's own release is under way (the
    `finally` of a resume): the second release does nothing, the lock's file goes and its fd is
    closed once."""
    lock, closed = files.RunLock(tmp_path), []
    lock.acquire()
    fd, unlink, close = lock.fd, Path.unlink, os.close

    def unlink_interrupted(path, *args, **kwargs):  # the signal comes here, mid-release
        lock.release()
        unlink(path, *args, **kwargs)

    monkeypatch.setattr(Path, "unlink", unlink_interrupted)
    monkeypatch.setattr(files.os, "close", lambda fd: (closed.append(fd), close(fd)))
    lock.release()
    assert closed.count(fd) == 1 and lock.fd is None and not (tmp_path / files.LOCK).exists()


HOLD_LOCK = """
import sys, time
from pathlib import Path
from jaxnav.io import files
folder, go = Path(sys.argv[1]), Path(sys.argv[2])
while not go.exists():
    time.sleep(0.005)
lock = files.RunLock(folder)
try:
    lock.acquire()
except ValueError:
    print("lost", flush=True)
    sys.exit(0)
print("won", flush=True)
time.sleep(float(sys.argv[3]))
lock.release()
"""


def hold_lock(folder: Path, go: Path, seconds: float = 60.0) -> subprocess.Popen:
    cmd = [sys.executable, "-c", HOLD_LOCK, str(folder), str(go), str(seconds)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_lock_refuses_a_second_writer_and_takes_over_a_dead_one(fake, tmp_path, capsys):
    """Slow: a second process holds the lock, then is killed."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    lock = tmp_path / "run" / files.LOCK
    (tmp_path / "go").touch()
    holder = hold_lock(tmp_path / "run", tmp_path / "go")
    try:
        assert holder.stdout.readline() == "won\n"
        assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8)) == 2
        one_error_line(capsys.readouterr().err, f"process {holder.pid}", "in use")
        assert fake("--out", "run2", *TINY_FLAGS) == 0  # another folder is not locked
    finally:
        holder.kill()  # as kill -9: the kernel drops its flock, the file stays
        holder.wait()
    assert lock.read_text() == f"{holder.pid}\n"
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0
    assert f"process {holder.pid} no longer holds it" in capsys.readouterr().err
    assert not lock.exists()  # released at the end


def test_a_lock_naming_a_reused_live_pid_does_not_block(fake, tmp_path, capsys):
    """A lock file left by a dead run whose pid now belongs to another live process."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    (tmp_path / "run" / files.LOCK).write_text(f"{os.getppid()}\n")
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0


@pytest.mark.slow
def test_processes_racing_for_a_stale_lock_one_wins(tmp_path):
    """Slow: 8 processes race for the lock."""
    (tmp_path / files.LOCK).write_text("999999999\n")  # left by a dead process
    go = tmp_path / "go"
    racers = [hold_lock(tmp_path, go, seconds=3.0) for _ in range(8)]
    time.sleep(1.0)  # all started and waiting
    go.touch()
    results = sorted(p.communicate(timeout=60)[0].strip() for p in racers)
    assert results == ["lost"] * 7 + ["won"]


def test_stale_temporary_rewrites_are_removed_on_resume(fake, tmp_path):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    run = tmp_path / "run"
    dead = [run / "metrics.csv.999999999.0123abcd.tmp", run / "config.json.999999999.deadbeef.tmp"]
    live = run / f"config.json.{os.getpid()}.0123abcd.tmp"  # a write under way: left alone
    other = run / "eval.json.999999999.0123abcd.tmp"  # not the run's own file
    for path in (*dead, live, other):
        path.write_text("half")
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 0
    assert [p.exists() for p in (*dead, live, other)] == [False, False, True, True]


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


# ------------------------------------------------------------------------------
# Nothing the user owns is lost: --out, interrupted starts and resumes


def user_files(folder: Path) -> dict[str, str]:
    (folder / "tb").mkdir(parents=True)
    mine = {"config.json": "mine", "metrics.csv": "mine", "tb/notes.txt": "mine"}
    for name, text in mine.items():
        (folder / name).write_text(text)
    return mine


def test_out_refuses_a_folder_that_is_not_a_jaxnav_run(fake, tmp_path, capsys):
    mine = user_files(tmp_path / "D")
    assert fake("--out", "D", *TINY_FLAGS) == 2
    one_error_line(capsys.readouterr().err, "--out D", "not empty and not a jaxnav run")
    assert {n: (tmp_path / "D" / n).read_text() for n in mine} == mine
    assert sorted(p.name for p in (tmp_path / "D").iterdir()) == [
        "config.json",
        "metrics.csv",
        "tb",
    ]
    (tmp_path / "E").mkdir()  # an empty folder is fine
    assert fake("--out", "E", *TINY_FLAGS) == 0


def test_out_holding_a_run_without_checkpoint_points_to_resume(fake, tmp_path, capsys):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    shutil.rmtree(tmp_path / "run" / "checkpoints")
    assert fake("--out", "run", *TINY_FLAGS) == 2
    one_error_line(capsys.readouterr().err, "already holds a training run", "--resume run")


def test_a_failed_start_removes_only_what_it_created(tmp_path):
    """The user's own file in an empty --out, added while the run starts, is never removed."""
    out = tmp_path / "D"
    out.mkdir()
    folder = train_module._RunFolder(out, train_module.build_config())
    folder.create()
    (out / "metrics.csv").write_text("rows")  # as the loop would
    (out / "notes.txt").write_text("mine")
    folder.remove()
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    made = train_module._RunFolder(tmp_path / "new", train_module.build_config())
    made.create()
    made.remove()
    assert not (tmp_path / "new").exists()
    assert "removed the unfinished run folder" in train_module._start_note(made)


def test_an_interrupted_resume_keeps_the_run(fake, tmp_path, capsys):
    """A run killed before its first checkpoint holds config.json: a resume that is stopped
    (here by a KeyboardInterrupt in its first chunk) leaves it, and the next resume finishes it."""
    assert fake("--out", "run", *TINY_FLAGS) == 0
    run = tmp_path / "run"
    shutil.rmtree(run / "checkpoints")
    config = (run / "config.json").read_text()

    def stop(update):
        raise KeyboardInterrupt

    fake.state["fail_at"] = stop
    assert fake("--resume", "run", "--no-progress") == 130
    assert (run / "config.json").read_text() == config and not (run / files.LOCK).exists()
    fake.state["fail_at"] = None
    assert fake("--resume", "run", "--no-progress") == 0
    assert rows(run) == list(range(1, UPDATES + 1))


def test_resume_on_a_full_disk_is_one_line_and_changes_nothing(fake, tmp_path, capsys, monkeypatch):
    assert fake("--out", "run", *TINY_FLAGS) == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(files, "write_atomic", full)
    assert fake("--resume", "run", "--total-steps", str(16 * 16 * 8), "--no-progress") == 1
    one_error_line(capsys.readouterr().err, "No space left", "--resume run")
    after = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}
    assert after == before


def test_out_on_a_read_only_filesystem_is_one_line(fake, tmp_path, capsys, monkeypatch):
    real_open = os.open

    def read_only(path, flags, *args):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *args)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(files.os, "open", read_only)
    monkeypatch.setattr(train_module.Path, "unlink", _refuse_unlink)  # as a read-only mount does
    assert fake("--out", "ro", *TINY_FLAGS) == 2
    one_error_line(capsys.readouterr().err, "--out ro", "Read-only file system")


def _refuse_unlink(self, missing_ok=False):
    raise OSError(errno.EROFS, "Read-only file system", str(self))


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 1 MiB tmpfs at tmp_path/mnt (root and a kernel that lets it mount; else skipped)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True
    ).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.slow
def test_a_real_read_only_and_full_filesystem(fake, small_tmpfs, capsys):
    """A run on a real full, then read-only, filesystem fails in one line and keeps what it had.
    Slow: it mounts a small tmpfs and fills it."""
    assert fake("--out", small_tmpfs / "run", *TINY_FLAGS) == 0
    with contextlib.suppress(OSError), open(small_tmpfs / "fill", "wb") as fh:
        while True:  # fill what is left
            fh.write(b"\0" * 4096)
            fh.flush()
    more = str(16 * 16 * 8)
    code = fake("--resume", small_tmpfs / "run", "--total-steps", more, "--no-progress")
    assert code == 1
    one_error_line(capsys.readouterr().err, "No space left", "--resume")
    (small_tmpfs / "fill").unlink()
    assert fake("--resume", small_tmpfs / "run", "--total-steps", more, "--no-progress") == 0
    assert rows(small_tmpfs / "run") == list(range(1, 9))
    subprocess.run(["mount", "-o", "remount,ro", str(small_tmpfs)], check=True)
    assert fake("--out", small_tmpfs / "new", *TINY_FLAGS) == 2
    one_error_line(capsys.readouterr().err, "Read-only file system")
    assert fake("--resume", small_tmpfs / "run", "--total-steps", str(16 * 16 * 10)) == 1
    one_error_line(capsys.readouterr().err, "Read-only file system")


def test_a_network_too_large_for_memory_is_refused_first(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code = train_cli.main(["--out", "run", "--hidden", "100000000", "100000000"])
    assert code == 2
    one_error_line(capsys.readouterr().err, "--hidden 100000000 100000000", "network alone")
    assert not (tmp_path / "run").exists()


def test_a_second_signal_while_a_chunk_runs_stops_at_once(monkeypatch, capsys):
    """The first SIGINT waits for the chunk and its checkpoint; a second one exits at once,
    saying what is kept (the loop waits on the device in `interruptible`, so the handler runs)."""

    class Exited(Exception):
        pass

    def exit_(code):
        raise Exited(code)

    monkeypatch.setattr(process.os, "_exit", exit_)
    stop = process.Interrupts()
    stop.defer(lambda: "kept checkpoint C")
    stop._handle(signal.SIGINT, None)
    assert stop.requested == ["SIGINT"] and "send it again" in capsys.readouterr().err
    with pytest.raises(Exited, match="130"):
        stop._handle(signal.SIGTERM, None)
    assert capsys.readouterr().err.strip() == "interrupted (SIGTERM): kept checkpoint C"
