"""One policy on the benchmark suite with moving obstacles against without.

    python benchmarks/moving_obstacles.py --checkpoint runs/avoid-cpu --episodes 20 \\
        --json benchmarks/results/moving_obstacles_avoid_cpu.json
    python benchmarks/moving_obstacles.py --checkpoint runs/goal-gpu --episodes 20 --steps 500 \\
        --json benchmarks/results/moving_obstacles_goal_h200.json

Runs `jaxnav.evaluation.evaluate(policy, suite="benchmark")` twice on the same rooms, spawns and
per-episode robot parameters (same seed): without moving obstacles, and with `--count` (default
1-3) bouncing cylinders per room at `--speed` (default 0.2-0.5 m/s) added by the evaluation's
randomisation (`--randomize.moving-count` of `python -m jaxnav.evaluate`). Reports per family and
overall the collision-free rate and mean speed of each, and for a goal policy the success rate
and SPL (the shortest path ignores the movers). Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from report import run_info, write_json

from jaxnav.evaluation import evaluate
from jaxnav.runs import load_policy

DEFAULT_JSON = Path(__file__).parent / "results" / "moving_obstacles_cpu.json"
KEYS = ("collision_free_rate", "mean_speed", "success_rate", "spl")  # those a task reports


def run(policy, args, moving: dict | None) -> dict:
    """The suite's per-family and overall metrics (`KEYS`) with `moving` obstacles (or none)."""
    tick = time.perf_counter()
    results = evaluate(
        policy,
        suite="benchmark",
        episodes=args.episodes,
        steps=args.steps,
        seed=args.seed,
        moving=moving,
    )
    pick = lambda m: {k: m[k] for k in KEYS if k in m}  # noqa: E731
    return {
        "families": {f: pick(m) for f, m in results["families"].items()},
        "overall": pick(results["overall"]),
        "moving": results.get("moving"),
        "seconds": round(time.perf_counter() - tick, 1),
    }


def format_table(still: dict, moving: dict) -> str:
    """One row per family and `overall`: each metric without / with moving obstacles."""
    keys = [k for k in KEYS if k in still["overall"]]
    head = f"{'family':<14}" + "".join(f" {k + ' still/moving':>32}" for k in keys)
    lines = [head, "-" * len(head)]
    rows = [*still["families"], "overall"]
    for name in rows:
        a = still["overall"] if name == "overall" else still["families"][name]
        b = moving["overall"] if name == "overall" else moving["families"][name]
        cells = []
        for k in keys:
            scale, unit = (1, "") if k in ("mean_speed", "spl") else (100, " %")
            cells.append(f" {f'{scale * a[k]:.1f}{unit} / {scale * b[k]:.1f}{unit}':>32}")
            if scale == 1:
                cells[-1] = f" {f'{a[k]:.3f} / {b[k]:.3f}':>32}"
        lines.append(f"{name:<14}" + "".join(cells))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, help="a run folder or a checkpoint in it")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per room (32 rooms)")
    parser.add_argument("--steps", type=int, default=600, help="control steps per episode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--count", type=int, nargs=2, default=(1, 3), help="movers per room")
    parser.add_argument("--speed", type=float, nargs=2, default=(0.2, 0.5), help="their speed, m/s")
    parser.add_argument("--json", default=str(DEFAULT_JSON), help="write the results here")
    args = parser.parse_args()
    policy = load_policy(args.checkpoint)
    movers = {"moving_count": tuple(args.count), "moving_speed": tuple(args.speed)}
    still, moving = run(policy, args, None), run(policy, args, movers)
    print(format_table(still, moving))
    result = {
        **run_info("device", "python", "jax"),
        "checkpoint": args.checkpoint,
        "task": policy.env,
        "episodes_per_room": args.episodes,
        "steps": args.steps,
        "seed": args.seed,
        "still": still,
        "moving": moving,
    }
    write_json(args.json, result)
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
