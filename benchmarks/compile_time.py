"""Where a run's start-up goes: tracing and compiling the training chunk, and what the persistent
compilation cache saves a repeated run with the same shapes.

    python benchmarks/compile_time.py --preset cpu             # avoid and goal, on this machine
    python benchmarks/compile_time.py --preset gpu --json benchmarks/results/compile_time_h100.json
    python benchmarks/compile_time.py --pieces --json benchmarks/results/compile_time_cpu.json
    python benchmarks/compile_time.py --xla-flags ",--xla_backend_optimization_level=3" --json ...

`--pieces`: each piece of the training program lowered and compiled on its own in this process
with jaxnav's compiler options and the preset's shapes (`PIECES`), `--repeats` times in fresh
programs (medians): trace+lower and XLA compile seconds, and the size of its HLO (ops of the
lowered StableHLO, characters of the optimised HLO).

Per task: in this process, each of a run's programs (`Trainer.programs`: the draws, start, rollout
and learner, or init, the rollout and the learner with `--reset-ahead false`)
lowered (tracing: `jax.stages` `.lower`) and compiled (`.compile`) on its own, in turn, with the
process's CPU seconds in its compile (`compile_cpu_s`: XLA spreads one compile over cores), the
size of its HLO text, and the sums over the chunk's (all but init and start); then `python -m
jaxnav.train` run twice in subprocesses with one fresh cache folder (`XDG_CACHE_HOME`), each with a
budget of one chunk: the seconds to its "compiled and ran the first chunk" line, to the start of
that chunk's run (its "compiled in", the chunk compiled and init run: when training starts) and the
whole command's wall time, cold and with the cache warm, and JAX's compile events of each run per
program (tracing, lowering, XLA compiles or cache loads, cache retrievals; `LISTENED`). Prints the
table last; writes the JSON.

`--checkout DIR`: the command-line runs only (those above, or those of `--xla-flags` and
`--train-flags`), of the jaxnav in DIR (a checkout of an earlier commit, e.g. `git worktree add
DIR COMMIT`, run from a folder outside this one), for a before and after pair measured back to
back.

`--xla-log` (a GPU): the chunk's programs lowered and compiled as above, in a subprocess with
XLA's compile log on: XLA's own seconds in the chunk's HLO passes, in the autotuning of its matrix
products (one of those passes), in code generation and in its IR emission (`xla_log`), and each
program's slowest HLO passes (`pass_seconds`).

`--xla-flags A,B,...`: per task and per `XLA_FLAGS` value (an empty one: jaxnav's own compiler
options, `jaxnav.core.xla`), `python -m jaxnav.train --no-compile-cache` for `--chunks` chunks: the
seconds to its first chunk's end and the training pace after it (env steps per second, from the
run's metrics.csv), so that a faster compile is seen not to cost speed. `--train-flags A,B,...`:
the same, with each entry as more flags of the command line instead (e.g. `--threefry-kernel
false`). `--total-steps N` instead of `--chunks`: a budget of N env steps, e.g. the preset's own,
whose last chunk is a part of one (`--train-flags "" --total-steps 100000000`: the gpu preset's
whole run; its pace then covers every chunk after the first).
"""

from __future__ import annotations

import argparse
import csv
import json
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
    from jaxnav.training import build_config, make_run_env

    config = build_config(preset, env=env, overrides={"ppo": {"updates_per_chunk": 1}})
    tick = time.perf_counter()
    trainer = make_train(config.ppo, make_run_env(config))
    key = jax.random.PRNGKey(0)
    out = {"build_s": round(time.perf_counter() - tick, 1), "programs": {}}
    for name, program in trainer.programs.items():  # each from its abstract arguments, in turn
        tick = time.perf_counter()
        lowered = program.lower(*trainer.arguments(name, trainer.programs, key))
        lower = time.perf_counter() - tick
        tick, cpu = time.perf_counter(), time.process_time()
        lowered.compile()
        compiled, cpu = time.perf_counter() - tick, time.process_time() - cpu
        out["programs"][name] = {"lower_s": round(lower, 1), "compile_s": round(compiled, 1)}
        out["programs"][name]["compile_cpu_s"] = round(cpu, 1)  # the process's cores' seconds
        out["programs"][name]["hlo_chars"] = len(lowered.as_text())
    chunk = [p for name, p in out["programs"].items() if name not in ("init", "start")]
    for field in ("lower_s", "compile_s", "compile_cpu_s", "hlo_chars"):  # the chunk's, summed
        out[field] = round(sum(p[field] for p in chunk), 1)
    return out


