"""The goal task's memory and training mix on BARN, the benchmark suites, CrowdNav's circle crossing
and a 25 m hall: goal policies trained with and without the memory, with BARN-like dense fields,
walkers or long halls in their room mix, weighted as the cpu preset weighs its families, at the
Kobuki's top speed, trained twice as long (`memory_hall_long`), and the gpu preset with a clearance
cost (`memory_hall_clear10`, `_clear20`), a stop action (`memory_hall_stop`), a collision margin
in training (5, 7.5 and 10 cm: `memory_hall_margin5`, `_margin7`, `_margin10`; 7.5 cm with a
collision costing 30 and a discount of 0.995: `_margin7_c30_g995`) or 12 sectors of 5
degrees rather than 8 of 7.5 (`memory_hall_s12`, as many rays), and the mix of every hard family
with the clearance (`memory_hard_clear20`); among people, a 360 deg lidar instead of the camera
(`lidar_crowd_fast`, with the clearance: `_clear20`) and a fifth of the walkers giving way in
training rather than half (`memory_crowd_fast_nr`, `lidar_crowd_fast_nr`), turning at 3 rad/s
(`memory_crowd_fast_turn3`, with a stop action: `_stop`), backing away
(`memory_crowd_fast_back`; with twice the training: `_back_long`, walkers in half the rooms:
`_back_crowd9`, a fifth of them giving way: `_back_nr`), the lidar backing away
(`lidar_crowd_fast_back`, twice the training: `_long`) and walkers aimed across the robot's way
in training (half of them: `memory_crowd_fast_aimed`, all: `_aimed_all`; backing away too:
`_aimed_back`, `_aimed_all_back`; all, twice the training: `_aimed_all_long`; all, with a
collision costing 30 rather than 10: `_aimed_all_c30`, a discount of 0.995: `_g995`, both:
`_c30_g995`; all, with continuous commands: `_aimed_all_cont`; all and none giving way:
`_aimed_nr0`, with a stop action: `_aimed_nr0_stop`, and a discount of 0.995 too: `_stop_g995`;
the same with walkers in half the rooms, `memory_crowd9_fast_aimed_nr0` (`_stop_g995`), or in
every room, `crowd_only_fast_aimed_nr0` (`_stop`, `_stop_g995`, continuous commands: `_cont`);
and the gpu preset with the walkers of `_aimed_nr0` in a quarter of its rooms and the stop
action, at 0.5 or 0.7 m/s: `memory_hall_margin7_steps40_crowd_nr0_stop`, `_crowd_fast_nr0_stop`);
and with `--preset cpu` (the README's goal run, whose training wall time is its row's
`train_wall_s`) the
cpu preset until 2026-11-29 (`cpu_preset`: no memory, no margin, 28 M steps), with a 7.5 cm
collision margin (`cpu_preset_margin7`), with the memory too (`cpu_preset_memory_margin7`; with
25 M steps: `_25m`; with 23 M steps, the cpu preset until b5ebe30: `_23m`; with 18, 16 (the
cpu preset since), 14 or 12 M: `_18m`, `_16m`, `_14m`, `_12m`) and with long halls in a tenth of
its rooms (`cpu_preset_hall`).

    python benchmarks/memory.py --preset gpu --variants plain,memory,memory_dense \\
        --runs runs/memory --json benchmarks/results/memory_h100.json

Each variant trains `python -m jaxnav.train --env goal --preset P --seed S --out RUNS/NAME FLAGS`
(its flags below, given in full so that a row does not depend on the preset's defaults), then is
evaluated on BARN's 300 worlds (`--suite barn`, `--barn-episodes` a world, 100 s, as
`benchmarks/barn.py`), on the 32 rooms of the benchmark suite (`--suite benchmark`, 20 episodes
a room), on CrowdNav's circle crossing (`benchmarks/crowdnav.py`, `--crowd-episodes` a room;
0 leaves it out), and by `hard_suite.py` on the hard suite (`--suite hard`: dense fields, long
halls and people, 20 episodes a room, 60 s) and in `scenes/halls/hall_25m.json`, whose goal is
20 m down the hall (20 episodes, 100 s; rows measured before these were added have none). Rows are kept per variant and
seed: those already in the JSON file stay where this run does not measure them again, so variants
and seeds may be run in several calls. Prints a table last: each variant's mean over its seeds,
the lowest and highest BARN success, the circle crossing's success among reactive and
non-reactive people, the hard suite's (overall and per family) and the hall's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import hard_suite
import numpy as np
from crowdnav import KINDS, circle_crossing
from make_suite import HARD
from report import run_info, write_json

from jaxnav.tasks.presets import GOAL_CPU_FAMILIES, GOAL_GPU_FAMILIES

ROOT = Path(__file__).resolve().parent.parent
VARIANTS = {
    "plain": ("--task.memory-bins", "0", "--randomize.families", "all"),
    "plain_dense": ("--task.memory-bins", "0", "--randomize.families", "all,dense_field:3"),
    "memory": ("--task.memory-bins", "16", "--randomize.families", "all"),
    "memory_dense": ("--task.memory-bins", "16", "--randomize.families", "all,dense_field:3"),
    "memory_weighted": ("--task.memory-bins", "16", "--randomize.families", GOAL_CPU_FAMILIES),
    "memory_crowd": ("--task.memory-bins", "16", "--randomize.families", "all,crowd:3"),
    "memory_fast": ("--task.memory-bins", "16", "--randomize.families", "all")
    + ("--task.forward-speed", "0.7"),
    "memory_crowd_fast": ("--task.memory-bins", "16", "--randomize.families", "all,crowd:3")
    + ("--task.forward-speed", "0.7"),
    "memory_hall": ("--task.memory-bins", "16", "--randomize.families", GOAL_GPU_FAMILIES),
    "memory_hall_long": ("--task.memory-bins", "16", "--randomize.families", GOAL_GPU_FAMILIES)
    + ("--total-steps", "200000000"),
    "memory_hard": ("--task.memory-bins", "16", "--randomize.families")
    + ("all,dense_field:1,long_hall:1,crowd:1",),
}
VARIANTS["cpu_preset"] = ("--task.memory-bins", "0", "--total-steps", "28000000")
VARIANTS["cpu_preset"] += ("--randomize.families", GOAL_CPU_FAMILIES)
# ... with long halls in about a tenth of its rooms, as the gpu preset has them.
VARIANTS["cpu_preset_hall"] = (*VARIANTS["cpu_preset"][:-1], GOAL_CPU_FAMILIES + ",long_hall:1.5")
VARIANTS["memory_hall_stop"] = VARIANTS["memory_hall"] + ("--task.actions", "discrete_stop")
VARIANTS["memory_hall_clear10"] = VARIANTS["memory_hall"] + ("--task.clearance", "0.1")
VARIANTS["memory_hall_clear20"] = VARIANTS["memory_hall"] + ("--task.clearance", "0.2")
VARIANTS["memory_hard_clear20"] = VARIANTS["memory_hard"] + ("--task.clearance", "0.2")
VARIANTS["memory_hall_s12"] = VARIANTS["memory_hall"] + ("--sensor.num-sectors", "12")
VARIANTS["memory_hall_s12"] += ("--sensor.rays-per-sector", "2")
# A 2-D lidar all round (one row, 48 sectors of 7.5 deg, 0.15-8 m) instead of the camera, among
# people: without the memory, which reads the camera.
LIDAR_360 = ("--sensor.model", "lidar", "--sensor.fov", "6.283185", "--sensor.num-sectors", "48")
LIDAR_360 += ("--sensor.rows", "1", "--sensor.range-min", "0.15")
VARIANTS["lidar_crowd_fast"] = ("--task.memory-bins", "0", *VARIANTS["memory_crowd_fast"][2:])
VARIANTS["lidar_crowd_fast"] += LIDAR_360
VARIANTS["lidar_crowd_fast_clear20"] = VARIANTS["lidar_crowd_fast"] + ("--task.clearance", "0.2")
# ... and with a fifth of the walkers giving way in training rather than half.
NOT_YIELDING = ("--randomize.walkers", "reactive=0.2")
VARIANTS["memory_crowd_fast_nr"] = VARIANTS["memory_crowd_fast"] + NOT_YIELDING
VARIANTS["lidar_crowd_fast_nr"] = VARIANTS["lidar_crowd_fast"] + NOT_YIELDING
# ... and turning at 3 rad/s rather than 1.5 (the Kobuki's limit: pi), with a stop action too.
TURN_3 = ("--task.turn-rate", "3.0")
VARIANTS["memory_crowd_fast_turn3"] = VARIANTS["memory_crowd_fast"] + TURN_3
VARIANTS["memory_crowd_fast_turn3_stop"] = VARIANTS["memory_crowd_fast_turn3"] + (
    "--task.actions",
    "discrete_stop",
)
# ... and with a fourth action that backs away (half the forward speed); twice the training.
BACK = ("--task.actions", "discrete_back")
LONG = ("--total-steps", "200000000")
VARIANTS["memory_crowd_fast_back"] = VARIANTS["memory_crowd_fast"] + BACK
# ... and with half the walkers aimed across the robot's way (all of them: `_all`), as
# CrowdNav's people cross the circle's centre.
AIMED_HALF = ("--randomize.walkers", "aimed=0.5")
AIMED_ALL = ("--randomize.walkers", "aimed=1")
VARIANTS["memory_crowd_fast_aimed"] = VARIANTS["memory_crowd_fast"] + AIMED_HALF
VARIANTS["memory_crowd_fast_aimed_all"] = VARIANTS["memory_crowd_fast"] + AIMED_ALL
# ... and backing away with twice the training, walkers in half the rooms, or a fifth yielding.
VARIANTS["memory_crowd_fast_back_long"] = VARIANTS["memory_crowd_fast_back"] + LONG
VARIANTS["memory_crowd_fast_back_crowd9"] = (
    ("--task.memory-bins", "16", "--randomize.families", "all,crowd:9")
    + ("--task.forward-speed", "0.7")
    + BACK
)
VARIANTS["memory_crowd_fast_back_nr"] = VARIANTS["memory_crowd_fast_back"] + NOT_YIELDING
# ... and the 360 deg lidar with the back action (twice the training: `_long`).
VARIANTS["lidar_crowd_fast_back"] = VARIANTS["lidar_crowd_fast"] + BACK
VARIANTS["lidar_crowd_fast_back_long"] = VARIANTS["lidar_crowd_fast_back"] + LONG
VARIANTS["memory_crowd_fast_aimed_back"] = VARIANTS["memory_crowd_fast_aimed"] + BACK
VARIANTS["memory_crowd_fast_aimed_all_back"] = VARIANTS["memory_crowd_fast_aimed_all"] + BACK
VARIANTS["memory_crowd_fast_aimed_all_long"] = VARIANTS["memory_crowd_fast_aimed_all"] + LONG
# ... and continuous commands (forward m/s, yaw rad/s) rather than three actions, so that the
# robot can slow down and wait for a person to pass.
CONTINUOUS = ("--task.actions", "continuous")
VARIANTS["memory_crowd_fast_aimed_all_cont"] = VARIANTS["memory_crowd_fast_aimed_all"] + CONTINUOUS
# ... and a collision that costs 30 rather than 10, a longer horizon (discount 0.995 rather than
# 0.99), or both: waiting for a person to pass costs less against a collision.
COLLISION_30 = ("--task.collision-reward", "-30")
GAMMA_995 = ("--gamma", "0.995")
VARIANTS["memory_crowd_fast_aimed_all_c30"] = VARIANTS["memory_crowd_fast_aimed_all"] + COLLISION_30
VARIANTS["memory_crowd_fast_aimed_all_g995"] = VARIANTS["memory_crowd_fast_aimed_all"] + GAMMA_995
VARIANTS["memory_crowd_fast_aimed_all_c30_g995"] = (
    VARIANTS["memory_crowd_fast_aimed_all_c30"] + GAMMA_995
)
# ... and every walker aimed across the robot's way and none giving way (CrowdNav's non-reactive
# people: a robot that waits for them to pass reaches the goal, `crowdnav_foresight.py`), in
# the crowd rooms of the mix (`_nr0`), in half the rooms (`crowd9`) or in every room
# (`crowd_only`).
AIMED_NR0 = ("--randomize.walkers", "aimed=1,reactive=0")
VARIANTS["memory_crowd_fast_aimed_nr0"] = VARIANTS["memory_crowd_fast"] + AIMED_NR0
VARIANTS["memory_crowd9_fast_aimed_nr0"] = (
    ("--task.memory-bins", "16", "--randomize.families", "all,crowd:9")
    + ("--task.forward-speed", "0.7")
    + AIMED_NR0
)
VARIANTS["crowd_only_fast_aimed_nr0"] = (
    ("--task.memory-bins", "16", "--randomize.families", "crowd")
    + ("--task.forward-speed", "0.7")
    + AIMED_NR0
)
# ... and with a fourth action that stands (stop), so that waiting need not turn the camera away.
STOP = ("--task.actions", "discrete_stop")
VARIANTS["crowd_only_fast_aimed_nr0_stop"] = VARIANTS["crowd_only_fast_aimed_nr0"] + STOP
VARIANTS["crowd_only_fast_aimed_nr0_cont"] = VARIANTS["crowd_only_fast_aimed_nr0"] + CONTINUOUS
VARIANTS["memory_crowd_fast_aimed_nr0_stop"] = VARIANTS["memory_crowd_fast_aimed_nr0"] + STOP
VARIANTS["crowd_only_fast_aimed_nr0_stop_g995"] = VARIANTS["crowd_only_fast_aimed_nr0_stop"] + (
    GAMMA_995
)
VARIANTS["memory_crowd_fast_aimed_nr0_stop_g995"] = VARIANTS["memory_crowd_fast_aimed_nr0_stop"] + (
    GAMMA_995
)
VARIANTS["memory_crowd9_fast_aimed_nr0_stop_g995"] = (
    VARIANTS["memory_crowd9_fast_aimed_nr0"] + STOP + GAMMA_995
)
# Every variant names its collision margin (none unless it says), so that its row does not
# depend on the preset's default.
MARGIN = "--randomize.collision-margin"
VARIANTS = {name: (*flags, MARGIN, "0", "0") for name, flags in VARIANTS.items()}
VARIANTS["memory_hall_margin5"] = (*VARIANTS["memory_hall"][:-3], MARGIN, "0.05", "0.05")
VARIANTS["memory_hall_margin10"] = (*VARIANTS["memory_hall"][:-3], MARGIN, "0.1", "0.1")
VARIANTS["memory_hall_margin7"] = (*VARIANTS["memory_hall"][:-3], MARGIN, "0.075", "0.075")
# ... the gpu preset since (`memory_hall_margin7`) with a collision costing 30 and a discount
# of 0.995.
VARIANTS["memory_hall_margin7_c30_g995"] = (
    VARIANTS["memory_hall_margin7"] + COLLISION_30 + GAMMA_995
)
# ... trained twice as long (200 M steps), and with a margin drawn per episode between 5 and 10 cm.
VARIANTS["memory_hall_margin7_long"] = VARIANTS["memory_hall_margin7"] + LONG
VARIANTS["memory_hall_margin5_10"] = (*VARIANTS["memory_hall"][:-3], MARGIN, "0.05", "0.1")
# ... with a memory of 32 directions of 11.25° rather than 16, or of the last 4 s rather than 2.
VARIANTS["memory_hall_margin7_bins32"] = VARIANTS["memory_hall_margin7"] + (
    "--task.memory-bins",
    "32",
)
VARIANTS["memory_hall_margin7_steps40"] = VARIANTS["memory_hall_margin7"] + (
    "--task.memory-steps",
    "40",
)
# ... the gpu preset (`_steps40`) with walkers in a quarter of its rooms, every one aimed and none
# giving way, and the stop action: at the Kobuki's top speed (`_crowd_fast_nr0_stop`) or the
# preset's 0.5 m/s (`_crowd_nr0_stop`).
VARIANTS["memory_hall_margin7_steps40_crowd_nr0_stop"] = (
    VARIANTS["memory_hall_margin7_steps40"]
    + ("--randomize.families", GOAL_GPU_FAMILIES + ",crowd:3")
    + AIMED_NR0
    + STOP
)
VARIANTS["memory_hall_margin7_steps40_crowd_fast_nr0_stop"] = VARIANTS[
    "memory_hall_margin7_steps40_crowd_nr0_stop"
] + ("--task.forward-speed", "0.7")
VARIANTS["cpu_preset_margin7"] = (*VARIANTS["cpu_preset"][:-3], MARGIN, "0.075", "0.075")
VARIANTS["cpu_preset_memory_margin7"] = (
    "--task.memory-bins",
    "16",
    *VARIANTS["cpu_preset_margin7"][2:],
)
# ... with fewer steps (25, 23, 18, 16, 14, 12 M: the memory costs the 2-core CPU more a step).
for _steps in (25, 23, 18, 16, 14, 12):
    _flags = list(VARIANTS["cpu_preset_memory_margin7"])
    _flags[_flags.index("--total-steps") + 1] = f"{_steps}000000"
    VARIANTS[f"cpu_preset_memory_margin7_{_steps}m"] = tuple(_flags)
# Every variant names its memory's span too (2 s unless it says): the gpu preset's is 4 s since.
VARIANTS = {name: ("--task.memory-steps", "20", *flags) for name, flags in VARIANTS.items()}
GROUPS = ("easy", "medium", "hard")
BARN_KEYS = ("success_rate", "collision_free_rate", "timeout_rate", "spl", "barn_score")
SUITE_KEYS = ("success_rate", "collision_free_rate", "spl", "mean_speed")
HARD_FAMILIES = tuple(sorted(HARD))  # the hard suite's families, in its file order
CROWD_KEYS = ("success", "collision", "timeout", "time_to_goal", "robot_collision")


def train(preset: str, seed: int, out: Path, flags: list[str]) -> tuple[list[str], float]:
    """Trains one variant on the command line: (its command, wall seconds)."""
    command = ["python", "-m", "jaxnav.train", "--env", "goal", "--preset", preset]
    command += ["--seed", str(seed), "--out", str(out), "--no-progress", *flags]
    tick = time.perf_counter()
    done = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"memory: {' '.join(command)} failed:\n{done.stderr.strip()}")
    return command, time.perf_counter() - tick


def judge(run: Path, barn_episodes: int, crowd_episodes: int) -> dict:
    """BARN's groups, both suites' families and overall, the 25 m hall and (with
    `crowd_episodes` a room) CrowdNav's circle crossing (`benchmarks/crowdnav.py`) for the
    policy in `run`."""
    import jaxnav
    from jaxnav.evaluation import evaluate

    policy = jaxnav.load_policy(run)
    barn = evaluate(policy, suite="barn", episodes=barn_episodes, steps=1000)
    suite = evaluate(policy, suite="benchmark", episodes=20)
    people = (
        {k: circle_crossing(policy, k, crowd_episodes, 0) for k in KINDS} if crowd_episodes else {}
    )
    pick = lambda m, keys: {k: round(float(m[k]), 4) for k in keys}  # noqa: E731
    groups = {**barn["families"], "overall": barn["overall"]}  # easy, medium, hard, overall
    return {
        "barn": {g: pick(m, BARN_KEYS) for g, m in groups.items()},
        "suite": pick(suite["overall"], SUITE_KEYS),
        "suite_families": {f: pick(m, SUITE_KEYS) for f, m in suite["families"].items()},
        **hard_suite.measure(policy, 20),
        **({"crowdnav": {k: pick(m, CROWD_KEYS) for k, m in people.items()}} if people else {}),
    }


def mean(runs: list[dict], get) -> float:
    """The mean of `get(row)` over the rows of a variant's seeds."""
    return float(np.mean([get(r) for r in runs]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="gpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variants", default=",".join(VARIANTS), help=", ".join(VARIANTS))
    p.add_argument("--runs", type=Path, default=Path("runs/memory"), help="the runs' folder")
    p.add_argument("--barn-episodes", type=int, default=2, help="per BARN world (default 2)")
    p.add_argument("--crowd-episodes", type=int, default=10, help="per circle-crossing room")
    p.add_argument("--extra", default="", help="more training flags for every variant, quoted")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "memory.json")
    args = p.parse_args()
    # This process evaluates between trainings: on a GPU it takes what it needs, not 75 % of it,
    # so that the next variant's training process has the rest.
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    names = args.variants.split(",")
    if unknown := sorted(set(names) - set(VARIANTS)):
        p.error(f"--variants: unknown {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    rows = json.loads(args.json.read_text())["rows"] if args.json.exists() else {}
    for name in names:
        run = (args.runs / f"{name}-{args.seed}").resolve()
        flags = [*VARIANTS[name], *args.extra.split()]
        command, wall = train(args.preset, args.seed, run, flags)
        rows.setdefault(name, {})[str(args.seed)] = {
            "training": " ".join(command).replace(str(run), f"runs/{name}-{args.seed}"),
            "train_wall_s": round(wall, 1),
            **run_info("commit", "dirty", "device", "jax", "date"),
            **judge(run, args.barn_episodes, args.crowd_episodes),
        }
        print(f"{name}: trained in {wall:.0f} s", file=sys.stderr)
        info = {**run_info("command", "python"), "barn_episodes": args.barn_episodes}
        info["crowd_episodes"] = args.crowd_episodes
        write_json(args.json, {**info, "rows": rows})  # after each: a later failure keeps it
    head = f"{'variant':<18}{'seeds':>6}{'BARN':>7}{'min-max':>14}{'easy':>7}{'medium':>8}"
    head += f"{'hard':>7}{'suite':>7}{'SPL':>6}{'crowd r/n':>12}{'hard suite':>11}"
    print(head + "".join(f"{f:>13}" for f in HARD_FAMILIES) + f"{'hall_25m':>10}")
    for name, seeds in rows.items():
        runs = list(seeds.values())
        barn = [r["barn"]["overall"]["success_rate"] for r in runs]
        groups = [mean(runs, lambda r, g=g: r["barn"][g]["success_rate"]) for g in GROUPS]
        seen = [r["crowdnav"] for r in runs if "crowdnav" in r]
        crowd = "/".join(
            f"{np.mean([c[k]['success'] for c in seen]):.0%}" for k in (KINDS if seen else ())
        )
        print(
            f"{name:<18}{len(runs):>6}{np.mean(barn):>7.1%}"
            f"{f'{min(barn):.1%}-{max(barn):.1%}':>14}{groups[0]:>7.1%}{groups[1]:>8.1%}"
            f"{groups[2]:>7.1%}{mean(runs, lambda r: r['suite']['success_rate']):>7.1%}"
            f"{mean(runs, lambda r: r['suite']['spl']):>6.2f}{crowd or '-':>12}" + _later(runs)
        )


def _later(runs: list[dict]) -> str:
    """The table's columns of the hard suite's families and the hall, '-' where rows lack them."""
    seen = [r for r in runs if "hard" in r]
    if not seen:
        return f"{'-':>11}" + "".join(f"{'-':>13}" for _ in HARD_FAMILIES) + f"{'-':>10}"
    get = lambda f: mean(seen, lambda r: r["hard_families"][f]["success_rate"])  # noqa: E731
    hard = mean(seen, lambda r: r["hard"]["success_rate"])
    hall = mean(seen, lambda r: r["hall_25m"]["success_rate"])
    return f"{hard:>11.1%}" + "".join(f"{get(f):>13.1%}" for f in HARD_FAMILIES) + f"{hall:>10.0%}"


if __name__ == "__main__":
    main()
