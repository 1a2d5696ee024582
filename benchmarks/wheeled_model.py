"""The wheeled validation model alone: how it tracks commands, and how small a timestep it needs.

    python benchmarks/wheeled_model.py --json benchmarks/results/wheeled_model_cpu.json

Runs the wheeled model (`SceneConfig(physics="wheeled")`, its room model with the floor, on a
floor of traction 1) in C MuJoCo (float64), a few seconds of CPU:
1. tracking: each command held 3 s from rest at the model's own timestep and solver: the speed
   reached (mean over the last second), the time to 90 % of it, the largest pitch and roll (rad)
   and the range of the base's height (m);
2. convergence: one random sequence of the `avoid` actions (forward 0.5 m/s, turn +-1.5 rad/s,
   each held 1-4 control steps of 0.1 s) at several timesteps and solver iteration counts, and the
   base's position error against a 1 ms, 20-iteration reference after 1, 5, 10 and 15 s.
"""

from __future__ import annotations

import argparse

import mujoco
import numpy as np
from report import write_json

from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.core.scene import Scene, SceneConfig

CONTROL_PERIOD = 0.1  # s
SETTINGS = ((0.005, 4), (0.005, 2), (0.01, 4), (0.01, 2), (0.02, 4))  # (timestep s, iterations)
REFERENCE = (0.001, 20)
READ_AT_S = (1, 5, 10, 15)
COMMANDS = ((0.3, 0.0), (0.5, 0.0), (0.7, 0.0), (0.0, 1.5), (0.0, -1.5), (0.0, 3.14), (0.3, 1.0))


def commands(seed: int = 0, steps: int = 150) -> list[tuple[float, float]]:
    """`steps` control steps of the avoid actions, each held 1-4 steps."""
    rng = np.random.default_rng(seed)
    table = [(0.5, 0.0), (0.0, 1.5), (0.0, -1.5)]
    seq = [table[a] for a in rng.integers(0, 3, steps) for _ in range(rng.integers(1, 5))]
    return seq[:steps]


def run(scene: Scene, timestep: float, iterations: int, seq, every: int = 0) -> np.ndarray:
    """[n, 9] qpos[:6] (x, y, yaw, z, pitch, roll) and qvel[:3] (vx, vy, yaw rate) after each
    control step of `seq` (forward m/s, yaw rad/s), or after every `every` physics steps."""
    m = scene.mj_model
    m.opt.timestep, m.opt.iterations, m.opt.ls_iterations = timestep, iterations, iterations
    m.geom_friction[scene.floor, 0] = 1.0
    d = mujoco.MjData(m)
    half, radius = 0.5 * TURTLEBOT2I.wheelbase, scene.wheel_radius
    substeps = round(CONTROL_PERIOD / timestep)
    out = []
    for v, w in seq:
        d.ctrl[scene.wheel_actuators] = [(v - w * half) / radius, (v + w * half) / radius]
        for i in range(substeps):
            mujoco.mj_step(m, d)
            if (every and (i + 1) % every == 0) or (not every and i + 1 == substeps):
                out.append(np.concatenate([d.qpos[:6], d.qvel[:3]]))
    return np.array(out)


def tracking(scene: Scene, timestep: float, iterations: int) -> list[dict]:
    """Per command of COMMANDS, held 3 s from rest: what the base does (module docstring)."""
    rows = []
    for v, w in COMMANDS:
        q = run(scene, timestep, iterations, [(v, w)] * 30, every=1)
        t = timestep * np.arange(1, len(q) + 1)
        forward = np.cos(q[:, 2]) * q[:, 6] + np.sin(q[:, 2]) * q[:, 7]
        last = t > t[-1] - 1.0
        speed, rate = float(forward[last].mean()), float(q[last, 8].mean())
        signal, final = (forward, speed) if v else (q[:, 8], rate)
        rows.append(
            {
                "command": [v, w],
                "speed": speed,
                "yaw_rate": rate,
                "time_to_90pct_s": float(t[np.argmax(np.abs(signal) >= 0.9 * abs(final))]),
                "max_pitch_rad": float(np.abs(q[:, 4]).max()),
                "max_roll_rad": float(np.abs(q[:, 5]).max()),
                "height_range_m": [float(q[:, 3].min()), float(q[:, 3].max())],
            }
        )
    return rows


def convergence(scene: Scene) -> list[dict]:
    """Per (timestep, iterations) of SETTINGS: the position error against REFERENCE."""
    seq = commands()
    ref = run(scene, *REFERENCE, seq)
    rows = []
    for timestep, iterations in SETTINGS:
        q = run(scene, timestep, iterations, seq)
        err = np.linalg.norm(q[:, :2] - ref[:, :2], axis=1)
        rows.append(
            {
                "timestep": timestep,
                "iterations": iterations,
                "position_error_m": {
                    f"{s}s": float(err[round(s / CONTROL_PERIOD) - 1]) for s in READ_AT_S
                },
                "max_pitch_rad": float(np.abs(q[:, 4]).max()),
                "height_range_m": [float(q[:, 3].min()), float(q[:, 3].max())],
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    scene = Scene(SceneConfig(physics="wheeled", num_boxes=0, num_cylinders=0))
    own = (scene.timestep, int(scene.mj_model.opt.iterations))
    tracked = tracking(scene, *own)
    print(f"tracking at {own[0]} s x {own[1]} iterations, each command held 3 s from rest:")
    print(f"{'command':>12} {'speed':>7} {'yaw rate':>8} {'to 90 % s':>9} {'pitch':>6} {'roll':>6}")
    for r in tracked:
        print(
            f"{str(tuple(r['command'])):>12} {r['speed']:>7.3f} {r['yaw_rate']:>8.3f} "
            f"{r['time_to_90pct_s']:>9.3f} {r['max_pitch_rad']:>6.3f} {r['max_roll_rad']:>6.3f}"
        )
    converged = convergence(scene)
    print(f"\nconvergence against {REFERENCE[0]} s x {REFERENCE[1]} iterations:")
    print(f"{'timestep s':>10} {'iterations':>10}  position error m after 1/5/10/15 s   pitch")
    for r in converged:
        errors = " / ".join(f"{v:.4f}" for v in r["position_error_m"].values())
        print(f"{r['timestep']:>10} {r['iterations']:>10}  {errors:>36}   {r['max_pitch_rad']:.3f}")
    if args.json:
        result = {"tracking": tracked, "reference": REFERENCE, "convergence": converged}
        write_json(args.json, result)


if __name__ == "__main__":
    main()
