"""The README's Results table, from fresh runs: every line names the command that made it.

    python benchmarks/readme_results.py --train --write-readme          # on the 2-core CPU
    python benchmarks/readme_results.py --run runs/avoid-cpu             # evaluate an existing run

On this machine it (1) trains the quick start, `python -m jaxnav.train --out RUN` (timed, wall clock,
compile included, with an empty compilation cache as on a fresh machine), unless `--run` names a
finished run, (2) evaluates it on the held-out room of the paper's Fig. 6 (100 episodes) and on the
benchmark suite (20 episodes a room) exactly as `python -m jaxnav.evaluate` does, and (3) with
`--paper` trains the `paper` preset and evaluates it on the suite (`--gather-only --paper`: only
that, keeping the other CPU lines of the last run).
The accelerator lines come from the JSON their own scripts wrote on the H200 (commands in
`GATHERED`). Everything lands in `benchmarks/results/readme.json`; `--write-readme` puts `render()`
of it between the README's results markers, and tests/test_readme_results.py checks that the README's
table is exactly that, so the two cannot drift apart.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from report import write_json

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
OUT = RESULTS / "readme.json"
# The runs this script trains by default (git-ignored), which a new run of it replaces.
OWN_RUNS = (RESULTS / "readme-run", RESULTS / "readme-run-paper")
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
QUICK = "python -m jaxnav.train"
SUITE = ("--suite", "benchmark", "--episodes", "20")  # how the README judges a policy on the suite
# Accelerator lines: (JSON under benchmarks/results/, the command that wrote it, what it measures).
GATHERED = (
    (
        "env_rollout_h200_movers.json",
        "python benchmarks/env_rollout.py --num-envs 65536 --steps 64 --repeats 2 "
        "--variants default,movers",
        "env-only throughput, random policy, 65,536 robots",
    ),
    (
        "throughput_h200.json",
        "python benchmarks/throughput.py --num-envs 65536 --steps 50 --updates 3 --repeats 2 "
        "--variants default --pieces none",
        "PPO training throughput, 65,536 robots",
    ),
    (
        "time_to_solve_h200_gpu.json",
        "python benchmarks/time_to_solve.py --preset gpu --full --max-seconds 60 --eval-every 5",
        "the gpu preset: training time to the suite's bar",
    ),
    (
        "barn_h200.json",
        "python -m jaxnav.train --env goal --preset gpu && python benchmarks/barn.py "
        "--checkpoint RUN --episodes 5",
        "the gpu preset's goal policy on BARN's 300 worlds (never trained on), 5 episodes a world",
    ),
)


def machine() -> str:
    cores = os.cpu_count()
    return f"{cores}-core CPU ({platform.machine()}), Python {platform.python_version()}"


def sh(*args: str, env: dict | None = None) -> None:
    print("+", " ".join(args), flush=True)
    subprocess.run(args, check=True, cwd=ROOT, env=env)


def train(run: Path, *flags: str) -> float:
    """Wall seconds of `python -m jaxnav.train --out run *flags` as on a fresh machine: with an
    empty compilation cache and program store (a new JAX_COMPILATION_CACHE_DIR), so that no
    earlier run's programs shorten it. A run this script trained before in its own folders
    (`OWN_RUNS`, git-ignored) is replaced; any other folder must be new (the training refuses one
    that holds a run)."""
    if run.resolve() in OWN_RUNS and run.exists():
        print(f"readme_results.py: replacing this script's earlier run in {run}", flush=True)
        shutil.rmtree(run)
    with tempfile.TemporaryDirectory(prefix="jaxnav-cache-") as cache:
        env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache}
        command = (sys.executable, "-m", "jaxnav.train", "--out", str(run), "--no-progress")
        tick = time.perf_counter()
        sh(*command, *flags, env=env)
        return time.perf_counter() - tick


def evaluate(run: Path, out: Path, *flags: str, pictures: str = "readme_pictures") -> dict:
    """The JSON of `python -m jaxnav.evaluate` on `run`, its pictures in RESULTS/pictures; the
    JSON gains the evaluation's command, this commit and the date."""
    args = ("--checkpoint", str(run), "--json", str(out), "--plots", str(RESULTS / pictures))
    sh(sys.executable, "-m", "jaxnav.evaluate", *args, *flags)
    command = " ".join(["python -m jaxnav.evaluate", *args, *flags]).replace(f"{ROOT}/", "")
    result = json.loads(out.read_text())
    write_json(out, {"command": command, **result})
    return result


def pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def suite_text(ev: dict) -> str:
    o = ev["overall"]
    fam = ", ".join(f"{name} {pct(m['collision_free_rate'])}" for name, m in ev["families"].items())
    slowest = min(ev["families"].items(), key=lambda kv: kv[1]["mean_speed"])
    return (
        f"**{pct(o['collision_free_rate'])} collision-free, {o['mean_speed']:.3f} m/s**, coverage "
        f"{pct(o['coverage'])}; per family: {fam}; slowest family {slowest[0]} "
        f"{slowest[1]['mean_speed']:.3f} m/s"
    )


def cpu_lines(args, run: Path) -> list[dict]:
    lines, today = [], datetime.date.today().isoformat()
    line = lambda what, command, result: dict(  # noqa: E731
        what=what, command=command, machine=machine(), date=today, result=result
    )
    if args.train:
        seconds = train(run)
        lines.append(
            line(
                "the quick start's training (cpu preset)",
                QUICK,
                f"{seconds / 60:.1f} min wall, compile included",
            )
        )
    room = evaluate(run, RESULTS / "readme_cpu_inference_room.json")
    o = room["overall"]
    lines.append(
        line(
            "the quick start's policy in the held-out room of Fig. 6, 100 episodes × 600 steps",
            f"{QUICK} && python -m jaxnav.evaluate --checkpoint runs/avoid-cpu",
            f"**{pct(o['collision_free_rate'])} collision-free, {o['mean_speed']:.3f} m/s**, "
            f"coverage {pct(o['coverage'])}",
        )
    )
    suite = evaluate(run, RESULTS / "readme_cpu_suite.json", *SUITE)
    lines.append(
        line(
            "the same policy on the 32 rooms of the benchmark suite (never trained on), 20 episodes a room",
            "python -m jaxnav.evaluate --checkpoint runs/avoid-cpu --suite benchmark --episodes 20",
            suite_text(suite),
        )
    )
    return lines


