"""The `paper` preset over training seeds: how much one robot's 150k steps depend on the seed.

    python benchmarks/paper_seeds.py --seeds 0,1,2 --json benchmarks/results/paper_seeds_cpu.json

For each seed: `python -m jaxnav.train --preset paper --seed S` (timed, wall clock) into a run
folder under `--runs`, then `python -m jaxnav.evaluate --suite benchmark --episodes 20` on it,
as the README's paper line does for seed 0 (`readme_results.py`). Prints one line per seed and
writes the suite's overall and per-family figures of each to the JSON.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from readme_results import SUITE, evaluate, machine, pct, train
from report import write_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated training seeds")
    parser.add_argument("--runs", help="folder for the run folders (default: a temporary one)")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    runs = Path(args.runs or tempfile.mkdtemp(prefix="jaxnav-paper-"))
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        run = runs / f"paper-{seed}"
        seconds = train(run, "--preset", "paper", "--seed", str(seed))
        pictures = str(runs / "pictures" / f"paper-{seed}")
        ev = evaluate(run, runs / f"paper-{seed}.json", *SUITE, pictures=pictures)
        o = ev["overall"]
        rows.append(
            {
                "seed": seed,
                "train_s": round(seconds, 1),
                "collision_free_rate": o["collision_free_rate"],
                "mean_speed": o["mean_speed"],
                "families": {k: v["collision_free_rate"] for k, v in ev["families"].items()},
            }
        )
        print(
            f"seed {seed}: {pct(o['collision_free_rate'])} collision-free, "
            f"{o['mean_speed']:.3f} m/s, trained in {seconds:.0f} s",
            flush=True,
        )
    if args.json:
        write_json(args.json, {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
