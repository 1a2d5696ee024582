"""The goal grid's flood on one GPU, as a Pallas (Triton) kernel.

`goals.grid_steps` floods a batch of occupancy grids from their goal cells by rounds of four
directional min-plus scans. Written in XLA's operations, every scan is a pass over the whole batch
in memory (`goals._flood_scans`: log-depth passes each), or a kernel a row (`goals._flood_rows`);
on a GPU either is bound by memory traffic or by kernel launches. This kernel gives each program
`LANES` grids, laid out [H, W, lanes] (the grids on the minor axis, so a row of cells is one
contiguous load), and runs every round's scans inside it: an east or west scan loops over the
columns, one [H, lanes] tile (column j of every row) a step, a south or north scan over the rows,
one [W, lanes] tile a step. The cells a program writes stay in the GPU's cache for its next scan.

Same rule and integer steps as `goals._flood_rows`, so the same result bit for bit
(`tests/test_goal.py` runs it through Pallas' interpreter on the CPU; docs/results.md has the
GPU's timings).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxnav.core.xla import pow2

LANES = 64  # grids per program: 128 B of int16 steps per row of a tile
FAR = 30_000  # int16 steps of an unreached cell (every reachable count is below it)
MAX_CELLS = 30_000  # the largest grid whose counts fit below FAR
# The fewest grids for which the kernel beats the associative scans on one H200: a program's
# rounds are a chain of (H + W) x 2 x 8 dependent steps, so a small batch leaves most of the GPU
# idle. At 4,096 grids 3.0 ms against 5.8 ms (54 x 54 cells) and 9.8 against 16.2 ms (60 x 150);
# at 2,048 1.6 against 3.0 ms and 8.8 against 7.7 ms (benchmarks/results/flood_h200.json).
MIN_BATCH = 4096


def _kernel(free_ref, steps_ref, out_ref, *, sweeps: int, interpret: bool):
    """One program: `sweeps` rounds over its [H, W, lanes] block of `out_ref` (aliased to
    `steps_ref`, the start), east, west, south, north; `free_ref` 1 where a cell is free."""
    del steps_ref  # the same buffer as out_ref
    h, w, lanes = out_ref.shape
    far, one = jnp.int16(FAR), jnp.int16(1)

    def scan(along_rows: bool, reverse: bool):
        """Along every row (a tile: column j of the H rows) or every column (row j)."""
        length, size = (w, h) if along_rows else (h, w)  # the scan's steps, the tile's rows

        def cell(i, run):  # run: [size, lanes]
            j = length - 1 - i if reverse else i
            tile = (slice(None), j, slice(None)) if along_rows else (j, slice(None), slice(None))
            here = out_ref[tile]
            run = jnp.where(free_ref[tile] != 0, jnp.minimum(here, run + one), far)
            out_ref[tile] = run
            return run

        jax.lax.fori_loop(0, length, cell, jnp.full((size, lanes), FAR, jnp.int16))

    def barrier():  # the next scans read cells other threads of the program wrote
        if not interpret:
            from jax.experimental.pallas import triton as pltriton

            pltriton.debug_barrier()

    def round_(_, carry):
        for along_rows in (True, False):
            scan(along_rows, False)
            scan(along_rows, True)
            barrier()
        return carry

    jax.lax.fori_loop(0, sweeps, round_, 0)


def flood(free: jax.Array, seed: jax.Array, sweeps: int, interpret: bool = False) -> jax.Array:
    """`goals.grid_steps` of grids [..., H, W] (bool `free` and `seed`, same shape), as float32
    steps (inf where unreached). H and W are padded to powers of two with blocked cells, the
    batch to a multiple of LANES with empty grids."""
    from jax.experimental import pallas as pl  # here: a GPU's goal task only needs it
    from jax.experimental.pallas import triton as pltriton

    lead, (h, w) = free.shape[:-2], free.shape[-2:]
    if h * w >= MAX_CELLS:
        raise ValueError(f"flood_kernel.flood: a grid of {h} x {w} cells is over {MAX_CELLS}")
    free, seed = (x.reshape(-1, h, w) for x in (free, seed))
    b = free.shape[0]
    hp, wp, bp = pow2(h), pow2(w), -(-b // LANES) * LANES
    pad = ((0, hp - h), (0, wp - w), (0, bp - b))
    ok = jnp.pad(jnp.moveaxis(free, 0, -1).astype(jnp.int16), pad)  # [Hp, Wp, Bp]
    start = jnp.where(seed & free, 0, FAR).astype(jnp.int16)
    start = jnp.pad(jnp.moveaxis(start, 0, -1), pad, constant_values=FAR)
    block = pl.BlockSpec((hp, wp, LANES), lambda p: (0, 0, p))
    params = None if interpret else pltriton.CompilerParams(num_warps=4, num_stages=1)
    steps = pl.pallas_call(
        functools.partial(_kernel, sweeps=sweeps, interpret=interpret),
        out_shape=jax.ShapeDtypeStruct((hp, wp, bp), jnp.int16),
        grid=(bp // LANES,),
        in_specs=[block, block],
        out_specs=block,
        input_output_aliases={1: 0},
        interpret=interpret,
        compiler_params=params,
    )(ok, start)
    steps = jnp.moveaxis(steps[:h, :w, :b], -1, 0)
    steps = jnp.where(steps >= FAR, jnp.inf, steps.astype(jnp.float32))
    return steps.reshape(*lead, h, w)
