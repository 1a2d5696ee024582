"""Does one seed train to the same weights twice? Copies of one training command run at once, as
a lab would start them, and each final checkpoint's state (weights, optimiser, normaliser, robots,
RNG) is hashed.

    python benchmarks/determinism.py --copies 2 --json benchmarks/results/determinism_h200.json \\
        -- --env goal --preset gpu --seed 0 --total-steps 40000000
    XLA_FLAGS=--xla_gpu_deterministic_ops=false python benchmarks/determinism.py ...  # XLA's way

Each copy runs `python -m jaxnav.train ARGS --out TMP/copy_I --no-progress` with this process's
environment (on a GPU each copy takes an equal share of its memory unless
XLA_PYTHON_CLIENT_MEM_FRACTION is set). Prints each copy's hash and wall time and whether all
agree; writes JSON with the training command, XLA_FLAGS, the hashes and `identical`.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from report import run_info, write_json

ROOT = Path(__file__).resolve().parent.parent


def state_hash(run: Path) -> tuple[str, int]:
    """(sha256 of every array of the run's newest checkpoint state, in name order, its update)."""
    from jaxnav.io import checkpoint

    digest = hashlib.sha256()
    with np.load(checkpoint.resolve(run) / "train_state.npz") as state:
        for name in sorted(state.files):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(state[name]).tobytes())
        return digest.hexdigest(), int(state[".update"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--copies", type=int, default=2, help="training runs at once (default 2)")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks/results/determinism.json")
    p.add_argument("train", nargs=argparse.REMAINDER, help="-- then jaxnav.train's flags")
    args = p.parse_args()
    flags = [f for f in args.train if f != "--"]
    if args.copies < 2:
        p.error("--copies: need at least 2 to compare")
    env = dict(os.environ)
    env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{0.9 / args.copies:.2f}")
    with tempfile.TemporaryDirectory(prefix="jaxnav-determinism-") as tmp:
        runs = [Path(tmp) / f"copy_{i}" for i in range(args.copies)]
        tick = time.perf_counter()
        procs = [
            subprocess.Popen(
                [sys.executable, "-m", "jaxnav.train", *flags, "--out", str(run), "--no-progress"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            for run in runs
        ]
        walls = []
        for proc in procs:
            _, err = proc.communicate()
            walls.append(round(time.perf_counter() - tick, 1))
            if proc.returncode:
                raise SystemExit(f"determinism: a copy failed:\n{err.strip()[-2000:]}")
        hashes = [state_hash(run) for run in runs]
    identical = len({h for h, _ in hashes}) == 1
    for i, ((h, update), wall) in enumerate(zip(hashes, walls, strict=True)):
        print(f"copy {i}: {h[:16]}  update {update}  {wall:.0f} s")
    print(f"identical: {identical}")
    write_json(
        args.json,
        {
            **run_info("command", "commit", "dirty", "device", "jax", "date"),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "training": "python -m jaxnav.train " + " ".join(flags),
            "copies": [
                {"sha256": h, "update": u, "wall_s": w}
                for (h, u), w in zip(hashes, walls, strict=True)
            ],
            "identical": identical,
        },
    )


if __name__ == "__main__":
    main()
