"""Env-only throughput: random-policy rollouts of the training distribution of `python -m jaxnav.train`.

    python benchmarks/env_rollout.py --num-envs 1024 --steps 96 --json benchmarks/results/env_rollout_cpu.json
    python benchmarks/env_rollout.py --variants default,rows1,no_fidelity,pool_all ...

Each variant is the default training env (5-row camera, sim-to-real ranges of randomize.FIDELITY,
the auto-reset pool of the PPO default, each 32 steps' new episodes drawn in one batch ahead of
them as PPO's `reset_ahead` draws a rollout's) with one thing changed, to time what each piece
costs: `per_step` (the new episodes drawn at every step instead, as every task trained before
2026-11-30; `rows1_per_step` with a 1-row camera), `rows1`/`rows3` (a 1- or 3-row camera),
`no_fidelity` (randomize.FIDELITY off), `families` (sampled rooms drawn from every room family),
`pool_all` (a new episode drawn for every robot at every step), `wheeled` (the wheeled
validation model, `SceneConfig.physics`), `movers` (0-3 moving obstacles per room,
`RandomizeConfig.moving_count`); the `goal` task (`goal_families`: rooms of every family,
`goal_history0`: no stacked frames, `goal_straight`: straight-line progress, no distance field,
`goal_pool64`: new episodes drawn for 1/64 of the robots per step instead of 1/16, as the goal
task trains); the speed levers: `full` (MJX's
contact pass in every physics step, `SceneConfig.fast_contacts`, and the auto-reset's select in
every row, `PPOConfig.reset_in_place` off, as by default), `contacts` (MJX's contact pass alone)
and `in_place` (the auto-reset writing the finished rows only).

`analytic` is a bound for `rows1`: its rays on its rooms' shapes without MJX or what the robot's
drive and camera add (`analytic_step`), the same batch of rooms and spawns.

Times a jitted `lax.scan` of `--steps` batched steps (auto-reset included) after compiling it once,
and prints env-steps/s per variant and batch size. `--trace DIR` then runs each timed rollout once
more under JAX's profiler (into DIR/VARIANT-ROBOTS) and adds to its row the ops a step (on a GPU
its kernels), what MJX's step takes of them (`mjx_share`) and those that took the most time
(`throughput.top_ops`); on a GPU, set XLA_FLAGS to `--xla_gpu_enable_command_buffer=` so
that each kernel runs, and is named, on its own.

    python benchmarks/env_rollout.py --num-envs 65536 --steps 64 --repeats 2 --variants rows1,analytic
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time

import jax
import jax.numpy as jnp
from report import run_info, write_json
from throughput import op_events, print_top, top_ops

import jaxnav
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import FIDELITY, TRAINING
from jaxnav.core.scene import SceneConfig
from jaxnav.core.sensors import SensorConfig, ray_depths
from jaxnav.ppo.config import PPOConfig
from jaxnav.wrappers import AutoReset

NO_FIDELITY = {k: getattr(jaxnav.core.randomize.RandomizeConfig(), k) for k in FIDELITY}
VARIANTS = {
    "default": {},
    "per_step": {"ahead": False},
    "rows1": {"sensor": SensorConfig(rows=1)},
    "rows1_per_step": {"sensor": SensorConfig(rows=1), "ahead": False},
    "rows3": {"sensor": SensorConfig(rows=3)},
    "no_fidelity": {"randomize": dataclasses.replace(TRAINING, **NO_FIDELITY)},
    "families": {"randomize": dataclasses.replace(TRAINING, families="all")},
    "pool_all": {"reset_share": 1.0, "ahead": False},
    "wheeled": {"scene": SceneConfig(physics="wheeled")},
    "movers": {"randomize": dataclasses.replace(TRAINING, moving_count=(0, 3))},
    # The speed levers (benchmarks/throughput.py --variants has them too): the full MJX path, and
    # each lever against the defaults.
    "full": {"scene": SceneConfig(fast_contacts=True), "in_place": False},
    "contacts": {"scene": SceneConfig(fast_contacts=True)},
    "in_place": {"in_place": True},
    # The goal task (its default 16-frame memory and geodesic progress), and what its pieces cost.
    "goal": {"task": "goal"},
    "goal_families": {"task": "goal", "randomize": dataclasses.replace(TRAINING, families="all")},
    "goal_history0": {"task": "goal", "history": 0},
    "goal_straight": {"task": "goal", "progress": "straight"},
    "goal_pool64": {"task": "goal", "reset_share": 1 / 64},
}
WINDOW = 32  # steps whose new episodes are drawn in one batch ahead of them (a PPO rollout)


def _ahead(variant: str) -> bool:
    """Whether `variant` draws each WINDOW steps' new episodes ahead of them, as PPO does."""
    return VARIANTS[variant].get("ahead", PPOConfig().reset_ahead)