PIECES = {
    "env_reset": "the task's reset, vmapped over the robots",
    "env_step": "the task's step, vmapped over the robots",
    "autoreset_draw": "AutoReset.draw: a rollout's new episodes in one batch (reset_ahead)",
    "autoreset_step": "AutoReset(EpisodeStats) step, as the rollout takes it",
    "init": "Trainer.init: reset of every robot, network and optimiser",
    "rollout": "the rollout scan (policy, auto-reset step)",
    "learn": "GAE, epochs x minibatch scan of loss, grad and optax",
    "update": "one update as one program, the rollout and the learner (a run compiles them apart)",
}


def piece_programs(env_name: str, preset: str) -> dict:
    """{piece: (function, abstract args)} of `PIECES` for the preset's shapes."""
    import jax

    from jaxnav.ppo.train import make_train
    from jaxnav.training import build_config, make_run_env
    from jaxnav.wrappers import AutoReset, EpisodeStats

    config = build_config(preset, env=env_name, overrides={"ppo": {"updates_per_chunk": 1}})
    cfg, env = config.ppo, make_run_env(config)
    trainer = make_train(cfg, env)
    parts, shape = trainer.parts, jax.eval_shape
    key = shape(jax.random.PRNGKey, 0)  # raw key data: (2,) for threefry
    keys = jax.ShapeDtypeStruct((cfg.num_envs, *key.shape), key.dtype)
    ts = trainer.arguments("state", trainer.programs, key)  # init's TrainState
    rollout_args = trainer.arguments("rollout", trainer.programs, key)  # (ts, drawn ahead?)
    rolled = shape(parts["rollout"], *rollout_args)  # (ts, traj)
    action = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), rolled[1].action
    )
    wrapped = AutoReset(EpisodeStats(env), cfg.reset_pool, cfg.reset_in_place)
    state = shape(jax.vmap(env.reset), keys)
    programs = {
        "env_reset": (jax.vmap(env.reset), (keys,)),
        "env_step": (jax.vmap(env.step), (state, action)),
    }
    if cfg.reset_ahead:
        fresh = shape(lambda s: wrapped.draw(s, cfg.rollout_length)[1], ts.env_state)
        state, fresh, banks = shape(wrapped.bank, ts.env_state, fresh)  # as the rollout banks
        one = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), fresh)
        programs["autoreset_draw"] = (
            lambda s: wrapped.draw(s, cfg.rollout_length),
            (ts.env_state,),
        )
        programs["autoreset_step"] = (wrapped.step, (state, action, one, banks))
    else:
        programs["autoreset_step"] = (wrapped.step, (ts.env_state, action))
    programs["init"] = (parts["init"], (key,))
    programs["rollout"] = (parts["rollout"], rollout_args)
    programs["learn"] = (parts["learn"], rolled)
    programs["update"] = (parts["update"], rollout_args)
    return programs


