"""Wall seconds until a `goal` training run first meets the bar on the benchmark rooms.

    python benchmarks/time_to_solve_goal.py --preset cpu --json benchmarks/results/goal_cpu.json
    python benchmarks/time_to_solve_goal.py --preset gpu --json benchmarks/results/goal_h200.json

The bar: over `--episodes` episodes in each of the 32 rooms of `scenes/benchmark/` (the layout's
spawn, a reachable goal drawn per episode at least `goal_min_distance` away, `--steps` control
steps), a success rate of at least 90 % and an SPL of at least 0.7 (issue 12). Every
`--eval-every` chunks the greedy policy is evaluated in one compiled batch; SPL is evaluate's
(`jaxnav.evaluate.spl_values`: the grid's shortest path less the success radius), its shortest
paths from `jaxnav.core.goals.ShortestPaths` built once per room.
Training time excludes the evaluations and the compile, which is reported on its own. `--set
GROUP.FIELD=VALUE` overrides any run-config field, as in `time_to_solve.py`.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from time_to_solve import parse_sets  # benchmarks/: the script's own folder

import jaxnav
from jaxnav.core.goals import ShortestPaths
from jaxnav.evaluate import eval_randomize, load_suite, make_rollout, spl_from
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.networks import normalize
from jaxnav.ppo.train import make_train
from jaxnav.train import build_config, make_run_env

SUCCESS_BAR, SPL_BAR = 0.9, 0.7


def make_evaluator(trainer, config, episodes: int, steps: int, sample: bool = False):
    """(params, obs_stats, key) -> (success rate, SPL, {family: success rate}) on the benchmark
    rooms, the policy's most likely action (`sample`: drawn from the policy) each step."""
    suite = load_suite("benchmark")
    rooms = [room for group in suite.values() for room in group]
    family = np.repeat([f for f, group in suite.items() for _ in group], episodes)
    kwargs = {**config.env_kwargs(), "randomize": eval_randomize("layout"), "max_steps": steps}
    env = jaxnav.make_env("goal", rooms, **kwargs)
    cfg = config.ppo
    dist = make_distribution(env.action_spec)
    paths = [ShortestPaths(room) for room in rooms]

    @jax.jit
    def rollout(params, stats, key):
        def act(obs, key):
            obs = normalize(stats, obs) if cfg.normalize_obs else obs
            out = trainer.network.apply(params, obs)[0]
            return dist.sample(key, out) if sample else dist.mode(out)

        track, _ = make_rollout(env, act, episodes, steps, keep=1, pinned=True)(key)
        return track

    def evaluate(params, stats, key):
        track = jax.device_get(rollout(params, stats, key))
        success = np.asarray(track.metrics["success"]) > 0
        spl = np.zeros(len(success))
        for r, shortest in enumerate(paths):
            e = slice(r * episodes, (r + 1) * episodes)
            reach = shortest(track.start[e], track.goal[e]) - env.task.success_radius
            room = {"metrics": {"success": success[e]}, "distance": track.distance[e]}
            spl[e] = spl_from(reach, room)
        per = {f: round(float(success[family == f].mean()), 3) for f in suite}
        return float(success.mean()), float(spl.mean()), per

    return evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--num-envs", type=int)
    parser.add_argument("--total-steps", type=int)
    parser.add_argument("--actions", default="discrete", choices=("discrete", "continuous"))
    parser.add_argument("--set", action="append", default=[], metavar="GROUP.FIELD=VALUE")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=5, help="per benchmark room")
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--updates-per-chunk", type=int, default=10)
    parser.add_argument("--eval-every", type=int, default=2, help="chunks between evaluations")
    parser.add_argument("--max-seconds", type=float, default=1200.0)
    parser.add_argument("--sample", action="store_true", help="evaluate drawn, not greedy actions")
    parser.add_argument("--json")
    args = parser.parse_args()
    sets = parse_sets(args.set)
    ppo = sets.setdefault("ppo", {})
    ppo["updates_per_chunk"] = args.updates_per_chunk
    for name in ("num_envs", "total_steps"):
        if getattr(args, name):
            ppo[name] = getattr(args, name)
    sets.setdefault("task", {})["actions"] = args.actions
    config = build_config(args.preset, args.seed, None, sets, "goal")
    cfg = config.ppo
    trainer = make_train(cfg, make_run_env(config))
    evaluate = make_evaluator(trainer, config, args.episodes, args.steps, args.sample)
    ts = jax.block_until_ready(trainer.init(jax.random.PRNGKey(args.seed)))
    tick = time.perf_counter()
    run_chunk = trainer.run_chunk.lower(ts).compile()  # compile apart from the timed training
    compile_s = time.perf_counter() - tick
    train_s, history, solved, chunk = 0.0, [], None, 0
    while True:
        tick = time.perf_counter()
        ts, metrics = jax.block_until_ready(run_chunk(ts))
        train_s += time.perf_counter() - tick
        chunk += 1
        done = int(ts.update) >= cfg.num_updates or train_s > args.max_seconds
        if chunk % args.eval_every and not done:
            continue
        success, spl, per = evaluate(ts.params, ts.obs_stats, jax.random.PRNGKey(int(ts.update)))
        history.append(
            {
                "update": int(ts.update),
                "env_steps": int(ts.update) * cfg.batch_size,
                "train_s": round(train_s, 2),
                "train_success": float(jnp.nanmean(metrics["success"])),
                "success_rate": success,
                "spl": spl,
                "families": per,
            }
        )
        print(json.dumps(history[-1]), flush=True)
        if success >= SUCCESS_BAR and spl >= SPL_BAR:
            solved = history[-1]
            break
        if done:
            break
    device = jax.devices()[0]
    result = {
        "device": f"{device.platform}: {device.device_kind}",
        "preset": args.preset,
        "num_envs": cfg.num_envs,
        "actions": args.actions,
        "sets": args.set,
        "sample": args.sample,
        "episodes_per_room": args.episodes,
        "bar": {"success_rate": SUCCESS_BAR, "spl": SPL_BAR},
        "compile_s": round(compile_s, 1),
        "solved": solved,
        "history": history,
    }
    print(
        f"solved at {solved['train_s']} s wall ({solved['env_steps']:,} env steps)"
        if solved
        else "not solved within the budget"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)


if __name__ == "__main__":
    main()
