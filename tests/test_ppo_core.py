"""Tests of the PPO core: GAE, the PPO loss terms, the actor-critic network and RunningStats."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnav.ppo.losses import Batch, compute_gae, ppo_loss
from jaxnav.ppo.networks import (
    ActorCritic,
    entropy,
    init_stats,
    log_prob,
    normalize,
    sample_action,
    update_stats,
)

# ---------------------------------------------------------------- GAE

GAMMA, LAM = 0.9, 0.8  # gamma * lam = 0.72
# T=3, B=2. Column 0's episode ends after t=1; column 1 runs through.
REWARDS = np.array([[1.0, 0.0], [2.0, 1.0], [3.0, -1.0]], np.float32)
VALUES = np.array([[0.5, 1.0], [1.0, 0.5], [2.0, 0.0]], np.float32)
DONES = np.array([[0, 0], [1, 0], [0, 0]], bool)
LAST_VALUE = np.array([4.0, 2.0], np.float32)


def test_gae_by_hand_with_done():
    # Column 0 (done after t=1):
    #   t=2: delta = 3 + 0.9*4 - 2 = 4.6                 adv = 4.6
    #   t=1: delta = 2 + 0 - 1 = 1.0 (no bootstrap)      adv = 1.0 (nothing carried)
    #   t=0: delta = 1 + 0.9*1.0 - 0.5 = 1.4             adv = 1.4 + 0.72*1.0 = 2.12
    # Column 1:
    #   t=2: delta = -1 + 0.9*2 - 0 = 0.8                adv = 0.8
    #   t=1: delta = 1 + 0.9*0 - 0.5 = 0.5               adv = 0.5 + 0.72*0.8 = 1.076
    #   t=0: delta = 0 + 0.9*0.5 - 1 = -0.55             adv = -0.55 + 0.72*1.076 = 0.22472
    adv, ret = compute_gae(REWARDS, VALUES, DONES, LAST_VALUE, GAMMA, LAM)
    want_adv = np.array([[2.12, 0.22472], [1.0, 1.076], [4.6, 0.8]])
    want_ret = np.array([[2.62, 1.22472], [2.0, 1.576], [6.6, 0.8]])
    np.testing.assert_allclose(adv, want_adv, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ret, want_ret, rtol=1e-5, atol=1e-6)


def test_gae_by_hand_with_truncation():
    # Column 0's episode is cut by the time limit after t=1: bootstrap with values[1] = 1.0.
    #   t=2: adv = 4.6 (unchanged)
    #   t=1: delta = 2 + 0.9*1.0 - 1.0 = 1.9             adv = 1.9 (nothing carried)
    #   t=0: delta = 1.4                                 adv = 1.4 + 0.72*1.9 = 2.768
    # Column 1 is as before.
    truncs = DONES.copy()
    adv, ret = compute_gae(REWARDS, VALUES, DONES, LAST_VALUE, GAMMA, LAM, truncations=truncs)
    want_adv = np.array([[2.768, 0.22472], [1.9, 1.076], [4.6, 0.8]])
    want_ret = np.array([[3.268, 1.22472], [2.9, 1.576], [6.6, 0.8]])
    np.testing.assert_allclose(adv, want_adv, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ret, want_ret, rtol=1e-5, atol=1e-6)


def _gae_reference(rewards, values, dones, last_value, gamma, lam, truncs):
    """Plain-python GAE, one scalar at a time."""
    steps, envs = rewards.shape
    adv = np.zeros((steps, envs))
    for b in range(envs):
        next_adv, next_value = 0.0, float(last_value[b])
        for t in reversed(range(steps)):
            if truncs[t, b]:
                target = rewards[t, b] + gamma * values[t, b]
            elif dones[t, b]:
                target = rewards[t, b]
            else:
                target = rewards[t, b] + gamma * next_value
            carry = 0.0 if dones[t, b] else gamma * lam * next_adv
            adv[t, b] = target - values[t, b] + carry
            next_adv, next_value = adv[t, b], values[t, b]
    return adv, adv + values


@pytest.mark.parametrize("with_truncations", [False, True])
def test_gae_matches_python_loop(with_truncations):
    rng = np.random.default_rng(0)
    steps, envs = 50, 7
    rewards = rng.normal(size=(steps, envs)).astype(np.float32)
    values = rng.normal(size=(steps, envs)).astype(np.float32)
    dones = rng.random((steps, envs)) < 0.15
    truncs = dones & (rng.random((steps, envs)) < 0.5) if with_truncations else None
    last_value = rng.normal(size=envs).astype(np.float32)
    gae = jax.jit(compute_gae, static_argnums=(4, 5))
    adv, ret = gae(rewards, values, dones, last_value, 0.99, 0.95, truncs)
    ref_truncs = truncs if with_truncations else np.zeros_like(dones)
    want_adv, want_ret = _gae_reference(rewards, values, dones, last_value, 0.99, 0.95, ref_truncs)
    assert adv.shape == ret.shape == (steps, envs)
    np.testing.assert_allclose(adv, want_adv, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(ret, want_ret, rtol=1e-4, atol=1e-4)
    if with_truncations:
        plain, _ = gae(rewards, values, dones, last_value, 0.99, 0.95, None)
        assert not np.allclose(plain, adv)  # truncations do change the estimate


# ---------------------------------------------------------------- PPO loss

CLIP = 0.2
LOG3 = math.log(3.0)


def _fixed_apply(params, obs):
    """A stand-in network whose outputs are the `params` themselves."""
    del obs
    return params["logits"], params["value"]


def _batch(**kw):
    """Two-sample batch with uniform-policy log_probs and advantages [1, -1] (mean 0, std 1)."""
    fields = {
        "obs": jnp.zeros((2, 8)),
        "action": jnp.array([0, 2]),
        "log_prob": jnp.full((2,), -LOG3),
        "value": jnp.zeros(2),
        "advantage": jnp.array([1.0, -1.0]),
        "target": jnp.zeros(2),
    }
    return Batch(**(fields | kw))


UNIFORM = {"logits": jnp.zeros((2, 3)), "value": jnp.zeros(2)}


def test_ppo_loss_ratio_one_with_network():
    model = ActorCritic(action_size=3)
    obs = jax.random.normal(jax.random.key(1), (6, 8))
    params = model.init(jax.random.key(0), obs)
    logits, value = model.apply(params, obs)
    action = jnp.array([0, 1, 2, 0, 1, 2])
    batch = Batch(
        obs=obs,
        action=action,
        log_prob=log_prob(logits, action),
        value=value,
        advantage=jnp.array([3.0, -1.0, 0.5, 2.0, -4.0, 1.0]),
        target=value,
    )
    loss, m = ppo_loss(
        params, model.apply, batch, clip_eps=CLIP, vf_coef=0.5, ent_coef=0.01, clip_value=True
    )
    # ratio = 1 everywhere: surrogate = normalised advantage, whose mean is 0.
    assert abs(float(m["policy_loss"])) < 1e-6
    assert float(m["clip_fraction"]) == 0.0
    assert abs(float(m["approx_kl"])) < 1e-6
    assert abs(float(m["value_loss"])) < 1e-10  # target = value
    np.testing.assert_allclose(m["entropy"], jnp.mean(entropy(logits)), rtol=1e-6)
    np.testing.assert_allclose(loss, -0.01 * m["entropy"], rtol=1e-5, atol=1e-7)


def test_ppo_loss_clipped_surrogate_by_hand():
    # New log_prob is -log 3 (uniform); old log_prob set so that ratio = 1.5 and 0.5.
    old = jnp.array([-LOG3 - math.log(1.5), -LOG3 - math.log(0.5)])
    _, m = ppo_loss(
        UNIFORM, _fixed_apply, _batch(log_prob=old),
        clip_eps=CLIP, vf_coef=0.5, ent_coef=0.0, clip_value=False,
    )  # fmt: skip
    # adv +1, ratio 1.5: min(1.5, 1.2) = 1.2;  adv -1, ratio 0.5: min(-0.5, -0.8) = -0.8
    # policy_loss = -(1.2 - 0.8) / 2 = -0.2
    np.testing.assert_allclose(m["policy_loss"], -0.2, rtol=1e-5)
    assert float(m["clip_fraction"]) == 1.0
    # k3 KL: mean(r - 1 - log r) = ((0.5 - log 1.5) + (-0.5 - log 0.5)) / 2
    want_kl = ((0.5 - math.log(1.5)) + (-0.5 - math.log(0.5))) / 2
    np.testing.assert_allclose(m["approx_kl"], want_kl, rtol=1e-5)

    # Both ratios 1.5: adv -1 keeps the unclipped, more pessimistic -1.5.
    old = jnp.full((2,), -LOG3 - math.log(1.5))
    _, m = ppo_loss(
        UNIFORM, _fixed_apply, _batch(log_prob=old),
        clip_eps=CLIP, vf_coef=0.5, ent_coef=0.0, clip_value=False,
    )  # fmt: skip
    np.testing.assert_allclose(m["policy_loss"], -(1.2 - 1.5) / 2, rtol=1e-5)  # 0.15


def test_ppo_loss_value_and_entropy_by_hand():
    params = {"logits": jnp.zeros((2, 3)), "value": jnp.array([1.0, -2.0])}
    batch = _batch(value=jnp.array([0.0, -2.0]), target=jnp.array([1.5, 1.0]))
    kw = {"clip_eps": CLIP, "vf_coef": 0.5, "ent_coef": 0.01}
    loss, m = ppo_loss(params, _fixed_apply, batch, clip_value=False, **kw)
    # 0.5 * mean((1 - 1.5)^2, (-2 - 1)^2) = 0.5 * (0.25 + 9) / 2 = 2.3125
    np.testing.assert_allclose(m["value_loss"], 2.3125, rtol=1e-6)
    np.testing.assert_allclose(m["entropy"], LOG3, rtol=1e-6)  # uniform over 3 actions
    np.testing.assert_allclose(m["policy_loss"], 0.0, atol=1e-6)  # ratio 1
    np.testing.assert_allclose(loss, 0.5 * 2.3125 - 0.01 * LOG3, rtol=1e-5)
    np.testing.assert_allclose(m["total"], loss)

    _, m = ppo_loss(params, _fixed_apply, batch, clip_value=True, **kw)
    # Sample 0: clipped value 0 + clip(1 - 0, +-0.2) = 0.2; max(0.25, (0.2 - 1.5)^2 = 1.69).
    # Sample 1: old value equals the new one, error 9.  0.5 * (1.69 + 9) / 2 = 2.6725
    np.testing.assert_allclose(m["value_loss"], 2.6725, rtol=1e-6)


def test_ppo_loss_gradient_is_finite():
    model = ActorCritic(action_size=3, critic_output="linear")
    obs = jax.random.normal(jax.random.key(2), (4, 8))
    params = model.init(jax.random.key(0), obs)
    batch = Batch(obs, jnp.array([0, 1, 2, 1]), jnp.full((4,), -1.2), jnp.zeros(4),
                  jnp.array([1.0, 2.0, -1.0, 0.0]), jnp.array([-100.0, 0.0, 5.0, 1.0]))  # fmt: skip
    grad_fn = jax.jit(
        jax.grad(ppo_loss, has_aux=True),
        static_argnames=("apply_fn", "clip_value"),
    )
    grads, _ = grad_fn(params, model.apply, batch, clip_eps=CLIP, vf_coef=0.5, ent_coef=0.01,
                       clip_value=True)  # fmt: skip
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert any(float(jnp.max(jnp.abs(g))) > 0 for g in leaves)


# ---------------------------------------------------------------- network


def test_network_shapes_and_separate_trunks():
    model = ActorCritic(action_size=3)
    obs = jax.random.normal(jax.random.key(0), (5, 8))
    params = model.init(jax.random.key(1), obs)
    logits, value = model.apply(params, obs)
    assert logits.shape == (5, 3)
    assert value.shape == (5,)
    np.testing.assert_allclose(jnp.sum(jax.nn.softmax(logits), axis=-1), 1.0, rtol=1e-6)
    # Two unshared MLPs, each Dense 64 -> Dense 64 -> head.
    p = params["params"]
    assert set(p) == {"actor", "critic"}
    assert p["actor"]["Dense_0"]["kernel"].shape == (8, 64)
    assert p["actor"]["Dense_1"]["kernel"].shape == (64, 64)
    assert p["actor"]["Dense_2"]["kernel"].shape == (64, 3)
    assert p["critic"]["Dense_2"]["kernel"].shape == (64, 1)
    # Policy head initialised small: nearly uniform initial policy.
    assert float(jnp.max(jnp.abs(logits))) < 0.1


def test_privileged_critic_inputs_reach_the_value_only():
    """With critic inputs C the critic's first layer takes D + C; the actor's logits do not
    depend on them (acting may leave them out), the value does."""
    model = ActorCritic(action_size=3, critic_output="linear", critic_inputs=4)
    obs = jax.random.normal(jax.random.key(0), (5, 8))
    extra = jax.random.normal(jax.random.key(2), (5, 4))
    params = model.init(jax.random.key(1), obs, extra)
    assert params["params"]["critic"]["Dense_0"]["kernel"].shape == (12, 64)
    assert params["params"]["actor"]["Dense_0"]["kernel"].shape == (8, 64)
    logits, value = model.apply(params, obs, extra)
    acting, zero_extra = model.apply(params, obs)  # what a robot runs: no critic inputs
    np.testing.assert_array_equal(logits, acting)
    np.testing.assert_allclose(zero_extra, model.apply(params, obs, 0 * extra)[1], rtol=1e-6)
    assert float(jnp.max(jnp.abs(value - zero_extra))) > 1e-3
    plain = ActorCritic(action_size=3, critic_output="linear")
    trunk = {
        "params": {
            **params["params"],
            "critic": plain.init(jax.random.key(1), obs)["params"]["critic"],
        }
    }
    np.testing.assert_array_equal(plain.apply(trunk, obs)[0], logits)  # the same actor


def test_tanh_critic_bounded_linear_not():
    obs = 1e3 * jax.random.normal(jax.random.key(0), (64, 8))  # large inputs saturate tanh
    linear = ActorCritic(action_size=3, critic_output="linear")
    params = linear.init(jax.random.key(1), obs)  # same parameter tree for every variant
    _, v_lin = linear.apply(params, obs)
    assert float(jnp.max(jnp.abs(v_lin))) > 1.0
    for scale in (1.0, 50.0):
        model = ActorCritic(action_size=3, critic_output="tanh", value_scale=scale)
        _, v = model.apply(params, obs)
        assert float(jnp.max(jnp.abs(v))) <= scale
        np.testing.assert_allclose(v, scale * jnp.tanh(v_lin), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError):
        ActorCritic(action_size=3, critic_output="relu").init(jax.random.key(1), obs)


def test_network_jit_matches_eager():
    model = ActorCritic(action_size=3)
    obs = jax.random.normal(jax.random.key(0), (5, 8))
    params = jax.jit(model.init)(jax.random.key(1), obs)
    logits_j, value_j = jax.jit(model.apply)(params, obs)
    logits, value = model.apply(params, obs)
    np.testing.assert_allclose(logits_j, logits, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(value_j, value, rtol=1e-5, atol=1e-6)


def test_policy_helpers():
    logits = jnp.array([[0.0, 1.0, 2.0], [5.0, -1.0, 0.0]])
    action = jnp.array([2, 0])
    x = np.asarray(logits, np.float64)
    logp = x - np.log(np.exp(x).sum(-1, keepdims=True))  # float64 reference
    np.testing.assert_allclose(log_prob(logits, action), [logp[0, 2], logp[1, 0]], atol=1e-6)
    np.testing.assert_allclose(entropy(jnp.zeros((4, 3))), np.full(4, LOG3), rtol=1e-6)
    np.testing.assert_allclose(entropy(logits), -(np.exp(logp) * logp).sum(-1), rtol=1e-5)
    # A -inf logit (impossible action) contributes 0, not nan.
    np.testing.assert_allclose(entropy(jnp.array([0.0, 0.0, -jnp.inf])), math.log(2), rtol=1e-6)

    keys = jax.random.split(jax.random.key(0), 4000)
    probs = jnp.array([0.7, 0.2, 0.1])
    samples = jax.jit(jax.vmap(sample_action, (0, None)))(keys, jnp.log(probs))
    assert samples.dtype == jnp.int32 and samples.shape == (4000,)
    freq = np.bincount(np.asarray(samples), minlength=3) / 4000
    np.testing.assert_allclose(freq, probs, atol=0.03)
    batch_actions = sample_action(jax.random.key(1), jnp.array([[-1e9, 0.0, -1e9]] * 5))
    np.testing.assert_array_equal(batch_actions, np.ones(5))


# ---------------------------------------------------------------- observation normalisation


def test_running_stats_match_numpy():
    rng = np.random.default_rng(0)
    batches = [
        rng.normal(5.0, 3.0, size=(17, 8)),
        rng.normal(-2.0, 0.5, size=(40, 8)),
        rng.normal(0.0, 10.0, size=(3, 8)),
    ]
    update = jax.jit(update_stats)
    stats = init_stats(8)
    for i, b in enumerate(batches):
        stats = update(stats, jnp.asarray(b, jnp.float32))
        seen = np.concatenate(batches[: i + 1])
        np.testing.assert_allclose(stats.mean, seen.mean(0), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(stats.var, seen.var(0), rtol=1e-5, atol=1e-5)
        assert float(stats.count) == len(seen)

    obs = jnp.asarray(batches[0], jnp.float32)
    seen = np.concatenate(batches)
    want = np.clip((batches[0] - seen.mean(0)) / np.sqrt(seen.var(0) + 1e-8), -10, 10)
    np.testing.assert_allclose(normalize(stats, obs), want, rtol=1e-4, atol=1e-5)
    assert float(jnp.max(jnp.abs(normalize(stats, 1e6 * obs, clip=5.0)))) == 5.0


def test_normalize_before_any_update_is_identity():
    obs = jnp.arange(8.0)
    np.testing.assert_allclose(normalize(init_stats(8), obs), obs, rtol=1e-6)


# ---------------------------------------------------------------- the update's pieces


class _LineEnv:
    """A robot on a line, pushed by its action: enough env for PPO's jitted pieces."""

    observation_size = 2
    metric_names = ("collision",)

    def __init__(self):
        from jaxnav.tasks.avoid import AvoidConfig

        self.action_spec = AvoidConfig().action_spec

    def _state(self, x, steps, key, reward=0.0, done=False):
        from jaxnav.core.types import EnvState

        f0 = jnp.float32(0)
        return EnvState(
            data=x,
            obs=jnp.stack([x, steps.astype(jnp.float32)]),  # [2]
            reward=jnp.float32(reward),
            done=jnp.bool_(done),
            truncated=jnp.bool_(done) & (steps >= 5),
            metrics={"collision": f0},
            info={"steps": steps, "key": key},
        )

    def reset(self, key):
        key, k_x = jax.random.split(key)
        return self._state(jax.random.uniform(k_x, (), minval=-1.0, maxval=1.0), jnp.int32(0), key)

    def step(self, state, action):
        x = state.data + 0.1 * (action.astype(jnp.float32) - 1.0)
        steps = state.info["steps"] + 1
        done = (jnp.abs(x) > 1.0) | (steps >= 5)
        return self._state(x, steps, state.info["key"], -jnp.abs(x), done)


