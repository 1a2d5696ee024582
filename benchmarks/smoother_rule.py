"""The velocity smoother's rule in the simulator: each component limited on its own (per-axis)
against kobuki_velocity_smoother's coupled rule (`RandomizeConfig.coupled_smoother`).

    python benchmarks/smoother_rule.py --checkpoints runs/avoid-gpu,runs/avoid-gpu-coupled \
        --episodes 20 --json benchmarks/results/smoother_rule_h100.json

Each policy is evaluated on the benchmark suite (`--episodes` per room, its own physics, the
evaluation's sim-to-real ranges) under both rules, all rooms in one compiled batch per rule
(`jaxnav.evaluation.evaluate_rooms`). A policy trained per-axis and run on the robot meets the
coupled rule: its "coupled" row is what the robot would see, and a policy trained with
`--randomize.coupled-smoother true` shows what training with the robot's rule gives. Prints
collision-free rate, mean speed and, for goal policies, success rate and SPL; writes the JSON with
the command and the commit.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import jax
from report import run_info, write_json

from jaxnav import load_policy
from jaxnav.evaluation import eval_randomize, evaluate_rooms, load_suite, pool

RESULTS = Path(__file__).parent / "results"
KEPT = ("collision_free_rate", "mean_speed", "success_rate", "spl")


def rows(checkpoint: str, episodes: int, steps: int) -> dict:
    """{rule: overall metrics} of one policy on the benchmark suite under both rules."""
    policy = load_policy(checkpoint)
    layouts = [room for rooms in load_suite("benchmark").values() for room in rooms]
    out = {}
    for rule, coupled in (("per-axis", False), ("coupled", True)):
        randomize = dataclasses.replace(eval_randomize(), coupled_smoother=coupled)
        rooms = evaluate_rooms(
            policy, layouts, jax.random.PRNGKey(0), episodes=episodes, steps=steps,
            randomize=randomize,
        )  # fmt: skip
        overall = pool(rooms)
        out[rule] = {k: overall[k] for k in KEPT if k in overall}
        print(checkpoint, rule, out[rule], flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoints", required=True, help="training run folders, comma-separated")
    p.add_argument("--episodes", type=int, default=20, help="episodes per room")
    p.add_argument("--steps", type=int, default=600, help="control steps per episode")
    p.add_argument("--json", type=Path, default=RESULTS / "smoother_rule.json")
    args = p.parse_args()
    table = {ckpt: rows(ckpt, args.episodes, args.steps) for ckpt in args.checkpoints.split(",")}
    info = run_info("command", "device", "jax", "date")
    write_json(args.json, {**info, "episodes": args.episodes, "rows": table})
    print(f"{'policy':<40} {'rule':<9} " + " ".join(f"{k:>19}" for k in KEPT))
    for ckpt, by_rule in table.items():
        for rule, m in by_rule.items():
            cells = " ".join(f"{m[k]:>19.3f}" if k in m else f"{'':>19}" for k in KEPT)
            print(f"{ckpt[-40:]:<40} {rule:<9} {cells}")


if __name__ == "__main__":
    main()
