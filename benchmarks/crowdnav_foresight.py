"""What a robot of the goal task's speeds could do in CrowdNav's circle crossing if it knew where
every person will walk (a ceiling for any policy), and what waiting alone does.

    python benchmarks/crowdnav_foresight.py --forward-speed 0.5 --blind-waits 0,2,4,6,8 \\
        --json benchmarks/results/crowdnav_foresight_cpu.json
    python benchmarks/crowdnav_foresight.py --forward-speed 0.7 --blind-waits 0,2,4,6,8 \\
        --json benchmarks/results/crowdnav_foresight_fast_cpu.json     # the people recipe's speed

Non-reactive people walk the same way whatever the robot does, so a plan that reaches the goal in
one run of a room does in every run with exact physics. Each plan waits at the start for W s
(the (0, 0) command), then drives to a waypoint and on to the goal, turning towards its target
and driving at `--forward-speed` once it heads within 0.3 rad of it (the continuous commands of
`--task.actions continuous`, within the goal task's speeds); the waypoints lie on a grid around
the straight way (none: straight to the goal). Every room's plans run in one batch of the
circle-crossing rooms (`scenes/crowdnav/`, `benchmarks/make_crowdnav.py`) with the evaluation's
time limit (25 s) and success (within 0.3 m), in exact physics, or, `--stochastic`, with the
robot as it really is (the evaluation's sim-to-real draws, one per plan). Reports per room and
kind of people whether some plan succeeds, the share of plans that do, the least wait of a
successful one and of a successful straight drive (for reactive people, who give way to the
robot, the same plans). Then the blind plans: stand W s (each of `--blind-waits`), then drive
straight whatever the camera reads, `--episodes` episodes a room with the evaluation's
stochastic robot, scored as CrowdNav scores (success, collision, timeout). Prints a table and
writes JSON.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from crowdnav import KINDS, SCENES, STEPS
from report import run_info, write_json

DEFAULT_JSON = Path(__file__).parent / "results" / "crowdnav_foresight_cpu.json"
WAITS = np.arange(0.0, 10.01, 0.5)  # s waited at the start
WAYPOINTS_X = (-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)  # m off the straight way, at...
WAYPOINTS_Y = (-2.0, 0.0, 2.0)  # ... these points along it (the way runs -4 -> 4)
HEADING_TOLERANCE = 0.3  # rad off the target's bearing within which the robot drives
YAW_GAIN = 3.0  # 1/s: the yaw rate per radian of bearing, clipped to the turn rate
ARRIVED = 0.2  # m from the waypoint at which the robot heads for the goal


def plans() -> tuple[np.ndarray, np.ndarray]:
    """[P] waits (s) and [P, 2] waypoints (NaN: none), every wait with every waypoint."""
    points = [(np.nan, np.nan)] + [(x, y) for y in WAYPOINTS_Y for x in WAYPOINTS_X]
    waits = np.repeat(WAITS, len(points))
    return waits, np.tile(np.asarray(points), (len(WAITS), 1))


def make_run(env, waits, points):
    """A jitted `run(key) -> (success, collision, walker_hit)` [R * P] of every plan in every room
    (episode e: room e // P, plan e % P) of `env`, a goal task with continuous commands, whose
    bounds are the plans' top speed and turn rate."""
    import jax
    import jax.numpy as jnp

    from jaxnav.core.xla import compiler_options
    from jaxnav.evaluation import first_state

    n, period = len(waits), env.control_period
    forward, turn = env.action_spec.high  # m/s, rad/s
    step = jax.vmap(env.step)

    def act(state, via, t):
        pose = state.data.qpos[:, :3]  # [E, 3] x, y, yaw
        goal = state.info["goal"]  # [E, 2]
        target = jnp.where(via[:, None], points_e, goal)
        d = target - pose[:, :2]
        bearing = jnp.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]
        bearing = jnp.arctan2(jnp.sin(bearing), jnp.cos(bearing))
        yaw = jnp.clip(YAW_GAIN * bearing, -turn, turn)
        ahead = jnp.where(jnp.abs(bearing) < HEADING_TOLERANCE, forward, 0.0)
        go = t * period >= waits_e
        command = jnp.stack([jnp.where(go, ahead, 0.0), jnp.where(go, yaw, 0.0)], -1)
        near = jnp.linalg.norm(points_e - pose[:, :2], axis=-1) < ARRIVED
        return command, via & ~near

    def body(carry, t):
        state, via, done, out = carry
        command, via = act(state, via, t)
        nxt = step(state, command)
        m = nxt.metrics
        hit = jnp.stack([m["success"], m["collision"], m["walker_hit"]], -1) > 0
        out = out | (hit & ~done[:, None])
        return (nxt, via, done | nxt.done, out), None

    rooms = env.bank.size
    waits_e = jnp.tile(jnp.asarray(waits, jnp.float32), rooms)
    points_np = np.tile(points, (rooms, 1))
    points_e = jnp.asarray(np.nan_to_num(points_np), jnp.float32)
    via0 = jnp.asarray(~np.isnan(points_np[:, 0]))

    def run(key):
        state = first_state(env, key, n, True)
        e = state.done.shape[0]
        carry = (state, via0, jnp.zeros(e, bool), jnp.zeros((e, 3), bool))
        (_, _, _, out), _ = jax.lax.scan(body, carry, jnp.arange(STEPS))
        return out[:, 0], out[:, 1], out[:, 2]

    return jax.jit(run, compiler_options=compiler_options())


