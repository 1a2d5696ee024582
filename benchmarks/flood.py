"""The goal grid's flood (`goals.grid_steps`) on one device: each implementation's time per batch
of grids, and that all give the same steps.

    python benchmarks/flood.py --sizes 1024,4096,32768 --json benchmarks/results/flood_h200.json

Random occupancy grids (30 % of cells blocked, one seed cell each) of the goal task's two grid
shapes: 54 x 54 cells (rooms up to 10.5 m) and 60 x 150 (the gpu preset's, long halls in the mix),
flooded by the task's 8 rounds. `scans`: log-depth associative scans (`goals._flood_scans`, any
device); `kernel`: the Pallas kernel of one GPU (`core.flood_kernel`); `rows`: the CPU's loop
over rows (`goals._flood_rows`). Each timing is the best of `--repeats` jitted calls after a
compile (`throughput.timed`); `same` compares every implementation's steps with the first's.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
from report import run_info, write_json
from throughput import timed

from jaxnav.core import flood_kernel, goals

SHAPES = ((54, 54), (60, 150))
SWEEPS = goals.SWEEPS


def floods(backend: str) -> dict:
    """The implementations that run on `backend`."""
    out = {"scans": lambda f, s: goals._flood_scans(f, s, SWEEPS)}
    if backend == "gpu":
        out["kernel"] = lambda f, s: flood_kernel.flood(f, s, SWEEPS)
    if backend == "cpu":
        out["rows"] = lambda f, s: goals._flood_rows(f, s, SWEEPS)
    return out


def grids(n: int, shape: tuple[int, int], seed: int = 0):
    """([n, H, W] bool free, [n, H, W] bool seed): 30 % of cells blocked, one seed cell a grid."""
    rng = np.random.default_rng(seed)
    free = rng.random((n, *shape)) > 0.3
    start = np.zeros_like(free)
    start[np.arange(n), rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] = True
    return jax.numpy.asarray(free), jax.numpy.asarray(start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1024,4096,32768", help="comma-separated batch sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    result = {**run_info("device", "python", "date", "jax"), "sweeps": SWEEPS, "rows": []}
    impls = floods(jax.default_backend())
    print(f"{'grids':>8} {'cells':>9} " + " ".join(f"{k + ' ms':>10}" for k in impls) + "  same")
    for shape in SHAPES:
        for n in (int(x) for x in args.sizes.split(",")):
            free, seed = grids(n, shape)
            row, ref, same = {"grids": n, "shape": list(shape)}, None, True
            for name, fn in impls.items():
                flood = jax.jit(fn)
                _, best = timed(flood, free, seed, repeats=args.repeats)
                out = np.asarray(flood(free, seed))
                row[f"{name}_ms"] = round(1e3 * best, 3)
                ref = out if ref is None else ref
                same = same and np.array_equal(out, ref)
            row["same"] = bool(same)
            result["rows"].append(row)
            times = " ".join(f"{row[k + '_ms']:>10.2f}" for k in impls)
            print(f"{n:>8} {shape[0]:>4}x{shape[1]:<4} {times}  {same}", flush=True)
            if args.json:
                write_json(args.json, result)


if __name__ == "__main__":
    main()
