"""XLA's compile options for jaxnav's programs (`jax.jit(..., compiler_options=compiler_options())`).

On the CPU, XLA hands its fused kernels to LLVM at -O3. jaxnav's programs are large (a reset holds
every room family's sampler) and each kernel runs briefly, so -O2 compiles the training chunk in
about three quarters of the time and trains as fast (`benchmarks/compile_time.py --opt-levels`,
docs/results.md). Other backends keep XLA's defaults, and so does a user's own
`--xla_backend_optimization_level` in `XLA_FLAGS`.

On a GPU, JAX inlines every jax.random call as the unrolled rounds of threefry:
`threefry_kernel` has them call JAX's CUDA kernel instead (the same bits; off by default,
`PPOConfig.threefry_kernel`). jaxnav's resets draw their numbers in blocks (`jaxnav.core.draws`),
so few calls are left to inline.

`pow2` rounds a size up as a Pallas (Triton) block's sides must be, for jaxnav's GPU kernels.
"""

from __future__ import annotations

import os

import jax

CPU_OPT_LEVEL = 2  # LLVM's optimisation level for jaxnav's CPU programs (XLA's own default: 3)
OPTION = "xla_backend_optimization_level"


def pow2(n: int, least: int = 1) -> int:
    """n rounded up to a power of two, at least `least` (a Triton block's side)."""
    return max(least, 1 << max(n - 1, 0).bit_length())


def compiler_options(backend: str | None = None) -> dict[str, int] | None:
    """The options for a program on `backend` (default: JAX's default backend), or None for
    XLA's defaults: on the CPU `CPU_OPT_LEVEL`, unless `XLA_FLAGS` sets the level itself."""
    if OPTION in os.environ.get("XLA_FLAGS", ""):
        return None
    return {OPTION: CPU_OPT_LEVEL} if (backend or jax.default_backend()) == "cpu" else None


THREEFRY_KERNEL = "jax_threefry_gpu_kernel_lowering"


def threefry_kernel(on: bool, backend: str | None = None) -> None:
    """On a GPU `backend` (default: JAX's default backend), programs lowered from now on in this
    process call jax.random's threefry as one CUDA kernel (`on`) or inline its rounds (JAX's
    default); the random bits are the same either way. Other backends have no such kernel, and
    their setting is left as it is (it is part of every jit's cache key)."""
    if (backend or jax.default_backend()) == "gpu":
        jax.config.update(THREEFRY_KERNEL, bool(on))
