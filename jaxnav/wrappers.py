"""Wrappers over the env contract: per-episode auto-reset and episode statistics for training.

`EpisodeStats` sums the reward and each declared metric over an episode and publishes the sums in
`info["episode"]` on the step that ends it (per env: vmap it); `AutoReset` runs a batch of envs and
starts a new episode (a fresh draw of room, spawn and parameters: the task's own `reset`) wherever
one ended. Training uses `AutoReset(EpisodeStats(env), pool)`; evaluation uses the bare task and
stops each episode itself.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp

from jaxnav.core import xla
from jaxnav.core.types import Banked, EnvState

EPISODE = "episode"  # info key of the finished-episode sums: return, length and each metric
RUNNING = "episode_running"  # info key of the sums of the episode in progress
RESET_KEY = "reset_key"  # info key of AutoReset's PRNG key
OBSERVED_APART = 2  # batches of a draw's first observations (`AutoReset._observed_apart`)


class Wrapper:
    """Forwards the contract's attributes to the wrapped env."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)


class EpisodeStats(Wrapper):
    """info["episode"]: {"return", "length", *metric_names} of the last finished episode."""

    def _zeros(self) -> dict:
        names = ("return", "length", *self.env.metric_names)
        return {k: jnp.float32(0) for k in names}

    def reset(self, key: jax.Array) -> EnvState:
        return self._counting(self.env.reset(key))

    def begin(self, key: jax.Array) -> tuple[EnvState, jax.Array]:
        """The wrapped task's `begin` (its reset in two parts, `jaxnav.tasks.base.NavTask`)."""
        state, k_obs = self.env.begin(key)
        return self._counting(state), k_obs

    def _counting(self, state: EnvState) -> EnvState:
        return state.replace(info={**state.info, RUNNING: self._zeros(), EPISODE: self._zeros()})

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        running = state.info[RUNNING]
        nxt = self.env.step(state, action)
        step_values = {"return": nxt.reward, "length": jnp.float32(1), **nxt.metrics}
        total = {k: running[k] + step_values[k].astype(jnp.float32) for k in running}
        done = nxt.done
        finished = {k: jnp.where(done, total[k], state.info[EPISODE][k]) for k in total}
        running = {k: jnp.where(done, 0.0, v) for k, v in total.items()}
        return nxt.replace(info={**nxt.info, RUNNING: running, EPISODE: finished})


