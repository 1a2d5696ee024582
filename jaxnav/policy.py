"""Policies as plain functions: a trained network (`load_policy`) or a baseline."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxnav.core import robot

ActFn = Callable[[jax.Array, jax.Array], jax.Array]  # (obs [..., 8], key) -> action int32 [...]


@dataclasses.dataclass(frozen=True)
class Policy:
    """A jittable action function and the env settings it was trained with."""

    name: str
    """Shown in tables and file names."""
    act: ActFn
    """(obs [..., 8] float32, PRNG key) -> action [...] int32 in {0, 1, 2}."""
    env_kwargs: dict = dataclasses.field(default_factory=dict)
    """`make_env` keyword arguments of training (task, sensor, scene configs); {} for baselines."""


def forward_policy() -> Policy:
    """Always drives forward: collides in most rooms, the floor any learned policy must beat."""
    return Policy("forward", lambda obs, key: jnp.zeros(obs.shape[:-1], jnp.int32))


def random_policy() -> Policy:
    """Uniformly random actions."""
    n = len(robot.ACTION_NAMES)
    return Policy("random", lambda obs, key: jax.random.randint(key, obs.shape[:-1], 0, n))


BASELINES = {"forward": forward_policy, "random": random_policy}
