"""Policies as plain functions: a trained network (`load_policy`) or a baseline."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxnav.core.types import DiscreteActions
from jaxnav.tasks.avoid import AvoidConfig

ActFn = Callable[[jax.Array, jax.Array], jax.Array]  # (obs [..., D], key) -> action int32 [...]
PAPER_ACTIONS = AvoidConfig().action_spec


@dataclasses.dataclass(frozen=True)
class Policy:
    """A jittable action function and the env settings it was trained with."""

    name: str
    """Shown in tables and file names."""
    act: ActFn
    """(obs [..., D] float32, PRNG key) -> action [...] int32, an index of the task's actions."""
    env_kwargs: dict = dataclasses.field(default_factory=dict)
    """`make_env` keyword arguments of training (task, sensor, scene, robot); {} for baselines."""
    env: str = "avoid"
    """The registered task the policy acts in."""


def forward_policy(actions: DiscreteActions = PAPER_ACTIONS) -> Policy:
    """Always the fastest forward action: collides in most rooms, the floor to beat."""
    fastest = int(actions.table()[:, 0].argmax())
    return Policy("forward", lambda obs, key: jnp.full(obs.shape[:-1], fastest, jnp.int32))


def random_policy(actions: DiscreteActions = PAPER_ACTIONS) -> Policy:
    """Uniformly random actions."""
    return Policy("random", lambda obs, key: jax.random.randint(key, obs.shape[:-1], 0, actions.n))


BASELINES = {"forward": forward_policy, "random": random_policy}
