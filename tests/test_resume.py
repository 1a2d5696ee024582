"""Nothing trained is lost: SIGINT/SIGTERM checkpoints, bit-exact resume, atomic writes, NaN guard."""

import signal
import subprocess
import sys

import jax
import numpy as np
import pytest
from conftest import TINY_FLAGS, run_cli

import jaxnav.cli.train as train_cli
from jaxnav import training as train_module
from jaxnav.io import checkpoint
from jaxnav.ppo.train import make_train


def saved_state(ckpt):
    with np.load(ckpt / "train_state.npz") as data:
        return {k: data[k] for k in data.files}


def interrupt(out, sig):
    """Starts a tiny run, signals it once its first chunk has run (training has something to
    save), and waits for it to exit."""
    cmd = [sys.executable, "-m", "jaxnav.train", "--out", str(out), *TINY_FLAGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith("jaxnav: compiled"):
            break
    assert seen[-1].startswith("jaxnav: compiled"), "".join(seen) + proc.stderr.read()
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=600)
    return proc.returncode, stdout, stderr


# SIGINT's own handling (exit at once in one line, an unfinished folder removed) is tested in
# test_reliability.py; its checkpoint-and-resume is the same path as SIGTERM's.
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_checkpoints_then_resume_matches_uninterrupted(tiny_run, tmp_path, sig):
    """Slow: two training processes (the interrupted run and its resume) each start Python and
    compile the whole trainer before the bit-for-bit comparison can be made."""
    reference, _ = tiny_run  # the same flags, never interrupted
    out = tmp_path / "run"
    code, stdout, stderr = interrupt(out, sig)
    assert code == 0, stderr
    lines = [line for line in stdout.splitlines() if line.startswith("interrupted")]
    assert len(lines) == 1 and f"--resume {out}" in lines[0] and sig.name in lines[0]
    # The chunk under way when the signal came finishes and is checkpointed.
    assert checkpoint.list_checkpoints(out)[-1].name in ("update_000002", "update_000004")
    proc = run_cli("--resume", str(out), "--no-progress")
    assert proc.returncode == 0, proc.stderr
    final, expected = checkpoint.resolve(out), checkpoint.resolve(reference)
    assert final.name == expected.name == "update_000006"
    got, want = saved_state(final), saved_state(expected)
    assert got.keys() == want.keys()
    for key in want:  # params, optimiser, normaliser, robots and RNG: bit for bit
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    rows = (out / "metrics.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == [1, 2, 3, 4, 5, 6]


@pytest.mark.slow
def test_resume_refuses_other_flags(tiny_run):
    """A resume with a changed flag is refused in one line. Slow: the tiny CLI run, then a CLI
    process."""
    out, _ = tiny_run
    proc = run_cli("--resume", str(out), "--num-envs", "32")
    assert proc.returncode == 2 and "drop --num-envs" in proc.stderr


def tiny_config():
    flags = train_cli.parse_args(TINY_FLAGS)
    return train_module.build_config("cpu", 0, None, train_cli.overrides_from_args(flags))


@pytest.mark.slow
def test_same_seed_same_params():
    """Two runs of one seed give the same parameters. Slow: two whole training runs."""
    config = tiny_config()
    env = train_module.make_run_env(config)
    runs = [make_train(config.ppo, env).train(jax.random.PRNGKey(7))[0].params for _ in range(2)]
    for a, b in zip(*map(jax.tree_util.tree_leaves, runs), strict=True):
        np.testing.assert_array_equal(a, b)


def test_crash_during_checkpoint_write_keeps_previous(tmp_path, monkeypatch):
    config = tiny_config()
    trainer = make_train(config.ppo, train_module.make_run_env(config))
    ts = trainer.init(jax.random.PRNGKey(0))
    first = checkpoint.save(tmp_path, ts, config, {})
    before = saved_state(first)

    def crash(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(checkpoint.os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(tmp_path, ts.replace(update=ts.update + 1), config, {})
    assert checkpoint.list_checkpoints(tmp_path) == [first]
    assert not [p for p in (tmp_path / "checkpoints").iterdir() if p.name.startswith(".tmp")]
    after = saved_state(checkpoint.resolve(tmp_path))
    assert all(np.array_equal(before[k], after[k]) for k in before)


@pytest.mark.slow
def test_nan_stops_training_and_keeps_last_good_checkpoint(tmp_path, monkeypatch):
    """A NaN loss stops the run and keeps the last good checkpoint. Slow: a training run with a
    poisoned update compiled for it."""
    real = train_module.make_train

    def poisoned(cfg, env):
        trainer = real(cfg, env)

        def compose(programs):  # whichever programs the run compiles, a poisoned chunk
            init, chunk = trainer.compose(programs)

            def run_chunk(ts):
                ts, metrics = chunk(ts)
                if int(ts.update) > 2:  # the second chunk diverges
                    params = jax.tree_util.tree_map(lambda x: x * np.nan, ts.params)
                    ts = ts.replace(params=params)
                return ts, metrics

            return init, run_chunk

        return trainer._replace(compose=compose).with_programs()

    monkeypatch.setattr(train_module, "make_train", poisoned)
    with pytest.raises(FloatingPointError, match="NaN/Inf in the weights") as err:
        train_module.run(tiny_config(), tmp_path, progress=False)
    assert "update_000002" in str(err.value)
    kept = checkpoint.list_checkpoints(tmp_path)
    assert [c.name for c in kept] == ["update_000002"]
    assert all(np.isfinite(v).all() for v in saved_state(kept[0]).values() if v.dtype.kind == "f")