def time_piece(fn, args, repeats: int) -> dict:
    """Median trace+lower and compile seconds of `fn` on `args` over `repeats` fresh jits; the
    sizes of its HLO."""
    import statistics

    import jax

    from jaxnav.core.xla import compiler_options

    lowers, compiles = [], []
    for _ in range(repeats):
        jax.clear_caches()
        tick = time.perf_counter()
        lowered = jax.jit(fn, compiler_options=compiler_options()).lower(*args)
        lowers.append(time.perf_counter() - tick)
        tick = time.perf_counter()
        compiled = lowered.compile()
        compiles.append(time.perf_counter() - tick)
    text = lowered.as_text()
    return {
        "lower_s": round(statistics.median(lowers), 2),
        "compile_s": round(statistics.median(compiles), 2),
        "lower_runs_s": [round(x, 2) for x in lowers],
        "compile_runs_s": [round(x, 2) for x in compiles],
        "hlo_ops": sum(
            " = stablehlo." in line or ' = "stablehlo.' in line for line in text.splitlines()
        ),
        "hlo_kchars": len(text) // 1000,
        "compiled_kchars": len(compiled.as_text() or "") // 1000,
    }


def pieces(env: str, preset: str, repeats: int, only=None) -> dict:
    """{piece: time_piece(...)} of one task, printed as they come."""
    rows = {}
    for name, (fn, args) in piece_programs(env, preset).items():
        if only and name not in only:
            continue
        rows[name] = time_piece(fn, args, repeats)
        print(env, name, rows[name], flush=True)
    return rows


def print_pieces(rows: dict) -> None:
    print(
        f"{'env':<6} {'piece':<15} {'lower s':>8} {'compile s':>10} {'HLO ops':>8} {'opt kchars':>10}"
    )
    for env, table in rows.items():
        for name, r in table.items():
            print(
                f"{env:<6} {name:<15} {r['lower_s']:>8} {r['compile_s']:>10} {r['hlo_ops']:>8} "
                f"{r['compiled_kchars']:>10}"
            )


def cli_runs(env: str, preset: str, checkout: Path | None = None) -> dict:
    """Two runs of the command line with one fresh cache: (first chunk s, wall s) each; of the
    jaxnav in `checkout` if given."""
    cache = tempfile.mkdtemp(prefix="jaxnav-cache-")
    environ = _environ(checkout)
    environ["XDG_CACHE_HOME"] = cache
    out = {}
    for label in ("cold", "warm"):
        run = tempfile.mkdtemp(prefix="jaxnav-run-") + "/run"
        events = Path(run).parent / "events.json"
        cmd = [
            sys.executable,
            "-c",
            LISTENED,
            str(events),
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
            cwd=cache if checkout else None,  # not this folder, which `python -m` imports from
        )
        wall = time.perf_counter() - tick
        out[label] = {
            **_first_chunk(proc.stdout),
            "wall_s": round(wall, 1),
            "rc": proc.returncode,
            **(json.loads(events.read_text()) if events.exists() else {}),
        }
    return out


def _first_chunk(stdout: str) -> dict:
    """{first_chunk_s, compiled_s} of a run's compile line: the seconds from its start to the
    end of the first chunk, and to the start of its run (init run and the chunk compiled)."""
    found = re.search(r"first chunk in ([\d.]+) s(?: \(compiled in ([\d.]+) s\))?", stdout)
    if not found:
        return {"first_chunk_s": None, "compiled_s": None}
    compiled = found.group(2)
    return {"first_chunk_s": float(found.group(1)), "compiled_s": compiled and float(compiled)}


def _environ(checkout: Path | None) -> dict:
    """This process's environment for a command-line run, without a compilation cache folder of
    its own; with the jaxnav in `checkout` first on the path if given."""
    environ = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    if checkout is not None:
        paths = [str(Path(checkout).resolve()), environ.get("PYTHONPATH", "")]
        environ["PYTHONPATH"] = os.pathsep.join(p for p in paths if p)
    return environ


