"""Checkpoints: restore by tree path, format versions, checksums, fallback past a corrupt newest one."""

import json
import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnav import runs
from jaxnav.io import checkpoint
from jaxnav.io.checkpoint import CheckpointError
from jaxnav.ppo.config import preset
from jaxnav.ppo.networks import init_stats
from jaxnav.ppo.train import TrainState, make_network
from jaxnav.runconfig import RunConfig
from jaxnav.tasks.avoid import AvoidConfig

PPO = preset("cpu", num_envs=2, rollout_length=4, minibatch_size=8, total_steps=8, hidden=(8,))


@pytest.fixture(scope="module")
def state():
    """A small TrainState (untrained network, no env) and its run config."""
    params = make_network(PPO, AvoidConfig().action_spec).init(
        jax.random.PRNGKey(0), jnp.zeros((1, 8))
    )
    ts = TrainState(params, (), init_stats(8), (), jax.random.PRNGKey(1), jnp.int32(1))
    return ts, RunConfig(ppo=PPO)


def save_updates(run, state, updates):
    ts, config = state
    return [checkpoint.save(run, ts.replace(update=jnp.int32(u)), config, {}) for u in updates]


def assert_one_line(err, *needles):
    text = str(err.value)
    assert "\n" not in text and all(n in text for n in needles), text


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


class Swapped(NamedTuple):  # the same names in the other order: flatten order differs
    b: jax.Array
    a: jax.Array


class Only(NamedTuple):
    a: jax.Array


class Renamed(NamedTuple):
    a: jax.Array
    c: jax.Array


def test_tree_is_restored_by_name(tmp_path):
    file = tmp_path / "tree.npz"
    x, y = jnp.arange(4.0), -jnp.arange(4.0)
    checkpoint.save_tree(file, {"a": x, "b": y})
    got = checkpoint.load_tree(file, {"b": jnp.zeros(4), "a": jnp.zeros(4)})
    np.testing.assert_array_equal(got["a"], x)
    np.testing.assert_array_equal(got["b"], y)
    checkpoint.save_tree(file, Pair(x, y))
    got = checkpoint.load_tree(file, Swapped(jnp.zeros(4), jnp.zeros(4)))
    np.testing.assert_array_equal(got.a, x)  # by flatten order it would be y
    np.testing.assert_array_equal(got.b, y)
    with pytest.raises(CheckpointError) as err:
        checkpoint.load_tree(file, Renamed(jnp.zeros(4), jnp.zeros(4)))
    assert_one_line(err, str(file), "no entry .c")
    with pytest.raises(CheckpointError) as err:
        checkpoint.load_tree(file, Only(jnp.zeros(4)))
    assert_one_line(err, str(file), "unexpected entry .b")
    with pytest.raises(CheckpointError) as err:
        checkpoint.load_tree(file, Pair(jnp.zeros(4), jnp.zeros(5)))
    assert_one_line(err, str(file), ".b is float32[4], this configuration needs float32[5]")


def test_train_state_entries_are_tree_paths(tmp_path, state):
    (ckpt,) = save_updates(tmp_path, state, [1])
    with np.load(ckpt / "train_state.npz") as data:
        names = set(data.files)
        assert int(data["format_version"]) == 2
    assert ".params['params']['actor']['Dense_0']['kernel']" in names
    assert ".obs_stats.mean" in names and ".update" in names
    restored = checkpoint.restore_train_state(ckpt, state[0])
    for a, b in zip(
        jax.tree_util.tree_leaves(restored), jax.tree_util.tree_leaves(state[0]), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    sums = json.loads((ckpt / "checksums.json").read_text())
    assert sorted(sums) == ["config.json", "meta.json", "policy.msgpack", "train_state.npz"]


def test_format_1_checkpoint_is_refused_in_one_line(tmp_path, state):
    (ckpt,) = save_updates(tmp_path, state, [1])
    leaves = jax.tree_util.tree_leaves(state[0])
    np.savez(ckpt / "train_state.npz", **{f"leaf_{i:05d}": x for i, x in enumerate(leaves)})
    with pytest.raises(CheckpointError) as err:
        checkpoint.restore_train_state(ckpt, state[0])
    assert_one_line(err, str(ckpt / "train_state.npz"), "written by an older jaxnav (format 1)")


def test_robots_state_of_another_physics_restarts_episodes(tmp_path, state, capsys):
    """A checkpoint whose robots' state (`env_state`) no longer fits, as one written before the
    physics state changed its fields, restores everything learnt and renews only the robots'
    state, with a note; a learner that does not fit is still refused."""
    ts, config = state
    saved = ts.replace(env_state={"geom_xpos": jnp.ones((2, 22, 3)), "qpos": jnp.ones((2, 3))})
    ckpt = checkpoint.save(tmp_path, saved, config, {})
    template = ts.replace(
        params=jax.tree_util.tree_map(jnp.zeros_like, ts.params),
        env_state={"geom_xpos": jnp.zeros((2, 5, 3)), "qpos": jnp.zeros((2, 3))},
    )
    got = checkpoint.restore_train_state(ckpt, template)
    learnt = lambda t: jax.tree_util.tree_leaves(t.replace(env_state=()))  # noqa: E731
    for a, b in zip(learnt(got), learnt(saved), strict=True):  # weights, optimiser, RNG, ...
        np.testing.assert_array_equal(a, b)
    assert got.env_state["geom_xpos"].shape == (2, 5, 3)
    np.testing.assert_array_equal(got.env_state["qpos"], 0.0)  # all of it from the template
    err = capsys.readouterr().err
    assert "robots start new episodes" in err and "['geom_xpos'] is float32[2, 22, 3]" in err, err
    same = template.replace(env_state=saved.env_state)  # fits: restored as saved, silently
    np.testing.assert_array_equal(checkpoint.restore_train_state(ckpt, same).env_state["qpos"], 1)
    assert capsys.readouterr().err == ""
    wider = make_network(PPO, AvoidConfig().action_spec)  # the learner no longer fits
    other = template.replace(params=wider.init(jax.random.PRNGKey(0), jnp.zeros((1, 9))))
    with pytest.raises(CheckpointError) as err:
        checkpoint.restore_train_state(ckpt, other)
    assert_one_line(err, "Dense_0']['kernel'] is float32[8, 8]", "needs float32[9, 8]")


def truncate(file):
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])


