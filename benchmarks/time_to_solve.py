"""Wall seconds until a training run first meets the evaluation bar on the benchmark suite.

    python benchmarks/time_to_solve.py --preset cpu --json benchmarks/results/time_to_solve_cpu.json
    python benchmarks/time_to_solve.py --preset cpu --set sensor.rows=3 --set ppo.learning_rate=3e-4

The bar (issue "Policies that generalise"): over `--episodes` episodes of `--steps` control steps in
every room of `scenes/benchmark/` (rooms nobody trained on) from the room's spawn, under the
sim-to-real physics and sensing of `python -m jaxnav.evaluate`: at least 95 % collision-free overall
and 90 % in every family, a mean speed of at least 0.2 m/s overall and 0.1 m/s in every family. After
every chunk of updates the greedy policy is evaluated on the whole suite in one compiled batch;
training time excludes the evaluations and the compile, which is reported on its own. `--set
GROUP.FIELD=VALUE` overrides any run-config field (`ppo.`, `task.`, `randomize.`, `sensor.`, `scene.`),
the value parsed as JSON where it parses.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from report import run_info, write_json

import jaxnav
from jaxnav.core.goals import ShortestPaths
from jaxnav.core.xla import compiler_options
from jaxnav.evaluation import eval_randomize, load_suite, rollout_program
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.networks import normalize
from jaxnav.ppo.train import make_train
from jaxnav.tasks.goal import spl_from
from jaxnav.training import build_config, find_programs, make_run_env

BAR = {"overall_free": 0.95, "family_free": 0.90, "overall_speed": 0.2, "family_speed": 0.1}


def parse_sets(items: list[str]) -> dict[str, dict]:
    """{group: {field: value}} from GROUP.FIELD=VALUE strings (values as JSON where they parse)."""
    out: dict[str, dict] = {}
    for item in items:
        key, sep, text = item.partition("=")
        group, dot, field = key.partition(".")
        if not (sep and dot):
            raise SystemExit(f"--set: expected GROUP.FIELD=VALUE, got {item!r}")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out.setdefault(group, {})[field] = tuple(value) if isinstance(value, list) else value
    return out


def greedy_policy(trainer, config, sample: bool = False):
    """policy((params, obs_stats), obs [E, D], key) -> actions [E, ...]: a jaxnav PPO network's
    greedy action (argmax of the logits, or the Gaussian's mean clipped to the bounds), or with
    `sample` one drawn from its distribution."""
    dist = make_distribution(config.task.action_spec)

    def policy(policy_params, obs, key):
        params, stats = policy_params
        obs = normalize(stats, obs) if config.ppo.normalize_obs else obs
        out = trainer.network.apply(params, obs)[0]
        return dist.sample(key, out) if sample else dist.mode(out)

    return policy


def make_evaluator(policy, config, episodes: int, steps: int):
    """(evaluate, family [E]): `evaluate(policy_params, key)` runs `episodes` episodes of `steps`
    control steps in every suite room in one compiled batch, for any `policy(policy_params,
    obs [E, D], key) -> actions [E, ...]` of the run's task, and returns per-episode numpy arrays
    [E]: `collided`, `speed` (m/s) and, for a goal task (one with a `success` metric), `success`
    and `spl` (`jaxnav.tasks.goal.spl_from`, the shortest paths of `ShortestPaths` built once per
    room, less the success radius). `family` names each episode's room family."""
    suite = load_suite("benchmark")
    layouts = [room for rooms in suite.values() for room in rooms]
    family = np.repeat([f for f, rooms in suite.items() for _ in rooms], episodes)
    kwargs = {**config.env_kwargs(), "randomize": eval_randomize("layout"), "max_steps": steps}
    env = jaxnav.make_env(config.env, layouts, **kwargs)
    period = env.control_period
    paths = [ShortestPaths(room) for room in layouts] if "success" in env.metric_names else None

    def rollout(policy_params, key):
        act = lambda obs, k: policy(policy_params, obs, k)  # noqa: E731
        track, _ = rollout_program(env, act, episodes, steps, keep=1, pinned=True)(key)
        return track, track.distance / (jnp.maximum(track.steps, 1) * period)

    rollout = jax.jit(rollout, compiler_options=compiler_options())

    def evaluate(policy_params, key) -> dict:
        track, speed = jax.device_get(rollout(policy_params, key))
        out = {"collided": track.collided, "speed": speed}
        if paths is not None:
            out["success"] = track.metrics["success"] > 0
            out["spl"] = suite_spl(paths, track, out["success"], env.task.success_radius)
        return out

    return evaluate, family


def suite_spl(paths, track, success: np.ndarray, success_radius: float) -> np.ndarray:
    """[E] SPL per episode of a pinned rollout's `track` (rooms in order, the same number of
    episodes in each), from each room's `ShortestPaths` less the success radius."""
    episodes = len(success) // len(paths)
    spl = np.zeros(len(success))
    for r, shortest in enumerate(paths):
        e = slice(r * episodes, (r + 1) * episodes)
        reach = shortest(track.start[e], track.goal[e]) - success_radius
        room = {"metrics": {"success": success[e]}, "distance": track.distance[e]}
        spl[e] = spl_from(reach, room)
    return spl


def judge(collided: np.ndarray, speed: np.ndarray, family: np.ndarray) -> dict:
    """Collision-free rate and mean speed overall and per family, and whether they meet BAR."""
    per = {
        f: {
            "free": float(1 - collided[family == f].mean()),
            "speed": float(speed[family == f].mean()),
        }
        for f in dict.fromkeys(family)
    }
    out = {"free": float(1 - collided.mean()), "speed": float(speed.mean()), "families": per}
    out["solved"] = bool(
        out["free"] >= BAR["overall_free"]
        and out["speed"] >= BAR["overall_speed"]
        and all(v["free"] >= BAR["family_free"] for v in per.values())
        and all(v["speed"] >= BAR["family_speed"] for v in per.values())
    )
    return out


def train_to_bar(trainer, config, env, judge_state, max_seconds: float, full=False, every: int = 1):
    """Trains in chunks of `updates_per_chunk` updates of `trainer` (on `config`'s `env`; its
    programs traced and compiled at once first, as a run's, and init run: the compile's seconds),
    calling `judge_state(ts, metrics, record) -> (entry, met)` after every `every` chunks and
    after the last, until the bar is met (or, `full`, the budget is spent) or `max_seconds` of
    training. `record` holds update, env_steps and train_s; `metrics` are the last chunk's.
    Returns (compile s, history: the entries, the first entry that met the bar or None)."""
    key = jax.random.PRNGKey(config.seed)
    tick = time.perf_counter()  # the programs compiled at once, as a run's: apart from training
    trainer, _, ahead = find_programs(trainer, config, env, key)
    ts = jax.block_until_ready(trainer.init(key))
    for program in trainer.programs.values() if ahead else ():
        program.wait()
    compile_s = time.perf_counter() - tick
    run_chunk = trainer.run_chunk
    train_s, history, solved, chunk = 0.0, [], None, 0
    while int(ts.update) < config.ppo.num_updates and train_s < max_seconds:
        tick = time.perf_counter()
        ts, metrics = jax.block_until_ready(run_chunk(ts))
        train_s += time.perf_counter() - tick
        chunk += 1
        last = int(ts.update) >= config.ppo.num_updates or train_s >= max_seconds
        if chunk % every and not last:
            continue
        steps = int(ts.update) * config.ppo.batch_size
        record = {"update": int(ts.update), "env_steps": steps, "train_s": round(train_s, 2)}
        entry, met = judge_state(ts, metrics, record)
        history.append(entry)
        if met and solved is None:
            solved = entry
            if not full:
                break
    return compile_s, history, solved


def suite_judge(evaluate, family):
    """`train_to_bar`'s judge_state: the suite's judgement of the training state's policy (`BAR`)."""

    def judge_state(ts, metrics, record):
        key = jax.random.PRNGKey(record["update"])
        result = judge_policy(evaluate, family, (ts.params, ts.obs_stats), key, record)
        return result, result["solved"]

    return judge_state


def judge_policy(evaluate, family, policy_params, key, record: dict) -> dict:
    """`record` (env_steps, train_s, ...) with the suite's judgement of the policy, printed."""
    out = evaluate(policy_params, key)
    result = {**record, **judge(out["collided"], out["speed"], family)}
    worst = min(result["families"].items(), key=lambda kv: kv[1]["free"])
    print(
        f"{record['env_steps']:>12,} steps {record['train_s']:7.1f} s  free {result['free']:.3f}  "
        f"speed {result['speed']:.3f}  worst {worst[0]} {worst[1]['free']:.2f}",
        flush=True,
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--env", default="avoid")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="GROUP.FIELD=VALUE")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per suite room")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--eval-every", type=int, default=10, help="updates between evaluations")
    parser.add_argument("--max-seconds", type=float, default=1200.0)
    parser.add_argument(
        "--full", action="store_true", help="train the whole budget, not to the bar"
    )
    parser.add_argument("--json")
    args = parser.parse_args()
    sets = parse_sets(args.set)
    sets.setdefault("ppo", {})["updates_per_chunk"] = args.eval_every
    config = build_config(args.preset, args.seed, None, sets, args.env)
    env = make_run_env(config)
    trainer = make_train(config.ppo, env)
    evaluate, family = make_evaluator(
        greedy_policy(trainer, config), config, args.episodes, args.steps
    )
    judge_state = suite_judge(evaluate, family)
    compile_s, history, solved = train_to_bar(
        trainer, config, env, judge_state, args.max_seconds, args.full
    )
    out = {
        **run_info("device", "python", "date"),
        "preset": args.preset,
        "sets": args.set,
        "num_envs": config.ppo.num_envs,
        "compile_s": round(compile_s, 1),
        "bar": BAR,
        "solved": solved,
        "history": history,
    }
    print(
        f"solved at {solved['train_s']} s wall ({solved['env_steps']:,} env steps), "
        f"compile {compile_s:.0f} s"
        if solved
        else f"not solved within the budget (compile {compile_s:.0f} s)"
    )
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