class _CountedLineEnv(_LineEnv):
    """`_LineEnv` whose step tells the host each time it runs."""

    def __init__(self, calls: list):
        super().__init__()
        self.calls = calls

    def step(self, state, action):
        jax.debug.callback(lambda: self.calls.append(1))
        return super().step(state, action)


@pytest.mark.slow
@pytest.mark.parametrize("ahead", [False, True])
def test_update_is_its_rollout_then_its_learner(ahead):
    """`Trainer.parts`, the pieces benchmarks/compile_time.py compiles on their own, compose to
    the update `run_chunk` runs, bit for bit; a chunk runs only the updates the budget has left
    (4 updates in chunks of 3: the second chunk runs one, a third none, and the env steps only
    for those). With new episodes drawn ahead (`ahead`), a chunk is a loop of the draws' program
    and the update's, and the same. Slow: the parts, the update and a chunk each compile."""
    from jaxnav.ppo.config import PPOConfig
    from jaxnav.ppo.train import make_train

    calls = []
    cfg = PPOConfig(
        num_envs=8,
        rollout_length=4,
        minibatch_size=16,
        updates_per_chunk=3,
        total_steps=128,
        reset_ahead=ahead,
    )
    trainer = make_train(cfg, _CountedLineEnv(calls))
    ts = trainer.init(jax.random.PRNGKey(0))
    rollout, learn, update = (jax.jit(trainer.parts[k]) for k in ("rollout", "learn", "update"))
    split_ts, split_metrics = learn(*rollout(ts))
    whole_ts, whole_metrics = update(ts)
    jax.effects_barrier()
    calls.clear()
    expected = [whole_ts]
    for _ in range(cfg.num_updates - 1):
        expected.append(update(expected[-1])[0])
    jax.effects_barrier()
    steps_per_update = len(calls) // (cfg.num_updates - 1)
    assert steps_per_update >= cfg.rollout_length
    calls.clear()

    chunk_ts, chunks = jax.tree_util.tree_map(jnp.copy, ts), []
    for _ in range(3):
        chunk_ts, metrics = trainer.run_chunk(chunk_ts)
        chunks.append((jax.tree_util.tree_map(jnp.copy, chunk_ts), metrics))
    jax.effects_barrier()
    assert len(calls) == cfg.num_updates * steps_per_update  # none for the skipped updates
    assert [np.asarray(m["live"]).tolist() for _, m in chunks] == [
        [True] * 3,
        [True, False, False],
        [False] * 3,
    ]
    # [want, got]: the parts against the update; each chunk's end against updates in turn
    pairs = [(split_ts, whole_ts), (expected[2], chunks[0][0])]
    pairs += [(expected[3], chunks[1][0]), (expected[3], chunks[2][0])]
    for want, got in pairs:
        leaves = zip(*map(jax.tree_util.tree_leaves, (want, got)), strict=True)
        for a, b in leaves:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for k, v in split_metrics.items():
        np.testing.assert_array_equal(np.asarray(v), np.asarray(whole_metrics[k]))
        np.testing.assert_array_equal(np.asarray(v), np.asarray(chunks[0][1][k][0]))


