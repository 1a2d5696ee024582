"""How do trained policies do in the hard suite (dense fields, long halls, people) and in a 25 m
hall, a goal policy driving to the goal 20 m down it?

    python -m jaxnav.train --out runs/avoid-cpu
    python benchmarks/hard_suite.py --runs runs/avoid-cpu \\
        --json benchmarks/results/hard_suite_cpu.json
    python benchmarks/hard_suite.py --baselines stand --json benchmarks/results/hard_suite_stand.json

Each run's policy is evaluated (`jaxnav.evaluation.evaluate`, as `python -m jaxnav.evaluate`
does) on `--suite hard` (`--episodes` a room, 60 s an episode) and in
`scenes/halls/hall_25m.json` (`--episodes`, 100 s; `avoid` drives the hall, `goal` drives to the
hall's goal). Prints a table last: per run, each family's collision-free rate and speed, and for
goal policies the success rate. `--baselines` adds baselines (`jaxnav.policy.BASELINES`) acting in
`--env`'s task: `stand`, which never drives, shows what the people do to a robot that does not
move (its collisions are all theirs).
"""

from __future__ import annotations

import argparse

from long_hall import HALL
from report import run_info, write_json

from jaxnav.evaluation import baseline, evaluate
from jaxnav.io.layouts import load_layout
from jaxnav.policy import BASELINES
from jaxnav.runs import load_policy

HALL_STEPS = 1000  # 100 s at the control period of 0.1 s
KEYS = (
    "collision_free_rate",
    "mean_speed",
    "success_rate",
    "spl",
    "time_to_goal",
    "robot_collision_rate",
    "collision_free_unhit_rate",
    "success_unhit_rate",
)


def measure(policy, episodes: int) -> dict:
    """The hard suite overall and per family, and the 25 m hall, for `policy`: the metrics of
    `KEYS` the task reports."""
    hard = evaluate(policy, suite="hard", episodes=episodes)
    hall = evaluate(policy, load_layout(HALL), episodes=episodes, steps=HALL_STEPS)
    pick = lambda m: {k: round(float(m[k]), 4) for k in KEYS if k in m}  # noqa: E731
    return {
        "hard": pick(hard["overall"]),
        "hard_families": {f: pick(m) for f, m in hard["families"].items()},
        "hall_25m": pick(hall["overall"]),
    }


def _cell(m: dict) -> str:
    """'collision-free % / speed', for goal policies ' / success %', and among people the share of
    episodes ending in a collision the robot caused."""
    text = f"{m['collision_free_rate']:.0%} {m['mean_speed']:.2f}"
    text += f" {m['success_rate']:.0%}" if "success_rate" in m else ""
    return text + (
        f" (robot {m['robot_collision_rate']:.0%})" if "robot_collision_rate" in m else ""
    )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", nargs="+", default=[], help="training run folders")
    parser.add_argument(
        "--baselines", nargs="+", default=[], choices=sorted(BASELINES), help="baselines too"
    )
    parser.add_argument("--env", default="avoid", help="the baselines' task (default avoid)")
    parser.add_argument("--episodes", type=int, default=20, help="per room (default 20)")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    if not args.runs and not args.baselines:
        parser.error("give --runs, --baselines or both")
    policies = {run: load_policy(run) for run in args.runs}
    policies |= {f"baseline:{name}": baseline(name, args.env) for name in args.baselines}
    runs = {name: {"env": p.env, **measure(p, args.episodes)} for name, p in policies.items()}
    result = {**run_info("command", "commit", "dirty", "device", "jax", "date"), "runs": runs}
    result["episodes"] = args.episodes
    if args.json:
        write_json(args.json, result)
    print("collision-free, m/s (success; among people, robot-caused) per family; the 25 m hall")
    for run, r in runs.items():
        cells = [_cell(m) for m in (*r["hard_families"].values(), r["hard"], r["hall_25m"])]
        names = [*r["hard_families"], "overall", "hall_25m"]
        print(run, " | ".join(f"{n} {c}" for n, c in zip(names, cells, strict=True)))
    return result


if __name__ == "__main__":
    main()
