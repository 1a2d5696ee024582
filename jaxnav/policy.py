"""Policies as plain functions: a trained network (`load_policy`) or a baseline."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxnav.core.types import ActionSpec, ContinuousActions
from jaxnav.tasks.avoid import AvoidConfig

# (obs [..., D], key) -> action: int32 [...] (an index of the task's actions) or float32 [..., A]
# (continuous commands)
ActFn = Callable[[jax.Array, jax.Array], jax.Array]
PAPER_ACTIONS = AvoidConfig().action_spec


@dataclasses.dataclass(frozen=True)
class Policy:
    """A jittable action function and the env settings it was trained with."""

    name: str
    """Shown in tables and file names."""
    act: ActFn
    """(obs [..., D] float32, PRNG key) -> action: [...] int32, an index of the task's actions, or
    [..., A] float32 commands for continuous actions."""
    env_kwargs: dict = dataclasses.field(default_factory=dict)
    """`make_env` keyword arguments of training (task, sensor, scene, robot); {} for baselines."""
    env: str = "avoid"
    """The registered task the policy acts in."""


def forward_policy(actions: ActionSpec = PAPER_ACTIONS) -> Policy:
    """Always the fastest forward action (top speed, no turn): collides in most rooms, the floor
    to beat."""
    if isinstance(actions, ContinuousActions):
        top = jnp.array([actions.high[0], 0.0])
        return Policy("forward", lambda obs, key: jnp.broadcast_to(top, (*obs.shape[:-1], 2)))
    fastest = int(actions.table()[:, 0].argmax())
    return Policy("forward", lambda obs, key: jnp.full(obs.shape[:-1], fastest, jnp.int32))


def random_policy(actions: ActionSpec = PAPER_ACTIONS) -> Policy:
    """Uniformly random actions (continuous: uniform within the bounds)."""
    if isinstance(actions, ContinuousActions):
        low, high = jnp.array(actions.low), jnp.array(actions.high)
        shape = lambda obs: (*obs.shape[:-1], actions.size)  # noqa: E731
        return Policy(
            "random",
            lambda obs, key: jax.random.uniform(key, shape(obs), minval=low, maxval=high),
        )
    return Policy("random", lambda obs, key: jax.random.randint(key, obs.shape[:-1], 0, actions.n))


def stand_policy(actions: ActionSpec = PAPER_ACTIONS) -> Policy:
    """Never drives: the (0, 0) command, or the discrete action with the least forward speed and
    then the least turn (stop where the actions have it, else turning in place). It causes no
    collision: what is left is what moving people and obstacles do to a robot that does not move."""
    if isinstance(actions, ContinuousActions):
        zero = jnp.zeros(actions.size, jnp.float32)
        shape = lambda obs: (*obs.shape[:-1], actions.size)  # noqa: E731
        return Policy("stand", lambda obs, key: jnp.broadcast_to(zero, shape(obs)))
    table = np.abs(actions.table())  # [n, 2] |forward|, |turn|
    still = int(np.lexsort((table[:, 1], table[:, 0]))[0])
    return Policy("stand", lambda obs, key: jnp.full(obs.shape[:-1], still, jnp.int32))


BASELINES = {"forward": forward_policy, "random": random_policy, "stand": stand_policy}
