"""The twin against the simulator: one exported policy in the same rooms, both ways.

    python benchmarks/twin.py --checkpoint runs/avoid-cpu --episodes 5 --tag cpu
    python benchmarks/twin.py --checkpoint runs/avoid-cpu --rooms clutter-0,open-3 --episodes 10
    python benchmarks/twin.py --checkpoint runs/avoid-cpu --steps 300 --calibration-pitch-deg 2
    python benchmarks/twin.py --checkpoint runs/goal-gpu --rooms all --episodes 2 --no-per-axis \
        --eval-episodes 20 --wheeled-episodes 4 --tag suite_goal

The run's policy is exported (`jaxnav.export.export`, numpy) and run in the chosen rooms of the
benchmark suite (default: the first room of every other family; `--rooms all`: all of them,
pooled per family too) by
1. `jaxnav.twin.run_twin`: the robot's own control loop on depth images rendered by classic MuJoCo,
   the wheeled Kobuki, the velocity smoother, latency and mount error (`--episodes` per room),
   with kobuki_velocity_smoother's rule and, unless `--no-per-axis`, again with the simulator's
   per-axis one (the difference is the smoother's share of any gap);
2. `jaxnav.evaluation.evaluate` on the same rooms and spawns, the evaluation's sim-to-real ranges
   on with the twin's smoother rule (`--coupled-smoother`, kobuki_velocity_smoother's), under the
   fast physics (`--eval-episodes` per room: cheap, so its figure is the tighter one) and under the
   wheeled model (`--wheeled-episodes`), the twin's own physics.
Episodes run the policy's own time limit (its task's `max_steps`: 600 steps avoid, 500 goal) unless
`--steps` says otherwise; goal episodes end at the goal on both sides, and the twin draws goals at
the task's `goal_min_distance`. Prints, per room, per family and overall, side by side with
binomial standard errors: success rate and SPL (goal policies), collision-free rate and mean
speed; and writes them to `benchmarks/results/twin_<tag>.json` with the command and the commit
(`report.write_json`), the twin's speed (control steps per second), where its loop sent zero
velocity (`loop_states`, overall and per room under "room_loop_states"), each twin episode's
outcome, draws and path (every 10th pose, under "episodes"), and `observation_gap`: the twin's
reading against the simulator's sensor at the same poses (where the two runs part). Runs on the
CPU; the twin's cost is rendering.

`--calibration-pitch-deg D` runs only the twin, with the camera D deg further down than the
policy's mount in every episode, three times: the node reading depth at the policy's mount, with
its start-up calibration (`calibration:=use`), and at the true mount; the collision-free rate and
speed of each go into the JSON's "calibration" entry (with its own command and commit), the rest
of the JSON kept.
"""

from __future__ import annotations

import argparse
import dataclasses
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
from jaxnav.robot_side.observation import BlindFrame
from jaxnav.twin import Twin, TwinConfig, run_twin

RESULTS = Path(__file__).parent / "results"
PHYSICS = ("fast", "wheeled")
EVERY = 10  # control steps between the poses at which the two sensors are compared


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a training run folder (avoid or goal)")
    p.add_argument(
        "--rooms", help="room names of the benchmark suite, comma-separated, or 'all' (32 rooms)"
    )
    p.add_argument("--episodes", type=int, default=5, help="twin episodes per room")
    p.add_argument(
        "--eval-episodes", type=int, default=100, help="evaluate's episodes per room, fast physics"
    )
    p.add_argument(
        "--wheeled-episodes", type=int, default=20, help="evaluate's, wheeled (about 18x slower)"
    )
    p.add_argument(
        "--steps", type=int, help="control steps per episode (default: the task's max_steps)"
    )
    p.add_argument(
        "--no-per-axis",
        dest="per_axis",
        action="store_false",
        help="skip the twin's second run with the simulator's per-axis smoother (half the cost)",
    )
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


SUITE = "benchmark"