# `python -m jaxnav.train` with JAX's compile events summed per kind and program, written as JSON
# to argv[1] at exit: the seconds from the start to the compile line ("to_compile_line_s"), and
# {event: {program: seconds}} of tracing, lowering, XLA compiles or cache loads, cache retrievals.
LISTENED = """
import atexit, collections, json, runpy, sys, time
start = time.perf_counter()
import jax
path, sums, marks = sys.argv.pop(1), collections.defaultdict(dict), {}
def listen(event, seconds, **kw):
    name = kw.get("fun_name", "")
    kind = event.rsplit("/", 1)[-1]
    if seconds >= 0.05:
        sums[kind][name] = round(sums[kind].get(name, 0.0) + seconds, 2)
jax.monitoring.register_event_duration_secs_listener(listen)
class Marked:
    def __init__(self, out): self.out = out
    def write(self, text):
        if "compiling the training step" in text and "line" not in marks:
            marks["line"] = round(time.perf_counter() - start, 2)
        return self.out.write(text)
    def __getattr__(self, name): return getattr(self.out, name)
sys.stdout = Marked(sys.stdout)
atexit.register(lambda: open(path, "w").write(json.dumps(
    {"to_compile_line_s": marks.get("line"), "events": sums})))
sys.argv[0] = "jaxnav.train"
runpy.run_module("jaxnav.train", run_name="__main__", alter_sys=True)
"""


def flag_runs(
    env: str,
    preset: str,
    flags: list[str],
    chunks: int,
    train: bool = False,
    checkout=None,
    total_steps: int | None = None,
) -> dict:
    """{flags: {first_chunk_s, steps_per_s after it, wall_s}} of `chunks`-chunk runs (or runs of
    `total_steps` env steps), each with one entry of `flags` as its XLA_FLAGS, or (`train`) as
    more flags of its command line; of the jaxnav in `checkout` if given."""
    from jaxnav.training import build_config

    cfg = build_config(preset, env=env).ppo
    out = {}
    for flag in flags:
        run = Path(tempfile.mkdtemp(prefix="jaxnav-run-")) / "run"
        environ = _environ(checkout) if train else {**_environ(checkout), "XLA_FLAGS": flag}
        cmd = [sys.executable, "-m", "jaxnav.train", "--env", env, "--preset", preset]
        cmd += flag.split() if train else []
        cmd += ["--out", str(run), "--no-progress", "--no-compile-cache"]
        budget = total_steps or chunks * cfg.updates_per_chunk * cfg.batch_size
        cmd += ["--total-steps", str(budget)]
        tick = time.perf_counter()
        proc = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            env=environ,
            timeout=1800,
            cwd=run.parent if checkout else None,  # not this folder, which `python -m` imports from
        )
        wall = time.perf_counter() - tick
        rows = list(csv.DictReader((run / "metrics.csv").open())) if proc.returncode == 0 else []
        first, last = (rows[cfg.updates_per_chunk - 1], rows[-1]) if rows else ({}, {})
        steps = int(last.get("env_steps", 0)) - int(first.get("env_steps", 0))
        seconds = float(last.get("elapsed_s", 0)) - float(first.get("elapsed_s", 0))
        out[flag or "jaxnav"] = {
            **_first_chunk(proc.stdout),
            "steps_per_s": round(steps / seconds) if seconds > 0 else None,
            "wall_s": round(wall, 1),
            "rc": proc.returncode,
        }
        print(env, flag or "jaxnav", out[flag or "jaxnav"], flush=True)
    return out


# XLA's own timers for the chunk's modules (`jit__rollout`, `jit__learn` and `jit__draws`),
# from its log on a GPU: regex -> key, summed over them.
CHUNK_MODULES = r"jit_(?:_draws|_rollout|_learn)"
PROGRAMS = r"jit_(?:_draws|_rollout|_learn|start|init)"  # every program of a run
XLA_TIMERS = {
    "hlo_passes_s": rf"RunHloPasses for {CHUNK_MODULES} time: ([\d.]+) (ms|s|min)",
    "backend_s": rf"GpuCompiler::RunBackend for {CHUNK_MODULES} time: ([\d.]+) (ms|s|min)",
    "ir_emission_s": rf"IR emission for {CHUNK_MODULES} time: ([\d.]+) (ms|s|min)",
}
UNITS = {"us": 1e-6, "ms": 1e-3, "s": 1.0, "min": 60.0}
PIPELINE = re.compile(r"Running HLO pass pipeline on module (\S+): ")
STARTS = re.compile(r"\]\s+HLO pass (\S+)$")
PASS = re.compile(r"HLO pass: (\S+) time: ([\d.]+) (us|ms|s|min) ")