def make(variant: str, num_envs: int):
    """(the training env of `variant`, auto-reset as PPO runs it; whether it draws ahead)."""
    kwargs = dict(VARIANTS[variant])
    ahead = _ahead(variant)
    kwargs.pop("ahead", None)
    ppo = PPOConfig(
        num_envs=num_envs,
        minibatch_size=num_envs,  # unused here; any size that divides a rollout
        reset_share=kwargs.pop("reset_share", PPOConfig().reset_share),
        reset_in_place=kwargs.pop("in_place", PPOConfig().reset_in_place),
    )
    env = jaxnav.make_env(kwargs.pop("task", "avoid"), **kwargs)
    return AutoReset(env, pool=ppo.reset_pool, in_place=ppo.reset_in_place), ahead


def measure(
    num_envs: int, steps: int, repeats: int, variant: str = "default", trace: str | None = None
) -> dict:
    env, ahead = make(variant, num_envs)
    reset = jax.jit(env.reset)
    window = WINDOW if ahead else steps  # `main` checked that WINDOW divides steps

    @jax.jit
    def rollout(state, key):
        def run_window(carry, k):
            state, total = carry
            fresh, banks = None, {}
            if ahead:  # as a PPO rollout: its task's banked arrays left in place (AutoReset.bank)
                state, fresh, banks = env.bank(*env.draw(state, window))

            def body(carry, xs):
                state, total = carry
                k, fresh = xs
                action = jax.random.randint(k, (num_envs,), 0, env.action_spec.n)
                state = env.step(state, action, fresh, banks)
                return (state, total + state.reward.sum()), None

            keys = jax.random.split(k, window)
            state, total = jax.lax.scan(body, (state, total), (keys, fresh))[0]
            return (env.unbank(state, banks), total), None

        (state, total), _ = jax.lax.scan(
            run_window, (state, jnp.float32(0)), jax.random.split(key, steps // window)
        )
        return state, total

    state = jax.block_until_ready(reset(jax.random.split(jax.random.PRNGKey(0), num_envs)))
    return _timed(rollout, state, num_envs, steps, repeats, variant, trace)


def analytic_step(env, state, action):
    """The one-row step without MJX, the bound of `analytic`: the command integrated as a
    unicycle over the control period (no smoother, latency, gains or traction), the same rays on
    the same shapes (`sensors.ray_depths`: noiseless, no dropout), the sectors' minimum, the
    bumper's signed distance, Table I; an episode that ends starts again at its spawn in its
    room (no new draw). `state` = (qpos [3], steps [], obs [S], params); one robot."""
    qpos, steps, obs, params = state
    cfg, task = env.sensor, env.task
    command = env.command(action)  # [2] forward m/s, yaw rad/s
    v, w = command
    yaw = qpos[2] + w * env.control_period
    step = v * env.control_period * jnp.stack([jnp.cos(yaw), jnp.sin(yaw)])
    qpos = jnp.concatenate([qpos[:2] + step, yaw[None]])
    depth = ray_depths(params, qpos, cfg, env.robot).reshape(cfg.num_sectors, -1).min(-1)
    sectors = jnp.clip(depth, cfg.range_min, cfg.range_max)  # [S]
    span = tuple(jnp.float32(h) for h in env.scene.bumper_z)
    hit = signed_distance(params, qpos[:2], span) < env.scene.bumper_radius
    reward = env._reward(obs, action, command, hit)  # Table I, as the env's step gives it
    done = hit | (steps + 1 >= task.max_steps)
    qpos = jnp.where(done, params.spawn, qpos)
    return (qpos, jnp.where(done, 0, steps + 1), sectors, params), reward


def measure_analytic(num_envs: int, steps: int, repeats: int, trace: str | None = None) -> dict:
    """`analytic`: `analytic_step` in the rooms and spawns of the `rows1` env's resets."""
    env = jaxnav.make_env("avoid", **VARIANTS["rows1"])
    first = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs))
    params = first.info["params"]
    sectors = first.obs[:, : env.sensor.num_sectors]  # the newest frame
    state = (first.data.qpos[:, :3], jnp.zeros(num_envs, jnp.int32), sectors, params)
    step = jax.vmap(lambda s, a: analytic_step(env, s, a))

    @jax.jit
    def rollout(state, key):
        def body(carry, k):
            state, total = carry
            action = jax.random.randint(k, (num_envs,), 0, env.action_spec.n)
            state, reward = step(state, action)
            return (state, total + reward.sum()), None

        return jax.lax.scan(body, (state, jnp.float32(0)), jax.random.split(key, steps))[0]

    return _timed(rollout, state, num_envs, steps, repeats, "analytic", trace)


