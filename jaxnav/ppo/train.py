"""PPO as jitted chunks: `make_train(cfg, env)` -> `Trainer(init, run_chunk, train)`.

One update = `_rollout` (scan over the horizon, all robots vmapped) -> GAE -> `_update_epoch` x E,
each a scan of `_update_minibatch`. `run_chunk` scans `updates_per_chunk` updates so the host can log,
draw and checkpoint between chunks; `train` runs everything in one jitted call.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxnav.core.types import ContinuousActions
from jaxnav.core.xla import compiler_options, threefry_kernel
from jaxnav.ppo import fused
from jaxnav.ppo.config import PPOConfig
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.losses import Batch, compute_gae, ppo_loss
from jaxnav.ppo.networks import ActorCritic, RunningStats, init_stats, normalize, update_stats
from jaxnav.wrappers import EPISODE, AutoReset, EpisodeStats


@struct.dataclass
class TrainState:
    """Everything a run needs to continue: the learner, the robots and the RNG."""

    params: dict  # actor and critic weights
    opt_state: optax.OptState
    obs_stats: RunningStats  # observation normaliser (identity when normalize_obs is off)
    env_state: object  # the wrapped env's EnvState with a leading [num_envs] axis
    key: jax.Array
    update: jax.Array  # [] int32, updates done


class Transition(NamedTuple):
    raw_obs: jax.Array  # [T, N, D] observation as sensed, for the normaliser
    obs: jax.Array  # [T, N, D] normalised observation the action was chosen on
    action: jax.Array  # [T, N] int, or [T, N, A] float commands
    log_prob: jax.Array  # [T, N]
    value: jax.Array  # [T, N]
    reward: jax.Array  # [T, N] the task's raw reward
    done: jax.Array  # [T, N]
    truncated: jax.Array  # [T, N]
    episode: dict  # {"return", "length", *metric_names}: [T, N] sums of the episode that ended
    critic: jax.Array | None  # [T, N, C] what only the critic sees (None: it sees obs alone)


class Trainer(NamedTuple):
    network: ActorCritic
    init: callable  # key -> TrainState
    run_chunk: callable  # TrainState -> (TrainState, metrics [updates_per_chunk])
    train: callable  # key -> (TrainState, metrics [num_updates // updates_per_chunk * chunk])
    # The pieces of one update, not jitted (benchmarks/compile_time.py times each): "rollout":
    # ts -> (env_state, key, traj); "learn": (ts, env_state, key, traj) -> (ts, metrics); "update":
    # ts -> (ts, metrics), the two in turn; and "init", "chunk": `init` and `run_chunk` unjitted
    # (what `jaxnav.programs` exports).
    parts: dict | None = None


def make_optimizer(cfg: PPOConfig) -> optax.GradientTransformation:
    lr = cfg.learning_rate
    if cfg.anneal_lr:
        steps = cfg.num_updates * cfg.num_epochs * cfg.num_minibatches
        lr = optax.linear_schedule(cfg.learning_rate, 0.0, steps)
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(lr, eps=1e-5))


def critic_inputs(cfg: PPOConfig, env) -> int:
    """C, what only the critic sees: the env's `critic_size` with `cfg.privileged_critic`, else 0;
    privileged without such inputs is a ValueError naming the flag."""
    size = getattr(env, "critic_size", 0)
    if cfg.privileged_critic and not size:
        raise ValueError(
            "--privileged-critic: this task has no inputs for the critic alone (the goal task "
            "has); leave it off"
        )
    return size if cfg.privileged_critic else 0


def make_network(cfg: PPOConfig, action_spec, critic_inputs: int = 0) -> ActorCritic:
    """The actor-critic for an env's `action_spec`: logits for a table of commands, a Gaussian's
    means and log-stds for continuous commands (`jaxnav.ppo.distributions`). `critic_inputs`: C,
    what only the critic sees (`critic_inputs`: 0 unless `cfg.privileged_critic`)."""
    continuous = isinstance(action_spec, ContinuousActions)
    size = action_spec.size if continuous else make_distribution(action_spec).out_size
    return ActorCritic(
        size,
        hidden=tuple(cfg.hidden),
        critic_output=cfg.critic_output,
        continuous=continuous,
        critic_inputs=critic_inputs,
    )


def loss_grad(cfg: PPOConfig, network: ActorCritic, dist):
    """`(params, batch) -> (grads, metrics)`: `jax.grad` of `ppo_loss` with `cfg`'s coefficients,
    for `network`'s outputs read by `dist` (`batch.obs`: the observation and the critic's own
    inputs, or None)."""

    def grad(params, batch: Batch):
        return jax.grad(ppo_loss, has_aux=True)(
            params,
            lambda p, inputs: network.apply(p, *inputs),
            batch,
            clip_eps=cfg.clip_eps,
            vf_coef=cfg.vf_coef,
            ent_coef=cfg.ent_coef,
            clip_value=cfg.clip_value,
            dist=dist,
        )

    return grad


def log_name(key: str) -> str:
    """The metrics-log column of an episode statistic: return and length get an episode_ prefix."""
    return {"return": "episode_reward", "length": "episode_length"}.get(key, key)


def episode_metrics(traj: Transition) -> dict[str, jax.Array]:
    """Means over the episodes that ended during a rollout (nan if none did): episode_reward,
    episode_length and each of the task's metrics (its per-episode sum), plus `episodes`."""
    done = traj.done.astype(jnp.float32)
    n = done.sum()
    mean = lambda x: jnp.where(n > 0, (x * done).sum() / jnp.maximum(n, 1.0), jnp.nan)  # noqa: E731
    return {**{log_name(k): mean(v) for k, v in traj.episode.items()}, "episodes": n}


