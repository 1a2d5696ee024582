"""jaxnav's PPO and brax's PPO side by side on one task: env-steps/s and wall time to the bar.

    python benchmarks/vs_brax.py --num-envs 256 --steps 98304 --eval-every 4 --episodes 1 \\
        --json benchmarks/results/vs_brax_cpu.json
    python benchmarks/vs_brax.py --preset gpu --num-envs 8192 --steps 104857600 --eval-every 40 \\
        --trainers jaxnav,brax --json benchmarks/results/vs_brax_h200.json

One process trains `avoid` with continuous actions (forward m/s, yaw rad/s) from one seed with
jaxnav's PPO (`jaxnav.ppo.train.make_train`) and with brax's (`brax.training.agents.ppo.train`
on `jaxnav.brax_env.BraxEnv` over the same env): the same training distribution, robots and
env-step budget, and the preset's hyper-parameters for both (`brax_kwargs` maps them one to one).
After every `--eval-every` updates' worth of env steps each greedy policy is judged on the
benchmark suite by `time_to_solve.py`'s evaluator and bar, with the same keys for both. Reported
per trainer: compile s, env-steps/s of training (compile and evaluations excluded), training s and
env steps to the first evaluation that meets the bar, the last evaluation's collision-free rate and
speed, and the trainer's whole wall time (building, compiling and evaluating included).

What still differs, each trainer as its authors wrote it:
- the actor: jaxnav's is a Gaussian clipped to the bounds with a learned log-std; brax's a
  tanh-squashed Gaussian with a learned scale, mapped from [-1, 1] onto the bounds; jaxnav
  initialises layers orthogonally, brax lecun-uniform.
- the time limit: jaxnav bootstraps the value at a truncation, brax leaves those steps out of
  the loss.
- resets: jaxnav's AutoReset draws new episodes for 1/16 of the robots per step, brax's wrappers
  (through the adapter) one per robot per step. `jaxnav-reset-all` is jaxnav's PPO with one draw
  per robot per step (`reset_share` 1): the same env cost as brax's, so the rest is the trainer's.
- brax times its epochs with their compiles: its env-steps/s here are those of its fastest epoch
  after the first, its training s the env steps at that pace, its compile s the rest of its epochs'
  time (the first epoch's compile, and any later one).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time

import jax
from brax.training.agents.ppo import networks as brax_networks
from brax.training.agents.ppo import train as brax_ppo
from report import run_info, write_json
from time_to_solve import (
    BAR,
    greedy_policy,
    judge_policy,
    make_evaluator,
    suite_judge,
    train_to_bar,
)

from jaxnav.brax_env import BraxEnv, to_command
from jaxnav.ppo.train import make_train
from jaxnav.training import build_config, make_run_env

TRAINERS = ("jaxnav", "jaxnav-reset-all", "brax")


def brax_kwargs(ppo) -> dict:
    """brax `ppo.train` arguments equal to jaxnav's PPOConfig `ppo`: per update every robot runs
    `rollout_length` steps, split into minibatches of `minibatch_size` transitions."""
    network = functools.partial(
        brax_networks.make_ppo_networks,
        policy_hidden_layer_sizes=ppo.hidden,
        value_hidden_layer_sizes=ppo.hidden,
        activation=jax.nn.leaky_relu,  # slope 0.01, as jaxnav's
    )
    return dict(
        num_envs=ppo.num_envs,
        unroll_length=ppo.rollout_length,
        batch_size=ppo.minibatch_size // ppo.rollout_length,  # rollouts per minibatch
        num_minibatches=ppo.num_minibatches,
        num_updates_per_batch=ppo.num_epochs,
        learning_rate=ppo.learning_rate,
        entropy_cost=ppo.ent_coef,
        discounting=ppo.gamma,
        gae_lambda=ppo.gae_lambda,
        clipping_epsilon=ppo.clip_eps,
        vf_loss_coefficient=ppo.vf_coef,
        max_grad_norm=ppo.max_grad_norm,
        reward_scaling=ppo.reward_scale,
        normalize_observations=ppo.normalize_obs,
        normalize_advantage=True,  # jaxnav normalises per minibatch too
        network_factory=network,
    )


def run_jaxnav(config, episodes: int, steps: int) -> dict:
    """jaxnav's PPO over the whole budget, judged after every chunk."""
    env = make_run_env(config)
    trainer = make_train(config.ppo, env)
    evaluate, family = make_evaluator(greedy_policy(trainer, config), config, episodes, steps)
    judge_state = suite_judge(evaluate, family)
    compile_s, history, _ = train_to_bar(trainer, config, env, judge_state, float("inf"), full=True)
    rate = history[-1]["env_steps"] / history[-1]["train_s"]
    return {"compile_s": compile_s, "env_steps_per_s": rate, "history": history}


