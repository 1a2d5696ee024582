"""The learner's shuffle of a rollout's transitions: `jaxnav.core.draws.hashed_permutation` (a
keyed Feistel permutation, the learner's since 2026-11-30) against `jax.random.permutation` (two
rounds of sorting by random keys, the learner's before), per size, on this machine.

    python benchmarks/shuffle.py --sizes 8192,16384,2097152 --json benchmarks/results/shuffle_cpu.json

8,192 and 16,384 indices are an epoch's of the `avoid` and goal cpu presets (256 and 512 robots x
32 steps), 2,097,152 that of `benchmarks/throughput.py` at 65,536 robots. Each time is the best of
`--repeats` jitted calls on fresh keys, after a compile (`throughput.timed`).
"""

from __future__ import annotations

import argparse

import jax
from report import run_info, write_json
from throughput import timed

from jaxnav.core.draws import hashed_permutation

SHUFFLES = {
    "hashed_permutation": hashed_permutation,
    "jax.random.permutation": jax.random.permutation,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="8192,16384,2097152", help="comma-separated")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    result = {**run_info("device", "python", "date", "jax"), "rows": []}
    print(f"{'indices':>10} {'shuffle':>24} {'ms':>9}")
    for n in (int(x) for x in args.sizes.split(",")):
        for name, shuffle in SHUFFLES.items():
            fn = jax.jit(shuffle, static_argnums=1)
            _, best = timed(fn, jax.random.PRNGKey(n), n, repeats=args.repeats)
            result["rows"].append({"indices": n, "shuffle": name, "ms": round(1e3 * best, 3)})
            print(f"{n:>10} {name:>24} {1e3 * best:>9.3f}", flush=True)
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