def shard_envs(num_envs: int, devices=None, axis: int = 0):
    """A function placing [num_envs, ...] arrays across `devices` (default: every device of every
    process, `jax.devices()`), split along `axis` (1: the robot blocks of `AutoReset.draw`).

    Robots are split evenly between devices, so each device (and each process) simulates only its
    own; parameters stay replicated, and XLA inserts the all-reduce of the gradients. With one
    device this is the identity.
    """
    devices = list(devices or jax.devices())
    if len(devices) == 1:
        return lambda tree: tree
    if num_envs % len(devices):
        raise ValueError(f"--num-envs {num_envs} must be a multiple of the {len(devices)} devices")
    spec = PartitionSpec(*[None] * axis, "envs")
    sharding = NamedSharding(Mesh(np.array(devices), ("envs",)), spec)
    return lambda tree: jax.lax.with_sharding_constraint(tree, sharding)


def block_count(cfg: PPOConfig, devices=None) -> int:
    """`cfg.groups`, or one block per device; each device must hold whole blocks."""
    count = len(devices or jax.devices())
    groups = cfg.groups or count
    if groups % count:
        raise ValueError(f"--groups {groups} must be a multiple of the {count} devices")
    for name, value in (("--num-envs", cfg.num_envs), ("--minibatch-size", cfg.minibatch_size)):
        if value % groups:
            raise ValueError(f"{name} {value} must be a multiple of the {groups} robot blocks")
    return groups