def pass_seconds(log: str, top: int = 6) -> dict:
    """{module: {pass: seconds}}: the `top` slowest HLO passes of each module XLA compiled, summed
    over their runs, from its log with `TF_CPP_VMODULE=hlo_pass_pipeline=1`. A pass belongs to
    the module whose pipeline it started in (its time comes at its end, after the modules that
    an autotuning pass compiles inside it); a pass that runs a pipeline holds that one's time."""
    seconds, module, started = {}, None, {}
    for line in log.splitlines():
        if found := PIPELINE.search(line):
            module = found.group(1)
        elif found := STARTS.search(line):
            started.setdefault(found.group(1), []).append(module)
        elif (found := PASS.search(line)) and started.get(found.group(1)):
            name, value, unit = found.groups()
            passes = seconds.setdefault(started[name].pop(), {})
            passes[name] = passes.get(name, 0.0) + float(value) * UNITS[unit]
    slowest = lambda passes: sorted(passes.items(), key=lambda kv: -kv[1])[:top]  # noqa: E731
    return {m: {n: round(v, 2) for n, v in slowest(p)} for m, p in seconds.items() if m}


def xla_log(env: str, preset: str) -> dict:
    """`split` in a subprocess with XLA's compile log on (a GPU's timers and pass statistics):
    its seconds, XLA's time in the chunk's HLO passes, in code generation and in its IR emission,
    the autotuning of its matrix products (the largest "config-assigner" pass in the log), and
    each program's slowest passes (`passes`: `pass_seconds`)."""
    code = f"import json, sys; sys.path.insert(0, {str(HERE)!r}); import compile_time as c; "
    code += "print('SPLIT', json.dumps(c.split(sys.argv[1], sys.argv[2])))"
    environ = {**os.environ, "TF_CPP_MIN_LOG_LEVEL": "0"}
    environ["TF_CPP_VMODULE"] = "gpu_compiler=2,compile_module_to_llvm_ir=2,hlo_pass_pipeline=1"
    environ["XLA_FLAGS"] = "--xla_gpu_print_compilation_stats=true"
    proc = subprocess.run(
        [sys.executable, "-c", code, env, preset], capture_output=True, text=True, env=environ
    )
    found = re.search(r"^SPLIT (.*)$", proc.stdout, re.M)
    out = {**(json.loads(found.group(1)) if found else {}), "rc": proc.returncode}
    for key, pattern in XLA_TIMERS.items():
        if hits := re.findall(pattern, proc.stderr):
            out[key] = round(sum(float(v) * UNITS[unit] for v, unit in hits), 2)
    tuned = [float(x) for x in re.findall(r"\] config-assigner, \d+, ([\d.]+)", proc.stderr, re.I)]
    out["autotune_s"] = round(max(tuned) / 1000, 2) if tuned else None
    passes = pass_seconds(proc.stderr)
    out["passes"] = {m: p for m, p in passes.items() if re.fullmatch(PROGRAMS, m)}
    return out


