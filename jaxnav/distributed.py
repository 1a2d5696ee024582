"""One run over several processes (hosts): start-up, who writes, and host copies of global arrays.

    python -m jaxnav.train --coordinator HOST:PORT --num-processes N --process-id I ...  # each host

Every process runs the same program over the global mesh of all processes' devices (`jax.devices()`);
each simulates only the robots on its own devices (the sharded reset and step of `jaxnav.ppo.train`).
Process 0 alone writes the run folder (config, metrics, pictures, checkpoints); on resume every
process reads the checkpoint, so the run folder must be on a filesystem all hosts share.

Without the flags, `JAX_COORDINATOR_ADDRESS` (read by JAX) starts the same way, with the count and
the index from `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID` (read here: JAX itself takes them only from
a SLURM, Open MPI or Kubernetes job, which it detects when they are unset).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import threading

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

ENV_VARS = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
FLAGS = ("--coordinator", "--num-processes", "--process-id", "--init-timeout")


@dataclasses.dataclass(frozen=True)
class ClusterConfig:
    """How this process joins a run of several processes; all None: a run of one process."""

    coordinator: str | None = None
    """HOST:PORT where process 0 serves the start-up (the same on every process)."""
    num_processes: int | None = None
    """Processes in the run (usually one per host)."""
    process_id: int | None = None
    """This process's index, 0 .. num_processes - 1; process 0 writes the run folder."""
    timeout_s: int = 300
    """Seconds to wait for every process to reach the coordinator."""

    def __post_init__(self):
        if self.coordinator is not None:
            host, _, port = self.coordinator.rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(
                    f"--coordinator: expected HOST:PORT (port 1-65535), got {self.coordinator!r}"
                )
        if self.num_processes is not None and self.num_processes < 1:
            raise ValueError(f"--num-processes: must be >= 1, got {self.num_processes}")
        if self.process_id is not None and self.num_processes is not None:
            if not 0 <= self.process_id < self.num_processes:
                raise ValueError(
                    f"--process-id {self.process_id}: out of range for --num-processes "
                    f"{self.num_processes} (0 to {self.num_processes - 1})"
                )
        if self.timeout_s < 1:
            raise ValueError(f"--init-timeout: must be >= 1 s, got {self.timeout_s}")

    @property
    def enabled(self) -> bool:
        return self.coordinator is not None


def add_flags(parser: argparse.ArgumentParser) -> None:
    """The flags of `ClusterConfig` (each process of a run gets the same but --process-id)."""
    group = parser.add_argument_group(
        "hosts: one run over several processes",
        "or JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID; see jaxnav/distributed.py",
    )
    group.add_argument(
        "--coordinator", metavar="HOST:PORT", help="process 0's host and a free port on it"
    )
    group.add_argument("--num-processes", type=int, metavar="N", help="processes in the run")
    group.add_argument(
        "--process-id", type=int, metavar="I", help="this process's index (0 writes the run)"
    )
    group.add_argument(
        "--init-timeout",
        type=int,
        default=300,
        metavar="S",
        help="seconds to wait for every process to join (default 300)",
    )


def from_args(args: argparse.Namespace, environ=os.environ) -> ClusterConfig:
    """The flags, else the environment variables (`ENV_VARS`); a half-given trio is an error."""
    given = [args.coordinator, args.num_processes, args.process_id]
    if any(x is not None for x in given):
        missing = [flag for flag, x in zip(FLAGS[:3], given, strict=True) if x is None]
        if missing:
            raise ValueError(f"{missing[0]}: needed with {', '.join(FLAGS[:3])}")
        return ClusterConfig(*given, timeout_s=args.init_timeout)
    if not environ.get(ENV_VARS[0]):
        return ClusterConfig(timeout_s=args.init_timeout)
    numbers = []
    for name in ENV_VARS[1:]:
        raw = environ.get(name)
        if raw is not None and not raw.strip().isdigit():
            raise ValueError(f"{name}: expected a whole number, got {raw!r}")
        numbers.append(None if raw is None else int(raw))
    try:
        return ClusterConfig(environ[ENV_VARS[0]], *numbers, timeout_s=args.init_timeout)
    except ValueError as err:
        raise ValueError(f"{err} (from {', '.join(ENV_VARS)})") from None


