"""Does an `avoid` policy drive a 25 m hall at speed, seeing what the robot's camera gives it?

Each policy is evaluated (`jaxnav.evaluation.evaluate`, the sim-to-real ranges on) in
`scenes/halls/hall_25m.json` and in the benchmark suite, twice: with the sensor it trained with,
and as on the robot, where the Astra returns 0 beyond 8 m (`far_invalid`) and the robot side reads
such a sector by the policy file's `far_reads_max` (near for a policy trained without it).

    python benchmarks/long_hall.py --runs runs/avoid-cpu runs/avoid-hall \
        --json benchmarks/results/long_hall_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from report import write_json

from jaxnav.core.sensors import SensorConfig
from jaxnav.evaluation import evaluate
from jaxnav.io.layouts import load_layout
from jaxnav.runs import load_policy

HALL = Path(__file__).resolve().parent.parent / "scenes" / "halls" / "hall_25m.json"
KEYS = ("collision_free_rate", "mean_speed")


def on_the_robot(policy):
    """`policy` with the sensor the robot gives it: beyond range is the camera's 0, read by
    the far rule the policy file carries."""
    robot = dataclasses.replace(policy.env_kwargs.get("sensor") or SensorConfig(), far_invalid=True)
    return dataclasses.replace(policy, env_kwargs={**policy.env_kwargs, "sensor": robot})


def _summary(result: dict) -> dict:
    """The collision-free rate and mean speed overall and per family (or room)."""
    rows = result.get("families") or result["layouts"]
    out = {"overall": {k: result["overall"][k] for k in KEYS}}
    out.update({name: {k: m[k] for k in KEYS} for name, m in rows.items()})
    return out


def measure(run: str, episodes: int) -> dict:
    """{sensor: {hall, suite}} of the policy in `run`, as trained and as on the robot."""
    trained = load_policy(run)
    sensor = trained.env_kwargs.get("sensor") or SensorConfig()
    out = {"far_invalid": sensor.far_invalid, "far_reads_max": sensor.far_reads_max}
    variants = {"as_trained": trained}
    if not sensor.far_invalid:  # else the robot's sensor is the trained one
        variants["on_the_robot"] = on_the_robot(trained)
    for name, policy in variants.items():
        hall = evaluate(policy, load_layout(HALL), episodes=episodes)
        suite = evaluate(policy, suite="benchmark", episodes=max(1, episodes // 4))
        out[name] = {"hall_25m": _summary(hall), "suite": _summary(suite)}
        print(run, name, out[name]["hall_25m"]["overall"], out[name]["suite"]["overall"])
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", nargs="+", required=True, help="training run folders")
    parser.add_argument("--episodes", type=int, default=40, help="episodes in the hall")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    result = {"runs": {run: measure(run, args.episodes) for run in args.runs}}
    if args.json:
        write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
