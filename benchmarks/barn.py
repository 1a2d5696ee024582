"""How a goal policy fares on BARN's 300 worlds, by the challenge's own score.

    python benchmarks/barn.py --checkpoint runs/goal-gpu                  # a trained goal policy
    python benchmarks/barn.py --train --preset gpu --out-run runs/barn-goal-gpu  # trains it first

Evaluates `python -m jaxnav.evaluate --suite barn` (all 300 worlds in one compiled batch, each from
BARN's start to its goal 10 m ahead, 100 s, the sim-to-real ranges on) and writes
`benchmarks/results/barn.json`: per difficulty group (easy, medium, hard: worlds 0-99, 100-199,
200-299) and overall, BARN's score (success x optimal time / clip(time, 2x, 8x optimal time),
optimal time at the challenge's 2 m/s and at the robot's own top speed), success, collision and
timeout rates, SPL; per world, its success rate and score. Prints the group table last.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from report import run_info, write_json

HERE = Path(__file__).resolve().parent
KEYS = (
    "barn_score",
    "barn_score_own_speed",
    "success_rate",
    "collision_free_rate",
    "timeout_rate",
    "spl",
    "time_to_goal",
)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", type=Path, help="a goal run folder or checkpoint")
    p.add_argument("--train", action="store_true", help="train the goal task first")
    p.add_argument("--preset", default="gpu", help="with --train (default gpu)")
    p.add_argument("--out-run", type=Path, default=Path("runs/barn-goal"), help="with --train")
    p.add_argument("--episodes", type=int, default=10, help="per world (default 10)")
    p.add_argument("--json", type=Path, default=HERE / "results" / "barn.json")
    args = p.parse_args()
    import jaxnav
    from jaxnav.evaluation import evaluate

    train_s = None
    if args.train:
        tick = time.perf_counter()
        jaxnav.train(out=args.out_run, preset=args.preset, env="goal", progress=False)
        train_s, args.checkpoint = time.perf_counter() - tick, args.out_run
    if args.checkpoint is None:
        p.error("give --checkpoint RUN or --train")
    policy = jaxnav.load_policy(args.checkpoint)
    tick = time.perf_counter()
    results = evaluate(policy, suite="barn", episodes=args.episodes, steps=1000)
    eval_s = time.perf_counter() - tick
    groups = {**results["families"], "overall": results["overall"]}
    out = {
        **run_info("command", "commit", "dirty", "device", "jax", "mujoco", "date"),
        "checkpoint": str(args.checkpoint),
        "train_s": train_s,
        "eval_s": round(eval_s, 1),
        "episodes_per_world": args.episodes,
        "groups": {g: {k: m.get(k) for k in KEYS} for g, m in groups.items()},
        "worlds": {
            name: {k: round(m[k], 4) for k in ("success_rate", "barn_score")}
            for name, m in results["layouts"].items()
        },
    }
    write_json(args.json, out)
    print(f"{'group':<8} " + " ".join(f"{k[:12]:>12}" for k in KEYS))
    for g, m in out["groups"].items():
        print(f"{g:<8} " + " ".join(f"{m[k]:>12.3f}" for k in KEYS))
    print(f"-> {args.json} (evaluation {eval_s:.0f} s)", file=sys.stderr)


if __name__ == "__main__":
    main()