def _timed(rollout, state, num_envs, steps, repeats, variant, trace=None) -> dict:
    """Compiles and runs `rollout` (state, key) -> (state, total) once, then times `repeats`
    runs: the best one's env-steps/s; with `trace` (a folder), one more run profiled."""
    tick = time.perf_counter()
    state, _ = jax.block_until_ready(rollout(state, jax.random.PRNGKey(1)))
    compile_s = time.perf_counter() - tick
    best = float("inf")
    for i in range(repeats):
        tick = time.perf_counter()
        state, _ = jax.block_until_ready(rollout(state, jax.random.PRNGKey(2 + i)))
        best = min(best, time.perf_counter() - tick)
    row = {
        "num_envs": num_envs,
        "variant": variant,
        "steps": steps,
        "compile_s": round(compile_s, 2),
        "seconds": round(best, 4),
        "env_steps_per_s": round(num_envs * steps / best),
    }
    if trace:
        folder = f"{trace}/{variant}-{num_envs}"
        key = jax.random.PRNGKey(2 + repeats)
        with jax.profiler.trace(folder):
            jax.block_until_ready(rollout(state, key))
        events = op_events(folder)
        row["ops_per_step"] = round(len(events) / steps, 1)
        row["trace_top"] = top_ops(events)
        row["trace_mjx"] = mjx_share(events, rollout.lower(state, key).compile().as_text(), steps)
    return row


# An instruction of XLA's optimised program and the op it came from (its metadata's op_name).
_INSTRUCTION = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+) = .*?metadata=\{op_name="([^"]*)"', re.M)
_MJX_STEP = re.compile(r"(^|/)step/(forward|euler)/")  # MJX's named scopes inside `mjx.step`


def _kernel(name: str) -> str:
    """An op's name as profiles and programs both write it ("loop_add_fusion_1")."""
    return name.replace(".", "_").replace("-", "_")


def mjx_share(events: list[dict], program: str, steps: int) -> dict:
    """What MJX's step takes of a profiled rollout of `steps` steps (`events`: its trace's
    `op_events`, on a GPU its kernels; on the CPU the host's events, which nest, so their sum
    overlaps): its ops a step and their microseconds a step, beside all ops'. Each op is looked
    up in the rollout's optimised `program` (HLO text) and is MJX's where its op came from inside
    `mjx.step`."""
    origin = {_kernel(n): op for n, op in _INSTRUCTION.findall(program)}
    mjx = [e for e in events if _MJX_STEP.search(origin.get(_kernel(e["name"]), ""))]
    return {
        "ops_per_step": round(len(mjx) / steps, 1),
        "us_per_step": round(sum(e["dur"] for e in mjx) / steps, 1),
        "all_us_per_step": round(sum(e["dur"] for e in events) / steps, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", default="1024", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=96, help="a multiple of 32 where drawn ahead")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--trace", help="profile each timed rollout once more into this folder")
    parser.add_argument(
        "--variants",
        default="default",
        help=f"comma-separated: {', '.join(VARIANTS)}, analytic",
    )
    args = parser.parse_args()
    sizes = [int(n) for n in args.num_envs.split(",")]
    variants = args.variants.split(",")
    for v in variants:  # every one checked before any is timed
        if v != "analytic" and v not in VARIANTS:
            parser.error(f"--variants: unknown '{v}' (known: {', '.join(VARIANTS)}, analytic)")
        if v != "analytic" and _ahead(v) and args.steps % WINDOW:
            parser.error(f"--steps {args.steps}: must be a multiple of {WINDOW} for '{v}'")
    rows = [
        measure_analytic(n, args.steps, args.repeats, args.trace)
        if v == "analytic"
        else measure(n, args.steps, args.repeats, v, args.trace)
        for v in variants
        for n in sizes
    ]
    result = {
        **run_info("device"),
        "devices": jax.local_device_count(),
        **run_info("python", "date", "jax"),
        "rows": rows,
    }
    print(
        f"{'variant':>14} {'robots':>8} {'steps':>6} {'compile s':>10} {'env-steps/s':>12}   "
        f"({result['device']})"
    )
    for r in rows:
        print(
            f"{r['variant']:>14} {r['num_envs']:>8} {r['steps']:>6} {r['compile_s']:>10} "
            f"{r['env_steps_per_s']:>12,}"
        )
    for r in (r for r in rows if "trace_top" in r):
        mjx = r["trace_mjx"]
        print(
            f"\n{r['variant']}, {r['num_envs']} robots: {r['ops_per_step']} ops a step "
            f"({mjx['all_us_per_step']} us), MJX's step {mjx['ops_per_step']} of them "
            f"({mjx['us_per_step']} us); the most time:"
        )
        print_top(r["trace_top"])
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
