"""Throughput of the `avoid` scene and of PPO training, per batch size, with a split of the step.

    python benchmarks/throughput.py --num-envs 1024,4096 --steps 100 --json benchmarks/throughput.json

For each size: (a) env-only random rollouts of the training distribution (sim-to-real ranges and the
5-row camera on, auto-reset with PPO's default pool) with every obstacle slot in use,
(b) full PPO updates of the `cpu` preset shape (rollout 32, 4 epochs, 4 minibatches), and the split of
one control step into physics / sensor / reset sampling / policy forward. Every timing is the best of
`--repeats` runs of a jitted scan, after compiling it, with `block_until_ready`.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import platform
import resource
import time

import jax
import jax.numpy as jnp

import jaxnav
from jaxnav.core.randomize import TRAINING
from jaxnav.ppo.config import PPOConfig, preset
from jaxnav.ppo.train import make_network, make_train
from jaxnav.tasks.avoid import AvoidConfig
from jaxnav.wrappers import AutoReset

# The training distribution (sim-to-real ranges on) with every obstacle slot in use.
FULL = dataclasses.replace(TRAINING, num_boxes=(8, 8), num_cylinders=(4, 4), sampled_room_prob=1.0)


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


def env_pieces(env, n, steps, repeats):
    """env-steps/s of a whole step and of its pieces, each run alone over `steps` steps."""
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    pool = PPOConfig(num_envs=n).reset_pool
    wrapped = AutoReset(env, pool)  # the step training runs (episode statistics aside)
    state = jax.jit(wrapped.reset)(keys)
    actions = jax.random.randint(jax.random.PRNGKey(1), (n,), 0, env.action_spec.n)
    cmd = jnp.array(env.action_spec.commands[0])  # forward

    def physics(s):
        d, _ = jax.vmap(lambda p, d: env.drive(p, d, cmd))(s.info["params"], s.data)
        return s.replace(data=d)

    def sensor(s):
        obs = jax.vmap(env.sense)(s.info["params"], s.data, keys)
        # Nudge the pose so that XLA cannot hoist the (otherwise loop-invariant) rays out of the scan.
        return s.replace(obs=obs, data=s.data.replace(qpos=s.data.qpos + 1e-4 * obs[:, :3]))

    def reset_sampling(s):
        steps = s.info["steps"]
        params, data = jax.vmap(env.new_episode)(jax.vmap(jax.random.fold_in)(keys, steps))
        return s.replace(data=data, info={**s.info, "params": params, "steps": steps + 1})

    pieces = {
        "step": lambda s: wrapped.step(s, actions),
        "physics": physics,
        "sensor": sensor,
        "reset_sampling": reset_sampling,
    }
    out = {}
    for name, fn in pieces.items():
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


def training(env, n, updates, repeats):
    cfg = preset(
        "cpu",
        num_envs=n,
        rollout_length=32,
        minibatch_size=n * 8,
        num_epochs=4,
        updates_per_chunk=updates,
        total_steps=n * 32 * updates * 100,
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
    return {
        "env_steps_per_s": round(n * 32 * updates / best),
        "compile_s": round(compile_s, 1),
        "s_per_update": best / updates,
    }


def peak_memory_mb() -> float:
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10  # host RSS on CPU


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", default="1024", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=100, help="control steps per env timing")
    parser.add_argument("--updates", type=int, default=5, help="PPO updates per training timing")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-train", action="store_true", help="env timings only")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    env = jaxnav.make_env("avoid", randomize=FULL)
    device = jax.devices()[0]
    result = {
        "device": f"{device.platform}: {device.device_kind}",
        "devices": jax.device_count(),
        "python": platform.python_version(),
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
        "rows": [],
    }
    for n in (int(x) for x in args.num_envs.split(",")):
        row = {
            "num_envs": n,
            "env": env_pieces(env, n, args.steps, args.repeats),
            "policy_forward": policy_piece(n, args.steps, args.repeats),
        }
        if not args.no_train:
            row["train"] = training(env, n, args.updates, args.repeats)
        row["peak_memory_mb"] = round(peak_memory_mb())
        result["rows"].append(row)
        print(json.dumps(row), flush=True)
    print(f"\n{result['device']} x{result['devices']}, jax {result['jax']}")
    print(
        f"{'robots':>8} {'env steps/s':>12} {'physics':>10} {'sensor':>10} {'reset':>10} "
        f"{'policy':>10} {'train steps/s':>14} {'compile s':>10} {'peak MB':>8}"
    )
    for r in result["rows"]:
        e = r["env"]
        t = r.get("train", {})
        print(
            f"{r['num_envs']:>8} {e['step']['env_steps_per_s']:>12,} "
            f"{e['physics']['env_steps_per_s']:>10,} {e['sensor']['env_steps_per_s']:>10,} "
            f"{e['reset_sampling']['env_steps_per_s']:>10,} "
            f"{r['policy_forward']['env_steps_per_s']:>10,} {t.get('env_steps_per_s', 0):>14,} "
            f"{t.get('compile_s', 0):>10} {r['peak_memory_mb']:>8}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)


if __name__ == "__main__":
    main()