def make_train(cfg: PPOConfig, env, devices=None) -> Trainer:
    """Builds the jitted PPO functions for `env` (any object with vmappable reset/step).

    The robots are sharded over `devices` (default: every device of every process). On one GPU it
    sets how this process lowers jax.random from now on (`cfg.threefry_kernel`).
    """
    extra = critic_inputs(cfg, env)
    network = make_network(cfg, env.action_spec, extra)
    dist = make_distribution(env.action_spec)
    devices_used = list(devices or jax.devices())
    inputs = (env.observation_size, env.observation_size + extra)
    fused_grad = fused.make(cfg, network, dist, devices_used, inputs)  # None: jax.grad's
    optimizer = make_optimizer(cfg)
    shard = shard_envs(cfg.num_envs, devices)
    g = block_count(cfg, devices)
    env = AutoReset(EpisodeStats(env), cfg.reset_pool, cfg.reset_in_place, groups=g)
    reset = lambda keys: shard(env.reset(keys))  # noqa: E731
    step = lambda state, action, fresh: shard(env.step(state, action, fresh))  # noqa: E731
    shard_draws = shard_envs(cfg.num_envs, devices, axis=1)  # [T, G, P/G, ...]: by block
    norm = (lambda stats, obs: normalize(stats, obs)) if cfg.normalize_obs else (lambda s, o: o)
    # The critic's own inputs [N, C] of a state, or None; the loss's inputs are (obs, those).
    critic_in = lambda state: state.info["critic"] if cfg.privileged_critic else None  # noqa: E731

    def init(key: jax.Array) -> TrainState:
        k_net, k_env, key = jax.random.split(key, 3)
        env_state = reset(jax.random.split(k_env, cfg.num_envs))
        extra = critic_in(env_state)
        params = network.init(k_net, env_state.obs[:1], None if extra is None else extra[:1])
        return TrainState(
            params=params,
            opt_state=optimizer.init(params),
            obs_stats=init_stats(env.observation_size),
            env_state=env_state,
            key=key,
            update=jnp.int32(0),
        )

    def _rollout(ts: TrainState):
        def _env_step(carry, fresh):
            env_state, key = carry
            key, k_act = jax.random.split(key)
            obs = norm(ts.obs_stats, env_state.obs)  # [N, D]
            extra = critic_in(env_state)
            logits, value = network.apply(ts.params, obs, extra)
            action = dist.sample(k_act, logits)  # [N] or [N, A]
            nxt = step(env_state, action, fresh)
            tr = Transition(
                env_state.obs,
                obs,
                action,
                dist.log_prob(logits, action),
                value,
                nxt.reward,
                nxt.done,
                nxt.truncated,
                nxt.info[EPISODE],
                extra,
            )
            return (nxt, key), tr

        env_state, fresh = ts.env_state, None  # fresh: the rollout's new episodes, drawn ahead
        # Named in the program (profiles; tests check that no rollout op waits on another device).
        with jax.named_scope("rollout"):
            if cfg.reset_ahead:
                env_state, fresh = env.draw(env_state, cfg.rollout_length)
                fresh = shard_draws(fresh)
            (env_state, key), traj = jax.lax.scan(
                _env_step, (env_state, ts.key), fresh, cfg.rollout_length
            )
        return env_state, key, traj

    grad = fused_grad or loss_grad(cfg, network, dist)  # (grads, metrics) of a minibatch

    def _update_minibatch(carry, batch: Batch):
        params, opt_state = carry
        grads, metrics = grad(params, batch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def _update_epoch(carry, _):
        params, opt_state, batch, key = carry
        key, k_perm = jax.random.split(key)
        perm = jax.random.permutation(k_perm, cfg.batch_size // g)  # the same in every block

        def minibatches(x):  # [G, B/G, ...] -> [B/M, M, ...], minibatch i: every block's i-th part
            x = x[:, perm].reshape(g, cfg.num_minibatches, cfg.minibatch_size // g, *x.shape[2:])
            return x.swapaxes(0, 1).reshape(cfg.num_minibatches, cfg.minibatch_size, *x.shape[3:])

        shuffled = jax.tree_util.tree_map(minibatches, batch)
        (params, opt_state), metrics = jax.lax.scan(
            _update_minibatch, (params, opt_state), shuffled
        )
        return (params, opt_state, batch, key), metrics

    def _learn(ts: TrainState, env_state, key, traj: Transition) -> tuple[TrainState, dict]:
        last_obs = norm(ts.obs_stats, env_state.obs)
        last_value = network.apply(ts.params, last_obs, critic_in(env_state))[1]  # [N]
        adv, targets = compute_gae(
            traj.reward * cfg.reward_scale,
            traj.value,
            traj.done,
            last_value,
            cfg.gamma,
            cfg.gae_lambda,
            truncations=traj.truncated,
        )

        def blocks(x):  # [T, N, ...] -> [G, T * N/G, ...]: each block's own transitions
            x = x.reshape(x.shape[0], g, cfg.num_envs // g, *x.shape[2:]).swapaxes(0, 1)
            return x.reshape(g, cfg.batch_size // g, *x.shape[3:])

        critic = None if traj.critic is None else blocks(traj.critic)
        batch = Batch(
            (blocks(traj.obs), critic),
            *map(blocks, (traj.action, traj.log_prob, traj.value, adv, targets)),
        )
        key, k_epochs = jax.random.split(key)
        (params, opt_state, _, _), losses = jax.lax.scan(
            _update_epoch, (ts.params, ts.opt_state, batch, k_epochs), None, cfg.num_epochs
        )
        stats = (
            update_stats(ts.obs_stats, blocks(traj.raw_obs).reshape(cfg.batch_size, -1))
            if cfg.normalize_obs
            else ts.obs_stats
        )
        ts = TrainState(
            params=params,
            opt_state=opt_state,
            obs_stats=stats,
            env_state=env_state,
            key=key,
            update=ts.update + 1,
        )
        metrics = {
            **episode_metrics(traj),
            **jax.tree_util.tree_map(jnp.mean, losses),
            "obs_finite": jnp.isfinite(traj.raw_obs).all(),
        }
        return ts, metrics

    def _update(ts: TrainState) -> tuple[TrainState, dict]:
        return _learn(ts, *_rollout(ts))

    update = jax.jit(_update)  # traced once per chunk's trace, inlined by XLA

    def run_chunk(ts: TrainState):
        # Chunks have one shape so they compile once; a loop of as many updates as the budget
        # has left runs them, so updates past it cost nothing. Their metrics rows stay zero.
        n = cfg.updates_per_chunk
        live = jnp.clip(cfg.num_updates - ts.update, 0, n)  # [] updates this chunk runs
        rows = jax.eval_shape(update, ts)[1]  # traces the update; the loop's body reuses it
        rows = jax.tree_util.tree_map(lambda a: jnp.zeros((n, *a.shape), a.dtype), rows)

        def body(carry):
            i, ts, rows = carry
            ts, metrics = update(ts)
            rows = jax.tree_util.tree_map(lambda r, m: r.at[i].set(m), rows, metrics)
            return i + 1, ts, rows

        _, ts, rows = jax.lax.while_loop(lambda c: c[0] < live, body, (0, ts, rows))
        return ts, {**rows, "live": jnp.arange(n) < live}  # rows [updates_per_chunk]

    def train(key: jax.Array):
        return jax.lax.scan(lambda ts, x: _update(ts), init(key), None, cfg.num_updates)

    parts = {
        "rollout": _rollout,
        "learn": _learn,
        "update": _update,
        "init": init,
        "chunk": run_chunk,
    }
    platform = devices_used[0].platform
    options = compiler_options(platform)
    # On one device only: XLA cannot split the kernel's call over the devices the robots are
    # sharded over, and several GPUs are not measured with it.
    threefry_kernel(cfg.threefry_kernel and len(devices_used) == 1, platform)
    jit = lambda fn, **kw: jax.jit(fn, compiler_options=options, **kw)  # noqa: E731
    return Trainer(network, jit(init), jit(run_chunk, donate_argnums=0), jit(train), parts)
