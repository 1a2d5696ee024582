"""One policy under both physics: the fast drive against the wheeled validation model.

    python benchmarks/wheeled_vs_fast.py --checkpoint runs/avoid-cpu --episodes 10 \\
        --json benchmarks/results/wheeled_vs_fast_cpu.json
    python benchmarks/wheeled_vs_fast.py --episodes 4   # no checkpoint: the forward/random baselines

For each policy (the checkpoint, else the `forward` and `random` baselines):
1. closed loop: `jaxnav.evaluation.evaluate(policy, suite="benchmark", physics=...)` under "fast"
   and "wheeled" on the same rooms, spawns and per-episode parameters (same seed): collision-free
   rate and mean speed of each, and their difference in points (the issue's target: within 3);
2. open loop: the fast model's action sequence of every episode, replayed unchanged through the
   wheeled model from the same reset; the distance between the two base positions after 1, 5 and
   10 s (mean and max over the episodes that neither model has ended by then), and the mean speed
   of each model over the same commands (each episode until either model ended it).

Prints a table and writes JSON (default `benchmarks/results/wheeled_vs_fast_cpu.json`).
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from report import run_info, write_json

from jaxnav.evaluation import eval_randomize, evaluate, first_state, load_suite, make_eval_env
from jaxnav.policy import BASELINES

HORIZONS_S = (1.0, 5.0, 10.0)  # when the open-loop divergence is read
DEFAULT_JSON = Path(__file__).parent / "results" / "wheeled_vs_fast_cpu.json"


def record_and_replay(policy, rooms, *, episodes, steps, seed, stochastic_env):
    """Runs `policy` closed loop under the fast physics, then its actions open loop under the
    wheeled one, from the same resets. Returns the base positions of both [E, steps + 1, 2] and
    how many steps each episode ran in each [E] (E = rooms x episodes), and the control period."""
    randomize = eval_randomize("layout", stochastic_env)
    envs = {
        p: make_eval_env(policy, rooms, steps=steps, randomize=randomize, physics=p)
        for p in ("fast", "wheeled")
    }
    k_reset, k_act = jax.random.split(jax.random.PRNGKey(seed))
    keys = jax.random.split(k_act, steps)

    def run(env, actions=None):
        state = first_state(env, k_reset, episodes, pinned=True)

        def body(state, x):
            key, action = x
            action = policy.act(state.obs, key) if actions is None else action
            nxt = jax.vmap(env.step)(state, action)
            return nxt, (action, nxt.data.qpos[:, :2], nxt.done)

        given = jnp.zeros((steps, state.obs.shape[0]), jnp.int32) if actions is None else actions
        _, (acts, xy, done) = jax.lax.scan(body, state, (keys, given))
        xy = jnp.concatenate([state.data.qpos[None, :, :2], xy])  # [steps + 1, E, 2]
        ran = jnp.where(done.any(0), jnp.argmax(done, 0) + 1, steps)  # [E] steps until it ended
        return acts, jnp.swapaxes(xy, 0, 1), ran, state.info["params"].spawn

    actions, xy_fast, ran_fast, spawn_fast = jax.jit(functools.partial(run, envs["fast"]))()
    _, xy_wheel, ran_wheel, spawn_wheel = jax.jit(functools.partial(run, envs["wheeled"]))(actions)
    np.testing.assert_array_equal(spawn_fast, spawn_wheel)  # the same episodes in both
    out = jax.device_get((xy_fast, ran_fast, xy_wheel, ran_wheel))
    return (*out, envs["fast"].control_period)


def divergence(xy_fast, ran_fast, xy_wheel, ran_wheel, period) -> dict:
    """{"1s": {"mean_m", "max_m", "episodes"}, ...}: position gaps of the episodes that both
    models were still running at each horizon."""
    out = {}
    for seconds in HORIZONS_S:
        k = int(round(seconds / period))
        if k >= xy_fast.shape[1]:
            continue
        alive = (ran_fast >= k) & (ran_wheel >= k)
        gap = np.linalg.norm(xy_fast[:, k] - xy_wheel[:, k], axis=-1)[alive]
        out[f"{seconds:g}s"] = {
            "mean_m": float(gap.mean()) if gap.size else None,
            "max_m": float(gap.max()) if gap.size else None,
            "episodes": int(alive.sum()),
        }
    return out


def open_loop_speeds(xy_fast, ran_fast, xy_wheel, ran_wheel, period) -> dict:
    """{"fast", "wheeled"}: mean speed (m/s) along each model's path for the same commands, each
    episode over the steps that both models ran."""
    both = np.minimum(ran_fast, ran_wheel)  # [E]
    out = {}
    for name, xy in (("fast", xy_fast), ("wheeled", xy_wheel)):
        moved = np.linalg.norm(np.diff(xy, axis=1), axis=-1)  # [E, steps]
        live = np.arange(moved.shape[1]) < both[:, None]
        out[name] = float(np.mean((moved * live).sum(1) / (np.maximum(both, 1) * period)))
    return out


def compare(policy, args) -> dict:
    """Both physics' suite metrics and the open-loop divergence of one policy."""
    row = {"policy": policy.name}
    for physics in ("fast", "wheeled"):
        tick = time.perf_counter()
        results = evaluate(
            policy,
            suite="benchmark",
            episodes=args.episodes,
            steps=args.steps,
            seed=args.seed,
            physics=physics,
            stochastic_env=not args.deterministic_env,
        )
        row[physics] = {
            "overall": results["overall"],
            "families": results["families"],
            "seconds": round(time.perf_counter() - tick, 1),
        }
    rates = [row[p]["overall"]["collision_free_rate"] for p in ("fast", "wheeled")]
    row["collision_free_gap_points"] = 100 * (rates[1] - rates[0])
    rooms = [room for family in load_suite("benchmark").values() for room in family]
    xy_fast, ran_fast, xy_wheel, ran_wheel, period = record_and_replay(
        policy,
        rooms,
        episodes=args.episodes,
        steps=args.steps,
        seed=args.seed,
        stochastic_env=not args.deterministic_env,
    )
    row["open_loop_divergence"] = divergence(xy_fast, ran_fast, xy_wheel, ran_wheel, period)
    row["open_loop_speed"] = open_loop_speeds(xy_fast, ran_fast, xy_wheel, ran_wheel, period)
    return row