def pick_rooms(names: str | None):
    """The benchmark suite's rooms named in `names` (all of them in suite order for "all"), else
    the first room of every other family."""
    families = load_suite(SUITE)
    if names is None:
        return [rooms[0] for rooms in list(families.values())[::2]]
    if names == "all":
        return [room for rooms in families.values() for room in rooms]
    by_name = {room.name: room for rooms in families.values() for room in rooms}
    unknown = sorted(set(names.split(",")) - set(by_name))
    if unknown:
        raise SystemExit(
            f"--rooms: not in the benchmark suite: {unknown}; rooms: {sorted(by_name)}"
        )
    return [by_name[name] for name in names.split(",")]


def where(rooms, args) -> dict:
    """`evaluate`'s and `run_twin`'s rooms: the whole suite (families pooled too) for --rooms all,
    else the layouts."""
    return {"suite": SUITE} if args.rooms == "all" else {"layouts": rooms}


def run_evaluate(policy, rooms, args) -> dict:
    """evaluate's metrics per physics: {physics: {"layouts", "overall", "seconds"}}, and
    "families" with --rooms all."""
    out = {}
    episodes = {"fast": args.eval_episodes, "wheeled": args.wheeled_episodes}
    for physics in PHYSICS:
        tick = time.perf_counter()
        results = evaluate(
            policy, **where(rooms, args), episodes=episodes[physics], steps=args.steps,
            seed=args.seed, physics=physics, coupled_smoother=TwinConfig.smoother_coupled,
        )  # fmt: skip
        keys = ("layouts", "families", "overall")
        out[physics] = {
            **{k: results[k] for k in keys if k in results},
            "seconds": round(time.perf_counter() - tick, 1),
        }
    return out


def observation_gap(policy, rooms, twin: dict, npz, cfg: TwinConfig) -> dict:
    """What the twin's loop reads against what the simulator's sensor reads (noiseless) at the
    same poses and camera mounts: every EVERY-th pose of every twin episode, the robot at rest.
    Per room and overall: the share of sectors within 3 cm, and nearer or farther by over 10 cm
    in the twin; and the poses whose frame the loop refuses as blind (a surface inside the blind
    zone across the view: the robot stops there), which are left out of the shares."""
    env = make_eval_env(policy, rooms, steps=1, randomize=eval_randomize(stochastic_env=False))
    sense = jax.jit(lambda p, q: observe(p, q, jax.random.PRNGKey(0), env.sensor, env.robot))
    gaps, blind = {}, {}
    for i, (name, room) in enumerate(twin["_rooms"].items()):
        params = reset_in(env, jax.random.PRNGKey(0), jnp.int32(i)).info["params"]
        reader, diff, blind[name] = Twin(rooms[i], npz, cfg), [np.zeros(0)], 0
        for draw, poses in zip(room["draws"], room["poses"], strict=True):
            mount = params.replace(camera=jnp.asarray(draw.camera, jnp.float32))
            for pose in poses[::EVERY]:
                sim = np.asarray(sense(mount, jnp.asarray(pose, jnp.float32)))
                try:
                    diff.append(reader.reading(draw, pose)[: sim.size] - sim)
                except BlindFrame:
                    blind[name] += 1
        reader.close()
        gaps[name] = np.concatenate(diff)
    gaps["overall"] = np.concatenate(list(gaps.values()))
    blind["overall"] = sum(blind.values())
    return {
        name: {
            "sectors": int(d.size),
            "within_3cm": float(np.mean(np.abs(d) <= 0.03)),
            "twin_nearer_10cm": float(np.mean(d < -0.1)),
            "twin_farther_10cm": float(np.mean(d > 0.1)),
            "blind_poses": blind[name],
        }
        for name, d in gaps.items()
    }


def stderr(rate: float, n: int) -> float:
    """The binomial standard error of a rate measured over n episodes."""
    return math.sqrt(max(rate * (1 - rate), 0.0) / max(n, 1))


ROWS = {
    "success %": "success_rate",
    "SPL": "spl",
    "collision-free %": "collision_free_rate",
    "speed m/s": "mean_speed",
}
RATES = ("success_rate", "collision_free_rate")


