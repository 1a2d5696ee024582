"""Where a PPO update of a preset goes on this machine: its three programs timed, and their XLA ops
summed by the line of jaxnav's source they came from.

    python benchmarks/update_profile.py --env goal --preset cpu --json benchmarks/results/update_profile_goal_cpu.json

A training update is three programs (`ppo.train.make_train`): `draws` (the rollout's new episodes),
`rollout` (the env steps and the policy) and `learn` (GAE and the epochs of minibatches). Each is
timed per update (min and median of `--timed` updates, after two to warm up). Then `--profiled`
more updates run under JAX's profiler; every op of the trace is charged to the innermost frame of
jaxnav's code in its HLO metadata (XLA's fusions keep the source line of the op they were named
after), and the lines are listed by their summed time per update. Two threads of the CPU's
runtime run independent ops at once, so a program's summed op time can exceed its wall time.
"""

from __future__ import annotations

import argparse
import collections
import re
import tempfile
import time

import jax
import numpy as np
from report import run_info, write_json
from throughput import trace_events

from jaxnav.ppo.train import make_train
from jaxnav.training import build_config, make_run_env

PROGRAMS = ("draws", "rollout", "learn")


def _table(hlo: str, name: str, following: str | None) -> str:
    """The lines of the table `name` at the end of an HLO module's text (up to `following`)."""
    part = hlo.split(f"\n{name}\n", 1)[1]
    return part.split(f"\n{following}\n", 1)[0] if following else part


def source_lines(hlo: str) -> dict[str, str]:
    """{op name: "file.py:function:line"} of every op of a compiled module's text whose stack
    frames reach jaxnav's code: the innermost such frame."""
    files = dict(re.findall(r'^(\d+) "(.*)"', _table(hlo, "FileNames", "FunctionNames"), re.M))
    names = dict(re.findall(r'^(\d+) "(.*)"', _table(hlo, "FunctionNames", "FileLocations"), re.M))
    where = {
        i: (files[f], names[fn], line)
        for i, f, fn, line in re.findall(
            r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)",
            _table(hlo, "FileLocations", "StackFrames"),
            re.M,
        )
    }
    frames = {
        i: (loc, parent)
        for i, loc, parent in re.findall(
            r"^(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)",
            _table(hlo, "StackFrames", None),
            re.M,
        )
    }

    def innermost(frame: str) -> str | None:
        seen = set()
        while frame in frames and frame not in seen:
            seen.add(frame)
            loc, parent = frames[frame]
            path, function, line = where[loc]
            if "/jaxnav/" in path and "/benchmarks/" not in path:
                return f"{path.rsplit('/jaxnav/', 1)[1]}:{function}:{line}"
            frame = parent
        return None

    ops = re.findall(r"^\s*(?:ROOT )?%([\w.\-]+) = .*?stack_frame_id=(\d+)", hlo, re.M)
    return {op: src for op, frame in ops if (src := innermost(frame))}


def charged(events, sources: dict) -> dict:
    """{program: Counter(source line -> microseconds)} of a trace's op `events`, each op charged to
    its program's `sources` line; a loop's own span (which holds its body's ops) is left out."""
    summed = collections.defaultdict(collections.Counter)
    for e in events:
        module, op = e.get("args", {}).get("hlo_module"), e["name"]
        if module in sources and not op.startswith(("while", "call", "conditional")):
            summed[module][sources[module].get(op, "(no jaxnav frame)")] += e["dur"]
    return summed


def profile(args) -> dict:
    """The preset's update: each program's min and median ms, and its ops by source line."""
    config = build_config(args.preset, env=args.env, overrides={"ppo": {"updates_per_chunk": 1}})
    trainer = make_train(config.ppo, make_run_env(config))
    programs, compiled = trainer.programs, {}
    ts = jax.block_until_ready(trainer.init(jax.random.PRNGKey(args.seed)))

    def run(name, *operands):  # compiled once, from the first operands, so its text is at hand
        if name not in compiled:
            compiled[name] = programs[name].lower(*operands).compile()
        return jax.block_until_ready(compiled[name](*operands))

    def update(ts, times=None):
        t0 = time.perf_counter()
        drawn = run("draws", ts.env_state.info["reset_key"])
        t1 = time.perf_counter()
        out = run("rollout", ts, drawn)
        t2 = time.perf_counter()
        ts, _ = run("learn", *out)
        if times is not None:
            times.append((t1 - t0, t2 - t1, time.perf_counter() - t2))
        return ts

    times = []
    for i in range(2 + args.timed):  # two to warm up
        ts = update(ts, times if i >= 2 else None)
    ms = np.asarray(times) * 1e3  # [timed, 3]
    sources = {  # each program's ops -> their jaxnav source line
        f"jit__{name}": source_lines(program.as_text()) for name, program in compiled.items()
    }
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        for _ in range(args.profiled):
            ts = update(ts)
        jax.profiler.stop_trace()
        summed = charged(trace_events(folder)[0], sources)
    per_update = lambda us: round(us / 1e3 / args.profiled, 2)  # noqa: E731  ms
    return {
        "config": {"env": args.env, "preset": args.preset, "num_envs": config.ppo.num_envs},
        "programs": {
            name: {
                "min_ms": round(float(ms[:, i].min()), 1),
                "median_ms": round(float(np.median(ms[:, i])), 1),
                "op_ms": round(per_update(sum(summed[f"jit__{name}"].values())), 1),
                "top": [
                    {"source": src, "ms": per_update(us)}
                    for src, us in summed[f"jit__{name}"].most_common(args.top)
                ],
            }
            for i, name in enumerate(PROGRAMS)
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="goal", help="the task: avoid or goal")
    parser.add_argument("--preset", default="cpu", help="the preset whose update is profiled")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timed", type=int, default=12, help="updates timed per program")
    parser.add_argument("--profiled", type=int, default=5, help="updates under the profiler")
    parser.add_argument("--top", type=int, default=12, help="source lines listed per program")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args()
    result = {**run_info("device", "python", "date", "jax"), **profile(args)}
    for name, p in result["programs"].items():
        print(
            f"\n{name}: {p['min_ms']} ms (median {p['median_ms']}) an update, "
            f"its ops {p['op_ms']} ms summed"
        )
        for row in p["top"]:
            print(f"  {row['ms']:8.2f} ms  {row['source']}")
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
