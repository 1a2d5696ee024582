"""The twin against the simulator: one exported policy in the same rooms, both ways.

    python benchmarks/twin.py --checkpoint runs/avoid-cpu --episodes 5 --tag cpu
    python benchmarks/twin.py --checkpoint runs/avoid-cpu --rooms clutter-0,open-3 --episodes 10
    python benchmarks/twin.py --checkpoint runs/avoid-cpu --steps 300 --calibration-pitch-deg 2

The run's policy is exported (`jaxnav.export.export`, numpy) and run in the chosen rooms of the
benchmark suite (default: the first room of every other family) by
1. `jaxnav.twin.run_twin`: the robot's own control loop on depth images rendered by classic MuJoCo,
   the wheeled Kobuki, the velocity smoother, latency and mount error (`--episodes` per room),
   with kobuki_velocity_smoother's rule and again with the simulator's per-axis one (the
   difference is the smoother's share of any gap);
2. `jaxnav.evaluation.evaluate` on the same rooms and spawns, the evaluation's sim-to-real ranges on,
   under the fast physics (`--eval-episodes` per room: cheap, so its figure is the tighter one)
   and under the wheeled model (`--wheeled-episodes`), the twin's own physics.
Prints collision-free rate and mean speed side by side, per room and overall, with the twin's
binomial standard error, and writes them to `benchmarks/results/twin_<tag>.json` with the command
and the commit (`report.write_json`), the twin's speed (control steps per second), where its
loop sent zero velocity, and `observation_gap`: the twin's reading against the simulator's sensor
at the same poses (where the two runs part). Runs on the CPU; the twin's cost is rendering.

`--calibration-pitch-deg D` runs only the twin, with the camera D deg further down than the
policy's mount in every episode, three times: the node reading depth at the policy's mount, with
its start-up calibration (`calibration:=use`), and at the true mount; the collision-free rate and
speed of each go into the JSON's "calibration" entry (with its own command and commit), the rest
of the JSON kept.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from report import run_info, write_json

from jaxnav import load_policy
from jaxnav.core.sensors import observe
from jaxnav.evaluation import (
    eval_randomize,
    evaluate,
    load_suite,
    make_eval_env,
    reset_in,
    strip_private,
    unique_names,
)
from jaxnav.export import export
from jaxnav.twin import Twin, TwinConfig, run_twin

RESULTS = Path(__file__).parent / "results"
PHYSICS = ("fast", "wheeled")
EVERY = 10  # control steps between the poses at which the two sensors are compared


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
    p.add_argument(
        "--calibration-pitch-deg",
        type=float,
        help="instead: the camera pitched this much more down than the policy's mount in every "
        "episode, the node given the policy's mount, its start-up estimate, or the true mount; "
        "written to the JSON's 'calibration' (the rest kept)",
    )
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


def observation_gap(policy, rooms, twin: dict, npz, cfg: TwinConfig) -> dict:
    """What the twin's loop reads against what the simulator's sensor reads (noiseless) at the
    same poses and camera mounts: every EVERY-th pose of every twin episode, the robot at rest.
    Per room and overall: the share of sectors within 3 cm, and nearer or farther by over 10 cm
    in the twin."""
    env = make_eval_env(policy, rooms, steps=1, randomize=eval_randomize(stochastic_env=False))
    sense = jax.jit(lambda p, q: observe(p, q, jax.random.PRNGKey(0), env.sensor, env.robot))
    gaps = {}
    for i, (name, room) in enumerate(twin["_rooms"].items()):
        params = reset_in(env, jax.random.PRNGKey(0), jnp.int32(i)).info["params"]
        reader, diff = Twin(rooms[i], npz, cfg), []
        for draw, poses in zip(room["draws"], room["poses"], strict=True):
            mount = params.replace(camera=jnp.asarray(draw.camera, jnp.float32))
            for pose in poses[::EVERY]:
                sim = np.asarray(sense(mount, jnp.asarray(pose, jnp.float32)))
                diff.append(reader.reading(draw, pose)[: sim.size] - sim)
        reader.close()
        gaps[name] = np.concatenate(diff)
    gaps["overall"] = np.concatenate(list(gaps.values()))
    return {
        name: {
            "sectors": int(d.size),
            "within_3cm": float(np.mean(np.abs(d) <= 0.03)),
            "twin_nearer_10cm": float(np.mean(d < -0.1)),
            "twin_farther_10cm": float(np.mean(d > 0.1)),
        }
        for name, d in gaps.items()
    }


def stderr(rate: float, n: int) -> float:
    """The binomial standard error of a rate measured over n episodes."""
    return math.sqrt(max(rate * (1 - rate), 0.0) / max(n, 1))


def table(names, columns: dict) -> str:
    """Per room and overall, collision-free % (+- its binomial standard error) and mean speed
    (m/s), one column per run in `columns` ({label: results with "layouts" and "overall"})."""
    width = max(14, *(len(label) + 2 for label in columns))
    lines = []
    for title, key in (("collision-free %", "collision_free_rate"), ("speed m/s", "mean_speed")):
        lines += [f"{title:<16}" + "".join(f"{label:>{width}}" for label in columns)]
        for name in [*names, "overall"]:
            row = f"{name:<16}"
            for results in columns.values():
                m = results["overall"] if name == "overall" else results["layouts"][name]
                rate, n = m[key], m["episodes"]
                cell = f"{100 * rate:.1f} +-{100 * stderr(rate, n):.1f}"
                row += f"{cell if key != 'mean_speed' else f'{rate:.3f}':>{width}}"
            lines.append(row)
    return "\n".join(lines)


def run_twins(npz, rooms, args) -> tuple[dict, dict]:
    """The twin with the Kobuki smoother's coupled rule and with the simulator's per-axis one:
    ({label: results}, the first run's full results, per-episode poses included)."""
    out, first = {}, None
    for label, coupled in (("twin", True), ("twin per-axis smoother", False)):
        cfg = TwinConfig(
            episodes=args.episodes, steps=args.steps, seed=args.seed, width=args.width,
            height=args.height, smoother_coupled=coupled,
        )  # fmt: skip
        tick = time.perf_counter()
        full = run_twin(npz, rooms, cfg=cfg, log=print)
        out[label] = {**strip_private(full), "seconds": round(time.perf_counter() - tick, 1)}
        first = first or full
    return out, first


MOUNTS = {"policy's mount": "policy", "start-up calibration": "calibrate", "true mount": "true"}


def run_calibration(npz, rooms, args) -> dict:
    """The twin with the camera pitched `--calibration-pitch-deg` down from the policy's mount
    (height and yaw errors drawn as usual), once per way the node learns the mount (MOUNTS):
    {label: results}, with the settings and the command."""
    out = {}
    for label, mount in MOUNTS.items():
        cfg = TwinConfig(
            episodes=args.episodes, steps=args.steps, seed=args.seed, width=args.width,
            height=args.height, camera_pitch_error=0.0,
            camera_pitch_bias=math.radians(args.calibration_pitch_deg), mount=mount,
        )  # fmt: skip
        tick = time.perf_counter()
        full = run_twin(npz, rooms, cfg=cfg, log=print)
        out[label] = {**strip_private(full), "seconds": round(time.perf_counter() - tick, 1)}
    return {"pitch_error_deg": args.calibration_pitch_deg, "runs": out}


def main_calibration(args, rooms, names) -> None:
    """--calibration-pitch-deg: the 'calibration' entry of results/twin_<tag>.json."""
    with tempfile.TemporaryDirectory() as tmp:
        npz = export(args.checkpoint, "numpy", Path(tmp) / "policy.npz")
        runs = run_calibration(npz, rooms, args)
    print(table(names, runs["runs"]))
    for label, run in runs["runs"].items():
        print(f"{label}: loop {run['loop_states']}")
    out = RESULTS / f"twin_{args.tag}.json"
    previous = json.loads(out.read_text()) if out.exists() else {}
    runs = {**run_info("command", "commit", "dirty", "date"), "rooms": names, **runs}
    write_json(out, {**previous, "calibration": runs})
    print(f"wrote {out}")


def main(argv=None) -> None:
    args = parse_args(argv)
    rooms = pick_rooms(args.rooms)
    names = unique_names(rooms)
    if args.calibration_pitch_deg is not None:
        main_calibration(args, rooms, names)
        return
    policy = load_policy(args.checkpoint)
    with tempfile.TemporaryDirectory() as tmp:
        npz = export(args.checkpoint, "numpy", Path(tmp) / "policy.npz")
        twins, full = run_twins(npz, rooms, args)
        gap = observation_gap(policy, rooms, full, npz, TwinConfig(**full["twin"]))
    sim = run_evaluate(policy, rooms, args)
    print(table(names, {**twins, **{f"sim {p}": sim[p] for p in PHYSICS}}))
    twin = twins["twin"]
    print(f"twin: {twin['control_steps_per_s']:.1f} control steps/s; loop: {twin['loop_states']}")
    print("sensors at the same poses (twin - simulator): " + ", ".join(
        f"{name} {100 * g['within_3cm']:.0f}% within 3 cm, {100 * g['twin_nearer_10cm']:.1f}% "
        f"nearer by > 10 cm, {100 * g['twin_farther_10cm']:.1f}% farther"
        for name, g in gap.items()
    ))  # fmt: skip
    out = RESULTS / f"twin_{args.tag}.json"
    write_json(
        out,
        {"checkpoint": args.checkpoint, "rooms": names, "twin": twins, "evaluate": sim,
         "observation_gap": gap},
    )  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
