"""One minibatch's PPO gradient on one GPU: XLA's kernels of `jax.grad(ppo_loss)` against the
fused kernel (`jaxnav.ppo.fused`) at each of its program shapes, and how far the two gradients are
apart.

    python benchmarks/learner.py --minibatches 524288,16384 --rows 32,64 --warps 2,4 \\
        --json benchmarks/results/learner_h200.json

The `avoid` task's network (its 8 inputs, the cpu preset's 2 x 64 LeakyReLU layers, 3 actions)
and random transitions, the parameters moved off their initial values so the ratios spread over
the clip. 524,288 rows are a minibatch of `benchmarks/throughput.py` at 65,536 robots, 16,384 the
gpu preset's. Each time is the best of `--repeats` jitted calls after a compile
(`throughput.timed`); `rel_err` is the largest difference of any gradient entry against XLA's,
relative to that weight's largest entry (both multiply in the GPU's TF32 by default).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from report import run_info, write_json
from throughput import timed

import jaxnav
from jaxnav.ppo import fused
from jaxnav.ppo.config import preset
from jaxnav.ppo.distributions import make_distribution
from jaxnav.ppo.losses import Batch
from jaxnav.ppo.train import loss_grad, make_network


def problem(rows: int, seed: int = 0):
    """(cfg, network, dist, params, batch) for a minibatch of `rows` random transitions."""
    env = jaxnav.make_env("avoid")
    cfg = preset("cpu", num_envs=rows // 32, minibatch_size=rows)
    dist = make_distribution(env.action_spec)
    net = make_network(cfg, env.action_spec)
    k = jax.random.split(jax.random.PRNGKey(seed), 8)
    obs = jax.random.normal(k[0], (rows, env.observation_size))
    params = net.init(k[1], obs[:1])
    params = jax.tree_util.tree_map(lambda p: p + 0.3 * jax.random.normal(k[2], p.shape), params)
    logits, value = net.apply(params, obs)
    action = jax.random.randint(k[3], (rows,), 0, dist.out_size)
    noise = lambda key: 0.3 * jax.random.normal(key, (rows,))  # noqa: E731
    batch = Batch(
        (obs, None),
        action,
        dist.log_prob(logits, action) + noise(k[4]),
        value + noise(k[5]),
        jax.random.normal(k[6], (rows,)),
        jax.random.normal(k[7], (rows,)),
    )
    return cfg, net, dist, env.observation_size, params, batch


def rel_err(ref, got) -> float:
    """The largest |ref - got| of any leaf, relative to that leaf's largest |ref|."""
    errs = jax.tree_util.tree_map(
        lambda a, b: float(jnp.abs(a - b).max() / (jnp.abs(a).max() + 1e-12)), ref, got
    )
    return max(jax.tree_util.tree_leaves(errs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minibatches", default="524288,16384", help="comma-separated rows")
    parser.add_argument("--rows", default=str(fused.ROWS), help="rows per program, comma-separated")
    parser.add_argument("--warps", default=str(fused.WARPS), help="warps per program")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    result = {**run_info("device", "python", "date", "jax"), "rows": []}
    print(f"{'minibatch':>10} {'gradient':>16} {'ms':>8} {'rel_err':>8}")
    for m in (int(x) for x in args.minibatches.split(",")):
        cfg, net, dist, d, params, batch = problem(m)
        xla = jax.jit(loss_grad(cfg, net, dist))
        ref = xla(params, batch)[0]
        runs = [("xla", None, None, xla)]
        for rows in (int(x) for x in args.rows.split(",")):
            for warps in (int(x) for x in args.warps.split(",")):
                fused.ROWS, fused.WARPS = rows, warps
                grad = fused.make(cfg, net, dist, jax.devices(), (d, d))
                if grad is not None:  # compiled now, with this program shape
                    fn = jax.jit(grad).lower(params, batch).compile()
                    runs.append((f"fused {rows} rows", rows, warps, fn))
        for name, rows, warps, fn in runs:
            _, best = timed(fn, params, batch, repeats=args.repeats)
            err = rel_err(ref, fn(params, batch)[0])
            row = {"minibatch": m, "gradient": "xla" if rows is None else "fused"}
            row.update({"rows": rows, "warps": warps, "ms": round(1e3 * best, 3), "rel_err": err})
            result["rows"].append(row)
            label = name if warps is None else f"{name}, {warps} w"
            print(f"{m:>10} {label:>16} {row['ms']:>8.3f} {err:>8.1e}", flush=True)
        if args.json:
            write_json(args.json, result)


if __name__ == "__main__":
    main()
