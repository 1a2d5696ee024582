"""Writes CrowdNav's circle crossing as layouts: people on a circle walking to the opposite point.

    python benchmarks/make_crowdnav.py            # -> scenes/crowdnav/circle_crossing_*.json

The scenario of CrowdNav (Chen, Liu, Kreiss and Alahi 2019, "Crowd-Robot Interaction: Crowd-aware
Robot Navigation with Attention-based Deep Reinforcement Learning", ICRA; github.com/vita-epfl/
CrowdNav, `crowd_sim.py`'s `generate_circle_crossing_human` with its default `env.config`): 5
people of radius 0.3 m and preferred speed 1 m/s, each placed at a uniform angle on a 4 m circle
(plus uniform noise of +-0.5 m per axis) and walking to the point opposite; a person is drawn
again where it would come within its radius + the other's + 0.2 m (CrowdNav's discomfort
distance) of the robot, another person or either's goal. The robot starts at (0, -4) facing +y
and drives to (0, 4). CrowdNav draws its people anew every episode; a layout holds them fixed,
so each file holds `--rooms` rooms drawn from `--seed`, the same people in both files: one where
they give way to the robot (`"reactive": true`) and one where they do not (CrowdNav's "invisible
robot"; they still avoid one another). People stay at their goals (`"repeat": false`), as
CrowdNav's do. CrowdNav has no walls; the room is 12 m square, so the walls stay 1.5 m beyond
anyone's path. CrowdNav's time limit (25 s) and success (the robot's centre within its radius of
the goal) are the evaluation's: `benchmarks/crowdnav.py`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from jaxnav.io.layouts import Cylinder, Motion, RoomLayout, save_layouts

OUT = Path(__file__).resolve().parent.parent / "scenes" / "crowdnav"
PEOPLE = 5
RADIUS = 0.3  # m, CrowdNav's human radius
V_PREF = 1.0  # m/s, CrowdNav's human preferred speed
CIRCLE = 4.0  # m, CrowdNav's circle_radius
DISCOMFORT = 0.2  # m, CrowdNav's discomfort_dist
ROBOT_START, ROBOT_GOAL = (0.0, -CIRCLE), (0.0, CIRCLE)
ROBOT_RADIUS = 0.3  # m, CrowdNav's robot, for the placement rule (the TurtleBot's is smaller)
ROOM = (12.0, 12.0)  # m
HEIGHT = 1.7  # m, a person


def people(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """[PEOPLE] (start [2], goal [2]) drawn as CrowdNav's circle crossing draws them."""
    placed = [(np.array(ROBOT_START), np.array(ROBOT_GOAL), ROBOT_RADIUS)]
    while len(placed) < PEOPLE + 1:
        angle = rng.random() * 2 * np.pi
        noise = (rng.random(2) - 0.5) * V_PREF
        start = CIRCLE * np.array([np.cos(angle), np.sin(angle)]) + noise
        goal = -start
        near = lambda a, b, r: np.linalg.norm(a - b) < RADIUS + r + DISCOMFORT  # noqa: E731
        if not any(near(start, p, r) or near(goal, g, r) for p, g, r in placed):
            placed.append((start, goal, RADIUS))
    return [(s, g) for s, g, _ in placed[1:]]


def room(name: str, crossing, reactive: bool) -> RoomLayout:
    """A circle-crossing room of the people of `crossing` ([(start, goal)])."""
    walkers = tuple(
        Cylinder(
            pos=tuple(np.round(s, 3)),
            radius=RADIUS,
            height=HEIGHT,
            motion=Motion(
                goal=tuple(np.round(g, 3)), speed=V_PREF, reactive=reactive, repeat=False
            ),
        )
        for s, g in crossing
    )
    return RoomLayout(
        name=name,
        size=ROOM,
        robot_pos=ROBOT_START,
        robot_yaw=float(np.pi / 2),
        obstacles=walkers,
        goal_pos=ROBOT_GOAL,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rooms", type=int, default=10, help="rooms (draws of people) per file")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    crossings = [people(rng) for _ in range(args.rooms)]
    args.out.mkdir(parents=True, exist_ok=True)
    for kind, reactive in (("reactive", True), ("nonreactive", False)):
        rooms = [room(f"circle-{kind}-{i}", c, reactive) for i, c in enumerate(crossings)]
        path = args.out / f"circle_crossing_{kind}.json"
        save_layouts(path, rooms)
        print(f"{path}: {len(rooms)} rooms")


if __name__ == "__main__":
    main()
