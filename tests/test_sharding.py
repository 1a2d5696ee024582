"""The robots are sharded over every local device; results match the single-device run."""

import concurrent.futures
import gzip
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import benchmark_script, cpu_env

from jaxnav.core import xla
from jaxnav.core.types import EnvState
from jaxnav.ppo.config import preset
from jaxnav.ppo.train import block_count, shard_envs
from jaxnav.wrappers import AutoReset

SCRIPTS = Path(__file__).parent / "scripts"


def run_script(name: str, out: Path, devices: int = 2) -> Path:
    """OUT, written by `python tests/scripts/NAME OUT` on `devices` forced host devices."""
    proc = subprocess.run(
        [sys.executable, str(SCRIPTS / name), str(out)],
        env=cpu_env(devices),  # compile-bound: quicker compiles, the same on both sides
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


def train_on(devices: int, out: Path) -> dict:
    return dict(np.load(run_script("tiny_train.py", out, devices)))


@pytest.mark.slow
def test_two_devices_match_one(tmp_path):
    """Training sharded over two devices, as a run trains (init from the draws' and start's
    programs, then a chunk of the draws', rollout's and learner's), gives the one-device result,
    and no op of the programs an env step runs in waits for the other device (no collective in
    the compiled rollout or draws: a branch on all robots, as the in-place auto-reset has, would
    put one in every env step); compiled at their first calls or all at once before any has run.
    Slow: two training processes (a device count is fixed per process)."""
    one = train_on(1, tmp_path / "one.npz")
    two = train_on(2, tmp_path / "two.npz")
    assert int(one["devices"]) == 1 and int(two["devices"]) == 2
    assert int(two["shards"]) == 2  # the robots really were split between the devices
    assert int(one["updates"]) == int(two["updates"]) == 3
    assert int(two["rollout_ops"]) > 0  # the rollout is named in the compiled program
    assert int(two["rollout_collectives"]) == 0
    weights = [k for k in one if k.startswith("arr_")]
    assert weights
    for k in weights:
        np.testing.assert_allclose(one[k], two[k], atol=1e-5, rtol=1e-4)
    # Compiled at once before any program ran, as a run starts, on two devices as on one: the
    # same programs, so the same weights bit for bit as compiled at their first calls.
    assert bool(one["ahead"]) and bool(two["ahead"])
    for run in (one, two):
        for k in weights:
            np.testing.assert_array_equal(run["ahead_" + k[4:]], run[k])


def test_the_flood_kernel_floods_each_devices_own_grids(tmp_path):
    """On GPUs the goal task's flood kernel takes one device's batch: with the batch split
    between devices (`xla.on_devices`, as training's resets trace) each floods its own part
    (`jax.shard_map`, no op waiting for another device), the same steps as the scans; a batch
    that does not split evenly takes the scans. Pallas' interpreter on two CPU devices here."""
    got = json.loads(run_script("split_flood.py", tmp_path / "flood.json").read_text())
    assert got["devices"] == 2
    even, odd = got["even"], got["odd"]
    assert even["equal"] and even["kernel"] and even["split"] and even["collectives"] == 0
    assert odd["equal"] and not odd["kernel"] and not odd["split"]
    assert even["reached"] > 0 and odd["reached"] > 0


@pytest.mark.slow
def test_banked_arrays_stay_on_each_devices_own_robots(tmp_path):
    """With a block of robots on each of two devices, every block banks its own arrays
    (`AutoReset.bank`): the steps give the select's rewards and states bit for bit, and no op of
    the banked window waits for the other device. Slow: about 8 s on 2 cores, a process of two
    devices compiling both windows."""
    got = json.loads(run_script("banked_blocks.py", tmp_path / "banked.json").read_text())
    assert got["devices"] == 2 and got["shards"] == 2
    assert got["equal"] and got["ended"] > 0 and got["collectives"] == 0


def test_training_resets_trace_with_the_devices_they_run_on():
    """`AutoReset(devices=...)` traces every reset (the first, a step's own, the drawn-ahead
    ones) inside `xla.on_devices`, so that the flood knows the devices its batch is split
    between; outside, and in other threads, `xla.spanned` is what it was."""
    before = xla.spanned()
    seen = []
    env = AutoReset(_Recorder(seen), pool=2, groups=2, devices=("d0", "d1"))
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    state = env.reset(keys)
    env.step(state, jnp.zeros(4, jnp.int32))
    env.draw(state, 3)
    assert seen == [("d0", "d1")] * 3
    assert xla.spanned() == before
    # Per thread: a program traced in another thread meanwhile does not take them.
    with xla.on_devices(("d0", "d1")):
        elsewhere = concurrent.futures.ThreadPoolExecutor(1).submit(xla.spanned).result()
    assert elsewhere == before
    with pytest.raises(ValueError, match="AutoReset.groups"):
        AutoReset(_Recorder(seen), groups=3, devices=("d0", "d1"))


class _Recorder:
    """An env of one number whose reset records the devices `xla.spanned` names as it traces."""

    def __init__(self, seen: list):
        self.seen = seen

    def reset(self, key):
        self.seen.append(xla.spanned())
        return EnvState(
            data=jnp.float32(0),
            obs=jnp.zeros(1),
            reward=jnp.float32(0),
            done=jnp.bool_(False),
            truncated=jnp.bool_(False),
            metrics={},
            info={},
        )

    def step(self, state, action):
        return state.replace(done=jnp.bool_(True))


def test_num_envs_must_split_evenly():
    import jax

    devices = jax.local_devices() * 3  # stands in for three devices: only the count matters here
    with pytest.raises(ValueError, match="--num-envs 10 must be a multiple of the 3 devices"):
        shard_envs(10, devices)


def test_robot_blocks_must_split_evenly():
    import jax

    two = jax.local_devices() * 2  # stands in for two devices: only the count matters here
    cfg = lambda **kw: preset("cpu", num_envs=48, minibatch_size=48, **kw)  # noqa: E731
    assert block_count(cfg(), two) == 2 and block_count(cfg(groups=4), two) == 4
    with pytest.raises(ValueError, match="--groups 3 must be a multiple of the 2 devices"):
        block_count(cfg(groups=3), two)
    with pytest.raises(ValueError, match="--num-envs 48 must be a multiple of the 32 robot blocks"):
        block_count(cfg(groups=32), two)
    with pytest.raises(ValueError, match="--minibatch-size 12 must be a multiple of the 8 robot"):
        block_count(preset("cpu", num_envs=48, minibatch_size=12, groups=8), two)
    with pytest.raises(ValueError, match="--groups: must be >= 0"):
        cfg(groups=-1)


def test_scaling_speed_ups_are_strong_and_weak():
    """benchmarks/scaling.py's speed-ups on hand-made rows: strong against one device at the same
    robot count, weak against one device at the same robots per device (none where that row is
    missing, nor for a failed row)."""
    scaling = benchmark_script("scaling")
    row = lambda n, k, rate: {"num_envs": n, "devices": k, "env_steps_per_s": rate}  # noqa: E731
    rows = [
        row(64, 1, 100.0),
        row(64, 2, 150.0),
        row(128, 1, 120.0),
        row(128, 2, 196.0),
        row(256, 2, 240.0),
        {"num_envs": 256, "devices": 4, "error": "did not finish"},
    ]
    scaling.speed_ups(rows)
    got = [(r.get("speed_up"), r.get("weak_speed_up")) for r in rows]
    assert got == [(1.0, 1.0), (1.5, None), (1.0, 1.0), (1.633, 1.96), (None, 2.0), (None, None)]


def test_a_failed_scaling_row_keeps_its_workers_message(tmp_path):
    """benchmarks/scaling.py runs each row in worker processes; a worker that fails leaves its
    exception's message in the row (and the JSON), not only on the terminal."""
    scaling = benchmark_script("scaling")
    out = tmp_path / "rows.json"
    flags = ["--platform", "cpu", "--devices", "2", "--modes", "single", "--num-envs", "5"]
    flags += ["--updates", "1", "--repeats", "1", "--timeout", "120", "--json", str(out)]
    proc = subprocess.run(
        [sys.executable, scaling.__file__, *flags], capture_output=True, text=True, timeout=180
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (row,) = json.loads(out.read_text())["rows"]
    assert row["error"] == "failed: ValueError: --num-envs 5 must be a multiple of the 2 devices"
    assert "must be a multiple" in proc.stderr  # the worker's own output is still shown


def test_a_crashed_scaling_worker_is_named_by_its_signal():
    """A worker that a signal killed (a segmentation fault in XLA leaves no exception) gives its
    row the signal's name; others their last stderr line; success no error."""
    scaling = benchmark_script("scaling")
    assert scaling.failure(-11, "Extension modules: numpy") == (
        "killed by SIGSEGV (its stack is in its stderr)"
    )
    assert scaling.failure(1, "ValueError: bad") == "ValueError: bad"
    assert scaling.failure(0, "a warning") is None


def trace_op(pid: int, name: str, ts: float, dur: float) -> dict:
    """An op of a profiler trace: process `pid`, from `ts` for `dur` microseconds."""
    return {"ph": "X", "pid": pid, "name": name, "ts": ts, "dur": dur}


GPU_PROCESS = {"name": "process_name", "ph": "M", "pid": 1, "args": {"name": "/device:GPU:0"}}


def write_trace(folder: Path, events: list[dict]) -> str:
    """`events` written under `folder` as JAX's profiler writes a trace; the folder, as read."""
    profile = folder / "plugins" / "profile"
    profile.mkdir(parents=True)
    with gzip.open(profile / "x.trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    return str(folder)


def test_trace_device_time_on_a_hand_made_trace(tmp_path):
    """benchmarks/throughput.py's per-accelerator profile summary on a hand-made trace: the span
    from first op to last, busy as the union of overlapping ops, the time in collective ops;
    host processes are left out."""
    throughput = benchmark_script("throughput")
    events = [
        GPU_PROCESS,
        {"name": "process_name", "ph": "M", "pid": 2, "args": {"name": "/host:CPU"}},
        trace_op(1, "loop_fusion", 0, 2000),
        trace_op(1, "gemm_fusion", 1000, 2000),  # overlaps the first: busy 0-3 ms
        trace_op(1, "ncclDevKernel_AllReduce_Sum_f32", 5000, 4000),  # 5-9 ms
        trace_op(1, "all_reduce_30_fusion", 9000, 1000),  # 9-10 ms
        # within the one before: counted once
        trace_op(1, "ncclDevKernel_AllReduce_Sum_f32", 9500, 500),
        trace_op(1, "a_long_op_that_starts_early", 500, 11500),  # ends last: the span runs to 12 ms
        trace_op(2, "host_work", 0, 50000),
    ]
    trace = write_trace(tmp_path, events)
    rows = throughput.device_time(trace)
    assert rows == [
        {"device": "/device:GPU:0", "span_ms": 12.0, "busy_ms": 12.0, "collective_ms": 5.0}
    ]
    assert len(throughput.op_events(trace)) == 6  # the device's ops, not the host's
    top = throughput.top_ops(throughput.op_events(trace), top=2)
    assert top == [
        {"op": "a_long_op_that_starts_early", "ms": 11.5, "calls": 1},
        {"op": "ncclDevKernel_AllReduce_Sum_f32", "ms": 4.5, "calls": 2},
    ]


def test_env_rollout_profiles_each_timed_rollout(tmp_path):
    """benchmarks/env_rollout.py's `--trace`: each timed rollout run once more under JAX's
    profiler, its row given the ops a step and the ops that took the most time."""
    env_rollout = benchmark_script("env_rollout")
    row = env_rollout.measure_analytic(8, 4, 1, trace=str(tmp_path))
    assert (tmp_path / "analytic-8").is_dir() and row["ops_per_step"] > 0
    assert row["trace_top"] and all(op["ms"] >= 0 and op["calls"] >= 1 for op in row["trace_top"])
    assert "trace_top" not in env_rollout.measure_analytic(8, 4, 1)
    assert row["trace_mjx"]["ops_per_step"] == 0  # the bound has no MJX


def test_env_rollout_mjx_share_on_a_hand_made_trace(tmp_path):
    """`env_rollout.mjx_share`: a profile's kernels looked up in the program's HLO by name
    (its dots and dashes written as underscores), MJX's where their op came from inside
    `mjx.step`, counted and timed a step."""
    env_rollout = benchmark_script("env_rollout")
    program = "\n".join(
        [
            '  %loop_add_fusion.1 = f32[8]{0} fusion(%p), metadata={op_name="jit(rollout)/'
            'while/body/vmap()/step/forward/fwd_position/add"}',
            '  ROOT wrapped_gather = f32[8]{0} gather(%p), metadata={op_name="vmap()/step/'
            'euler/_advance/gather"}',
            '  %input_reduce-fusion = f32[8]{0} fusion(%q), metadata={op_name="vmap()/reduce_min"}',
            '  %loop_mul_fusion = f32[8]{0} fusion(%q), metadata={op_name="vmap()/mystep/'
            'forward/mul"}',
        ]
    )
    op = lambda name, dur: trace_op(1, name, 0, dur)  # noqa: E731
    events = [GPU_PROCESS]
    for _ in range(2):  # two steps
        events += [
            op("loop_add_fusion_1", 3.0),
            op("wrapped_gather", 1.0),
            op("input_reduce_fusion", 10.0),
            op("loop_mul_fusion", 4.0),  # a scope named like MJX's, but not its step
            op("MemcpyD2D", 2.0),  # in no program
        ]
    events = benchmark_script("throughput").op_events(write_trace(tmp_path, events))
    share = env_rollout.mjx_share(events, program, steps=2)
    assert share == {"ops_per_step": 2.0, "us_per_step": 4.0, "all_us_per_step": 20.0}
