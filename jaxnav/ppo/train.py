"""PPO as jitted programs: `make_train(cfg, env)` -> `Trainer(init, run_chunk, train)`.

One update = `_rollout` (scan over the horizon, all robots vmapped) -> GAE -> `_update_epoch` x E,
each a scan of `_update_minibatch`. `run_chunk` runs `updates_per_chunk` updates so the host can
log, draw and checkpoint between chunks: a loop in Python over them, each three programs (the
rollout's new episodes drawn ahead, `reset_ahead`; the rollout; the learner), or two where each
step draws its own (the rollout, then the learner), which XLA compiles at once. `train` runs
everything in one jitted call.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxnav.core.draws import hashed_permutation
from jaxnav.core.types import ContinuousActions
from jaxnav.core.xla import (
    compiler_options,
    deterministic,
    fusion_autotune,
    run_once,
    threefry_kernel,
)
from jaxnav.ppo import fused
from jaxnav.ppo.config import PPOConfig
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.losses import Batch, compute_gae, ppo_loss
from jaxnav.ppo.networks import ActorCritic, RunningStats, init_stats, normalize, update_stats
from jaxnav.wrappers import EPISODE, RESET_KEY, AutoReset, EpisodeStats, with_reset_keys


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
    # (ts, drawn) -> (ts with its robots moved on, traj); "learn": (ts, traj) -> (ts, metrics);
    # "update": (ts, drawn) -> (ts, metrics), the two in turn; and each of `programs` unjitted,
    # by its name (what `jaxnav.programs` exports).
    parts: dict | None = None
    # The jitted programs `init` and `run_chunk` call, in the order their arguments follow from
    # each other: "init", "rollout" and "learn", or, for new episodes drawn ahead, "draws",
    # "start", "rollout" and "learn" (`make_train`). `with_programs` swaps them (for stored or
    # compiled ones).
    programs: dict | None = None
    # (programs) -> (init, run_chunk) calling those programs.
    compose: callable = None
    # (name, programs, key) -> the abstract arguments program `name` takes in a run from `key`,
    # from the programs before it (`jax.eval_shape` of each); "state": init's abstract TrainState.
    arguments: callable = None
    # The programs init's TrainState follows from: "init", or "draws" and "start".
    state_from: tuple = ()
    # Every program's input and output shardings fixed when it was made (`make_train`), so that
    # on several devices each can compile before the programs before it have run.
    laid_out: bool = False

    def with_programs(self, **programs) -> Trainer:
        """This trainer with `programs` in place of the ones of the same names."""
        programs = {**self.programs, **programs}
        init, run_chunk = self.compose(programs)
        return self._replace(init=init, run_chunk=run_chunk, programs=programs)


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
    sharding = envs_sharding(devices, axis)
    return lambda tree: jax.lax.with_sharding_constraint(tree, sharding)


def envs_sharding(devices: list, axis: int = 0) -> NamedSharding:
    """The robots' layout over `devices`: arrays split along `axis` in equal consecutive parts,
    one a device (the mesh axis "envs")."""
    return NamedSharding(Mesh(np.array(devices), ("envs",)), PartitionSpec(*[None] * axis, "envs"))


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

    The robots are sharded over `devices` (default: every device of every process). On a GPU it
    sets how this process compiles (`cfg.deterministic`) and, on one, lowers jax.random
    (`cfg.threefry_kernel`) from now on.
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
    env = AutoReset(EpisodeStats(env), cfg.reset_pool, cfg.reset_in_place, g, devices_used)
    reset = lambda keys: shard(env.reset(keys))  # noqa: E731
    step = lambda *args: shard(env.step(*args))  # noqa: E731  (state, action, fresh, banks)
    shard_draws = shard_envs(cfg.num_envs, devices, axis=1)  # [T, G, P/G, ...]: by block
    norm = (lambda stats, obs: normalize(stats, obs)) if cfg.normalize_obs else (lambda s, o: o)
    # The critic's own inputs [N, C] of a state, or None; the loss's inputs are (obs, those).
    critic_in = lambda state: state.info["critic"] if cfg.privileged_critic else None  # noqa: E731

    def first_keys(key: jax.Array):
        k_net, k_env, key = jax.random.split(key, 3)
        return k_net, key, shard(jax.random.split(k_env, cfg.num_envs))  # [N, 2] reset keys

    def init(key: jax.Array) -> TrainState:
        k_net, key, keys = first_keys(key)
        return _train_state(k_net, key, reset(keys))

    def _train_state(k_net, key, env_state) -> TrainState:
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

    def _draws(keys: jax.Array):
        """A rollout's new episodes, drawn ahead from the robots' reset keys [N, 2]: (the keys
        advanced [N, 2], the episodes: leaves [T, G, P/G, ...])."""
        keys, fresh = env.draw_keys(keys, cfg.rollout_length)
        return shard(keys), shard_draws(fresh)

    def _rollout(ts: TrainState, drawn=None) -> tuple[TrainState, Transition]:
        """(ts with its robots and key moved on, the transitions). `drawn`: `_draws` of the
        robots' reset keys, with `cfg.reset_ahead` (None: drawn here); without it, each step
        draws its own."""

        def _env_step(carry, fresh):
            env_state, key = carry
            key, k_act = jax.random.split(key)
            obs = norm(ts.obs_stats, env_state.obs)  # [N, D]
            extra = critic_in(env_state)
            logits, value = network.apply(ts.params, obs, extra)
            action = dist.sample(k_act, logits)  # [N] or [N, A]
            nxt = step(env_state, action, fresh, banks)
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
        banks = {}  # the arrays the steps leave in place (`AutoReset.bank`)
        # Named in the program (profiles; tests check that no rollout op waits on another device).
        with jax.named_scope("rollout"):
            if cfg.reset_ahead:
                keys, fresh = _draws(env_state.info[RESET_KEY]) if drawn is None else drawn
                env_state, fresh, banks = env.bank(with_reset_keys(env_state, keys), fresh)
            (env_state, key), traj = jax.lax.scan(
                _env_step, (env_state, ts.key), fresh, cfg.rollout_length
            )
            env_state = shard(env.unbank(env_state, banks))
        return ts.replace(env_state=env_state, key=key), traj

    grad = fused_grad or loss_grad(cfg, network, dist)  # (grads, metrics) of a minibatch

    def _update_minibatch(carry, batch: Batch):
        params, opt_state = carry
        grads, metrics = grad(params, batch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def _update_epoch(carry, _):
        params, opt_state, batch, key = carry
        key, k_perm = jax.random.split(key)
        perm = hashed_permutation(k_perm, cfg.batch_size // g)  # the same in every block

        def minibatches(x):  # [G, B/G, ...] -> [B/M, M, ...], minibatch i: every block's i-th part
            x = x[:, perm].reshape(g, cfg.num_minibatches, cfg.minibatch_size // g, *x.shape[2:])
            return x.swapaxes(0, 1).reshape(cfg.num_minibatches, cfg.minibatch_size, *x.shape[3:])

        shuffled = jax.tree_util.tree_map(minibatches, batch)
        (params, opt_state), metrics = jax.lax.scan(
            _update_minibatch, (params, opt_state), shuffled
        )
        return (params, opt_state, batch, key), metrics

    def _learn(ts: TrainState, traj: Transition) -> tuple[TrainState, dict]:
        """The learner on a rollout's transitions, `ts` its robots' state after them."""
        env_state, key = ts.env_state, ts.key
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

    def _update(ts: TrainState, drawn=None) -> tuple[TrainState, dict]:
        return _learn(*_rollout(ts, drawn))

    n = cfg.updates_per_chunk

    def zero_rows(metrics) -> dict:  # [updates_per_chunk] zeros shaped like one update's
        return jax.tree_util.tree_map(lambda a: jnp.zeros((n, *a.shape), a.dtype), metrics)

    def train(key: jax.Array):
        return jax.lax.scan(lambda ts, x: _update(ts), init(key), None, cfg.num_updates)

    # The programs a run compiles, each on its own and at once (`training.find_programs`): an
    # update is a rollout's program and then the learner's (and with new episodes drawn ahead,
    # `cfg.reset_ahead`, the rollout's draws first), and a chunk a loop of updates in Python, so
    # that XLA compiles the rollout and the learner (and the task's reset) at the same time rather
    # than one program of all; init's robots are draws of that program too, so the reset compiles
    # once.
    per_draw = cfg.rollout_length * env.draws_per_block(cfg.num_envs)  # a block's episodes
    calls = -(-cfg.num_envs // g // per_draw)  # calls of `draws` for init's robots

    def start(k_net, key, keys, batches) -> TrainState:
        """init's TrainState from the robots' reset keys [N, 2] and `calls` batches of `_draws`
        (leaves [T, G, P/G, ...]): block b's robots are its first N/G of those episodes."""

        def robots(*xs):  # -> [N, ...]
            xs = [x.swapaxes(0, 1).reshape(g, per_draw, *x.shape[3:]) for x in xs]  # [G, T * P/G]
            x = jnp.concatenate(xs, 1)[:, : cfg.num_envs // g]
            return x.reshape(cfg.num_envs, *x.shape[2:])

        env_state = jax.tree_util.tree_map(robots, *batches)
        return _train_state(k_net, key, shard(with_reset_keys(env_state, keys)))

    platform = devices_used[0].platform
    deterministic(cfg.deterministic)
    fusion_autotune(cfg.fusion_autotune)
    # On one device only: XLA cannot split the kernel's call over the devices the robots are
    # sharded over, and several GPUs are not measured with it.
    threefry_kernel(cfg.threefry_kernel and len(devices_used) == 1, platform)

    def jit(fn, name: str | None = None, **kw):  # with the options of the program `name`
        return jax.jit(fn, compiler_options=compiler_options(platform, name), **kw)

    laid = layouts(devices_used, cfg.reset_ahead, calls)
    keys_of = jax.jit(first_keys, **laid.get("keys", {}))  # a few ops: XLA's own options

    def compose(programs: dict):
        rollout, learn, draws = programs["rollout"], programs["learn"], programs.get("draws")

        def init_drawn(key: jax.Array) -> TrainState:
            k_net, key, keys = keys_of(key)
            batches = []
            for _ in range(calls):
                keys, fresh = draws(keys)
                batches.append(fresh)
            return programs["start"](k_net, key, keys, tuple(batches))

        def update(ts: TrainState):
            drawn = () if draws is None else (draws(ts.env_state.info[RESET_KEY]),)
            return learn(*rollout(ts, *drawn))

        def chunk(ts: TrainState):
            # As many updates as the budget has left; their metrics rows stay zero.
            live = int(np.clip(cfg.num_updates - int(ts.update), 0, n))
            rows = []
            for _ in range(live):
                ts, metrics = update(ts)
                rows.append(metrics)
            if rows:
                return ts, chunk_rows(tuple(rows))
            keys = ts.env_state.info.get(RESET_KEY)  # none: zero rows
            drawn = () if draws is None else (jax.eval_shape(_draws, keys),)
            rows = zero_rows(jax.eval_shape(_update, ts, *drawn)[1])
            return ts, {**rows, "live": jnp.zeros(n, bool)}

        return (init_drawn if draws is not None else programs["init"]), chunk

    @jax.jit
    def chunk_rows(rows: tuple) -> dict:
        """The metrics of a chunk's updates `rows` (at least one) as the chunk's rows
        [updates_per_chunk], zeros past them."""

        def stack(*x):
            return jnp.concatenate([jnp.stack(x), jnp.zeros((n - len(x), *x[0].shape), x[0].dtype)])

        return {**jax.tree_util.tree_map(stack, *rows), "live": jnp.arange(n) < len(rows)}

    def arguments(name: str, programs: dict, key: jax.Array):
        # "state": init's TrainState, what the update's programs take.
        if name in ("init", "draws"):
            return (key,) if name == "init" else (jax.eval_shape(keys_of, key)[2],)
        drawn = ()
        if cfg.reset_ahead:
            k_net, key, keys = jax.eval_shape(keys_of, key)
            keys, fresh = jax.eval_shape(programs["draws"], keys)
            begin = (k_net, key, keys, (fresh,) * calls)  # start's arguments
            if name == "start":
                return begin
            ts, drawn = jax.eval_shape(programs["start"], *begin), ((keys, fresh),)
        else:
            ts = jax.eval_shape(programs["init"], key)
        if name == "state":
            return ts
        if name == "rollout":
            return (ts, *drawn)
        return jax.eval_shape(programs["rollout"], ts, *drawn)  # "learn"

    parts = {
        "rollout": _rollout,
        "learn": _learn,
        "update": _update,
        "init": init,
        "draws": _draws,
        "start": start,
    }
    pin = lambda fn, name, **kw: jit(fn, name, **laid.get(name, {}), **kw)  # noqa: E731
    first = (
        {"draws": pin(_draws, "draws"), "start": pin(start, "start")}
        if cfg.reset_ahead
        else {"init": pin(init, "init")}
    )
    first = run_once(first, platform, len(devices_used))  # on one GPU: threefry as the kernel
    # Both take the train state and reuse its buffers: the robots' and the learner's.
    steps = {
        "rollout": pin(_rollout, "rollout", donate_argnums=0),
        "learn": pin(_learn, "learn", donate_argnums=0),
    }
    programs = {**first, **steps}
    trainer = Trainer(
        network, None, None, jit(train), parts, {}, compose, arguments, tuple(first), laid_out=True
    )
    return trainer.with_programs(**programs)


def layouts(devices: list, ahead: bool, calls: int) -> dict:
    """{program: {"in_shardings": ..., "out_shardings": ...}} of `make_train`'s programs on
    several `devices` ({} on one): the learner's state on every device, the robots' state [N, ...]
    and the reset keys split along their first axis, the new episodes drawn ahead [T, G, P/G, ...]
    and the rollout's transitions [T, N, ...] along their second (`shard_envs`), as XLA lays
    them out when left to choose. Fixed, each program compiles from its arguments' shapes alone,
    before the programs before it have run (`training.find_programs`)."""
    if len(devices) == 1:
        return {}
    robots, steps = envs_sharding(devices, 0), envs_sharding(devices, 1)
    every = NamedSharding(robots.mesh, PartitionSpec())  # replicated
    state = TrainState(
        params=every, opt_state=every, obs_stats=every, env_state=robots, key=every, update=every
    )
    drawn = ((robots, steps),) if ahead else ()  # the draws' (reset keys, new episodes)
    shardings = {
        "keys": ((every,), (every, every, robots)),  # first_keys: (k_net, key, reset keys)
        "init": ((every,), state),
        "draws": ((robots,), (robots, steps)),
        "start": ((every, every, robots, (steps,) * calls), state),
        "rollout": ((state, *drawn), (state, steps)),
        "learn": ((state, steps), (state, every)),
    }
    names = ("in_shardings", "out_shardings")
    return {name: dict(zip(names, pair, strict=True)) for name, pair in shardings.items()}
