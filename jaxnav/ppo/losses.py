"""PPO losses: generalised advantage estimation and the clipped surrogate objective.

Paper Eq. 1-5 are standard PPO: clipped surrogate (1), value MSE (2), combined loss with
entropy bonus (3), TD residual (4) and GAE advantage (5).
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxnav.ppo.distributions import Categorical, Distribution


class Batch(NamedTuple):
    """A (mini)batch of N transitions collected by the behaviour policy."""

    obs: object  # what apply_fn reads: obs [N, D], or a tuple (the trainer's: obs, critic inputs)
    action: jax.Array  # [N] int (discrete) or [N, A] float (continuous commands)
    log_prob: jax.Array  # [N] log pi_old(action | obs)
    value: jax.Array  # [N] V_old(obs), used for value clipping
    advantage: jax.Array  # [N] GAE, not yet normalised
    target: jax.Array  # [N] value target (GAE return)


def _gae_step(carry, inputs, *, gamma: float, lam: float):
    """One reverse GAE step; carry = (V of the next state [B], next advantage [B])."""
    next_value, next_adv = carry
    reward, value, done, trunc = inputs  # each [B]
    # On truncation the true next state (the one the time limit cut off) is not stored, so
    # values[t] stands in for its value: an approximation, exact only when V changes little
    # over one step. On termination there is nothing to bootstrap.
    bootstrap = jnp.where(trunc, value, next_value)
    not_terminal = 1.0 - jnp.logical_and(done, jnp.logical_not(trunc)).astype(jnp.float32)
    delta = reward + gamma * bootstrap * not_terminal - value  # Eq. 4
    # Any episode end (termination or truncation) stops the advantage carrying over from
    # the next episode's first step.
    not_done = 1.0 - done.astype(jnp.float32)
    adv = delta + gamma * lam * not_done * next_adv  # Eq. 5
    return (value, adv), adv


def compute_gae(
    rewards: jax.Array,
    values: jax.Array,
    dones: jax.Array,
    last_value: jax.Array,
    gamma: float,
    lam: float,
    truncations: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimates and returns for a rollout.

    rewards, values, dones [T, B]; last_value [B] is V of the state after step T-1.
    dones[t]: the episode ended after step t, so values[t + 1] (a new episode) is not used.
    truncations[t] (optional, bool, meant as a subset of dones; a truncation also counts as
    an episode end): the episode hit its time limit after step t; bootstraps with values[t]
    as the estimate of the cut-off next state's value (see `_gae_step`).
    Returns (advantages [T, B], returns = advantages + values [T, B]).
    """
    values = jnp.asarray(values, jnp.float32)
    rewards = jnp.asarray(rewards, jnp.float32)
    dones = jnp.asarray(dones).astype(bool)
    if truncations is None:
        truncations = jnp.zeros_like(dones)
    truncations = jnp.asarray(truncations).astype(bool)
    dones = jnp.logical_or(dones, truncations)  # a truncation is an episode end as well

    def step(carry, inputs):
        return _gae_step(carry, inputs, gamma=gamma, lam=lam)

    last_value = jnp.asarray(last_value, jnp.float32)
    init = (last_value, jnp.zeros_like(last_value))  # [B], [B]
    _, advantages = jax.lax.scan(
        step, init, (rewards, values, dones, truncations), reverse=True
    )  # [T, B]
    return advantages, advantages + values


def ppo_loss(
    params,
    apply_fn: Callable,
    batch: Batch,
    *,
    clip_eps: float,
    vf_coef: float,
    ent_coef: float,
    clip_value: bool,
    dist: Distribution | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """PPO loss = -surrogate + vf_coef * value_loss - ent_coef * entropy (Eq. 3).

    apply_fn(params, batch.obs) -> (actor output [N, K], value [N]), e.g. `ActorCritic.apply`;
    `dist` reads the actor output (default: a categorical over K logits).
    Value clipping (when clip_value) keeps the new value within clip_eps of batch.value; it
    uses the same clip_eps as the policy, so with returns of order 100 it slows the critic.
    Returns (loss, metrics) with metrics total, policy_loss, value_loss, entropy, approx_kl,
    clip_fraction (fraction of samples whose ratio lies outside [1 - eps, 1 + eps]).
    """
    logits, value = apply_fn(params, batch.obs)  # [N, K], [N]
    dist = dist or Categorical(logits.shape[-1])
    new_log_prob = dist.log_prob(logits, batch.action)  # [N]
    log_ratio = new_log_prob - batch.log_prob
    ratio = jnp.exp(log_ratio)  # [N]

    # Per-minibatch normalisation makes the step size independent of the reward scale.
    adv = batch.advantage
    adv = (adv - jnp.mean(adv)) / (jnp.std(adv) + 1e-8)  # [N]

    # Eq. 1: pessimistic (min) of the unclipped and clipped surrogate.
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * adv)
    policy_loss = -jnp.mean(surrogate)

    # Eq. 2: squared error, optionally the larger of the unclipped and clipped errors.
    value_err = jnp.square(value - batch.target)  # [N]
    if clip_value:
        value_clipped = batch.value + jnp.clip(value - batch.value, -clip_eps, clip_eps)
        value_err = jnp.maximum(value_err, jnp.square(value_clipped - batch.target))
    value_loss = 0.5 * jnp.mean(value_err)

    ent = jnp.mean(dist.entropy(logits))
    total = policy_loss + vf_coef * value_loss - ent_coef * ent  # Eq. 3 as a loss

    metrics = {
        "total": total,
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": ent,
        # k3 estimator of KL(old || new): unbiased and non-negative (Schulman, 2020).
        "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),
        "clip_fraction": jnp.mean((jnp.abs(ratio - 1.0) > clip_eps).astype(jnp.float32)),
    }
    return total, metrics
