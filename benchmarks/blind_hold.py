"""The node's blind hold: what the robot does facing a surface nearer than the camera's range_min.

    python benchmarks/blind_hold.py --checkpoint runs/goal-gpu --holds 0,1.5,3 --episodes 12 --tag goal

A wall nearer than range_min across the whole view leaves a depth frame with no reading. The node
refuses such frames (`BlindFrame`: a covered lens, sunlight) and sends zero velocity; facing a wall
it then never moves again, where the simulator reads the frame as "everything near" and the
policy turns away. The node's `blind_hold` reads such a frame near for that many seconds after a
frame that measured a surface just beyond range_min (`ros_node.ControlLoop._sectors`).

This runs the exported policy in the twin (`jaxnav.twin.run_twin`: the node's own loop, rendered
depth, the Kobuki's smoother) in the benchmark suite's rooms where the node stopped facing a wall
(`--rooms`; default the six of `twin_suite_goal.json` with such stops), once per `--holds` value
(`--blind-hold S`, 0: off), and prints and writes to `benchmarks/results/blind_hold_<tag>.json`
per hold: success rate and SPL (goal policies), collision-free rate, mean speed, the episodes
whose loop stopped on a blind frame and the ticks it did, the ticks spent on the hold, and the
most seconds one episode spent on it.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from report import run_info, write_json

from jaxnav import load_policy
from jaxnav.evaluation import load_suite, strip_private, unique_names
from jaxnav.export import export
from jaxnav.robot_side.ros_node import BLIND_ZONE
from jaxnav.twin import TwinConfig, run_twin

RESULTS = Path(__file__).resolve().parent / "results"
ROOMS = "clutter-3,corridor-0,corridor-1,low_overhang-0,pillars-1,furniture-3"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a training run folder (avoid or goal)")
    p.add_argument("--rooms", default=ROOMS, help="benchmark suite rooms, comma-separated")
    p.add_argument("--holds", default="0,1.5,3", help="blind_hold values to compare, s")
    p.add_argument("--episodes", type=int, default=12, help="twin episodes per room")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tag", default="goal", help="the JSON is results/blind_hold_<tag>.json")
    return p.parse_args(argv)


def summary(full: dict, period: float) -> dict:
    """The figures of one twin run: pooled metrics and the loop's blind states."""
    rooms = full["_rooms"].values()
    episodes = [s for room in rooms for s in room["episode_states"]]
    blind = [sum(n for k, n in s.items() if k.startswith("sensor blind")) for s in episodes]
    held = [s.get(BLIND_ZONE, 0) for s in episodes]
    overall = full["overall"]
    out = {
        "episodes": len(episodes),
        "collision_free_rate": overall["collision_free_rate"],
        "mean_speed": overall["mean_speed"],
        "blind_stop_episodes": int(np.count_nonzero(blind)),
        "blind_stop_ticks": int(sum(blind)),
        "hold_episodes": int(np.count_nonzero(held)),
        "hold_ticks": int(sum(held)),
        "hold_seconds_max_episode": max(held) * period,
    }
    if "success_rate" in overall:
        out.update(success_rate=overall["success_rate"], spl=overall["spl"])
    return out


def main(argv=None) -> None:
    args = parse_args(argv)
    suite = {unique: room for unique, room in _suite_rooms()}
    names = args.rooms.split(",")
    missing = [n for n in names if n not in suite]
    if missing:
        raise SystemExit(f"--rooms: not in the benchmark suite: {', '.join(missing)}")
    layouts = [suite[n] for n in names]
    max_steps = load_policy(args.checkpoint).env_kwargs["task"].max_steps
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        npz = export(args.checkpoint, "numpy", Path(tmp) / "policy.npz")
        for hold in [float(h) for h in args.holds.split(",")]:
            cfg = TwinConfig(
                episodes=args.episodes,
                steps=max_steps,
                seed=args.seed,
                node_flags=("--blind-hold", str(hold)),
            )
            tick = time.perf_counter()
            full = run_twin(npz, layouts, cfg=cfg)
            period = next(iter(full["_rooms"].values()))["control_period"]
            runs[f"{hold:g}"] = {
                **summary(full, period),
                "layouts": strip_private(full)["layouts"],
                "seconds": round(time.perf_counter() - tick, 1),
            }
    keys = ("success_rate", "spl", "collision_free_rate", "mean_speed")
    print("hold s | " + " | ".join(keys) + " | blind-stop episodes | hold ticks | longest hold s")
    for hold, run in runs.items():
        cells = [f"{run[k]:.3f}" for k in keys if k in run]
        print(
            f"{hold} | {' | '.join(cells)} | {run['blind_stop_episodes']}/{run['episodes']} | "
            f"{run['hold_ticks']} | {run['hold_seconds_max_episode']:.1f}"
        )
    out = RESULTS / f"blind_hold_{args.tag}.json"
    info = run_info("command", "commit", "dirty", "date", "device", "mujoco")
    write_json(out, {**info, "checkpoint": args.checkpoint, "rooms": names, "runs": runs})
    print(f"wrote {out}")


def _suite_rooms():
    """(unique name, layout) of every room of the benchmark suite."""
    rooms = [r for group in load_suite("benchmark").values() for r in group]
    return zip(unique_names(rooms), rooms, strict=True)


if __name__ == "__main__":
    main()