def room_rows(success, collision, walker_hit, waits, points, names) -> list[dict]:
    """Per room: whether a plan succeeds, their share, the least wait of a successful plan, of a
    successful straight drive (no waypoint), and which waits a straight drive succeeds after."""
    p = len(waits)
    straight = np.isnan(points[:, 0])
    rows = []
    for r, name in enumerate(names):
        s, c, w = (x[r * p : (r + 1) * p] for x in (success, collision, walker_hit))
        rows.append(
            {
                "room": name,
                "solved": bool(s.any()),
                "plans_succeeding": float(s.mean()),
                "plans_colliding": float(c.mean()),
                "plans_walker_hit": float(w.mean()),
                "least_wait_s": float(waits[s].min()) if s.any() else None,
                "straight_wait_s": float(waits[s & straight].min())
                if (s & straight).any()
                else None,
                "straight_waits_ok": [float(x) for x in waits[s & straight]],
            }
        )
    return rows


def summary(rows: list[dict]) -> dict:
    """Over the rooms: the shares solved by some plan, by a straight drive after some wait, and
    without waiting; the waits after which a straight drive succeeds in every room."""
    every = set.intersection(*(set(r["straight_waits_ok"]) for r in rows))
    return {
        "rooms_solved": float(np.mean([r["solved"] for r in rows])),
        "rooms_solved_straight": float(np.mean([r["straight_wait_s"] is not None for r in rows])),
        "rooms_solved_without_waiting": float(np.mean([r["least_wait_s"] == 0.0 for r in rows])),
        "straight_waits_ok_everywhere": sorted(every),
    }