def _one_update(env: str, preset: str) -> int:
    from jaxnav.training import build_config

    return build_config(preset, env=env).ppo.batch_size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="cpu")
    p.add_argument("--envs", default="avoid,goal")
    p.add_argument("--json", type=Path, default=HERE / "results" / "compile_time.json")
    p.add_argument("--pieces", action="store_true", help="time each piece (module doc)")
    p.add_argument("--only", default="", help="with --pieces: these pieces only (comma list)")
    p.add_argument("--repeats", type=int, default=3, help="with --pieces: fresh jits per piece")
    p.add_argument("--xla-flags", default=None, help="comma list of XLA_FLAGS (module doc)")
    p.add_argument("--train-flags", default=None, help="comma list of training flags (doc)")
    p.add_argument("--chunks", type=int, default=3, help="with --xla-flags: chunks per run")
    p.add_argument("--total-steps", type=int, help="with --xla/train-flags: budget, not chunks")
    p.add_argument("--checkout", type=Path, help="command-line runs of the jaxnav there only")
    p.add_argument("--xla-log", action="store_true", help="XLA's own timers of the chunk (GPU)")
    args = p.parse_args()
    if args.xla_log:
        rows = {env: xla_log(env, args.preset) for env in args.envs.split(",")}
        info = run_info("command", "device", "jax", "mujoco", "date")
        write_json(args.json, {**info, "preset": args.preset, "rows": rows})
        for env, r in rows.items():
            print(env, r)
        return
    if args.checkout is not None and args.xla_flags is None and args.train_flags is None:
        rows = {env: cli_runs(env, args.preset, args.checkout) for env in args.envs.split(",")}
        info = run_info("command", "device", "jax", "mujoco", "date")
        write_json(
            args.json, {**info, "preset": args.preset, "checkout": str(args.checkout), "rows": rows}
        )
        for env, r in rows.items():
            cold, warm = r["cold"], r["warm"]
            print(
                f"{env:<6} cold {cold['first_chunk_s']} s (compiled {cold['compiled_s']} s), "
                f"warm {warm['first_chunk_s']} s (compiled {warm['compiled_s']} s)"
            )
        return
    if args.xla_flags is not None and args.train_flags is not None:
        p.error("--xla-flags and --train-flags: give one of them")
    if args.xla_flags is not None or args.train_flags is not None:
        train = args.xla_flags is None
        flags = (args.train_flags if train else args.xla_flags).split(",")
        if len(set(flags)) < len(flags):  # results are keyed by the flags: a repeat would overwrite
            p.error("--xla-flags/--train-flags: each entry once; run the command again to repeat")
        rows = {
            env: flag_runs(
                env, args.preset, flags, args.chunks, train, args.checkout, args.total_steps
            )
            for env in args.envs.split(",")
        }
        info = run_info("command", "device", "jax", "mujoco", "date")
        info |= {"preset": args.preset, "chunks": args.chunks, "total_steps": args.total_steps}
        info |= {"checkout": str(args.checkout or "")}
        write_json(args.json, {**info, "rows": rows})
        what = "training flags" if train else "XLA_FLAGS"
        print(
            f"{'env':<6} {what:<44} {'first chunk s':>13} {'compiled s':>10} {'steps/s after':>13}"
        )
        for env, table in rows.items():
            for flag, r in table.items():
                print(
                    f"{env:<6} {flag:<44} {r['first_chunk_s']!s:>13} {r['compiled_s']!s:>10} "
                    f"{r['steps_per_s']!s:>13}"
                )
        return
    if args.pieces:
        only = [x for x in args.only.split(",") if x]
        rows = {env: pieces(env, args.preset, args.repeats, only) for env in args.envs.split(",")}
        info = run_info("command", "device", "jax", "mujoco", "date")
        flags = os.environ.get("XLA_FLAGS", "")
        write_json(
            args.json,
            {**info, "preset": args.preset, "xla_flags": flags, "pieces": PIECES, "rows": rows},
        )
        print_pieces(rows)
        return
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
        f"{'env':<6} {'lower':>6} {'compile':>8} {'cpu':>6} {'HLO kchars':>10} {'cold 1st':>9} "
        f"{'compiled':>9} {'warm 1st':>9} {'compiled':>9}"
    )
    print(head)
    for env, r in rows.items():
        cold, warm = r["cold"], r["warm"]
        print(
            f"{env:<6} {r['lower_s']:>6} {r['compile_s']:>8} {r['compile_cpu_s']:>6} "
            f"{r['hlo_chars'] // 1000:>10} "
            f"{cold['first_chunk_s']!s:>9} {cold['compiled_s']!s:>9} "
            f"{warm['first_chunk_s']!s:>9} {warm['compiled_s']!s:>9}"
        )


if __name__ == "__main__":
    main()
