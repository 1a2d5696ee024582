"""Single-observation policy latency on one CPU core: numpy, onnxruntime and jitted JAX.

    python benchmarks/latency.py --json benchmarks/latency.json
    python benchmarks/latency.py --checkpoint runs/avoid-cpu --calls 50000
    python benchmarks/latency.py --env goal --preset gpu   # 221 inputs, 2 x 256 units

What the robot does every control step: one observation (numpy float32; [8] for `avoid`, [221] for
`goal`: 17 frames of sectors, goal and last command) in, one action (a Python int) out. Each call
is timed on its own (perf_counter_ns) and the median, p90 and p99 are reported.
Everything runs single-threaded (OMP_NUM_THREADS=1, onnxruntime with one intra-/inter-op thread, XLA
without its thread pool) and the process is pinned to one core (`--core`). Without --checkpoint a
freshly initialised network of the task's size on `--preset` is used (`--env`, `--preset`):
latency does not depend on the weights.
"""

from __future__ import annotations

import os

# Before numpy/jax are imported: their thread pools size themselves at import.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "")
    + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import argparse  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from report import run_info, write_json  # noqa: E402

TARGET_US = 20.0  # numpy policy budget per action


def time_calls(fn, obs: np.ndarray, calls: int, warmup: int = 1000) -> dict:
    """Median / p90 / p99 microseconds of fn(one observation) over `calls` timed calls."""
    for i in range(warmup):
        fn(obs[i % len(obs)])
    times = np.empty(calls)
    clock = time.perf_counter_ns
    for i in range(calls):
        o = obs[i % len(obs)]
        start = clock()
        fn(o)
        times[i] = clock() - start
    us = times / 1000.0
    return {
        "median_us": round(float(np.median(us)), 2),
        "p90_us": round(float(np.percentile(us, 90)), 2),
        "p99_us": round(float(np.percentile(us, 99)), 2),
        "calls": calls,
    }


def fresh_run(root: Path, env: str, preset: str) -> Path:
    """A run folder holding a freshly initialised network of task `env` on `preset`."""
    import jax
    import jax.numpy as jnp

    from jaxnav.io import checkpoint
    from jaxnav.ppo.networks import init_stats
    from jaxnav.ppo.train import TrainState, make_network
    from jaxnav.tasks.base import observation_size
    from jaxnav.tasks.registry import critic_size
    from jaxnav.training import build_config

    config = build_config(preset, env=env)
    size = observation_size(config.task, config.sensor)
    critic = critic_size(config.task, config.ppo.privileged_critic)
    init = jax.jit(make_network(config.ppo, config.task.action_spec, critic).init)
    params = init(jax.random.PRNGKey(0), jnp.zeros((1, size)))
    ts = TrainState(params, (), init_stats(size), (), jax.random.PRNGKey(1), jnp.int32(0))
    checkpoint.save(root, ts, config, {})
    return root


def backends(run: Path, tmp: Path) -> dict:
    """{name: fn(obs [D] float32) -> int action} of every backend that is installed."""
    import jax

    import jaxnav
    from jaxnav.export import export
    from jaxnav.robot_side.policy import NumpyPolicy

    fns = {"numpy": NumpyPolicy.from_npz(export(run, "numpy", tmp / "policy.npz"))}
    try:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        path = str(export(run, "onnx", tmp / "policy.onnx"))
        session = ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
        fns["onnxruntime"] = lambda o: int(session.run(["action"], {"obs": o[None]})[0][0])
    except ImportError:
        print("onnxruntime (or onnx) not installed: skipped")
    act, key = jax.jit(jaxnav.load_policy(run).act), jax.random.PRNGKey(0)
    fns["jax (jit)"] = lambda o: int(act(o, key))
    return fns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, help="run or checkpoint folder (default: fresh)")
    parser.add_argument("--calls", type=int, default=20000, help="timed calls per backend")
    parser.add_argument("--core", type=int, default=0, help="CPU core to pin to (-1: no pinning)")
    parser.add_argument("--env", default="avoid", help="the task of a fresh network")
    parser.add_argument("--preset", default="cpu", help="the preset of a fresh network")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    if args.core >= 0 and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.core})
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run = args.checkpoint or fresh_run(tmp / "run", args.env, args.preset)
        fns = backends(run, tmp)
        policy = fns["numpy"]  # the observation the policy was trained on
        sensor, size = policy.sensor, policy.observation_size
        rng = np.random.default_rng(0)
        obs = rng.uniform(sensor.range_min, sensor.range_max, (256, size)).astype(np.float32)
        actions = {name: [fn(o) for o in obs] for name, fn in fns.items()}
        assert all(a == actions["numpy"] for a in actions.values()), "backends disagree"
        results = {name: time_calls(fn, obs, args.calls) for name, fn in fns.items()}
    print(f"\nsingle-observation latency, 1 thread, {platform.processor() or platform.machine()}")
    print(f"{'backend':<14}{'median µs':>11}{'p90 µs':>9}{'p99 µs':>9}{'actions/s':>11}")
    for name, r in results.items():
        rate = 1e6 / r["median_us"]
        print(
            f"{name:<14}{r['median_us']:>11.2f}{r['p90_us']:>9.2f}{r['p99_us']:>9.2f}{rate:>11,.0f}"
        )
    ok = results["numpy"]["median_us"] <= TARGET_US
    print(f"numpy target <= {TARGET_US:.0f} µs/action: {'met' if ok else 'MISSED'}")
    if args.json:
        report = {
            "machine": platform.platform(),
            **run_info("python"),
            "pinned_core": args.core,
            "checkpoint": str(args.checkpoint) if args.checkpoint else "fresh (untrained)",
            "env": args.env if not args.checkpoint else None,
            "preset": args.preset if not args.checkpoint else None,
            "observation_size": size,
            "target_us": TARGET_US,
            "results": results,
        }
        write_json(args.json, report)


if __name__ == "__main__":
    main()