CORRUPTIONS = {  # file: what is done to it
    "train_state.npz": truncate,
    "policy.msgpack": lambda f: f.write_bytes(np.random.default_rng(0).bytes(64)),
    "meta.json": truncate,
}


@pytest.mark.parametrize("name", sorted(CORRUPTIONS))
def test_corrupt_file_is_named(tmp_path, state, name):
    (ckpt,) = save_updates(tmp_path, state, [1])
    CORRUPTIONS[name](ckpt / name)
    with pytest.raises(CheckpointError) as err:
        if name == "train_state.npz":
            checkpoint.restore_train_state(ckpt, state[0])
        else:
            runs.load_policy(ckpt)
    assert_one_line(err, str(ckpt / name))
    with pytest.raises(CheckpointError) as err:
        checkpoint.verify(ckpt)
    assert_one_line(err, str(ckpt / name), "corrupt")


def test_corrupt_newest_falls_back_to_previous(tmp_path, state, capsys):
    older, newest = save_updates(tmp_path, state, [1, 2])
    assert checkpoint.resolve(tmp_path) == newest and capsys.readouterr().err == ""
    truncate(newest / "train_state.npz")
    assert checkpoint.resolve(tmp_path) == older
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and str(newest) in lines[0] and str(older) in lines[0], lines
    checkpoint.restore_train_state(checkpoint.resolve(tmp_path), state[0])
    assert runs.load_policy(tmp_path).name.endswith("update_000001")
    with pytest.raises(CheckpointError) as err:  # named explicitly: no fallback
        runs.load_policy(newest)
    assert_one_line(err, str(newest / "train_state.npz"), "corrupt")
    truncate(older / "meta.json")  # none intact: the newest, whose load names the fault
    assert checkpoint.resolve(tmp_path) == newest


def test_save_keeps_newest_three_and_removes_stale_temporaries(tmp_path, state):
    root = tmp_path / "checkpoints"
    root.mkdir()
    stale = root / ".tmp-crashed"
    stale.mkdir()
    (stale / "policy.msgpack").write_bytes(b"half")
    past = time.time() - 60
    os.utime(stale, (past, past))
    kept = save_updates(tmp_path, state, [1, 2, 3, 4])
    assert checkpoint.list_checkpoints(tmp_path) == kept[1:]
    assert not stale.exists()


def test_checksums_of_another_checkpoint_blame_the_checksums_file(tmp_path, state, capsys):
    """Another run's checksums.json (same weights here) disowns three files; the message says
    that the checksums file does not match, not that config.json (the first it lists) is
    corrupt."""
    older, newest = save_updates(tmp_path / "a", state, [1, 2])
    (theirs,) = save_updates(tmp_path / "b", state, [3])
    _edit_seed(theirs)
    (newest / "checksums.json").write_bytes((theirs / "checksums.json").read_bytes())
    with pytest.raises(CheckpointError) as err:
        checkpoint.verify(newest)
    message = (
        f"{newest / 'checksums.json'}: does not match config.json, meta.json, train_state.npz "
        "(of 4 files): a checksums file of another checkpoint, or damaged (or several files are)"
    )
    assert str(err.value) == message
    assert checkpoint.resolve(tmp_path / "a") == older
    assert capsys.readouterr().err == f"warning: {message}; using the previous checkpoint {older}\n"


def _edit_seed(ckpt):
    """Rewrites a checkpoint's config.json with another seed, its checksums to match."""
    config = json.loads((ckpt / "config.json").read_text())
    config["seed"] += 1
    (ckpt / "config.json").write_text(json.dumps(config, indent=2))
    sums = json.loads((ckpt / "checksums.json").read_text())
    sums["config.json"] = checkpoint._sha256(ckpt / "config.json")
    (ckpt / "checksums.json").write_text(json.dumps(sums))
