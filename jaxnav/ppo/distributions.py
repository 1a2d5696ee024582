"""Action distributions of the actor: categorical for a table of commands, Gaussian for commands.

The actor network's output (`out`, [..., K]) is read by the distribution of the task's action spec
(`make_distribution`): K = A logits for `DiscreteActions`; K = 2A for `ContinuousActions`, a mean
and a log standard deviation per dimension in units of half the dimension's range.

Continuous actions use a diagonal Gaussian whose samples are sent to the env as they are and
clipped by the env to the spec's bounds (`NavTask.command`). Why clipped rather than tanh-squashed:
the log-probability and the entropy are exact and closed-form (a squashed Gaussian needs the tanh
Jacobian and has no closed-form entropy), and the bounds of our commands (full forward speed, full
turn rate) are where good driving often is: a clipped policy reaches them with a finite mean, a
squashed one only as its pre-activation grows without bound. The price is a bias in the gradient
where much probability lies beyond a bound, which the learned standard deviation shrinks.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnav.core.types import ContinuousActions, DiscreteActions
from jaxnav.ppo.networks import entropy as categorical_entropy
from jaxnav.ppo.networks import log_prob as categorical_log_prob
from jaxnav.ppo.networks import sample_action

LOG_SQRT_2PI_E = 0.5 * float(np.log(2 * np.pi * np.e))  # entropy of N(0, 1)
LOG_SQRT_2PI = 0.5 * float(np.log(2 * np.pi))


@dataclasses.dataclass(frozen=True)
class Categorical:
    """Softmax over `n` actions (the paper's actor); actions are int32 indices [...]."""

    n: int

    @property
    def out_size(self) -> int:
        """Actor outputs: one logit per action."""
        return self.n

    @property
    def action_shape(self) -> tuple[int, ...]:
        return ()

    def sample(self, key, out):
        return sample_action(key, out)

    def log_prob(self, out, action):
        return categorical_log_prob(out, action)

    def entropy(self, out):
        return categorical_entropy(out)

    def mode(self, out):
        """The greedy action: argmax of the logits."""
        return jnp.argmax(out, axis=-1).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class Gaussian:
    """Diagonal Gaussian over commands [..., A] in the spec's units, clipped by the env.

    The network's mean m and log-std s are in units of half the range: the command's mean is
    centre + half * m and its std half * exp(s), so one initialisation suits every unit.
    """

    low: tuple[float, ...]
    high: tuple[float, ...]

    @property
    def out_size(self) -> int:
        """Actor outputs: a mean and a log-std per dimension."""
        return 2 * len(self.low)

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (len(self.low),)

    def _moments(self, out):
        low, high = jnp.asarray(self.low), jnp.asarray(self.high)
        centre, half = 0.5 * (high + low), 0.5 * (high - low)
        a = len(self.low)
        mean, log_std = out[..., :a], out[..., a:]
        return centre + half * mean, jnp.log(half) + log_std  # [..., A] each

    def sample(self, key, out):
        mean, log_std = self._moments(out)
        return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)

    def log_prob(self, out, action):
        mean, log_std = self._moments(out)
        z = (action - mean) * jnp.exp(-log_std)
        return jnp.sum(-0.5 * z**2 - log_std - LOG_SQRT_2PI, axis=-1)

    def entropy(self, out):
        _, log_std = self._moments(out)
        return jnp.sum(log_std + LOG_SQRT_2PI_E, axis=-1)

    def mode(self, out):
        """The deterministic command: the mean, clipped to the bounds."""
        mean, _ = self._moments(out)
        return jnp.clip(mean, jnp.asarray(self.low), jnp.asarray(self.high))


Distribution = Categorical | Gaussian


def make_distribution(spec) -> Distribution:
    """The actor's distribution for an env's action spec."""
    if isinstance(spec, DiscreteActions):
        return Categorical(spec.n)
    if isinstance(spec, ContinuousActions):
        return Gaussian(tuple(spec.low), tuple(spec.high))
    raise ValueError(f"PPO: unknown action spec {type(spec).__name__}")
