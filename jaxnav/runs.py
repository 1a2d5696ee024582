"""A run as a whole: its config from a run folder, and the trained policy it holds.

This is where a run's files (`jaxnav.io.checkpoint`) meet what they describe: the run config
(`jaxnav.runconfig`), the network it trained (`jaxnav.ppo`) and the task it trained on
(`jaxnav.tasks`). The command lines and the public API (`jaxnav.load_policy`) read runs through it.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxnav.io.checkpoint import CheckpointError, one_line, resolve, verify
from jaxnav.io.files import MAX_BINARY_BYTES, FileProblem, read_bytes, read_json
from jaxnav.policy import Policy
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.networks import RunningStats, normalize
from jaxnav.ppo.train import make_network
from jaxnav.runconfig import RunConfig
from jaxnav.tasks.base import observation_size
from jaxnav.tasks.registry import critic_size


def load_config(folder: Path) -> RunConfig:
    """The RunConfig in `folder`/config.json (a run or checkpoint folder); errors name the file."""
    file = Path(folder) / "config.json"
    try:
        return RunConfig.from_dict(read_json(file))
    except FileProblem as err:
        raise CheckpointError(f"{file}: unreadable run config ({err.detail})") from None
    except (ValueError, TypeError) as err:
        raise CheckpointError(f"{file}: unreadable run config ({err})") from None


@dataclasses.dataclass(frozen=True, eq=False)
class SavedPolicy:
    """A checkpoint's policy, its weights checked against its run config (from `read_policy`)."""

    ckpt: Path
    """The checkpoint folder it was read from."""
    config: RunConfig
    """The run's settings (config.json): network, sensor and task."""
    params: dict
    """Actor and critic weights (flax variables), shaped as `network` builds them."""
    obs_stats: object
    """The observation normaliser (a RunningStats, [D] each); applied when ppo.normalize_obs."""

    @property
    def num_actions(self) -> int:
        """A: the width of the actor's output layer."""
        actor = self.params["params"]["actor"]
        return int(np.shape(actor[f"Dense_{len(actor) - 1}"]["bias"])[0])

    @functools.cached_property
    def network(self):
        """The ActorCritic module the weights belong to."""
        ppo, task = self.config.ppo, self.config.task
        return make_network(ppo, task.action_spec, critic_size(task, ppo.privileged_critic))

    @property
    def observation_size(self) -> int:
        """D: the depth sectors and the task's extra entries (the goal task's goal and command)."""
        return observation_size(self.config.task, self.config.sensor)

    @property
    def distribution(self):
        """The actor's action distribution (`jaxnav.ppo.distributions`)."""
        return make_distribution(self.config.task.action_spec)

    def logits(self, obs: jax.Array) -> jax.Array:
        """obs [..., D] -> the actor's output [..., K] (logits; a Gaussian's means and log-stds
        for continuous actions); jittable."""
        x = normalize(self.obs_stats, obs) if self.config.ppo.normalize_obs else obs
        return self.network.apply(self.params, x)[0]


def read_policy(ckpt: Path) -> SavedPolicy:
    """The policy of checkpoint folder `ckpt`: weights, normaliser and config, checked to fit."""
    config = load_config(ckpt)
    file = ckpt / "policy.msgpack"
    try:
        raw = serialization.msgpack_restore(read_bytes(file, MAX_BINARY_BYTES))
        params = jax.tree_util.tree_map(jnp.asarray, raw["params"])
        stats = RunningStats(**{k: jnp.asarray(v) for k, v in raw["obs_stats"].items()})
        saved = SavedPolicy(ckpt, config, params, stats)
        saved.num_actions  # noqa: B018 (the actor's output layer exists)
    except Exception as err:  # noqa: BLE001 (damaged bytes make msgpack raise many kinds)
        raise CheckpointError(f"{file}: unreadable ({one_line(err)})") from None
    _check_fits(saved, file)
    verify(ckpt)  # after the content checks: their messages name the field at fault
    return saved


def _check_fits(saved: SavedPolicy, file: Path) -> None:
    """The weights have the shapes of the network (and sensor) that config.json describes."""
    size = saved.observation_size
    expected = jax.eval_shape(saved.network.init, jax.random.PRNGKey(0), jnp.zeros((1, size)))
    shapes = lambda tree: {  # noqa: E731
        jax.tree_util.keystr(path): tuple(np.shape(x))
        for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]
    }
    want, got = shapes(expected), shapes(saved.params)
    want[".obs_stats.mean"], got[".obs_stats.mean"] = (size,), np.shape(saved.obs_stats.mean)
    if want != got:
        key = next(k for k in [*want, *got] if want.get(k) != got.get(k))
        raise CheckpointError(
            f"{file}: weights do not match the network of {saved.ckpt / 'config.json'} "
            f"({key}: saved {got.get(key)}, the config's network {want.get(key)})"
        )


def load_policy(path: str | os.PathLike, deterministic: bool = True) -> Policy:
    """The trained policy of a run or checkpoint folder: greedy (argmax; the clipped mean of
    continuous actions) or sampling actions."""
    saved = read_policy(resolve(path))
    dist = saved.distribution

    def act(obs, key):
        out = saved.logits(obs)
        return dist.mode(out) if deterministic else dist.sample(key, out)

    name = f"{saved.ckpt.parent.parent.name}/{saved.ckpt.name}"
    return Policy(name=name, act=act, env_kwargs=saved.config.env_kwargs(), env=saved.config.env)