class AutoReset(Wrapper):
    """A batch of N envs (`reset(keys [N, 2])`, `step(state, action [N])`) in which every env
    whose episode ends continues with a new one, drawn by the env's own `reset`.

    The step's reward, done, truncated and metrics are kept (they belong to the episode that
    ended); physics, observation and info come from the new episode, except the finished-episode
    statistics `info["episode"]`, which carry over.

    `pool`: new episodes drawn per step (None or >= N: one per env). Under vmap a draw costs the
    same whether it is used or not, and episodes last tens to hundreds of steps, so drawing one
    for every env at every step spends most of a step's sensing and room sampling on draws that
    are thrown away. With a pool of P, the k-th env to finish in a step (k = 0, 1, ...) takes draw
    k mod P; if more than P finish in one step, some of them start the same episode (room, spawn
    and parameters), and their trajectories part with the policy's own sampling.

    `in_place`: write the draws into the rows of the envs that finished only (at most P of them),
    instead of selecting between the old and the new state in every row: the same result bit for
    bit (tested), reading and writing P rows of state instead of N. A step in which more than P
    envs finish takes the select. Choosing is a branch on every step, which a GPU waits for, and
    with the blocks over devices, all of them (`PPOConfig.reset_in_place`, off by default).

    `groups`: G independent blocks of N/G consecutive envs, each with its own P/G draws from its
    own envs' keys (G = 1: one block). With the blocks sharded over devices, every device draws
    for its own robots only, and no step needs another device's data. `devices`: those devices
    (the envs split between them in equal consecutive parts), for the kernels that take one
    device's part of a batch (the goal task's flood on GPUs: `xla.on_devices`).

    Drawing ahead: `draw(state, steps)` draws the pools of the next `steps` steps in one batch
    (steps x P episodes), and `step(state, action, fresh)` takes one step's pool from it (a scan
    over the steps with the draws as its xs). The draws do not depend on the state, so the
    episodes come from the same distribution as the per-step draws, from other keys: one large
    batch instead of many small ones (PPO's default; docs/results.md has what it changes).

    Banking: over such a window, `bank(state, fresh)` puts each of the task's `banked_info` arrays
    (the goal task's geodesic field: most of its state) of the envs and of the new episodes in one
    bank and leaves each env its row; `step(..., banks)` hands the task its arrays `Banked` and
    selects the rows alone, and `unbank` gathers the arrays back. Without it, every step moves
    every env's array through the select whether its episode ended or not. Each block has a bank
    of its own, which its envs' steps read (a vmap over the blocks), so that blocks on devices
    read their own. The same states bit for bit (tested).
    """

    def __init__(
        self, env, pool: int | None = None, in_place: bool = False, groups: int = 1, devices=None
    ):
        super().__init__(env)
        if pool is not None and pool < 1:
            raise ValueError(f"AutoReset.pool: must be >= 1, got {pool}")
        if groups < 1:
            raise ValueError(f"AutoReset.groups: must be >= 1, got {groups}")
        if devices is not None and groups % len(devices):
            raise ValueError(f"AutoReset.groups: {groups} blocks over {len(devices)} devices")
        self.pool, self.in_place, self.groups, self.devices = pool, in_place, groups, devices
        self.banked = tuple(getattr(env, "banked_info", ()))

    def _on_devices(self):
        """The context the resets trace in: `xla.on_devices(self.devices)` where given."""
        return contextlib.nullcontext() if self.devices is None else xla.on_devices(self.devices)

    def reset(self, keys: jax.Array) -> EnvState:
        keys, k_reset = _split(keys)
        with self._on_devices():
            return with_reset_keys(jax.vmap(self.env.reset)(k_reset), keys)

    def draws_per_block(self, total: int) -> int:
        """P/G: the new episodes each block draws per step, for `total` envs."""
        return max(1, min(self.pool or total, total) // self.groups)

    def _pool_keys(self, k_reset: jax.Array) -> jax.Array:
        """[G, P/G, 2]: the keys of one step's draws, each block's from its first envs' keys."""
        return _blocks(k_reset, self.groups)[:, : self.draws_per_block(k_reset.shape[0])]

    def draw(self, state: EnvState, steps: int) -> tuple[EnvState, EnvState]:
        """(state with its keys advanced, the new episodes of the next `steps` steps: leaves
        [steps, G, P/G, ...]), for `step(..., fresh=draws[t])`."""
        keys, fresh = self.draw_keys(state.info[RESET_KEY], steps)
        return with_reset_keys(state, keys), fresh

    def draw_keys(self, keys: jax.Array, steps: int) -> tuple[jax.Array, EnvState]:
        """`draw` from the envs' reset keys [N, 2] (`state.info[RESET_KEY]`): (those keys
        advanced, the new episodes)."""
        keys, k_reset = _split(keys)  # [N, 2] each
        first = self._pool_keys(k_reset)  # [G, P/G, 2]
        per_step = jax.vmap(lambda t: jax.vmap(jax.vmap(lambda k: jax.random.fold_in(k, t)))(first))
        return keys, self._resets(per_step(jnp.arange(steps)), block_axis=1, apart=True)

    def bank(self, state: EnvState, fresh: EnvState) -> tuple[EnvState, EnvState, dict]:
        """(`state` [N] and `fresh` [T, G, P/G] of `draw` with every banked array replaced by its
        int32 row in its block's bank, the banks {key: [G, N/G + T x P/G, ...]}: each block's
        envs' arrays, then its new episodes'), for the T steps `step(..., fresh[t], banks)` and
        then `unbank`. ({} where the task banks nothing.) A block's bank lies where its envs do."""
        if not self.banked:
            return state, fresh, {}
        g, n, (t, _, p) = self.groups, state.done.shape[0], fresh.done.shape
        local = n // g  # a block's envs

        def join(mine, new):  # [N, ...], [T, G, P/G, ...] -> [G, N/G + T x P/G, ...]
            new = jnp.swapaxes(new, 0, 1).reshape(g, t * p, *new.shape[3:])
            return jnp.concatenate([mine.reshape(g, local, *mine.shape[1:]), new], 1)

        banks = {k: join(state.info[k], fresh.info[k]) for k in self.banked}
        own = jnp.tile(jnp.arange(local, dtype=jnp.int32), g)  # [N]
        drawn = local + jnp.arange(t * p, dtype=jnp.int32).reshape(t, 1, p)
        drawn = jnp.broadcast_to(drawn, (t, g, p))  # [T, G, P/G]
        rows = lambda index: dict.fromkeys(self.banked, index)  # noqa: E731
        return _with_info(state, rows(own)), _with_info(fresh, rows(drawn)), banks

    def unbank(self, state: EnvState, banks: dict) -> EnvState:
        """`state` [N] of `bank`'s steps with each env's arrays gathered from its block's bank."""
        g = self.groups
        gather = jax.vmap(lambda bank, index: bank[index])  # a block's: [M, ...], [N/G]

        def arrays(k):
            bank, index = banks[k], state.info[k].reshape(g, -1)
            return gather(bank, index).reshape(index.size, *bank.shape[2:])

        return _with_info(state, {k: arrays(k) for k in banks})

    def _resets(self, keys: jax.Array, block_axis: int, apart: bool = False) -> EnvState:
        """The env's resets of `keys` ([G, P/G, 2], or [steps, G, P/G, 2]: G at `block_axis`),
        leaves shaped like the keys. One vmap over all of a block's keys, so that the reset
        traces under one batching level, not one per axis; with G > 1 a vmap over the blocks
        outside it, so that blocks sharded over devices stay where they are. `apart`: the first
        observations made after the rooms (`_observed_apart`; the draws ahead: a step's own few
        draws would add a loop to every step, which costs a GPU 2 % of the env-only pace)."""

        def flat(k):  # [..., 2] -> [...]
            lead, k = k.shape[:-1], k.reshape(-1, k.shape[-1])
            out = self._observed_apart(k) if apart else jax.vmap(self.env.reset)(k)
            return jax.tree_util.tree_map(lambda x: x.reshape(*lead, *x.shape[1:]), out)

        with self._on_devices():
            if self.groups == 1:
                return flat(keys)
            return jax.vmap(flat, in_axes=block_axis, out_axes=block_axis)(keys)

    def _observed_apart(self, keys: jax.Array) -> EnvState:
        """The env's resets of `keys` [M, 2]. For a task whose reset comes in two parts (`begin`,
        `first_observation`: `jaxnav.tasks.base.NavTask.reset`), the first observations are made in
        OBSERVED_APART batches by a loop, after every episode is drawn: XLA's CPU backend would
        otherwise draw each room again inside every ray of its first observation (the 2-core CPU:
        avoid's draws 21 -> 9 ms an update, the goal task's ops 74 -> 63 ms of both threads'
        time, `benchmarks/update_profile.py`). The values are the reset's to within float
        rounding (XLA fuses the two parts apart)."""
        env = self.env
        if not hasattr(env, "first_observation"):  # a task with a reset of one part
            return jax.vmap(env.reset)(keys)
        states, obs_keys = jax.vmap(env.begin)(keys)
        m = keys.shape[0]
        parts = OBSERVED_APART if m % OBSERVED_APART == 0 else 1
        in_parts = lambda x: x.reshape(parts, m // parts, *x.shape[1:])  # noqa: E731
        observed = jax.lax.map(
            lambda part: jax.vmap(env.first_observation)(*part),
            jax.tree_util.tree_map(in_parts, (states, obs_keys)),
        )
        return jax.tree_util.tree_map(lambda x: x.reshape(m, *x.shape[2:]), observed)

    def _stepped(self, state: EnvState, action: jax.Array, banks) -> EnvState:
        """The env's step of every env [N]; with `banks` ({} or None: none), each env's banked
        arrays handed to it `Banked` in its block's bank, and left as they were (its rows)."""
        if not banks:
            return jax.vmap(self.env.step)(state, action)

        def block(bank: dict, s: EnvState, a: jax.Array) -> EnvState:  # a block's envs, its bank

            def env_step(s: EnvState, a: jax.Array) -> EnvState:
                lent = {k: Banked(bank[k], s.info[k]) for k in bank}
                out = self.env.step(_with_info(s, lent), a)
                return _with_info(out, {k: s.info[k] for k in bank})  # unchanged: its rows

            return jax.vmap(env_step)(s, a)

        g = self.groups
        if g == 1:
            return block({k: b[0] for k, b in banks.items()}, state, action)
        nxt = jax.vmap(block)(banks, _blocks(state, g), _blocks(action, g))
        return jax.tree_util.tree_map(lambda x: x.reshape(g * x.shape[1], *x.shape[2:]), nxt)

    def step(
        self, state: EnvState, action: jax.Array, fresh: EnvState | None = None, banks=None
    ) -> EnvState:
        """One step of every env; `fresh` (leaves [G, P/G, ...], one step of `draw`) are the new
        episodes, else this step draws its own. `banks`: `bank`'s, where `state` and `fresh`
        hold rows of them."""
        keys, k_reset = _split(state.info[RESET_KEY])  # [N, 2] each
        info = {k: v for k, v in state.info.items() if k != RESET_KEY}
        nxt = self._stepped(state.replace(info=info), action, banks)
        g, total = self.groups, action.shape[0]
        pool = self.draws_per_block(total)
        if fresh is None:
            fresh = self._resets(self._pool_keys(k_reset), block_axis=0)  # [G, P/G]
        # What a new episode replaces: physics, observation and info, except the finished
        # episode's statistics, which carry over.
        part = lambda s: (s.data, s.obs, {k: v for k, v in s.info.items() if k != EPISODE})  # noqa: E731
        done, old = _blocks(nxt.done, g), _blocks(part(nxt), g)
        if self.in_place and pool < total // g:
            overflow = (done.sum(axis=1) > pool).any()
            merged = jax.lax.cond(
                overflow, jax.vmap(_select), jax.vmap(_write), done, part(fresh), old
            )
        else:
            merged = jax.vmap(_select)(done, part(fresh), old)
        data, obs, info = jax.tree_util.tree_map(lambda x: x.reshape(total, *x.shape[2:]), merged)
        if EPISODE in nxt.info:
            info = {**info, EPISODE: nxt.info[EPISODE]}
        return nxt.replace(data=data, obs=obs, info={**info, RESET_KEY: keys})


def _with_info(state: EnvState, values: dict) -> EnvState:
    """`state` with `values` in its info."""
    return state.replace(info={**state.info, **values})


def with_reset_keys(state: EnvState, keys: jax.Array) -> EnvState:
    """`state` whose envs draw their next episodes from `keys` [N, 2]."""
    return _with_info(state, {RESET_KEY: keys})


def _blocks(tree, g: int):
    """Every leaf [N, ...] of `tree` as [G, N/G, ...]: G blocks of consecutive envs."""
    return jax.tree_util.tree_map(lambda x: x.reshape(g, x.shape[0] // g, *x.shape[1:]), tree)


def _select(done: jax.Array, fresh, old):
    """`old` [N] with the k-th env that is `done` [N] (k = 0, 1, ...) replaced by draw k mod P of
    `fresh` [P]: a gather and a select in every row."""
    pool = jax.tree_util.tree_leaves(fresh)[0].shape[0]
    slot = (jnp.cumsum(done) - 1) % pool  # [N] the draw each finishing env takes
    pick = lambda new, o: jnp.where(done.reshape(-1, *([1] * (o.ndim - 1))), new[slot], o)  # noqa: E731
    return jax.tree_util.tree_map(pick, fresh, old)


def _write(done: jax.Array, fresh, old):
    """`_select` when at most P envs are done: draw k written into the k-th done env's row."""
    pool = jax.tree_util.tree_leaves(fresh)[0].shape[0]
    rows = jnp.nonzero(done, size=pool, fill_value=done.shape[0])[0]  # [P]; N: no env
    return jax.tree_util.tree_map(lambda new, o: o.at[rows].set(new, mode="drop"), fresh, old)


def _split(keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each of the keys [N, 2] split in two: ([N, 2], [N, 2])."""
    pairs = jax.vmap(jax.random.split)(keys)  # [N, 2, 2]
    return pairs[:, 0], pairs[:, 1]