def start(cluster: ClusterConfig) -> None:
    """Joins the run's processes (before anything touches a device); a no-op for one process.

    A coordinator that does not answer within `timeout_s` is a one-line error naming it.
    """
    if not cluster.enabled:
        return
    # Cross-process collectives on CPU devices (JAX's default, set in case that changes).
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    # In a worker thread, under our own deadline: where JAX's own deadline passes, XLA ends the
    # process with a page of C++ log instead of an error. It gets 60 s more than ours.
    box: dict = {}

    def join():
        try:
            jax.distributed.initialize(
                cluster.coordinator,
                cluster.num_processes,
                cluster.process_id,
                initialization_timeout=cluster.timeout_s + 60,
            )
        except BaseException as err:  # noqa: BLE001 (handed to the main thread)
            box["error"] = err

    worker = threading.Thread(target=join, daemon=True)
    worker.start()
    worker.join(cluster.timeout_s)
    err = box.get("error")
    if isinstance(err, ValueError | TypeError):  # the count or index missing, from either source
        raise ValueError(
            f"--coordinator {cluster.coordinator}: {err} (give --num-processes and --process-id, "
            "or JAX_NUM_PROCESSES and JAX_PROCESS_ID)"
        ) from None
    if worker.is_alive() or err is not None:
        text = "" if err is None else ": " + " ".join(str(err).split())[:200]
        raise ConnectionError(
            f"--coordinator {cluster.coordinator}: process {cluster.process_id} of "
            f"{cluster.num_processes} did not join the run within --init-timeout "
            f"{cluster.timeout_s} s (are all processes started, with the same --coordinator and "
            f"--num-processes, and is the port open on process 0's host?){text}"
        )


def is_main() -> bool:
    """True on the process that writes the run folder (the only one of a single-process run)."""
    return jax.process_index() == 0


def _identity(tree):
    return tree


def to_host(tree):
    """A numpy copy of every leaf, whole, on every process.

    A collective where leaves are split over several processes (one jitted copy of them all onto
    every device): every process must call it together.
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    split = [
        i
        for i, x in enumerate(leaves)
        if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated
    ]
    if split:
        everywhere = NamedSharding(Mesh(np.array(jax.devices()), ("all",)), PartitionSpec())
        whole = jax.jit(_identity, out_shardings=everywhere)([leaves[i] for i in split])
        for i, x in zip(split, whole, strict=True):
            leaves[i] = x
    # What spans processes is now replicated: every process holds all of it on its devices.
    local = lambda x: x if x.is_fully_addressable else x.addressable_data(0)  # noqa: E731
    host = [np.asarray(local(x) if isinstance(x, jax.Array) else x) for x in leaves]
    return jax.tree_util.tree_unflatten(treedef, host)


def any_process(flag: bool) -> bool:
    """True if `flag` is true on any process (a collective with several processes)."""
    if jax.process_count() == 1:
        return bool(flag)
    from jax.experimental import multihost_utils

    return bool(np.asarray(multihost_utils.process_allgather(np.int32(flag))).any())


class PeerFailed(RuntimeError):
    """Another process stopped before training where this one did not; the message names it."""


# Whether this process has told the others how its start went (`ready` or `start_failed`).
_START = {"told": False}


def _tell(ok: bool) -> np.ndarray:
    """Every process's `ok` ([num_processes] int32), once per process; None for one process."""
    if jax.process_count() == 1 or _START["told"]:
        return None
    from jax.experimental import multihost_utils

    _START["told"] = True
    return np.asarray(multihost_utils.process_allgather(np.int32(ok)))


def ready() -> None:
    """Tells the other processes that this one starts training, and waits for theirs: where one
    stopped before (`start_failed`), raises `PeerFailed` here, so that no process waits forever in
    a collective for one that quit. Call it right before the first computation over all devices."""
    ok = _tell(True)
    if ok is not None and not ok.all():
        failed = ", ".join(str(i) for i in np.flatnonzero(ok == 0))
        raise PeerFailed(
            f"process {failed} stopped before training (see its error); this one stops too"
        )


@contextlib.contextmanager
def start_failed():
    """Around a process's start: an error raised before `ready` is told to the other processes
    (which wait in theirs) before it propagates."""
    try:
        yield
    except Exception:
        _tell(False)
        raise
