"""Wall seconds until a `goal` training run first meets the bar on the benchmark rooms.

    python benchmarks/time_to_solve_goal.py --preset cpu --json benchmarks/results/goal_cpu.json
    python benchmarks/time_to_solve_goal.py --preset gpu --json benchmarks/results/goal_h200.json

The bar: over `--episodes` episodes in each of the 32 rooms of `scenes/benchmark/` (the layout's
spawn, a reachable goal drawn per episode at least `goal_min_distance` away, `--steps` control
steps), a success rate of at least 90 % and an SPL of at least 0.7 (issue 12). Every
`--eval-every` chunks the greedy policy is evaluated in one compiled batch by `time_to_solve.py`'s
evaluator; SPL is evaluate's (`jaxnav.tasks.goal.spl_from`: the grid's shortest path less the
success radius), its shortest paths from `jaxnav.core.goals.ShortestPaths` built once per room.
Training time excludes the evaluations and the compile, which is reported on its own. `--set
GROUP.FIELD=VALUE` overrides any run-config field, as in `time_to_solve.py`. With `--full` the
run trains on after the bar is first met, to its steps or `--max-seconds`, so that runs can be
compared by the level their evaluations settle at, not by one favourable evaluation.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
from report import run_info, write_json
from time_to_solve import (  # benchmarks/: the script's own folder
    greedy_policy,
    make_evaluator,
    parse_sets,
    train_to_bar,
)

from jaxnav.ppo.train import make_train
from jaxnav.training import build_config, make_run_env

SUCCESS_BAR, SPL_BAR = 0.9, 0.7


def goal_judge(evaluate, family):
    """`train_to_bar`'s judge_state: success rate, SPL, collision rate and per-family success and
    collisions on the suite, printed as one JSON line, and whether they meet the bar."""

    names = dict.fromkeys(family)

    def per_family(flags):
        """{family: share of its episodes where flags [E]}."""
        return {f: round(float(flags[family == f].mean()), 3) for f in names}

    def judge_state(ts, metrics, record):
        out = evaluate((ts.params, ts.obs_stats), jax.random.PRNGKey(record["update"]))
        success = out["success"]  # [E] bool
        hit = out["collided"]  # [E] bool; the other failures ran out of time
        entry = {
            **record,
            "train_success": float(jnp.nanmean(metrics["success"])),
            "success_rate": float(success.mean()),
            "spl": float(out["spl"].mean()),
            "collision_rate": float(hit.mean()),
            "families": per_family(success),
            "families_collided": per_family(hit),
        }
        print(json.dumps(entry), flush=True)
        return entry, entry["success_rate"] >= SUCCESS_BAR and entry["spl"] >= SPL_BAR

    return judge_state


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
    parser.add_argument(
        "--full", action="store_true", help="train on after the bar is met (to compare runs)"
    )
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
    env = make_run_env(config)
    trainer = make_train(cfg, env)
    policy = greedy_policy(trainer, config, args.sample)
    judge_state = goal_judge(*make_evaluator(policy, config, args.episodes, args.steps))
    compile_s, history, solved = train_to_bar(
        trainer, config, env, judge_state, args.max_seconds, full=args.full, every=args.eval_every
    )
    result = {
        **run_info("device"),
        "preset": args.preset,
        "num_envs": cfg.num_envs,
        "actions": args.actions,
        "sets": args.set,
        "sample": args.sample,
        "full": args.full,
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
        write_json(args.json, result)


if __name__ == "__main__":
    main()