def run_brax(config, episodes: int, steps: int) -> dict:
    """brax's PPO over the whole budget on the adapter, judged after every epoch of
    `updates_per_chunk` updates."""
    env = BraxEnv(make_run_env(config))
    ppo, history, latest = config.ppo, [], {}

    def keep_params(step, make_policy, params):  # brax calls this, then progress_fn
        if "evaluate" not in latest:
            greedy = make_policy  # the inference function is the same object at every call

            def policy(p, obs, key):
                action, _ = greedy(p, deterministic=True)(obs, key)  # the key goes unused
                return to_command(env.env.action_spec, action)

            latest["evaluate"], latest["family"] = make_evaluator(policy, config, episodes, steps)
        latest["params"] = params

    def judge_epoch(step, metrics):
        update = step // ppo.batch_size
        record = {"update": update, "env_steps": step, "train_s": metrics["training/walltime"]}
        key = jax.random.PRNGKey(update)
        evaluate, family = latest["evaluate"], latest["family"]
        history.append(judge_policy(evaluate, family, latest["params"], key, record))

    brax_ppo.train(
        environment=env,
        num_timesteps=ppo.total_steps,
        episode_length=env.episode_length,
        num_evals=ppo.num_updates // ppo.updates_per_chunk + 1,
        run_evals=False,  # judged on the suite instead, in judge_epoch
        seed=config.seed,
        progress_fn=judge_epoch,
        policy_params_fn=keep_params,
        **brax_kwargs(ppo),
    )
    # brax times its epochs with their compiles (the first, and any later one): its pace is its
    # fastest epoch's after the first, its training time the env steps at that pace, the rest
    # of its epochs' time compile.
    walls = [0.0] + [h["train_s"] for h in history]
    steps = [0] + [h["env_steps"] for h in history]
    paces = [(steps[i] - steps[i - 1]) / (walls[i] - walls[i - 1]) for i in range(2, len(walls))]
    rate = max(paces)
    for h in history:
        h["train_s"] = round(h["env_steps"] / rate, 2)
    return {"compile_s": walls[-1] - steps[-1] / rate, "env_steps_per_s": rate, "history": history}


def summary(result: dict, wall_s: float) -> dict:
    """A trainer's row: compile, pace, the first evaluation meeting the bar, the last one."""
    solved = next((h for h in result["history"] if h["solved"]), None)
    final = result["history"][-1]
    return {
        "compile_s": round(result["compile_s"], 1),
        "env_steps_per_s": round(result["env_steps_per_s"]),
        "to_bar_s": None if solved is None else solved["train_s"],
        "to_bar_env_steps": None if solved is None else solved["env_steps"],
        "final_free": round(final["free"], 4),
        "final_speed": round(final["speed"], 4),
        "wall_s": round(wall_s, 1),
        "history": result["history"],
    }


def print_table(rows: dict) -> None:
    print(
        "| trainer | compile s | env-steps/s | to the bar: training s (env steps) | "
        "final collision-free | final speed m/s | wall s |\n|---|---|---|---|---|---|---|"
    )
    for name, r in rows.items():
        bar = (
            f"{r['to_bar_s']:.1f} ({r['to_bar_env_steps']:,})"
            if r["to_bar_s"] is not None
            else "not reached"
        )
        print(
            f"| {name} | {r['compile_s']:.1f} | {r['env_steps_per_s']:,} | {bar} | "
            f"{100 * r['final_free']:.1f} % | {r['final_speed']:.3f} | {r['wall_s']:.0f} |"
        )


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu", help="jaxnav PPO preset: the shared settings")
    parser.add_argument("--num-envs", type=int, help="robots, for both (default: the preset's)")
    parser.add_argument("--steps", type=int, default=98_304, help="env-step budget of each")
    parser.add_argument("--eval-every", type=int, default=10, help="updates between judgements")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per suite room")
    parser.add_argument("--eval-steps", type=int, default=600, help="control steps per episode")
    parser.add_argument("--trainers", default="jaxnav,brax", help=f"of {', '.join(TRAINERS)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json")
    args = parser.parse_args()
    args.trainers = args.trainers.split(",")
    unknown = sorted(set(args.trainers) - set(TRAINERS))
    if unknown:
        parser.error(f"--trainers: unknown {unknown}; valid: {', '.join(TRAINERS)}")
    return args


def make_config(args):
    """The run config both trainers share; the budget is whole judgements, at least two (brax's
    pace is measured after its first)."""
    overrides = {"updates_per_chunk": args.eval_every}
    if args.num_envs:
        overrides["num_envs"] = args.num_envs
    try:
        config = build_config(args.preset, args.seed, None, {"ppo": overrides}, "avoid")
        chunk = args.eval_every * config.ppo.batch_size
        if args.steps < 2 * chunk:
            raise ValueError(f"--steps: need at least two judgements of {chunk:,} env steps")
        ppo = dataclasses.replace(config.ppo, total_steps=args.steps // chunk * chunk)
        task = dataclasses.replace(config.task, actions="continuous")
        return dataclasses.replace(config, ppo=ppo, task=task)
    except ValueError as err:
        raise SystemExit(f"vs_brax: {err}") from None


def main() -> None:
    args = parse_args()
    config = make_config(args)
    rows = {}
    for name in args.trainers:
        print(f"{name}: {config.ppo.total_steps:,} env steps, {config.ppo.num_envs} robots")
        tick = time.perf_counter()
        if name == "brax":
            result = run_brax(config, args.episodes, args.eval_steps)
        else:
            share = 1.0 if name == "jaxnav-reset-all" else config.ppo.reset_share
            ppo = dataclasses.replace(config.ppo, reset_share=share)
            result = run_jaxnav(
                dataclasses.replace(config, ppo=ppo), args.episodes, args.eval_steps
            )
        rows[name] = summary(result, time.perf_counter() - tick)
    print_table(rows)
    out = {
        **run_info("device", "python", "date"),
        "args": {k: v for k, v in vars(args).items() if k != "json"},
        "ppo": dataclasses.asdict(config.ppo),
        "brax_kwargs": {k: v for k, v in brax_kwargs(config.ppo).items() if k != "network_factory"},
        "bar": BAR,
        "trainers": rows,
    }
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
