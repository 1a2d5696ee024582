"""One line per `time_to_solve_goal.py` result: where its evaluations settle, and when the bar
was first met. The goal tables of docs/results.md come from it.

    python benchmarks/goal_runs.py benchmarks/results/time_to_solve_goal_*.json
    python benchmarks/goal_runs.py --last 5 --families corridor clutter RUN.json ...

Columns: env steps trained, training seconds (evaluations and compile apart), env-steps/s, the
bar first met (training seconds, env steps), how many evaluations met ≥ 90 % success, the mean
and lowest success of the evaluations from the first that met the bar on, and the means over the
last `--last` evaluations: success, SPL, collision rate and the named families' success.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def settle(history: list[dict], last: int, families: list[str]) -> dict:
    """Means over the last `last` evaluations of a run's history."""
    rows = history[-last:]

    def mean(get):
        return sum(get(r) for r in rows) / len(rows)

    out = {
        "success": mean(lambda r: r["success_rate"]),
        "spl": mean(lambda r: r["spl"]),
        "collision": mean(lambda r: r.get("collision_rate", float("nan"))),
    }
    out.update({f: mean(lambda r, f=f: r["families"][f]) for f in families})
    return out


def summary(path: Path, last: int, families: list[str]) -> dict:
    run = json.loads(path.read_text())
    history, solved = run["history"], run["solved"]
    end = history[-1]
    met = [r for r in history if solved and r["env_steps"] >= solved["env_steps"]]
    after = [r["success_rate"] for r in met] or [float("nan")]
    return {
        "run": path.stem,
        "steps_m": end["env_steps"] / 1e6,
        "train_s": end["train_s"],
        "pace_k": end["env_steps"] / end["train_s"] / 1e3,
        "compile_s": run["compile_s"],
        "first_met_s": solved["train_s"] if solved else None,
        "first_met_m": solved["env_steps"] / 1e6 if solved else None,
        "at_90": f"{sum(r['success_rate'] >= 0.9 for r in history)} of {len(history)}",
        "after": f"{sum(after) / len(after):.3f} / {min(after):.3f}",
        **settle(history, last, families),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="time_to_solve_goal.py JSON files")
    parser.add_argument("--last", type=int, default=5, help="evaluations the means are over")
    parser.add_argument("--families", nargs="*", default=["corridor", "clutter"])
    args = parser.parse_args()
    rows = [summary(p, args.last, args.families) for p in args.runs]
    head = ["run", "steps M", "train s", "k steps/s", "compile s", "bar met s", "at M", ">= 90 %"]
    head += ["after: mean / lowest"]
    head += [f"last {args.last}: success", "SPL", "collided", *args.families]
    print(" | ".join(head))
    for r in rows:
        met = ("-", "-") if r["first_met_s"] is None else (r["first_met_s"], r["first_met_m"])
        cells = [r["run"], f"{r['steps_m']:.1f}", f"{r['train_s']:.0f}", f"{r['pace_k']:.1f}"]
        cells += [f"{r['compile_s']:.1f}", *(f"{m:.1f}" if m != "-" else m for m in met)]
        cells += [
            r["at_90"],
            r["after"],
            f"{r['success']:.3f}",
            f"{r['spl']:.3f}",
            f"{r['collision']:.3f}",
        ]
        cells += [f"{r[f]:.2f}" for f in args.families]
        print(" | ".join(cells))


if __name__ == "__main__":
    main()
