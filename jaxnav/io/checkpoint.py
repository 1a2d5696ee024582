"""Run folders and checkpoints: atomic writes, the latest checkpoint, and `load_policy`.

A run folder holds `config.json`, `metrics.csv`, `reward_curve.png` and `checkpoints/update_NNNNNN/`,
each checkpoint with `policy.msgpack` (network weights and observation normaliser: all a robot needs),
`train_state.npz` (everything else to continue training) and `meta.json`. A checkpoint is written in a
hidden temporary folder and renamed into place, so a crash mid-write leaves the previous ones intact.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxnav.core import robot
from jaxnav.io.runconfig import RunConfig
from jaxnav.policy import Policy

CKPT_DIR = "checkpoints"
PREFIX = "update_"


class CheckpointError(ValueError):
    """A checkpoint or run folder that cannot be used; the message names the path."""


def save(run_dir: Path, ts, config: RunConfig, meta: dict, keep: int = 3) -> Path:
    """Writes checkpoint `update_<ts.update>` atomically; keeps the newest `keep` of them."""
    root = Path(run_dir) / CKPT_DIR
    root.mkdir(parents=True, exist_ok=True)
    update = int(ts.update)
    target = root / f"{PREFIX}{update:06d}"
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=root))
    try:
        host = jax.device_get(ts)
        policy = {"params": host.params, "obs_stats": serialization.to_state_dict(host.obs_stats)}
        (tmp / "policy.msgpack").write_bytes(
            serialization.msgpack_serialize(serialization.to_state_dict(policy))
        )
        leaves = jax.tree_util.tree_leaves(host)
        np.savez(
            tmp / "train_state.npz",
            **{f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)},
        )
        (tmp / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
        (tmp / "meta.json").write_text(json.dumps({"update": update, **meta}, indent=2))
        for f in tmp.iterdir():  # data on disk before the rename makes it visible
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in list_checkpoints(run_dir)[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return target


def list_checkpoints(run_dir: Path) -> list[Path]:
    """Complete checkpoints of a run, oldest first."""
    root = Path(run_dir) / CKPT_DIR
    if not root.is_dir():
        return []
    found = [p for p in root.iterdir() if p.name.startswith(PREFIX) and (p / "meta.json").exists()]
    return sorted(found, key=lambda p: p.name)


def resolve(path: str | os.PathLike) -> Path:
    """A checkpoint folder from a run folder (its latest checkpoint) or a checkpoint folder."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint or run folder")
    if (path / "policy.msgpack").exists():
        return path
    found = list_checkpoints(path)
    if not found:
        raise CheckpointError(
            f"{path}: no checkpoint in this folder (expected {CKPT_DIR}/{PREFIX}*)"
        )
    return found[-1]


def load_config(ckpt: Path) -> RunConfig:
    try:
        return RunConfig.from_dict(json.loads((ckpt / "config.json").read_text()))
    except (OSError, json.JSONDecodeError, ValueError, TypeError) as err:
        raise CheckpointError(f"{ckpt / 'config.json'}: unreadable run config ({err})") from None


def restore_train_state(ckpt: Path, template):
    """The TrainState saved in `ckpt`, shaped like `template` (a fresh `Trainer.init` result)."""
    leaves, treedef = jax.tree_util.tree_flatten(template)
    try:
        with np.load(ckpt / "train_state.npz") as data:
            saved = [data[f"leaf_{i:05d}"] for i in range(len(data.files))]
    except (OSError, ValueError, KeyError) as err:
        raise CheckpointError(f"{ckpt / 'train_state.npz'}: unreadable ({err})") from None
    if len(saved) != len(leaves) or any(
        a.shape != np.shape(b) for a, b in zip(saved, leaves, strict=True)
    ):
        raise CheckpointError(f"{ckpt}: the saved state does not match this configuration")
    return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(x) for x in saved])


def load_policy(path: str | os.PathLike, deterministic: bool = True) -> Policy:
    """The trained policy of a run or checkpoint folder: greedy (argmax) or sampling actions."""
    from jaxnav.ppo.networks import RunningStats, normalize
    from jaxnav.ppo.train import make_network

    ckpt = resolve(path)
    config = load_config(ckpt)
    try:
        raw = serialization.msgpack_restore((ckpt / "policy.msgpack").read_bytes())
        params = jax.tree_util.tree_map(jnp.asarray, raw["params"])
        stats = RunningStats(**{k: jnp.asarray(v) for k, v in raw["obs_stats"].items()})
    except (OSError, KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{ckpt / 'policy.msgpack'}: unreadable ({err})") from None
    network = make_network(config.ppo, len(robot.ACTION_NAMES))
    expected = jax.eval_shape(
        network.init, jax.random.PRNGKey(0), jnp.zeros((1, stats.mean.shape[-1]))
    )
    same = jax.tree_util.tree_structure(expected) == jax.tree_util.tree_structure(params) and all(
        a.shape == b.shape
        for a, b in zip(
            jax.tree_util.tree_leaves(expected), jax.tree_util.tree_leaves(params), strict=True
        )
    )
    if not same:
        raise CheckpointError(
            f"{ckpt / 'policy.msgpack'}: weights do not match the network of {ckpt / 'config.json'}"
        )
    use_stats = config.ppo.normalize_obs

    def act(obs, key):
        logits, _ = network.apply(params, normalize(stats, obs) if use_stats else obs)
        if deterministic:
            return jnp.argmax(logits, axis=-1).astype(jnp.int32)
        return jax.random.categorical(key, logits).astype(jnp.int32)

    name = f"{ckpt.parent.parent.name}/{ckpt.name}"
    return Policy(name=name, act=act, env_kwargs=config.env_kwargs())