def blind(run, waits_s, episodes: int, key) -> dict:
    """{wait: CrowdNav's success, collision and timeout shares} of the plan that stands `wait` s
    and then drives straight to the goal, whatever the camera reads, over `episodes` episodes
    a room (`run`: `make_run` of those plans)."""
    success, collision, _ = (np.asarray(x) for x in run(key))
    out = {}
    for i, wait in enumerate(waits_s):
        s = success.reshape(-1, len(waits_s), episodes)[:, i]  # [R, episodes]
        c = collision.reshape(-1, len(waits_s), episodes)[:, i]
        out[f"{wait:g}"] = {
            "success": float(s.mean()),
            "collision": float(c.mean()),
            "timeout": max(0.0, float(1 - s.mean() - c.mean())),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--forward-speed", type=float, default=0.5, help="m/s (the goal task's)")
    parser.add_argument("--turn-rate", type=float, default=1.5, help="rad/s (the goal task's)")
    parser.add_argument("--stochastic", action="store_true", help="the plans' robot as it is")
    parser.add_argument(
        "--blind-waits", default="0,4,8", help="s: the blind plans' waits (comma-separated)"
    )
    parser.add_argument("--episodes", type=int, default=50, help="a blind plan's episodes a room")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=str(DEFAULT_JSON), help="write the results here")
    args = parser.parse_args()
    import jax

    from jaxnav import make_env
    from jaxnav.evaluation import eval_randomize
    from jaxnav.io.layouts import load_layouts
    from jaxnav.tasks.goal import GoalConfig

    waits, points = plans()
    blind_waits = [float(w) for w in args.blind_waits.split(",")]
    blind_plans = (
        np.repeat(blind_waits, args.episodes),
        np.full((len(blind_waits) * args.episodes, 2), np.nan),
    )
    task = GoalConfig(
        actions="continuous",
        forward_speed=args.forward_speed,
        turn_rate=args.turn_rate,
        max_steps=STEPS,
    )
    key = jax.random.PRNGKey(args.seed)
    results = {}
    for kind in KINDS:
        layouts = load_layouts([SCENES / f"circle_crossing_{kind}.json"], success_radius=0.3)
        env = make_env(
            "goal", layouts=layouts, task=task, randomize=eval_randomize("layout", args.stochastic)
        )
        start = time.perf_counter()
        out = [np.asarray(x) for x in make_run(env, waits, points)(key)]
        seconds = time.perf_counter() - start
        rows = room_rows(*out, waits, points, [lay.name for lay in layouts])
        if not args.stochastic:  # the blind plans run with the evaluation's stochastic robot
            env = make_env("goal", layouts=layouts, task=task, randomize=eval_randomize("layout"))
        run = make_run(env, *blind_plans)
        results[kind] = {
            **summary(rows),
            "plans_succeeding": float(out[0].mean()),
            "seconds": seconds,
            "blind": blind(run, blind_waits, args.episodes, key),
            "rooms": rows,
        }
    print(format_table(results))
    info = run_info("command", "commit", "dirty", "date", "device", "python", "jax")
    write_json(args.json, {**info, "plans_per_room": len(waits), **vars(args), "kinds": results})


def format_table(results: dict) -> str:
    """Per kind of people: the rooms solved by some plan, by a straight drive after a wait and
    without waiting, the plans' share that succeed, the least wait after which a straight drive
    succeeds in every room, and per room the least such wait; then the blind plans' shares."""
    head = f"{'people':<12}{'solved':>8}{'straight':>10}{'no wait':>9}{'plans ok':>10}"
    lines = [head + "  one wait for all (s)  straight: least wait per room (s)"]
    for kind, r in results.items():
        every = r["straight_waits_ok_everywhere"]
        one = f"{every[0]:g}" if every else "none"
        waits = " ".join(
            "-" if x["straight_wait_s"] is None else f"{x['straight_wait_s']:g}" for x in r["rooms"]
        )
        lines.append(
            f"{kind:<12}{r['rooms_solved']:>8.0%}{r['rooms_solved_straight']:>10.0%}"
            f"{r['rooms_solved_without_waiting']:>9.0%}{r['plans_succeeding']:>10.1%}"
            f"  {one:>20}  {waits}"
        )
    lines.append(
        f"\n{'people':<12}{'blind: wait (s)':>16}{'success':>9}{'collision':>11}{'timeout':>9}"
    )
    for kind, r in results.items():
        for wait, m in r["blind"].items():
            lines.append(
                f"{kind:<12}{wait:>16}{m['success']:>9.0%}{m['collision']:>11.0%}{m['timeout']:>9.0%}"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
