"""Actor-critic networks, observation normalisation and categorical-policy helpers.

The paper's networks are MLPs with two dense layers of 64 units and LeakyReLU. The actor
ends in 3 units with softmax (forward / left / right); the critic ends in one unit with tanh.
"""

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# The paper does not give LeakyReLU's negative slope; 0.01 is the common default
# (PyTorch, flax).
LEAKY_SLOPE = 0.01
CRITIC_OUTPUTS = ("tanh", "linear")
# Continuous actions: initial std of 0.6 half-ranges, e.g. +-0.15 m/s around 0.25 m/s forward:
# broad exploration that still rarely saturates a bound.
INIT_LOG_STD = -0.5


class MLP(nn.Module):
    """Dense + LeakyReLU layers, then a linear output layer of `out_size` units."""

    hidden: Sequence[int]
    out_size: int
    out_scale: float  # orthogonal-init gain of the output layer

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Maps x [..., D] to [..., out_size]."""
        ortho = jax.nn.initializers.orthogonal
        zeros = jax.nn.initializers.zeros
        for width in self.hidden:
            # sqrt(2) gain keeps activations' scale roughly constant through ReLU-like layers.
            x = nn.Dense(width, kernel_init=ortho(np.sqrt(2.0)), bias_init=zeros)(x)
            x = nn.leaky_relu(x, negative_slope=LEAKY_SLOPE)
        return nn.Dense(self.out_size, kernel_init=ortho(self.out_scale), bias_init=zeros)(x)


class ActorCritic(nn.Module):
    """Separate (unshared) actor and critic MLPs.

    Returns `(logits [..., A], value [...])` for observations `[..., D]`.

    The paper's actor output is `softmax(logits)`; the softmax is left to the callers
    (`log_prob`, `entropy`, `sample_action`), which work on logits for numerical stability.

    continuous: the actor's output is [..., 2A] instead: A means, then A log standard deviations
        (a learned parameter `log_std` [A], the same for every observation, starting at
        INIT_LOG_STD), read by `jaxnav.ppo.distributions.Gaussian`.

    critic_inputs: C > 0 gives the critic `critic_obs` [..., C] after the observation (inputs from
        the simulator that the robot lacks, `PPOConfig.privileged_critic`); the actor never sees
        them. Acting needs only the logits, so `critic_obs` may be left out: the critic then
        reads zeros and its value means nothing.

    critic_output:
        "tanh" (the paper's): value = value_scale * tanh(v). With value_scale = 1.0, the
            paper's setting, values lie in [-1, 1] although returns can reach -100.
        "linear": value = v, unbounded; use it (or a larger value_scale) when returns are
            far outside [-1, 1]. value_scale is ignored.
    """

    action_size: int
    hidden: tuple[int, ...] = (64, 64)
    critic_output: str = "tanh"
    value_scale: float = 1.0  # 1.0 is the paper's (plain tanh)
    continuous: bool = False  # A Gaussian's means and log-stds instead of A logits
    critic_inputs: int = 0  # C, inputs only the critic sees (a privileged critic)

    @nn.compact
    def __call__(self, obs: jax.Array, critic_obs: jax.Array | None = None):
        """obs [..., D] (critic_obs [..., C], the critic's own) -> (logits [..., A], value [...])."""
        if self.critic_output not in CRITIC_OUTPUTS:
            raise ValueError(
                f"critic_output must be one of {CRITIC_OUTPUTS}, got {self.critic_output!r}"
            )
        # Small policy-head gain: near-uniform initial policy, so early exploration is broad.
        logits = MLP(self.hidden, self.action_size, 0.01, name="actor")(obs)  # [..., A]
        if self.continuous:
            init = jax.nn.initializers.constant(INIT_LOG_STD)
            log_std = self.param("log_std", init, (self.action_size,))  # [A]
            logits = jnp.concatenate([logits, jnp.broadcast_to(log_std, logits.shape)], -1)
        if self.critic_inputs:
            if critic_obs is None:
                critic_obs = jnp.zeros((*obs.shape[:-1], self.critic_inputs), obs.dtype)
            obs = jnp.concatenate([obs, critic_obs], -1)  # [..., D + C]
        value = MLP(self.hidden, 1, 1.0, name="critic")(obs)[..., 0]  # [...]
        if self.critic_output == "tanh":
            value = self.value_scale * jnp.tanh(value)
        return logits, value


# ---------------------------------------------------------------- observation normalisation


@struct.dataclass
class RunningStats:
    """Running per-feature mean and population variance of observations.

    mean [D], var [D], count [] (float32: it stays usable, if inexact, past 2**24 samples
    instead of overflowing as int32 would).
    """

    mean: jax.Array
    var: jax.Array
    count: jax.Array


def init_stats(size: int) -> RunningStats:
    """Empty statistics for `size` features.

    count starts at 0 so the first update gives exactly that batch's mean/var; var starts at 1
    so `normalize` before any update only subtracts a zero mean.
    """
    return RunningStats(
        mean=jnp.zeros((size,), jnp.float32),
        var=jnp.ones((size,), jnp.float32),
        count=jnp.zeros((), jnp.float32),
    )


def update_stats(stats: RunningStats, batch_obs: jax.Array) -> RunningStats:
    """Folds a batch [N, D] (or [..., D], flattened) with N >= 1 into the statistics.

    Chan et al.'s parallel-variance combination, i.e. Welford's update over a whole batch:
    exact (up to rounding) mean and population variance of all data seen so far.
    """
    batch_obs = jnp.reshape(batch_obs, (-1, stats.mean.shape[-1])).astype(jnp.float32)  # [N, D]
    n = batch_obs.shape[0]
    batch_mean = jnp.mean(batch_obs, axis=0)  # [D]
    batch_var = jnp.var(batch_obs, axis=0)  # [D]
    total = stats.count + n
    delta = batch_mean - stats.mean  # [D]
    weight = n / total  # the new batch's share of all samples
    mean = stats.mean + delta * weight
    # Sums of squared deviations (M2) of both parts plus the between-means correction.
    m2 = stats.var * stats.count + batch_var * n + jnp.square(delta) * stats.count * weight
    return RunningStats(mean=mean, var=m2 / total, count=total)


def normalize(stats: RunningStats, obs: jax.Array, clip: float = 10.0) -> jax.Array:
    """(obs - mean) / std, clipped to [-clip, clip]; obs [..., D] -> [..., D]."""
    # The 1e-8 keeps constant features (var 0) finite.
    z = (obs - stats.mean) / jnp.sqrt(stats.var + 1e-8)
    return jnp.clip(z, -clip, clip)


# ---------------------------------------------------------------- categorical policy helpers


def sample_action(key: jax.Array, logits: jax.Array) -> jax.Array:
    """Samples from softmax(logits); logits [..., A] -> action [...] int32."""
    return jax.random.categorical(key, logits, axis=-1).astype(jnp.int32)


def log_prob(logits: jax.Array, action: jax.Array) -> jax.Array:
    """log softmax(logits)[action]; logits [..., A], action [...] -> [...]."""
    logp = jax.nn.log_softmax(logits, axis=-1)  # [..., A]
    action = jnp.asarray(action, jnp.int32)[..., None]  # [..., 1]
    return jnp.take_along_axis(logp, action, axis=-1)[..., 0]


def entropy(logits: jax.Array) -> jax.Array:
    """Entropy of softmax(logits); logits [..., A] -> [...]."""
    logp = jax.nn.log_softmax(logits, axis=-1)  # [..., A]
    p = jnp.exp(logp)
    # Actions of probability 0 (logit -inf) must add 0, not 0 * -inf = nan; masking logp
    # before the product keeps the gradient finite too.
    safe_logp = jnp.where(p > 0, logp, 0.0)
    return -jnp.sum(p * safe_logp, axis=-1)
