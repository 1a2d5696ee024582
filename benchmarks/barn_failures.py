"""Where a goal policy collides on BARN: the obstacle it hit, what it was doing, when it last saw it.

    python benchmarks/barn_failures.py --checkpoint runs/goal-gpu --episodes 2
    python benchmarks/barn_failures.py --checkpoint runs/goal-gpu --exact   # no sim-to-real ranges

Runs BARN's 300 worlds as `python -m jaxnav.evaluate --suite barn` does (one compiled batch, 100 s,
the policy's greedy actions, the sim-to-real ranges on unless `--exact`) and records every step's
pose, action and depth sectors. For each episode that ends in a collision it finds the cylinder the
robot touched (the nearest to it at the end of that step) and reports its bearing from the
heading, the policy's action on the colliding step and the steps before it, and how many steps
before the collision the cylinder was last where the camera could read it (within half the field
of view of the heading and at least range_min from the camera; occlusion is not checked, so this
is an upper bound on when it was seen). Writes `benchmarks/results/barn_failures.json` (per
collision and the tallies) and prints the tallies last.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from report import run_info, write_json

HERE = Path(__file__).resolve().parent
BEARINGS = (0, 15, 30, 45, 60, 90, 120, 180)  # deg, |bearing| bins of the cylinder hit
SINCE = (1, 3, 6, 11, 21)  # steps since last readable: 1-2, 3-5, 6-10, 11-20, never within 20


def rollout(policy, layouts, episodes: int, steps: int, exact: bool):
    """Per step [T, E]: pose (x, y, yaw) before it, action, the newest depth sectors, and
    whether the step collided in a still running episode; and the env."""
    import jax

    from jaxnav.evaluation import eval_randomize, make_eval_env, make_recorder

    randomize = eval_randomize(stochastic_env=not exact)
    env = make_eval_env(policy, layouts, steps=steps, randomize=randomize)
    sectors = env.sensor.num_sectors

    def record(state, action, nxt, running):
        hit = (nxt.metrics["collision"] > 0) & running
        return state.data.qpos[:, :3], action, state.obs[:, :sectors], hit

    run = make_recorder(env, policy.act, episodes, steps, record)
    return [np.asarray(x) for x in jax.device_get(run(jax.random.PRNGKey(0)))], env


def collisions(rec, layouts, episodes: int, env, moving=None) -> list[dict]:
    """One record per episode that collided (module docstring). `moving`: [T, E, C, 2] the
    centres of the cylinders at each step, slot i the layout's i-th (people who walk), instead
    of the layouts' still ones."""
    qpos, action, sectors, hit = rec
    half_fov, range_min = 0.5 * env.sensor.fov, env.sensor.range_min
    forward = env.robot.camera_forward
    out = []
    for e in np.flatnonzero(hit.any(0)):
        t = int(np.argmax(hit[:, e]))
        layout = layouts[e // episodes]
        radii = np.array([o.radius for o in layout.obstacles])  # [N]
        if moving is None:
            centres = np.array([o.pos for o in layout.obstacles])[None]  # [1, N, 2]
        else:
            centres = moving[:, e, : len(radii)]  # [T, N, 2]
        centres = np.broadcast_to(centres, (len(qpos), len(radii), 2))
        after = min(t + 1, len(qpos) - 1)  # the pose after the colliding step
        end = qpos[after, e]
        i = int(np.argmin(np.linalg.norm(centres[after] - end[:2], axis=1) - radii))
        first = max(0, t - 20)
        back = qpos[first : t + 1, e]  # [<= 21, 3] the poses up to the colliding step
        seen_at = centres[first : t + 1, i]  # [<= 21, 2] where the cylinder was then
        rel = seen_at - back[:, :2]
        bearing = (np.arctan2(rel[:, 1], rel[:, 0]) - back[:, 2] + math.pi) % (
            2 * math.pi
        ) - math.pi
        camera = back[:, :2] + forward * np.stack([np.cos(back[:, 2]), np.sin(back[:, 2])], -1)
        depth = np.linalg.norm(seen_at - camera, axis=1) - radii[i]
        readable = (np.abs(bearing) < half_fov) & (depth >= range_min)
        seen = np.flatnonzero(readable)
        last = len(back) - 1
        out.append(
            {
                "world": layout.name,
                "episode": int(e % episodes),
                "step": t,
                "bearing_deg": round(math.degrees(bearing[-1]), 1),
                "actions": action[max(0, t - 5) : t + 1, e].tolist(),
                "steps_since_readable": int(last - seen[-1]) if len(seen) else None,
                "sectors": np.round(sectors[t, e], 2).tolist(),
            }
        )
    return out


def tallies(rows: list[dict], names: tuple[str, ...]) -> dict:
    """Counts of the collisions by |bearing| bin, by the colliding step's action and by steps
    since the cylinder was last readable."""
    bearing = np.abs([r["bearing_deg"] for r in rows])
    since = [r["steps_since_readable"] for r in rows]
    seen = np.array([s for s in since if s is not None])
    return {
        "bearing_deg": {
            f"{a}-{b}": int(((bearing >= a) & (bearing < b)).sum())
            for a, b in zip(BEARINGS[:-1], BEARINGS[1:], strict=True)
        },
        "action": {n: sum(r["actions"][-1] == k for r in rows) for k, n in enumerate(names)},
        "steps_since_readable": {
            "0 (readable at contact)": int((seen == 0).sum()),
            **{
                f"{a}-{b - 1}": int(((seen >= a) & (seen < b)).sum())
                for a, b in zip(SINCE[:-1], SINCE[1:], strict=True)
            },
            "not within 20": sum(s is None for s in since),
        },
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", type=Path, required=True, help="a goal run or checkpoint")
    p.add_argument("--episodes", type=int, default=2, help="per world (default 2)")
    p.add_argument("--exact", action="store_true", help="no sim-to-real ranges")
    p.add_argument("--json", type=Path, default=HERE / "results" / "barn_failures.json")
    args = p.parse_args()
    import jaxnav
    from jaxnav.evaluation import load_suite

    policy = jaxnav.load_policy(args.checkpoint)
    layouts = [room for rooms in load_suite("barn").values() for room in rooms]
    rec, env = rollout(policy, layouts, args.episodes, 1000, args.exact)
    rows = collisions(rec, layouts, args.episodes, env)
    episodes = len(layouts) * args.episodes
    names = tuple(getattr(env.action_spec, "names", ()))  # () for continuous actions
    counts = tallies(rows, names)
    write_json(
        args.json,
        {
            **run_info("command", "commit", "dirty", "device", "jax", "date"),
            "checkpoint": str(args.checkpoint),
            "episodes": episodes,
            "exact": args.exact,
            "collided": len(rows),
            "tallies": counts,
            "collisions": rows,
        },
    )
    print(f"{len(rows)} of {episodes} episodes collided ({100 * len(rows) / episodes:.1f} %)")
    for what, table in counts.items():
        print(f"{what:>22}: " + ", ".join(f"{k} {v}" for k, v in table.items()))


if __name__ == "__main__":
    main()
