"""Throughput of the `avoid` scene and of PPO training, per batch size, with a split of the step.

    python benchmarks/throughput.py --num-envs 1024,4096 --steps 100 --json benchmarks/throughput.json
    python benchmarks/throughput.py --num-envs 65536 --variants default,full,in_place
    python benchmarks/throughput.py --env goal --num-envs 256 --steps 10 --no-train

For each size: (a) env-only random rollouts of the training distribution (sim-to-real ranges and the
5-row camera on, auto-reset with PPO's default pool) with every obstacle slot in use,
(b) full PPO updates of the `cpu` preset shape (rollout 32, 4 epochs, 4 minibatches), and the split of
one control step into physics / sensor / reset sampling / a whole reset / policy forward, and of
one PPO update into rollout and learning. `--env goal` times the `goal` task instead (its reset
also draws the goal and its distance field), with the task's own PPO defaults (new episodes for
1/64 of the robots). PPO draws a rollout's new episodes ahead of it; the env-only step draws
them per step, so an update's learning share (the update less 32 env-only steps) also holds
what drawing ahead saves. Every timing is
the best of `--repeats` runs of a jitted scan, after compiling it, with `block_until_ready`.

`--variants` times the speed levers on and off (`VARIANTS`): `full` is the full MJX path (MJX's
contact pass in every physics step, the auto-reset selecting in every row), `default` the
defaults, `contacts` and `in_place` one lever each against them, `people` every room of the
`crowd` family (its walkers' step in every env step), `groups2` two blocks of robots on one
device (`--groups 2`: as two devices split them, each block drawing and banking its own).
`--pieces` names the variants that also get the split; `--trace DIR` writes a JAX profiler
trace of one PPO chunk of the first variant (open it in TensorBoard or Perfetto) and prints its
top ops and, per accelerator, the chunk's span, busy time and time in cross-device ops (on
several GPUs: how long each waited for the others).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gzip
import json
import resource
import time
from pathlib import Path

import jax
import jax.numpy as jnp
from report import run_info, write_json

import jaxnav
from jaxnav.core.randomize import TRAINING
from jaxnav.core.scene import SceneConfig
from jaxnav.core.xla import threefry_kernel
from jaxnav.ppo.config import PPOConfig, preset
from jaxnav.ppo.train import make_network, make_train
from jaxnav.tasks.avoid import AvoidConfig
from jaxnav.tasks.registry import task_defaults
from jaxnav.wrappers import AutoReset

# The training distribution (sim-to-real ranges on) with every obstacle slot in use.
FULL = dataclasses.replace(TRAINING, num_boxes=(8, 8), num_cylinders=(4, 4), sampled_room_prob=1.0)
# The speed levers against the defaults: SceneConfig.fast_contacts (MJX's contact pass and solver)
# and PPOConfig.reset_in_place (the auto-reset writes the finished rows only, behind a branch).
VARIANTS = {
    "default": {},
    "full": {"scene": {"fast_contacts": True}, "ppo": {"reset_in_place": False}},
    "contacts": {"scene": {"fast_contacts": True}},
    "in_place": {"ppo": {"reset_in_place": True}},
    # Where the new episodes are drawn (PPOConfig.reset_ahead: each step's pool in the rollout
    # rather than a rollout's ahead of it) and how jax.random lowers on a GPU
    # (PPOConfig.threefry_kernel); the env-only rows draw per step either way.
    "per_step": {"ppo": {"reset_ahead": False}},
    "kernel": {"ppo": {"threefry_kernel": True}},
    "inline": {"ppo": {"threefry_kernel": False}},
    # New episodes for 1/64 of the robots per step instead of 1/16 (PPOConfig.reset_share).
    "pool64": {"ppo": {"reset_share": 1 / 64}},
    "pool64_per_step": {"ppo": {"reset_share": 1 / 64, "reset_ahead": False}},
    # The learner's gradient as XLA's kernels of jax.grad rather than one (PPOConfig.fused_learner).
    "xla_learner": {"ppo": {"fused_learner": False}},
    # Every room of the `crowd` family: 3-6 people walking (jaxnav.core.crowd) in each.
    "people": {"randomize": {"families": "crowd"}},
    # Two robot blocks on one device, each drawing and banking its own (as two devices split them).
    "groups2": {"ppo": {"groups": 2}},
}


def timed(fn, *args, repeats=3):
    """(compile seconds, best run seconds) of a jitted fn."""
    tick = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - tick
    best = float("inf")
    for _ in range(repeats):
        tick = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - tick)
    return compile_s, best


def scan_steps(fn, steps):
    """jit(state -> state after `steps` applications of fn), keeping every result alive."""
    return jax.jit(lambda s: jax.lax.scan(lambda c, _: (fn(c), None), s, None, steps)[0])


def env_pieces(env, n, steps, repeats, ppo: dict, split=True):
    """env-steps/s of a whole step and (`split`) of its pieces, each run alone over `steps` steps."""
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    cfg = PPOConfig(num_envs=n, total_steps=n * 1024, **ppo)  # at least one rollout of any length
    # The step training runs (episode statistics aside).
    wrapped = AutoReset(env, cfg.reset_pool, in_place=cfg.reset_in_place)
    state = jax.jit(wrapped.reset)(keys)
    actions = jax.random.randint(jax.random.PRNGKey(1), (n,), 0, env.action_spec.n)
    cmd = jnp.array(env.action_spec.commands[0])  # forward

    def physics(s):
        d, _ = jax.vmap(lambda p, d: env.drive(p, d, cmd))(s.info["params"], s.data)
        return s.replace(data=d)

    def sensor(s):
        obs = jax.vmap(env.sense)(s.info["params"], s.data, keys)  # [N, sectors]
        # Nudge the pose so that XLA cannot hoist the (otherwise loop-invariant) rays out of the scan.
        qpos = s.data.qpos + 1e-4 * obs[:, :3]
        return s.replace(obs=s.obs.at[:, : obs.shape[1]].set(obs), data=s.data.replace(qpos=qpos))

    def reset_sampling(s):
        steps = s.info["steps"]
        params, data = jax.vmap(env.new_episode)(jax.vmap(jax.random.fold_in)(keys, steps))
        return s.replace(data=data, info={**s.info, "params": params, "steps": steps + 1})

    def reset(s):  # the task's whole reset: room, spawn, goal if any, first observation
        steps = s.info["steps"]
        new = jax.vmap(env.reset)(jax.vmap(jax.random.fold_in)(keys, steps))
        return s.replace(
            data=new.data, obs=new.obs, info={**s.info, **new.info, "steps": steps + 1}
        )

    pieces = {
        "step": lambda s: wrapped.step(s, actions),
        "physics": physics,
        "sensor": sensor,
        "reset_sampling": reset_sampling,
        "reset": reset,
    }
    out = {}
    for name, fn in pieces.items() if split else [("step", pieces["step"])]:
        compile_s, best = timed(scan_steps(fn, steps), state, repeats=repeats)
        out[name] = {
            "env_steps_per_s": round(n * steps / best),
            "ms_per_step": 1e3 * best / steps,
            "compile_s": round(compile_s, 1),
        }
    return out


def policy_piece(n, steps, repeats):
    net = make_network(preset("cpu"), AvoidConfig().action_spec)
    params = net.init(jax.random.PRNGKey(0), jnp.zeros((1, 8)))
    obs = jnp.ones((n, 8))
    fn = scan_steps(lambda o: o + 1e-6 * net.apply(params, o)[0].sum(-1, keepdims=True), steps)
    _, best = timed(fn, obs, repeats=repeats)
    return {"env_steps_per_s": round(n * steps / best), "ms_per_step": 1e3 * best / steps}


def training(env, n, updates, repeats, ppo: dict, trace=None):
    """PPO env-steps/s of chunks of `updates` updates (the best of `repeats`), and a profiler
    trace of one more chunk into the folder `trace` if given."""
    cfg = preset(
        "cpu",
        num_envs=n,
        rollout_length=32,
        minibatch_size=n * 8,
        num_epochs=4,
        updates_per_chunk=updates,
        total_steps=n * 32 * updates * 100,
        **ppo,
    )
    trainer = make_train(cfg, env)
    ts = trainer.init(jax.random.PRNGKey(0))
    tick = time.perf_counter()
    ts, _ = jax.block_until_ready(trainer.run_chunk(ts))
    compile_s = time.perf_counter() - tick
    best = float("inf")
    for _ in range(repeats):
        tick = time.perf_counter()
        ts, _ = jax.block_until_ready(trainer.run_chunk(ts))
        best = min(best, time.perf_counter() - tick)
    if trace:
        with jax.profiler.trace(trace):
            jax.block_until_ready(trainer.run_chunk(ts))
    return {
        "env_steps_per_s": round(n * 32 * updates / best),
        "compile_s": round(compile_s, 1),
        "s_per_update": best / updates,
    }


def trace_events(folder: str) -> tuple[list[dict], dict]:
    """(the complete events of a profiler trace, {pid: process name})."""
    events = []
    for path in Path(folder).rglob("*.trace.json.gz"):
        raw = json.loads(gzip.open(path).read())
        events += raw["traceEvents"] if isinstance(raw, dict) else raw
    procs = {
        e.get("pid"): e.get("args", {}).get("name", "")
        for e in events
        if e.get("name") == "process_name"
    }
    timed = [e for e in events if e.get("ph") == "X" and "dur" in e]
    return timed, procs


def op_events(folder: str) -> list[dict]:
    """The ops of a profiler trace: on an accelerator its device ops, on the CPU the host's
    (Python frames left out)."""
    events, procs = trace_events(folder)
    device = {p for p, name in procs.items() if "/device:" in name}
    return [
        e
        for e in events
        if not e["name"].startswith("$") and not (device and e.get("pid") not in device)
    ]


def top_ops(events: list[dict], top: int = 15) -> list[dict]:
    """The ops of a profiler trace (its `op_events`) that took the most time in total."""
    total, calls = collections.Counter(), collections.Counter()
    for e in events:
        total[e["name"]] += e["dur"]
        calls[e["name"]] += 1
    return [
        {"op": name, "ms": round(us / 1e3, 2), "calls": calls[name]}
        for name, us in total.most_common(top)
    ]


# Cross-device ops in a trace (names lower-cased, "-" read as "_"): NCCL's kernels, XLA's fusions.
COLLECTIVE = (
    "nccl",
    "all_reduce",
    "all_gather",
    "reduce_scatter",
    "all_to_all",
    "collective_permute",
)


def _covered(spans: list[tuple[float, float]]) -> float:
    """The time the union of the intervals `spans` covers (overlaps counted once)."""
    total, end = 0.0, float("-inf")
    for a, b in sorted(spans):
        if b > end:
            total += b - max(a, end)
            end = b
    return total


def print_top(ops: list[dict]) -> None:
    """One line per op of `top_ops`: its total ms, its calls and its name."""
    for r in ops:
        print(f"{r['ms']:>10.1f} ms {r['calls']:>7} x  {r['op'][:90]}")


def device_time(folder: str) -> list[dict]:
    """Per accelerator of a trace: the span from its first op's start to its last op's end, the
    time some op ran (busy) and the time some cross-device op ran (NCCL kernels and XLA's
    collective fusions, their waiting for the other devices included), in ms. Empty on the CPU."""
    events, procs = trace_events(folder)
    rows = []
    for pid, name in sorted(procs.items(), key=lambda kv: kv[1]):
        if "/device:" not in name:
            continue
        mine = [e for e in events if e.get("pid") == pid]
        if not mine:
            continue
        spans = [(e["ts"], e["ts"] + e["dur"]) for e in mine]
        waits = [(e["ts"], e["ts"] + e["dur"]) for e in mine if _collective(e["name"])]
        ms = lambda us: round(us / 1e3, 2)  # noqa: E731
        rows.append(
            {
                "device": name,
                "span_ms": ms(max(b for _, b in spans) - min(a for a, _ in spans)),
                "busy_ms": ms(_covered(spans)),
                "collective_ms": ms(_covered(waits)),
            }
        )
    return rows


def _collective(op: str) -> bool:
    return any(c in op.lower().replace("-", "_") for c in COLLECTIVE)


def peak_memory_mb() -> float:
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10  # host RSS on CPU


def measure(n: int, variant: str, args, split: bool, trace=None) -> dict:
    """One row: the env step (and with `split` its pieces) and PPO training of `variant`."""
    levers = VARIANTS[variant]
    scene = SceneConfig(**levers.get("scene", {}))
    randomize = dataclasses.replace(FULL, **levers.get("randomize", {}))
    env = jaxnav.make_env(args.env, randomize=randomize, scene=scene)
    ppo = {**task_defaults(args.env).get("ppo", {}), **levers.get("ppo", {})}
    # For the env rows too, as make_train sets it for the PPO rows.
    threefry_kernel(ppo.get("threefry_kernel", False))
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    size = sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(state))
    row = {"num_envs": n, "variant": variant, "state_bytes": int(size)}  # one robot's EnvState
    row["env"] = env_pieces(env, n, args.steps, args.repeats, ppo, split)
    if split:
        row["policy_forward"] = policy_piece(n, args.steps, args.repeats)
    if not args.no_train:
        row["train"] = training(env, n, args.updates, args.repeats, ppo, trace)
        # An update's time beyond its 32 env-only steps: the policy, GAE and 4 x 4 gradient
        # steps, less what drawing a rollout's episodes ahead saves over drawing them per step.
        step_s = row["env"]["step"]["ms_per_step"] / 1e3
        row["train"]["learn_ms_per_update"] = 1e3 * (row["train"]["s_per_update"] - 32 * step_s)
    row["peak_memory_mb"] = round(peak_memory_mb())
    return row


def print_table(result: dict) -> None:
    print(f"\n{result['device']} x{result['devices']}, jax {result['jax']} (env-steps/s)")
    print(
        f"{'variant':>12} {'robots':>8} {'env step':>12} {'physics':>12} {'sensor':>12} "
        f"{'reset draw':>12} {'reset':>12} {'policy':>12} {'PPO train':>12} {'learn ms/upd':>12} "
        f"{'compile s':>9} {'peak MB':>8} {'state B':>8}"
    )
    for r in result["rows"]:
        e, t = r["env"], r.get("train", {})
        piece = lambda d, k: f"{d[k]['env_steps_per_s']:,}" if k in d else "-"  # noqa: E731
        print(
            f"{r['variant']:>12} {r['num_envs']:>8} {piece(e, 'step'):>12} "
            f"{piece(e, 'physics'):>12} {piece(e, 'sensor'):>12} "
            f"{piece(e, 'reset_sampling'):>12} {piece(e, 'reset'):>12} "
            f"{piece(r, 'policy_forward'):>12} "
            f"{t.get('env_steps_per_s', 0):>12,} {t.get('learn_ms_per_update', 0):>12.1f} "
            f"{t.get('compile_s', 0):>9} {r['peak_memory_mb']:>8} {r['state_bytes']:>8}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="avoid", help="the task timed (avoid or goal)")
    parser.add_argument("--num-envs", default="1024", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=100, help="control steps per env timing")
    parser.add_argument("--updates", type=int, default=5, help="PPO updates per training timing")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-train", action="store_true", help="env timings only")
    parser.add_argument(
        "--variants", default="default", help=f"comma-separated: {', '.join(VARIANTS)}"
    )
    parser.add_argument(
        "--pieces", default="all", help="variants that get the split ('all' or comma-separated)"
    )
    parser.add_argument("--trace", help="write a profiler trace of the first variant's PPO here")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    variants = args.variants.split(",")
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; valid: {', '.join(VARIANTS)}")
    pieces = variants if args.pieces == "all" else args.pieces.split(",")
    result = {
        **run_info("device"),
        "devices": jax.device_count(),
        **run_info("python", "date", "jax"),
        "env": args.env,
        "rows": [],
    }
    for n in (int(x) for x in args.num_envs.split(",")):
        for v in variants:
            trace = args.trace if v == variants[0] else None
            row = measure(n, v, args, v in pieces, trace)
            result["rows"].append(row)
            print(json.dumps(row), flush=True)
            if args.json:  # after every row, so that a run cut short keeps what it measured
                write_json(args.json, result)
    if args.trace:
        result["trace_top"] = top_ops(op_events(args.trace))
        result["trace_devices"] = device_time(args.trace)
        print(f"\nprofile of one PPO chunk of '{variants[0]}' (top ops, total ms; {args.trace}):")
        print_top(result["trace_top"])
        for r in result["trace_devices"]:
            print(
                f"{r['device']}: span {r['span_ms']} ms, busy {r['busy_ms']} ms, "
                f"in cross-device ops {r['collective_ms']} ms"
            )
        if args.json:
            write_json(args.json, result)
    print_table(result)


if __name__ == "__main__":
    main()