PAPER_WHAT = "the `paper` preset (Table II: one robot, 150k steps) on the suite"


def paper_line(run: Path) -> dict:
    """The paper preset trained (timed) next to `run` and evaluated on the suite."""
    paper = run.with_name(run.name + "-paper")
    seconds = train(paper, "--preset", "paper")
    ev = evaluate(
        paper, RESULTS / "readme_cpu_paper_suite.json", *SUITE, pictures="readme_pictures/paper"
    )
    return dict(
        what=PAPER_WHAT,
        command="python -m jaxnav.train --preset paper && python -m jaxnav.evaluate --checkpoint "
        "runs/avoid-paper --suite benchmark --episodes 20",
        machine=machine(),
        date=datetime.date.today().isoformat(),
        result=f"{suite_text(ev)}; trained in {seconds / 60:.1f} min wall",
    )


def gathered_lines() -> list[dict]:
    """The accelerator lines from their scripts' JSON (skipped, with a note, where absent)."""
    lines = []
    for name, command, what in GATHERED:
        path = RESULTS / name
        if not path.exists():
            print(f"note: {path} missing; run `{command}` on the accelerator", file=sys.stderr)
            continue
        data = json.loads(path.read_text())
        lines.append(
            dict(
                what=what,
                command=command,
                machine=f"{data['device']}, Python {data.get('python', '?')}",
                date=data.get("date", "?"),
                result=_gathered_result(name, data),
            )
        )
    return lines


def _gathered_result(name: str, data: dict) -> str:
    if name.startswith("env_rollout"):
        rows = {r["variant"]: r for r in data["rows"]}
        parts = [
            f"{rows['default']['env_steps_per_s'] / 1e6:.2f} M env-steps/s (5-row camera, sim-to-real on)"
        ]
        if "rows1" in rows:
            parts.append(f"{rows['rows1']['env_steps_per_s'] / 1e6:.2f} M with a 1-row camera")
        if "movers" in rows:
            parts.append(
                f"{rows['movers']['env_steps_per_s'] / 1e6:.2f} M with 0-3 moving obstacles"
            )
        return "; ".join(parts)
    if name.startswith("barn"):
        groups = data["groups"]
        per = ", ".join(f"{g} {pct(groups[g]['success_rate'])}" for g in ("easy", "medium", "hard"))
        m = groups["overall"]
        return (
            f"**{pct(m['success_rate'])} success**, {pct(1 - m['collision_free_rate'])} collided, "
            f"{pct(m['timeout_rate'])} timed out; BARN score {m['barn_score']:.3f} "
            f"({m['barn_score_own_speed']:.3f} at the robot's 0.7 m/s); by difficulty: {per}"
        )
    if name.startswith("throughput"):
        row = next((r for r in data["rows"] if r.get("variant") == "default"), data["rows"][-1])
        return f"{row['train']['env_steps_per_s'] / 1e6:.2f} M env-steps/s (compile {row['train']['compile_s']} s)"
    solved, last = data["solved"], data["history"][-1]
    head = (
        f"bar met after {solved['train_s']} s of training ({solved['env_steps'] / 1e6:.1f} M steps)"
        if solved
        else "bar not met"
    )
    return (
        f"{head}; after {last['train_s']} s: {pct(last['free'])} collision-free, "
        f"{last['speed']:.3f} m/s; compile {data['compile_s']} s"
    )


def render(results: dict) -> str:
    """The README's table (between the markers) for `results` (readme.json)."""
    rows = ["| what | command | machine, date | result |", "|---|---|---|---|"]
    for ln in results["lines"]:
        rows.append(
            f"| {ln['what']} | `{ln['command']}` | {ln['machine']}, {ln['date']} | {ln['result']} |"
        )
    return "\n".join(rows)


def write_readme(results: dict, readme: Path = ROOT / "README.md") -> None:
    text = readme.read_text()
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    readme.write_text(f"{head}{BEGIN}\n{render(results)}\n{END}{tail}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--run", help="a finished run to evaluate (default: benchmarks/results/readme-run)"
    )
    parser.add_argument(
        "--train", action="store_true", help="train the quick start into the run first"
    )
    parser.add_argument(
        "--paper", action="store_true", help="also train and evaluate the paper preset"
    )
    parser.add_argument(
        "--gather-only", action="store_true", help="keep the CPU lines of readme.json"
    )
    parser.add_argument("--write-readme", action="store_true")
    args = parser.parse_args()
    run = Path(args.run or OWN_RUNS[0]).resolve()  # the subprocesses run in ROOT
    if args.gather_only and OUT.exists():
        old = json.loads(OUT.read_text())["lines"]
        cpu = [ln for ln in old if "CPU" in ln["machine"]]
        cpu = [ln for ln in cpu if not (args.paper and ln["what"] == PAPER_WHAT)]
    else:
        cpu = cpu_lines(args, run)
    if args.paper:
        cpu.append(paper_line(run))
    results = {"lines": cpu + gathered_lines()}
    write_json(OUT, results)  # with the command and commit
    print(render(results))
    if args.write_readme:
        write_readme(results)


if __name__ == "__main__":
    main()
