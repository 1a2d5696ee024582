"""Wall seconds until a training run first meets the evaluation bar on the inference room.

    python benchmarks/time_to_solve.py --preset cpu --json benchmarks/time_to_solve_cpu.json

The bar: over `--episodes` episodes of `--steps` control steps from the layout's spawn, at least 95 %
collision-free and a mean speed of at least 50 % of the forward speed. After every chunk of updates the
greedy policy is evaluated; training time excludes the evaluations and the compile, which is reported
on its own.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxnav
from jaxnav.core.scene import SCENES_DIR
from jaxnav.evaluate import eval_randomize, make_rollout
from jaxnav.ppo.config import preset
from jaxnav.ppo.networks import normalize
from jaxnav.ppo.train import make_train


def make_evaluator(trainer, cfg, episodes, steps):
    """jit((params, obs_stats, key) -> (collision-free rate, mean speed m/s))."""
    layouts = jaxnav.load_layout(SCENES_DIR / "inference_room.json")
    env = jaxnav.make_env("avoid", layouts, randomize=eval_randomize("layout"), max_steps=steps)
    period = env.control_period

    @jax.jit
    def evaluate(params, stats, key):
        def act(obs, _):
            obs = normalize(stats, obs) if cfg.normalize_obs else obs
            return jnp.argmax(trainer.network.apply(params, obs)[0], axis=-1)

        track, _ = make_rollout(env, act, episodes, steps, keep=1)(key)
        speed = track.distance / (jnp.maximum(track.steps, 1) * period)
        return 1.0 - track.collided.mean(), speed.mean()

    return evaluate, env.task.forward_speed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--num-envs", type=int)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--updates-per-chunk", type=int, default=10)
    parser.add_argument("--max-seconds", type=float, default=1200.0)
    parser.add_argument("--json")
    args = parser.parse_args()
    overrides = {"updates_per_chunk": args.updates_per_chunk}
    if args.num_envs:
        overrides["num_envs"] = args.num_envs
    cfg = preset(args.preset, **overrides)
    trainer = make_train(cfg, jaxnav.make_env("avoid"))
    evaluate, forward_speed = make_evaluator(trainer, cfg, args.episodes, args.steps)
    ts = jax.block_until_ready(trainer.init(jax.random.PRNGKey(args.seed)))
    tick = time.perf_counter()
    run_chunk = trainer.run_chunk.lower(ts).compile()  # compile apart from the timed training
    compile_s = time.perf_counter() - tick
    train_s, history, solved = 0.0, [], None
    while True:
        tick = time.perf_counter()
        ts, _ = jax.block_until_ready(run_chunk(ts))
        train_s += time.perf_counter() - tick
        free, speed = map(
            float, evaluate(ts.params, ts.obs_stats, jax.random.PRNGKey(int(ts.update)))
        )
        steps = int(ts.update) * cfg.batch_size
        history.append(
            {
                "update": int(ts.update),
                "env_steps": steps,
                "train_s": round(train_s, 2),
                "collision_free_rate": free,
                "mean_speed": speed,
            }
        )
        print(json.dumps(history[-1]), flush=True)
        if free >= 0.95 and speed >= 0.5 * forward_speed:
            solved = history[-1]
            break
        if int(ts.update) >= cfg.num_updates or train_s > args.max_seconds:
            break
    device = jax.devices()[0]
    result = {
        "device": f"{device.platform}: {device.device_kind}",
        "preset": args.preset,
        "num_envs": cfg.num_envs,
        "compile_s": round(compile_s, 1),
        "solved": solved,
        "history": history,
    }
    print(
        f"solved at {solved['train_s']} s wall ({solved['env_steps']:,} env steps)"
        if solved
        else "not solved within the budget"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