@pytest.mark.parametrize(
    "case",
    [
        {"clip_value": True},  # the cpu preset's network, value clipping on
        {"critic_output": "tanh", "hidden": (32, 48, 20), "critic": 5},  # paper's critic, 3 layers
    ],
)
@pytest.mark.slow
def test_fused_gradient_matches_jax_grad(case):
    """The learner's one-kernel gradient (`jaxnav.ppo.fused`, through Pallas' interpreter) is
    jax.grad's of `ppo_loss`, and its metrics the loss's, to float32 rounding; ratios spread on
    both sides of the clip, a state the critic alone reads. Slow: the kernel compiled through
    Pallas' interpreter, on one device and split over two, for this check."""
    from jaxnav.core.types import DiscreteActions
    from jaxnav.ppo import fused
    from jaxnav.ppo.config import preset
    from jaxnav.ppo.distributions import make_distribution
    from jaxnav.ppo.train import loss_grad, make_network

    case = dict(case)
    c = case.pop("critic", 0)
    rows = 2 * fused.ROWS
    cfg = preset("cpu", num_envs=rows // 32, minibatch_size=rows, **case)
    spec = DiscreteActions(("f", "l", "r"), ((0.25, 0.0), (0.0, 1.0), (0.0, -1.0)))
    dist = make_distribution(spec)
    net = make_network(cfg, spec, c)
    k = jax.random.split(jax.random.PRNGKey(3), 9)
    obs = jax.random.normal(k[0], (rows, 8))
    extra = jax.random.normal(k[1], (rows, c)) if c else None
    params = net.init(k[2], obs[:1], None if extra is None else extra[:1])
    params = jax.tree_util.tree_map(lambda p: p + 0.3 * jax.random.normal(k[3], p.shape), params)
    logits, value = net.apply(params, obs, extra)
    action = jax.random.randint(k[4], (rows,), 0, 3)
    noise = lambda key: 0.3 * jax.random.normal(key, (rows,))  # noqa: E731
    batch = Batch(
        (obs, extra),
        action,
        dist.log_prob(logits, action) + noise(k[5]),
        value + noise(k[6]),
        jax.random.normal(k[7], (rows,)),
        jax.random.normal(k[8], (rows,)),
    )
    # Both in float32 throughout (on a GPU JAX's default rounds the products' inputs to TF32).
    float32 = jax.default_matmul_precision("highest")
    with float32:
        want, want_m = loss_grad(cfg, net, dist)(params, batch)  # the trainer's jax.grad
    grad = fused.make(cfg, net, dist, jax.devices(), (8, 8 + c), interpret=True)
    with float32:
        got, got_m = jax.jit(grad)(params, batch)
    assert 0.2 < float(want_m["clip_fraction"]) < 0.8  # both sides of the clip are exercised
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w, atol=1e-5 * float(jnp.abs(w).max()) + 1e-9)
    for name, w in want_m.items():
        np.testing.assert_allclose(got_m[name], w, rtol=2e-5, atol=1e-6)
    # Split over two devices (here two members of a vmap, whose named axis the sums run over):
    # each device's rows alone, the same gradient and metrics. Once: the sums do not depend on
    # the network, and the second case's critic reads a state of its own too.
    if c:
        split = functools.partial(grad.func, **grad.keywords, axis=("envs", 2))
        halves = jax.tree_util.tree_map(lambda x: x.reshape(2, rows // 2, *x.shape[1:]), batch)
        with float32:
            got2, got2_m = jax.jit(jax.vmap(split, (None, 0), axis_name="envs"))(params, halves)
        leaves = zip(*map(jax.tree_util.tree_leaves, (got2, want)), strict=True)
        for g, w in leaves:
            np.testing.assert_allclose(g[0], g[1])  # both devices hold the whole gradient
            np.testing.assert_allclose(g[0], w, atol=1e-5 * float(jnp.abs(w).max()) + 1e-9)
        for name, w in want_m.items():
            np.testing.assert_allclose(got2_m[name][0], w, rtol=2e-5, atol=1e-6)
    # Where it does not apply, the trainer keeps jax.grad: not a GPU, or a layer over MAX_WIDTH.
    assert fused.make(cfg, net, dist, jax.devices("cpu"), (8, 8 + c)) is None
    assert fused.make(cfg, net, dist, jax.devices(), (200, 200), interpret=True) is None


def test_fused_gradient_applies_where_it_was_measured():
    """The trainer takes the kernel on GPUs for the avoid task's network and at least `MIN_ROWS`
    of a minibatch on each; elsewhere (fewer rows a GPU, the goal task's 221 inputs or the gpu
    preset's 256-unit layers, continuous commands, ragged minibatches, switched off) jax.grad."""
    from types import SimpleNamespace

    import jaxnav
    from jaxnav.ppo import fused
    from jaxnav.ppo.config import preset
    from jaxnav.ppo.distributions import make_distribution
    from jaxnav.ppo.train import make_network

    gpu = [SimpleNamespace(platform="gpu")]
    avoid = jaxnav.make_env("avoid")
    d = avoid.observation_size

    def make(devices=gpu, inputs=(d, d), spec=avoid.action_spec, **ppo):
        cfg = preset("gpu", **ppo)
        return fused.make(cfg, make_network(cfg, spec), make_distribution(spec), devices, inputs)

    assert make() is not None  # the gpu preset's avoid: 8 inputs, 2 x 64, minibatches of 16,384
    assert make(devices=gpu * 2) is None  # two GPUs: 8,192 rows each of the preset's 16,384
    assert make(devices=[SimpleNamespace(platform="cpu")]) is None
    assert make(inputs=(221, 231)) is None  # the goal task's observation and critic inputs
    assert make(hidden=(256, 256)) is None
    assert make(minibatch_size=fused.MIN_ROWS // 2) is None
    assert make(num_envs=8200, minibatch_size=16400) is None  # not whole programs of ROWS
    assert make(fused_learner=False) is None
    continuous = jaxnav.make_env("avoid", actions="continuous").action_spec
    assert make(spec=continuous) is None
