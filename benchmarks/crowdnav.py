"""A goal policy in CrowdNav's circle crossing, with people who give way and people who do not.

    python benchmarks/crowdnav.py --checkpoint runs/goal-gpu --episodes 50 \\
        --json benchmarks/results/crowdnav_goal.json
    python benchmarks/crowdnav.py --policy forward --episodes 10   # a baseline: straight ahead
    python benchmarks/crowdnav.py --policy stand --episodes 10     # one that never drives

Evaluates as `python -m jaxnav.evaluate --checkpoint RUN --layouts
scenes/crowdnav/circle_crossing_K.json --steps 250` does, for K = reactive and nonreactive (the
rooms of `benchmarks/make_crowdnav.py`: 5 people on a 4 m circle walking to the opposite point,
the robot from (0, -4) to (0, 4)) and reports what CrowdNav reports (Chen et al. 2019,
"Crowd-Robot Interaction", Table I): the shares of episodes that reached the goal (success),
collided (collision) and ran out of CrowdNav's 25 s (timeout; 250 control steps), and the mean
time of the successful ones (time to goal, s; their "navigation time"). Beside them: the
collisions the robot caused, and the episodes in which a non-reactive person ran into the robot
while it stood (`walker_hit`). Success is the goal task's (its centre within `success_radius`,
0.3 m by default: CrowdNav's robot radius). `--action-shares`: also how often a discrete policy
took each of its actions, over the steps of running episodes. `--contacts`: also, for each
collision, the person the robot touched (the nearest after that step), its bearing from the
heading and how many steps before it was last where the camera could read it, tallied as
`benchmarks/barn_failures.py` tallies BARN's cylinders. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from barn_failures import collisions, tallies
from report import run_info, write_json

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes" / "crowdnav"
KINDS = ("reactive", "nonreactive")
STEPS = 250  # CrowdNav's time limit, 25 s, in control steps of 0.1 s
DEFAULT_JSON = Path(__file__).parent / "results" / "crowdnav.json"


def crowdnav_metrics(overall: dict) -> dict:
    """CrowdNav's figures from an evaluation's `overall` metrics (a goal task's)."""
    if "success_rate" not in overall:
        raise SystemExit("crowdnav: the checkpoint is not a goal policy (no success_rate)")
    success = overall["success_rate"]
    collision = 1.0 - overall["collision_free_rate"]
    return {
        "success": success,
        "collision": collision,
        "timeout": max(0.0, 1.0 - success - collision),
        "time_to_goal": overall["time_to_goal"],
        "robot_collision": overall.get("robot_collision_rate", collision),
        "walker_hit": overall.get("walker_hit", 0.0),
        "episodes": overall["episodes"],
    }


def circle_crossing(policy, kind: str, episodes: int, seed: int) -> dict:
    """`crowdnav_metrics` of a goal `Policy` on the circle crossing of `kind`: the evaluation
    `python -m jaxnav.evaluate --layouts scenes/crowdnav/circle_crossing_KIND.json --steps 250`
    runs, in this process."""
    from jaxnav.evaluation import evaluate, success_radius
    from jaxnav.io.layouts import load_layouts

    path = SCENES / f"circle_crossing_{kind}.json"
    layouts = load_layouts([path], success_radius=success_radius(policy))
    result = evaluate(policy, layouts, episodes=episodes, steps=STEPS, seed=seed)
    return crowdnav_metrics(result["overall"])


def people_steps(policy, kind: str, episodes: int, seed: int):
    """Per step [T, E] of the circle crossing of `kind` (the rooms, episodes, time limit and key
    of `circle_crossing`'s evaluation): (pose (x, y, yaw) before it, action, the newest depth
    sectors, whether it collided in a running episode), whether the episode was running, and the
    people's centres [T, E, C, 2]; with the env and the layouts."""
    import jax
    import numpy as np

    from jaxnav.evaluation import eval_randomize, make_eval_env, make_recorder, success_radius
    from jaxnav.io.layouts import load_layouts

    path = SCENES / f"circle_crossing_{kind}.json"
    layouts = load_layouts([path], success_radius=success_radius(policy))
    randomize = eval_randomize("layout", True, None, False)
    env = make_eval_env(policy, layouts, steps=STEPS, randomize=randomize)
    sectors = env.sensor.num_sectors

    def record(state, action, nxt, running):
        hit = (nxt.metrics["collision"] > 0) & running
        step = (state.data.qpos[:, :3], action, state.obs[:, :sectors], hit)
        return step, running, state.info["params"].cyl_pos

    run = make_recorder(env, policy.act, episodes, STEPS, record)
    rec, running, people = jax.tree_util.tree_map(np.asarray, run(jax.random.PRNGKey(seed)))
    return rec, running, people, env, layouts


def action_shares(action, running, names) -> dict:
    """{action name: share of the steps of running episodes} from [T, E] actions."""
    return {n: float(((action == i) & running).sum() / running.sum()) for i, n in enumerate(names)}


def format_table(results: dict) -> str:
    """One row per kind of people: CrowdNav's figures, then the attribution of collisions."""
    head = f"{'people':<12}{'success':>9}{'collision':>11}{'timeout':>9}{'time (s)':>10}"
    head += f"{'robot caused':>14}{'walker hit':>12}"
    lines = [head, "-" * len(head)]
    for kind, m in results.items():
        lines.append(
            f"{kind:<12}{m['success']:>9.0%}{m['collision']:>11.0%}{m['timeout']:>9.0%}"
            f"{m['time_to_goal']:>10.2f}{m['robot_collision']:>14.0%}{m['walker_hit']:>12.0%}"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--checkpoint", help="a goal run folder or a checkpoint in it")
    which.add_argument(
        "--policy", choices=("forward", "random", "stand"), help="a baseline instead"
    )
    parser.add_argument("--episodes", type=int, default=50, help="episodes per room (10 rooms)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=str(DEFAULT_JSON), help="write the results here")
    parser.add_argument(
        "--action-shares", action="store_true", help="also each action's share of the steps"
    )
    parser.add_argument(
        "--contacts",
        action="store_true",
        help="also where the people the robot touched were (benchmarks/barn_failures.py's tallies)",
    )
    args = parser.parse_args()
    import jaxnav
    from jaxnav.evaluation import baseline

    if args.checkpoint:
        policy = jaxnav.load_policy(args.checkpoint)
    else:
        policy = baseline(args.policy, "goal")
    results = {k: circle_crossing(policy, k, args.episodes, args.seed) for k in KINDS}
    print(format_table(results))
    for kind in KINDS if args.action_shares or args.contacts else ():
        rec, running, people, env, layouts = people_steps(policy, kind, args.episodes, args.seed)
        names = tuple(getattr(env.action_spec, "names", ()))  # () for continuous actions
        if args.action_shares and names:
            shares = action_shares(rec[1], running, names)
            results[kind]["action_shares"] = shares
            print(kind, " ".join(f"{n} {v:.1%}" for n, v in shares.items()))
        if args.contacts:
            rows = collisions(rec, layouts, args.episodes, env, moving=people)
            results[kind]["contacts"] = {"collided": len(rows), **tallies(rows, names)}
            print(f"{kind}: {len(rows)} collisions")
            for what, table in results[kind]["contacts"].items():
                if what != "collided":
                    print(f"{what:>22}: " + ", ".join(f"{k} {v}" for k, v in table.items()))
    result = {
        **run_info("device", "python", "jax"),
        "policy": args.checkpoint or args.policy,
        "episodes_per_room": args.episodes,
        "steps": STEPS,
        "seed": args.seed,
        "people": results,
    }
    write_json(args.json, result)
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
