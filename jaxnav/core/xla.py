"""XLA's compile options for jaxnav's programs (`jax.jit(..., compiler_options=compiler_options())`).

On the CPU, XLA hands its fused kernels to LLVM at -O3. jaxnav's programs are large (a reset holds
every room family's sampler) and each kernel runs briefly, so -O2 compiles the training chunk in
about three quarters of the time and trains as fast (`benchmarks/compile_time.py --opt-levels`,
docs/results.md). A user's own `--xla_backend_optimization_level` in `XLA_FLAGS` is kept.

On a GPU, XLA picks among kernels by timing them in each process (autotuning), and some of its
reductions add in whatever order threads finish, so two runs of one seed could round differently
and, over a training run, learn different policies. `deterministic` has jaxnav compile its GPU
programs with `xla_gpu_deterministic_ops` (`PPOConfig.deterministic`, off by default): a seed
then trains to the same bits on one machine, slower (docs/results.md, "One seed, one policy, on a
GPU"). A user's own `--xla_gpu_deterministic_ops` in `XLA_FLAGS` is kept.

That timing (autotuning) takes seconds of a GPU's compile, and the programs that run once a
rollout or once a run (`UNTUNED`: the draws, start, init) compile without it. The rollout's
kernels gain from it (at 65,536 robots PPO trained 9-11 % slower with the rollout untimed;
docs/results.md). A user's own `--xla_gpu_autotune_level` is kept.

XLA also times the Triton and its own kernels of some fusions (reductions, softmaxes) against
each other. `fusion_autotune` off has it not do so (`PPOConfig.fusion_autotune`, off for the goal
task, set by `make_train`): the goal task then started 2 s sooner on one H200 host and no sooner on
another, and its gpu preset trained 1-2 % slower; `avoid` started no sooner and trained 1.6 %
slower (docs/results.md). A user's own `--xla_gpu_experimental_enable_fusion_autotuner` is kept.

On a GPU, JAX inlines every jax.random call as the unrolled rounds of threefry:
`threefry_kernel` has them call JAX's CUDA kernel instead (the same bits; off by default,
`PPOConfig.threefry_kernel`). jaxnav's resets draw their numbers in blocks (`jaxnav.core.draws`),
so few calls are left to inline. The programs that run once a rollout or once a run (the draws
of new episodes, init) hold most of them, and XLA's fusion pass spends seconds on their unrolled
rounds; on one GPU those programs lower with the kernel (`run_once`, `threefry_lowering`):
they run as fast either way, and the goal task's draws compiled in 10.4-11.4 s rather than
15.9-16.6 s beside the other programs (docs/results.md).

`pow2` rounds a size up as a Pallas (Triton) block's sides must be, for jaxnav's GPU kernels.
`spanned` names the devices a batch being traced is split between (`on_devices`), for the kernels
that take one device's batch at a time (the goal flood's), which then run on each device's part.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

import jax

CPU_OPT_LEVEL = 2  # LLVM's optimisation level for jaxnav's CPU programs (XLA's own default: 3)
OPTION = "xla_backend_optimization_level"
DETERMINISTIC = "xla_gpu_deterministic_ops"  # XLA's option for the same bits every run
AUTOTUNE = "xla_gpu_autotune_level"  # XLA's option: 0 times no kernels (its default: 4)
UNTUNED = ("draws", "start", "init")  # run once a rollout or a run: not worth timing (the module)
FUSION_AUTOTUNE = "xla_gpu_experimental_enable_fusion_autotuner"  # XLA's: fusions' kernels timed
GPUS = ("gpu", "cuda", "rocm")  # the names a GPU backend or platform goes by
_deterministic = False  # set by `deterministic`
_fusion_autotune = True  # set by `fusion_autotune`
_tracing = threading.local()  # `.devices`: set by `on_devices` in the thread that traces


def pow2(n: int, least: int = 1) -> int:
    """n rounded up to a power of two, at least `least` (a Triton block's side)."""
    return max(least, 1 << max(n - 1, 0).bit_length())


def compiler_options(
    backend: str | None = None, program: str | None = None
) -> dict[str, int | bool] | None:
    """The options for a program on `backend` (default: JAX's default backend), or None for
    XLA's defaults: on the CPU `CPU_OPT_LEVEL`; on a GPU `DETERMINISTIC` where `deterministic`
    turned it on, `FUSION_AUTOTUNE` off where `fusion_autotune` turned it off, and no autotuning
    (`AUTOTUNE` 0) for a trainer's program named in `UNTUNED` (`program`: its name in
    `ppo.train.Trainer.programs`); each unless `XLA_FLAGS` sets it."""
    backend, flags = backend or jax.default_backend(), os.environ.get("XLA_FLAGS", "")
    options = {}
    if backend == "cpu" and OPTION not in flags:
        options[OPTION] = CPU_OPT_LEVEL
    if backend in GPUS and _deterministic and DETERMINISTIC not in flags:
        options[DETERMINISTIC] = True
    if backend in GPUS and not _fusion_autotune and FUSION_AUTOTUNE not in flags:
        options[FUSION_AUTOTUNE] = False
    if backend in GPUS and program in UNTUNED and AUTOTUNE not in flags:
        options[AUTOTUNE] = 0
    return options or None


def deterministic(on: bool) -> None:
    """jaxnav's GPU programs compiled from now on in this process with XLA's deterministic ops
    (`on`) or as XLA's defaults have them (`PPOConfig.deterministic`, set by `make_train`)."""
    global _deterministic
    _deterministic = bool(on)


def fusion_autotune(on: bool) -> None:
    """jaxnav's GPU programs compiled from now on in this process with XLA timing its fusions'
    kernels (`on`, XLA's default) or not (`PPOConfig.fusion_autotune`, set by `make_train`)."""
    global _fusion_autotune
    _fusion_autotune = bool(on)


THREEFRY_KERNEL = "jax_threefry_gpu_kernel_lowering"


def threefry_kernel(on: bool, backend: str | None = None) -> None:
    """On a GPU `backend` (default: JAX's default backend), programs lowered from now on in this
    process call jax.random's threefry as one CUDA kernel (`on`) or inline its rounds (JAX's
    default); the random bits are the same either way. Other backends have no such kernel, and
    their setting is left as it is (it is part of every jit's cache key)."""
    if (backend or jax.default_backend()) == "gpu":
        jax.config.update(THREEFRY_KERNEL, bool(on))


def threefry_lowering(kernel: bool):
    """A context: programs lowered in it, in this thread, call jax.random's threefry as JAX's CUDA
    kernel (`kernel`) or inline its rounds, whatever `threefry_kernel` set for the process (a
    GPU's lowering only; the same bits either way). A JAX without the setting lowers as it
    would."""
    try:
        from jax._src.config import threefry_gpu_kernel_lowering as state
    except ImportError:
        return contextlib.nullcontext()
    return state(bool(kernel))


def traced(args) -> bool:
    """Whether a program is called with `args` inside another trace (`jax.eval_shape`, a jit
    around it): some leaf is a tracer. There a jitted program with XLA's options cannot be
    called, as they belong to a top-level jit only; its function is traced in place instead
    (`LoweredWith`, `jaxnav.programs.Stored`)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args))


class LoweredWith:
    """A jitted program lowered (by `lower`, or by the call that compiles it) in `context()`,
    which `jaxnav.programs` also exports it in (`lowering`)."""

    def __init__(self, jitted, context):
        self.jitted, self.context = jitted, context

    def lower(self, *args):
        with self.context():
            return self.jitted.lower(*args)

    def __call__(self, *args):
        with self.context():
            if traced(args):  # e.g. `jax.eval_shape`, as `Trainer.arguments` calls it
                return self.jitted.__wrapped__(*args)
            return self.jitted(*args)


def run_once(programs: dict, platform: str, devices: int) -> dict:
    """`programs` (a trainer's that run once a rollout or once a run), each lowered with
    threefry as JAX's kernel (`LoweredWith`, `threefry_lowering`) on one GPU, where they compile
    sooner and run as fast; as they are elsewhere (several devices: XLA cannot split the
    kernel's call over the devices the robots are sharded over)."""
    if platform not in GPUS or devices != 1:
        return programs
    kernel = functools.partial(threefry_lowering, True)
    return {name: LoweredWith(program, kernel) for name, program in programs.items()}


def lowering(program):
    """The context `program` lowers in: a `LoweredWith`'s, else one that changes nothing."""
    return getattr(program, "context", contextlib.nullcontext)()


@contextlib.contextmanager
def on_devices(devices):
    """While the computations of a batch split between `devices` (its first axis, in equal
    consecutive parts, as `ppo.train.shard_envs` splits the robots) trace in this thread:
    `spanned` names them (programs may be traced in several threads at once)."""
    before = getattr(_tracing, "devices", None)
    _tracing.devices = tuple(devices)
    try:
        yield
    finally:
        _tracing.devices = before


def spanned() -> tuple | None:
    """The devices of the batch tracing now: `on_devices`' devices; else the only device, or
    None where there are several and which of them a batch is on is not known."""
    devices = getattr(_tracing, "devices", None)
    if devices is not None:
        return devices
    return tuple(jax.devices()) if jax.device_count() == 1 else None
