"""The twin against the simulator: one exported policy in the same rooms, both ways.

    python benchmarks/twin.py --checkpoint runs/avoid-cpu --episodes 5 --tag cpu
    python benchmarks/twin.py --checkpoint runs/avoid-cpu --rooms clutter-0,open-3 --episodes 10

The run's policy is exported (`jaxnav.export.export`, numpy) and run in the chosen rooms of the
benchmark suite (default: the first room of every other family) by
1. `jaxnav.twin.run_twin`: the robot's own control loop on depth images rendered by classic MuJoCo,
   the wheeled Kobuki, the velocity smoother, latency and mount error (`--episodes` per room);
2. `jaxnav.evaluate.evaluate` on the same rooms and spawns, the evaluation's sim-to-real ranges on,
   under the fast physics (`--eval-episodes` per room: cheap, so its figure is the tighter one)
   and under the wheeled model (`--wheeled-episodes`), the twin's own physics.
Prints collision-free rate and mean speed side by side, per room and overall, with the twin's
binomial standard error, and writes them to `benchmarks/results/twin_<tag>.json` with the command
and the commit (`report.write_json`), the twin's speed (control steps per second) and where its
loop sent zero velocity. Runs on the CPU; the twin's cost is mostly rendering.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from report import write_json

from jaxnav import load_policy
from jaxnav.evaluate import evaluate, load_suite, strip_private, unique_names
from jaxnav.export import export
from jaxnav.twin import TwinConfig, run_twin

RESULTS = Path(__file__).parent / "results"
PHYSICS = ("fast", "wheeled")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a training run folder (avoid or goal)")
    p.add_argument("--rooms", help="room names of the benchmark suite, comma-separated")
    p.add_argument("--episodes", type=int, default=5, help="twin episodes per room")
    p.add_argument(
        "--eval-episodes", type=int, default=100, help="evaluate's episodes per room, fast physics"
    )
    p.add_argument(
        "--wheeled-episodes", type=int, default=20, help="evaluate's, wheeled (about 18x slower)"
    )
    p.add_argument("--steps", type=int, default=600, help="control steps per episode")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=640, help="the twin's depth image width, px")
    p.add_argument("--height", type=int, default=480, help="the twin's depth image height, px")
    p.add_argument("--tag", default="cpu", help="the JSON is results/twin_<tag>.json")
    return p.parse_args(argv)


def pick_rooms(names: str | None):
    """The benchmark suite's rooms named in `names`, else the first room of every other family."""
    families = load_suite("benchmark")
    if names is None:
        return [rooms[0] for rooms in list(families.values())[::2]]
    by_name = {room.name: room for rooms in families.values() for room in rooms}
    unknown = sorted(set(names.split(",")) - set(by_name))
    if unknown:
        raise SystemExit(
            f"--rooms: not in the benchmark suite: {unknown}; rooms: {sorted(by_name)}"
        )
    return [by_name[name] for name in names.split(",")]


def run_evaluate(policy, rooms, args) -> dict:
    """evaluate's metrics per physics: {physics: {"layouts", "overall", "seconds"}}."""
    out = {}
    episodes = {"fast": args.eval_episodes, "wheeled": args.wheeled_episodes}
    for physics in PHYSICS:
        tick = time.perf_counter()
        results = evaluate(
            policy, rooms, episodes=episodes[physics], steps=args.steps, seed=args.seed,
            physics=physics,
        )  # fmt: skip
        out[physics] = {
            "layouts": results["layouts"],
            "overall": results["overall"],
            "seconds": round(time.perf_counter() - tick, 1),
        }
    return out


def stderr(rate: float, n: int) -> float:
    """The binomial standard error of a rate measured over n episodes."""
    return math.sqrt(max(rate * (1 - rate), 0.0) / max(n, 1))


def table(names, twin: dict, sim: dict) -> str:
    """Collision-free % and speed (m/s) per room and overall: the twin (+- its standard error)
    and evaluate under each physics."""
    head = f"{'room':<16} {'twin cf %':>13} " + " ".join(
        f"{'sim ' + p + ' cf %':>16}" for p in PHYSICS
    )
    head += f" {'twin m/s':>8} " + " ".join(f"{p + ' m/s':>11}" for p in PHYSICS)
    lines = [head, "-" * len(head)]
    for name in [*names, "overall"]:
        t = twin["overall"] if name == "overall" else twin["layouts"][name]
        s = {
            p: sim[p]["overall"] if name == "overall" else sim[p]["layouts"][name] for p in PHYSICS
        }
        rate, n = t["collision_free_rate"], t["episodes"]
        row = f"{name:<16} {100 * rate:>6.1f} +-{100 * stderr(rate, n):>4.1f} "
        row += " ".join(f"{100 * s[p]['collision_free_rate']:>16.1f}" for p in PHYSICS)
        row += f" {t['mean_speed']:>8.3f} " + " ".join(
            f"{s[p]['mean_speed']:>11.3f}" for p in PHYSICS
        )
        lines.append(row)
    return "\n".join(lines)


def main(argv=None) -> None:
    args = parse_args(argv)
    rooms = pick_rooms(args.rooms)
    names = unique_names(rooms)
    policy = load_policy(args.checkpoint)
    with tempfile.TemporaryDirectory() as tmp:
        npz = export(args.checkpoint, "numpy", Path(tmp) / "policy.npz")
        cfg = TwinConfig(
            episodes=args.episodes, steps=args.steps, seed=args.seed, width=args.width,
            height=args.height,
        )  # fmt: skip
        tick = time.perf_counter()
        twin = strip_private(run_twin(npz, rooms, cfg=cfg, log=print))
        twin["seconds"] = round(time.perf_counter() - tick, 1)
    sim = run_evaluate(policy, rooms, args)
    print(table(names, twin, sim))
    print(f"twin: {twin['control_steps_per_s']:.1f} control steps/s; loop: {twin['loop_states']}")
    out = RESULTS / f"twin_{args.tag}.json"
    write_json(out, {"checkpoint": args.checkpoint, "rooms": names, "twin": twin, "evaluate": sim})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