def format_table(rows: list[dict]) -> str:
    head = (
        f"{'policy':<10} {'cf fast %':>9} {'cf wheeled %':>12} {'gap pts':>7} {'speed fast':>10} "
        f"{'speed wheeled':>13} {'open-loop speed f/w':>19}  "
        "open-loop divergence mean / max m (episodes)"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        fast, wheel = r["fast"]["overall"], r["wheeled"]["overall"]
        speeds = f"{r['open_loop_speed']['fast']:.3f} / {r['open_loop_speed']['wheeled']:.3f}"
        div = "  ".join(
            f"{h}: {d['mean_m']:.3f} / {d['max_m']:.3f} ({d['episodes']})"
            if d["episodes"]
            else f"{h}: - ({d['episodes']})"
            for h, d in r["open_loop_divergence"].items()
        )
        lines.append(
            f"{r['policy'][:10]:<10} {100 * fast['collision_free_rate']:>9.1f} "
            f"{100 * wheel['collision_free_rate']:>12.1f} {r['collision_free_gap_points']:>+7.1f} "
            f"{fast['mean_speed']:>10.3f} {wheel['mean_speed']:>13.3f} {speeds:>19}  {div}"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", help="a training run folder or a checkpoint in it")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per room (32 rooms)")
    parser.add_argument("--steps", type=int, default=600, help="control steps per episode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--deterministic-env",
        action="store_true",
        help="no traction, speed-gain or sensor-noise randomisation",
    )
    parser.add_argument("--json", default=str(DEFAULT_JSON), help="write the results here")
    args = parser.parse_args()
    if args.checkpoint:
        from jaxnav.runs import load_policy

        policies = [load_policy(args.checkpoint)]
    else:
        policies = [BASELINES["forward"](), BASELINES["random"]()]
    rows = [compare(policy, args) for policy in policies]
    print(format_table(rows))
    result = {
        **run_info("device", "python", "jax"),
        "checkpoint": args.checkpoint,
        "episodes_per_room": args.episodes,
        "steps": args.steps,
        "seed": args.seed,
        "stochastic_env": not args.deterministic_env,
        "rows": rows,
    }
    write_json(args.json, result)
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