def table(names, columns: dict, group: str = "layouts") -> str:
    """Per room (or family, `group`) and overall, success % and SPL (goal policies), collision-free
    % and mean speed (m/s), rates with their binomial standard error, one column per run in
    `columns` ({label: results with `group` and "overall"})."""
    width = max(14, *(len(label) + 2 for label in columns))
    overall = next(iter(columns.values()))["overall"]
    lines = []
    for title, key in ((t, k) for t, k in ROWS.items() if k in overall):
        lines += [f"{title:<18}" + "".join(f"{label:>{width}}" for label in columns)]
        for name in [*names, "overall"]:
            row = f"{name:<18}"
            for results in columns.values():
                m = results["overall"] if name == "overall" else results[group][name]
                value, n = m[key], m["episodes"]
                cell = f"{100 * value:.1f} +-{100 * stderr(value, n):.1f}"
                row += f"{cell if key in RATES else f'{value:.3f}':>{width}}"
            lines.append(row)
    return "\n".join(lines)


def run_twins(npz, rooms, args, goal_min_distance: float) -> tuple[dict, dict]:
    """The twin with the Kobuki smoother's coupled rule and (`args.per_axis`) with the simulator's
    per-axis one: ({label: results}, the first run's full results, per-episode poses included)."""
    out, first = {}, None
    runs = (("twin", True), ("twin per-axis smoother", False))
    for label, coupled in runs if args.per_axis else runs[:1]:
        cfg = TwinConfig(
            episodes=args.episodes, steps=args.steps, seed=args.seed, width=args.width,
            height=args.height, smoother_coupled=coupled, goal_min_distance=goal_min_distance,
        )  # fmt: skip
        tick = time.perf_counter()
        full = run_twin(npz, **where(rooms, args), cfg=cfg, log=print)
        out[label] = {
            **strip_private(full),
            "room_loop_states": {
                name: dict(room["states"].most_common()) for name, room in full["_rooms"].items()
            },
            "episodes": episodes(full),
            "seconds": round(time.perf_counter() - tick, 1),
        }
        first = first or full
    return out, first


def episodes(full: dict) -> dict:
    """Each twin episode per room: outcome, control steps, distance (m), its draws (latency in
    control periods; camera height m, pitch and yaw rad errors; spawn; goal) and every EVERY-th
    pose (x, y m, yaw rad)."""
    out = {}
    for name, room in full["_rooms"].items():
        success = room["metrics"].get("success", np.zeros(len(room["steps"])))
        out[name] = [
            {
                "collided": bool(collided),
                "success": bool(won),
                "steps": int(steps),
                "distance": round(float(distance), 3),
                **{k: v for k, v in dataclasses.asdict(draw).items() if v is not None},
                "path": np.round(poses[::EVERY], 3).tolist(),
            }
            for collided, won, steps, distance, draw, poses in zip(
                room["collided"], success, room["steps"], room["distance"], room["draws"],
                room["poses"], strict=True,
            )
        ]  # fmt: skip
    return out


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
    policy = load_policy(args.checkpoint)
    task = policy.env_kwargs["task"]
    args.steps = args.steps or task.max_steps
    if args.calibration_pitch_deg is not None:
        main_calibration(args, rooms, names)
        return
    goal_min_distance = getattr(task, "goal_min_distance", TwinConfig.goal_min_distance)
    with tempfile.TemporaryDirectory() as tmp:
        npz = export(args.checkpoint, "numpy", Path(tmp) / "policy.npz")
        twins, full = run_twins(npz, rooms, args, goal_min_distance)
        gap = observation_gap(policy, rooms, full, npz, TwinConfig(**full["twin"]))
    sim = run_evaluate(policy, rooms, args)
    columns = {**twins, **{f"sim {p}": sim[p] for p in PHYSICS}}
    print(table(names, columns))
    if "families" in full:
        print(table(list(full["families"]), columns, group="families"))
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
        {"checkpoint": args.checkpoint, "rooms": names, "steps": args.steps, "twin": twins,
         "evaluate": sim, "observation_gap": gap},
    )  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
