"""Where a run's start-up goes: tracing and compiling the training chunk, and what the persistent
compilation cache saves a repeated run with the same shapes.

    python benchmarks/compile_time.py --preset cpu             # avoid and goal, on this machine
    python benchmarks/compile_time.py --preset gpu --json benchmarks/results/compile_time_h100.json

Per task: in this process, `trainer.run_chunk` lowered (tracing: `jax.stages` `.lower`) and
compiled (`.compile`) on its own, with the size of its HLO text; then `python -m jaxnav.train` run
twice in subprocesses with one fresh cache folder (`XDG_CACHE_HOME`), each with a budget of one
chunk: the seconds to its "compiled and ran the first chunk" line and the whole command's wall
time, cold and with the cache warm. Prints the table last; writes the JSON.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from report import run_info, write_json

HERE = Path(__file__).resolve().parent


def split(env: str, preset: str) -> dict:
    """Lowering and compiling the training chunk in this process (no cache)."""
    import jax

    from jaxnav.ppo.train import make_train
    from jaxnav.train import build_config, make_run_env

    config = build_config(preset, env=env, overrides={"ppo": {"updates_per_chunk": 1}})
    tick = time.perf_counter()
    trainer = make_train(config.ppo, make_run_env(config))
    ts = trainer.init(jax.random.PRNGKey(0))
    jax.block_until_ready(ts)
    build = time.perf_counter() - tick
    tick = time.perf_counter()
    lowered = trainer.run_chunk.lower(ts)
    lower = time.perf_counter() - tick
    tick = time.perf_counter()
    lowered.compile()
    compiled = time.perf_counter() - tick
    hlo = len(lowered.as_text())
    return {
        "build_init_s": round(build, 1),
        "lower_s": round(lower, 1),
        "compile_s": round(compiled, 1),
        "hlo_chars": hlo,
    }


def cli_runs(env: str, preset: str) -> dict:
    """Two runs of the command line with one fresh cache: (first chunk s, wall s) each."""
    cache = tempfile.mkdtemp(prefix="jaxnav-cache-")
    environ = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    environ["XDG_CACHE_HOME"] = cache
    out = {}
    for label in ("cold", "warm"):
        run = tempfile.mkdtemp(prefix="jaxnav-run-") + "/run"
        cmd = [
            sys.executable,
            "-m",
            "jaxnav.train",
            "--env",
            env,
            "--preset",
            preset,
            "--out",
            run,
            "--no-progress",
            "--updates-per-chunk",
            "1",
        ]
        tick = time.perf_counter()
        proc = subprocess.run(
            cmd + ["--total-steps", str(_one_update(env, preset))],
            capture_output=True,
            text=True,
            env=environ,
            timeout=1800,
        )
        wall = time.perf_counter() - tick
        found = re.search(r"compiled and ran the first chunk in ([\d.]+) s", proc.stdout)
        out[label] = {
            "first_chunk_s": float(found.group(1)) if found else None,
            "wall_s": round(wall, 1),
            "rc": proc.returncode,
        }
    return out


def _one_update(env: str, preset: str) -> int:
    from jaxnav.train import build_config

    return build_config(preset, env=env).ppo.batch_size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="cpu")
    p.add_argument("--envs", default="avoid,goal")
    p.add_argument("--json", type=Path, default=HERE / "results" / "compile_time.json")
    args = p.parse_args()
    rows = {}
    for env in args.envs.split(","):
        rows[env] = {**split(env, args.preset), **cli_runs(env, args.preset)}
        print(env, rows[env], flush=True)
    write_json(
        args.json,
        {
            **run_info("command", "device", "jax", "mujoco", "date"),
            "preset": args.preset,
            "rows": rows,
        },
    )
    head = (
        f"{'env':<6} {'lower':>6} {'compile':>8} {'HLO kchars':>10} {'cold 1st':>9} {'warm 1st':>9}"
    )
    print(head)
    for env, r in rows.items():
        print(
            f"{env:<6} {r['lower_s']:>6} {r['compile_s']:>8} {r['hlo_chars'] // 1000:>10} "
            f"{r['cold']['first_chunk_s']:>9} {r['warm']['first_chunk_s']:>9}"
        )


if __name__ == "__main__":
    main()
