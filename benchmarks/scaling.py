"""PPO throughput over 1, 2, 4 ... devices of one host: one process over all of them, and one
process per device joined by `jax.distributed` (the multi-host code path on one host).

    python benchmarks/scaling.py --devices 1,2,4 --num-envs 65536,131072 \\
        --json benchmarks/results/scaling_h200.json                   # a host with 4 GPUs
    python benchmarks/scaling.py --platform cpu --devices 1,2 --num-envs 64 --updates 1 \\
        --repeats 1                                                   # CPU, forced host devices

Each measurement runs in its own subprocess(es) (GPUs picked with CUDA_VISIBLE_DEVICES and, one per
process, JAX_LOCAL_DEVICE_IDS; on the CPU, `--xla_force_host_platform_device_count`), so the parent
never holds a device. The timing is
`benchmarks/throughput.py`'s PPO one (the `cpu` preset's update shape: rollout 32, 4 epochs,
4 minibatches; every obstacle slot in use; `--env goal`: the goal task with its own PPO defaults,
as `throughput.py --env goal` times it), the best of `--repeats` chunks of `--updates` updates
after the compile; env-steps/s counts every robot of every device.
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

from report import run_info, write_json

MODES = ("single", "multi")  # one process over k devices; k processes of one device each


def device_env(platform_: str, k: int, mine: int | None) -> dict:
    """The environment of a process of a run over `k` devices: all of them (`mine` None) or only
    device `mine` (one process per device). Every GPU of the run stays visible to CUDA, so that
    NCCL may link them directly; JAX takes its own from JAX_LOCAL_DEVICE_IDS."""
    env = dict(os.environ)
    if platform_ == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
        count = k if mine is None else 1
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={count}"
        return env
    env["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, range(k)))
    env.setdefault("NCCL_NVLS_ENABLE", "0")  # no NVLink multicast on shared hosts
    if mine is not None:
        env["JAX_LOCAL_DEVICE_IDS"] = str(mine)
    return env


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def measure(args, mode: str, k: int, n: int) -> dict:
    """One row: `mode` over `k` devices at `n` robots, from its subprocess(es)."""
    base = [sys.executable, __file__, "--worker", "--env", args.env, "--num-envs", str(n)]
    base += ["--updates", str(args.updates), "--repeats", str(args.repeats)]
    base += [f"--set={item}" for item in args.set]
    if mode == "single":
        mine, cluster = [None], []
    else:
        mine = list(range(k))
        cluster = ["--coordinator", f"localhost:{free_port()}", "--num-processes", str(k)]
    errs = [tempfile.TemporaryFile("w+") for _ in mine]  # files, not pipes: none can fill up
    procs = [
        subprocess.Popen(
            [*base, *cluster, *(["--process-id", str(i)] if cluster else [])],
            env=device_env(args.platform, k, i),
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
        for i, err in zip(mine, errs, strict=True)
    ]
    head = {"mode": mode, "devices": k, "processes": len(procs), "num_envs": n}
    try:
        outs = [proc.communicate(timeout=args.timeout)[0] for proc in procs]
    except subprocess.TimeoutExpired:
        for proc in procs:
            proc.kill()
            proc.wait()
        return {**head, "error": f"did not finish within {args.timeout} s"}
    finally:
        last = [_echo(err) for err in errs]
    failed = [failure(proc.returncode, line) for proc, line in zip(procs, last, strict=True)]
    failed = [line for line in failed if line]
    if failed:
        return {**head, "error": f"failed: {failed[0][:300]}"}
    return {**head, **json.loads(outs[0].strip().splitlines()[-1])}  # process 0 speaks for the run


def failure(returncode: int, last: str) -> str | None:
    """What a worker that ended with `returncode` and the stderr line `last` failed of: None for
    success; a signal's name where one killed it (its Python stack, from `faulthandler`, is in
    the stderr echoed above the row), else its last line."""
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return f"killed by {name} (its stack is in its stderr)"
    return last if returncode else None


def _echo(err) -> str:
    """Copies a worker's stderr (a temporary file) to this process's, and returns its last line
    (an exception's message), which the row keeps."""
    err.seek(0)
    text = err.read()
    err.close()
    sys.stderr.write(text)
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else "no message"


def worker(args) -> None:
    """Inside a subprocess: joins the run (multi), times PPO, prints one JSON line. Shortly before
    its time is up it prints every thread's stack to stderr, to show where a stuck run waits."""
    faulthandler.enable()  # a crash in XLA or a kernel: the Python stack where it happened
    faulthandler.dump_traceback_later(max(args.timeout - 10, 1), exit=False)
    sys.path.insert(0, str(Path(__file__).parent))
    from time_to_solve import parse_sets

    from jaxnav import distributed

    sets = parse_sets(args.set)
    if set(sets) - {"ppo"}:
        raise SystemExit(f"--set: only ppo.FIELD=VALUE here, got {', '.join(args.set)}")

    distributed.start(
        distributed.ClusterConfig(args.coordinator, args.num_processes, args.process_id)
    )
    import jax
    from throughput import FULL, training

    import jaxnav
    from jaxnav.tasks.registry import task_defaults

    env = jaxnav.make_env(args.env, randomize=FULL)
    (n,) = (int(x) for x in args.num_envs.split(","))
    ppo = {**task_defaults(args.env).get("ppo", {}), **sets.get("ppo", {})}
    result = training(env, n, args.updates, args.repeats, ppo)
    result.update(num_envs=n, **run_info("device"))
    result.update(device_count=jax.device_count(), **run_info("jax"))
    print(json.dumps(result), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="avoid", help="the task trained (avoid or goal)")
    parser.add_argument("--devices", default="1,2,4", help="comma-separated device counts")
    parser.add_argument("--num-envs", default="65536", help="comma-separated robot counts")
    parser.add_argument("--modes", default=",".join(MODES), help="single, multi or both")
    parser.add_argument("--platform", choices=("gpu", "cpu"), default="gpu")
    parser.add_argument("--updates", type=int, default=5, help="PPO updates per timed chunk")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--timeout", type=int, default=600, help="s per measurement")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        help="ppo.FIELD=VALUE (repeatable), e.g. "
        "ppo.reset_in_place=true; default: the default speed levers",
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--coordinator", help=argparse.SUPPRESS)
    parser.add_argument("--num-processes", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--process-id", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return worker(args)
    modes = args.modes.split(",")
    if set(modes) - set(MODES):
        parser.error(f"--modes: one or both of {', '.join(MODES)}, got {args.modes}")
    rows = []
    for n in (int(x) for x in args.num_envs.split(",")):
        for k in (int(x) for x in args.devices.split(",")):
            for mode in modes:
                if mode == "multi" and k == 1:
                    continue  # the same as single
                rows.append(measure(args, mode, k, n))
                print(json.dumps(rows[-1]), flush=True)
    speed_ups(rows)
    result = {
        **run_info("date", "python", "command"),
        "env": args.env,
        "ppo": args.set,
        "rows": rows,
    }
    print_table(rows)
    if args.json:
        write_json(args.json, result)


def speed_ups(rows) -> None:
    """Adds to each row its speed-up against one device: `speed_up` at the same robot count
    (strong scaling) and `weak_speed_up` at the same robots per device (weak scaling: how much
    more a run with more devices trains, each device as full as the one-device run's)."""
    done = [r for r in rows if "error" not in r]
    one = {r["num_envs"]: r["env_steps_per_s"] for r in done if r["devices"] == 1}
    for r in done:
        base = one.get(r["num_envs"])
        weak = one.get(r["num_envs"] // r["devices"])
        r["speed_up"] = round(r["env_steps_per_s"] / base, 3) if base else None
        r["weak_speed_up"] = round(r["env_steps_per_s"] / weak, 3) if weak else None


def print_table(rows) -> None:
    """Speed-up and efficiency are against one device at the same robot count; weak is against
    one device at the same robots per device (`speed_ups` adds both to the rows)."""
    done = [r for r in rows if "error" not in r]
    if done:
        print(f"\n{done[0]['device']}, jax {done[0]['jax']}")
    print(
        f"{'robots':>8} {'devices':>7} {'processes':>9} {'env steps/s':>12} {'speed-up':>8} "
        f"{'efficiency':>10} {'weak':>6} {'s/update':>9} {'compile s':>9}"
    )
    show = lambda x, fmt, width: format(x, fmt) if x is not None else "-".rjust(width)  # noqa: E731
    for r in rows:
        lead = f"{r['num_envs']:>8} {r['devices']:>7} {r['processes']:>9}"
        if "error" in r:
            print(f"{lead} {r['error']}")
            continue
        up, weak = r["speed_up"], r["weak_speed_up"]
        print(
            f"{lead} {r['env_steps_per_s']:>12,} {show(up, '>7.2f', 7)}x "
            f"{show(up and up / r['devices'], '>10.0%', 10)} {show(weak, '>5.2f', 5)}x "
            f"{r['s_per_update']:>9.3f} {r['compile_s']:>9}"
        )


if __name__ == "__main__":
    main()
