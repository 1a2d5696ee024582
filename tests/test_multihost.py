"""One run over two processes (two CPU processes on this host, gloo collectives between them) is
the single-process run over two devices, bit for bit, and it resumes across processes."""

import argparse
import re
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest
from conftest import cpu_env

from jaxnav import distributed
from jaxnav.io import checkpoint

# 6 updates in chunks of 2 over 16 robots, a checkpoint at the end only; episodes of at most 20
# steps, so that returns are logged.
FLAGS = [
    *("--num-envs", "16", "--rollout-length", "16", "--minibatch-size", "128"),
    *("--num-epochs", "2", "--updates-per-chunk", "2", "--checkpoint-every", "100"),
    *("--total-steps", str(16 * 16 * 6), "--task.max-steps", "20", "--seed", "3", "--no-progress"),
]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def start(cwd, devices: int, *args) -> subprocess.Popen:
    """`python -m jaxnav.train ARGS` in a process of `devices` CPU devices."""
    return subprocess.Popen(
        [sys.executable, "-m", "jaxnav.train", *args],
        cwd=cwd,
        env=cpu_env(devices),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(*procs) -> list[subprocess.CompletedProcess]:
    done = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=900)
        done.append(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr))
    return done


def two_processes(cwd, args0, args1=None) -> list[subprocess.Popen]:
    """Processes 0 and 1 of one run (ARGS0 and ARGS1, default the same), one CPU device each."""
    cluster = ["--coordinator", f"localhost:{free_port()}", "--num-processes", "2"]
    args = [args0, args1 or args0]
    return [start(cwd, 1, *args[i], *cluster, "--process-id", str(i)) for i in range(2)]


def saved_state(ckpt):
    with np.load(ckpt / "train_state.npz") as data:
        return {k: data[k] for k in data.files}


def logged(run):
    """metrics.csv without the columns of wall-clock time (steps/s, elapsed)."""
    lines = (run / "metrics.csv").read_text().splitlines()
    return [line.split(",")[:-2] for line in lines]


@pytest.mark.slow
def test_two_processes_match_one_process_of_two_devices(tmp_path):
    """Two `jax.distributed` processes train as one process of two devices does. Slow: three
    training processes, the process boundary being what is tested."""
    out = tmp_path / "run"
    first = finish(*two_processes(tmp_path, ["--out", "run", *FLAGS, "--checkpoint-every", "2"]))
    for i, proc in enumerate(first):
        assert proc.returncode == 0, f"process {i}: {proc.stderr[-3000:]}"
    assert "2 cpu device(s) of 2 processes" in first[0].stdout
    assert "done: process 1" in first[1].stdout
    # Process 0 alone wrote: one run folder, each checkpoint once.
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    ckpts = sorted(p.name for p in (out / checkpoint.CKPT_DIR).iterdir())
    assert ckpts == ["update_000002", "update_000004", "update_000006"]
    # As if the run had stopped after update 2: both processes read that checkpoint and go on.
    for name in ckpts[1:]:
        shutil.rmtree(out / checkpoint.CKPT_DIR / name)
    resumed = finish(*two_processes(tmp_path, ["--resume", "run", "--no-progress"]))
    for i, proc in enumerate(resumed):
        assert proc.returncode == 0, f"process {i}: {proc.stderr[-3000:]}"
    # The reference: one process of two devices, in one go.
    (ref,) = finish(start(tmp_path, 2, "--out", "ref", *FLAGS))
    assert ref.returncode == 0, ref.stderr[-3000:]
    # The same program over two devices: the same sums in the same order, so every array of the
    # state (weights, optimiser, normaliser, robots, RNG) agrees bit for bit, and so do the logs.
    got = saved_state(checkpoint.resolve(out))
    want = saved_state(checkpoint.resolve(tmp_path / "ref"))
    assert got.keys() == want.keys() and int(want[".update"]) == 6
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    rows, ref_rows = logged(out), logged(tmp_path / "ref")
    assert len(rows) == 7 and rows == ref_rows
    returns = [float(row[2]) for row in rows[1:]]
    assert not np.isnan(returns).all()  # episodes ended, so returns were compared


@pytest.mark.slow
def test_a_failing_process_stops_the_other(tmp_path):
    """Process 1 refuses its flags before training; process 0 stops too instead of waiting for it,
    and takes back the run folder it had started. Slow: two `jax.distributed` processes."""
    bad = ["--out", "run", *FLAGS, "--num-envs", "15", "--minibatch-size", "80"]
    zero, one = finish(*two_processes(tmp_path, ["--out", "run", *FLAGS], bad))
    assert one.returncode == 2
    assert one.stderr.strip().endswith("--num-envs 15 must be a multiple of the 2 devices")
    assert zero.returncode == 1
    assert zero.stderr.strip() == (
        "error: process 1 stopped before training (see its error); this one stops too"
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_unreachable_coordinator_times_out_in_one_line(tmp_path):
    """An unreachable coordinator ends the process in one line. Slow: a process that waits for
    its `--init-timeout`."""
    cluster = ["--coordinator", f"localhost:{free_port()}", "--num-processes", "2"]
    (proc,) = finish(
        start(tmp_path, 1, "--out", "run", *cluster, "--process-id", "1", "--init-timeout", "2")
    )
    assert proc.returncode == 1
    assert (
        proc.stderr.count("\n") == 1
        and "did not join the run within --init-timeout 2 s" in proc.stderr
    )


def flags(*argv) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    distributed.add_flags(parser)
    return parser.parse_args(argv)


def test_cluster_from_flags_or_environment():
    args = flags("--coordinator", "h:1234", "--num-processes", "4", "--process-id", "3")
    assert distributed.from_args(args, {}) == distributed.ClusterConfig("h:1234", 4, 3)
    env = {"JAX_COORDINATOR_ADDRESS": "h:99", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}
    assert distributed.from_args(flags(), env) == distributed.ClusterConfig("h:99", 2, 0)
    # The count and index left to JAX's detection of a SLURM, Open MPI or Kubernetes job.
    assert distributed.from_args(flags(), {"JAX_COORDINATOR_ADDRESS": "h:99"}).num_processes is None
    assert not distributed.from_args(flags(), {}).enabled  # one process


@pytest.mark.parametrize(
    "argv, env, message",
    [
        (
            ("--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"),
            {},
            "--process-id 2: out of range for --num-processes 2 (0 to 1)",
        ),
        (
            ("--coordinator", "h", "--num-processes", "2", "--process-id", "0"),
            {},
            "--coordinator: expected HOST:PORT",
        ),
        (("--coordinator", "h:1", "--num-processes", "2"), {}, "--process-id: needed with"),
        (
            (),
            {"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_PROCESS_ID": "one"},
            "JAX_PROCESS_ID: expected a whole number, got 'one'",
        ),
        (
            (),
            {"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "5"},
            "--process-id 5: out of range",
        ),
    ],
)
def test_bad_cluster_settings_name_the_flag(argv, env, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        distributed.from_args(flags(*argv), env)
