"""Goals of goal-reaching tasks: a reachable goal per episode, and shortest paths for SPL.

Every draw is traced data (a new goal never recompiles anything). Reachability is guaranteed in
two ways:

- Layouts: `make_goal_cells` precomputes, per layout, the free cells of its *main component* on the
  occupancy grid of `families.free_cells` (`CELL` = 0.1 m cells, free where the robot's disc touches
  nothing: walls and obstacles inflated by the robot radius; components 4-connected, as
  `families.reachable` floods them). The main component is the one holding the layout's goal, else
  its spawn, else the largest. A random spawn that lands off it (in a closed-off pocket) is moved
  onto one of its cells, and a sampled goal is one of its cells: spawn and goal are connected, to
  the grid's resolution. A layout whose fixed spawn and goal lie in different components is refused.
- Sampled rooms (`randomize.sample_room` and the room families): a traced grid of `GRID_CELL`
  cells, free where the robot's disc clears everything by half a cell (so the segment between two
  free neighbours is clear: clearance is 1-Lipschitz). The grid covers half extents (long,
  short), its columns along the long axis; where the two differ (a long hall in the mix), it lies
  on a room longer in y than in x transposed, so halls of either direction fit. The goal is a
  uniform cell at least the minimum distance from the spawn that keeps `clearance`; the grid is
  flooded from it once, by `SWEEPS` rounds of four directional min-plus scans (`grid_steps`), and
  that flood is both the reachability check and the goal's distance field (`geodesic`). A spawn
  the flood does not reach (in a pocket) moves to a uniform reached cell as far from the goal.
  Corridors, doorways and U-shapes keep their walls and the goal is often behind them. Where no
  cell is far enough (a spawn boxed in), every obstacle that would block an L-shaped path spawn ->
  corner -> goal (half-width robot radius + `path_clearance`) is removed instead.

`shortest_paths` measures the geodesic distance for SPL on the same grid, 8-connected (diagonal
steps only where both cells beside them are free, so no corner is cut).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, PartitionSpec
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from jaxnav.core import families, flood_kernel, types, xla
from jaxnav.core import layout as lay
from jaxnav.core.draws import Draws
from jaxnav.core.geometry import planar_distance, signed_distance
from jaxnav.core.randomize import SceneParams

CELL = families.CELL  # m, occupancy grid cell for goals and shortest paths
TRIES = 32  # uniform candidates per draw of a spawn or a goal
PATH_POINTS = 64  # points per leg of a sampled room's cleared L-shaped path
GRID_CELL = 0.2  # m, cell of the traced reachability grid of sampled rooms
GRID_HALF = 5.25  # m, least half extent of the traced grid per axis (every family room but halls)
SWEEPS = 8  # rounds of the traced flood; each follows a path through two turns, so 16 turns
GRID_BLOCKS = 2  # blocks of rows of the traced grid whose clearance is computed in a loop


@struct.dataclass
class GoalCells:
    """Per layout (K of them, padded to the largest): its goal and its main component's cells."""

    goal: jax.Array  # [K, 2] the layout's fixed goal, m (0 where it has none)
    has_goal: jax.Array  # [K] bool
    cells: jax.Array  # [K, N, 2] centres of the main component's free cells, m (padded)
    count: jax.Array  # [K] int32 cells in use
    main: jax.Array  # [K, H, W] bool: the cell is on the main component (padded with False)
    shape: jax.Array  # [K, 2] int32 the layout's grid rows H and columns W


def _nearest(free: np.ndarray, centres: np.ndarray, xy) -> int:
    """Flat index of the free cell whose centre is nearest `xy` (-1 if none is free)."""
    if not free.any():
        return -1
    dist = np.linalg.norm(centres - np.asarray(xy, np.float64), axis=-1)
    return int(np.argmin(np.where(free, dist, np.inf)))


def main_component(layout: lay.RoomLayout, radius: float = lay.ROBOT_RADIUS, cell: float = CELL):
    """([H, W] bool main component, [H, W, 2] cell centres) of a layout (see the module doc)."""
    free, centres = families.free_cells(layout, radius, cell)
    labels, count = ndimage.label(free)  # the default structure: 4-connected
    if count == 0:
        raise lay.LayoutError(
            None, f"no free {cell:g} m cell for the robot: no goal can be placed", room=layout.name
        )
    label_at = lambda xy: labels.flat[_nearest(free, centres, xy)]  # noqa: E731
    if layout.goal_pos is not None:
        main = label_at(layout.goal_pos)
        if layout.robot_pos is not None and label_at(layout.robot_pos) != main:
            raise lay.LayoutError(
                "goal.pos",
                f"not reachable from robot.pos {list(layout.robot_pos)}: the robot (radius "
                f"{radius} m) cannot pass between them on the {cell:g} m occupancy grid",
                room=layout.name,
            )
    elif layout.robot_pos is not None:
        main = label_at(layout.robot_pos)
    else:
        main = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    mask = labels == main
    if layout.robot_pos is not None:  # the spawn's own cell, even where the grid rounds it off
        mask.flat[_cell_index(layout, mask.shape, layout.robot_pos)] = True
    return mask, centres


def _cell_index(layout: lay.RoomLayout, shape, xy) -> int:
    """Flat index of the grid cell containing `xy` (the lookup `_on_main` does traced)."""
    half = 0.5 * np.asarray(layout.size)
    frac = (np.asarray(xy) + half) / (2 * half)
    row, col = (
        int(np.clip(np.floor(f * n), 0, n - 1)) for f, n in zip(frac[::-1], shape, strict=True)
    )
    return row * shape[1] + col


def make_goal_cells(layouts, radius: float = lay.ROBOT_RADIUS, cell: float = CELL) -> GoalCells:
    """The goal data of `layouts` for a `LayoutBank` (one dummy room when there are none)."""
    layouts = list(layouts) or [lay.RoomLayout(name="none", size=(4.0, 4.0))]
    masks, cells = [], []
    for layout in layouts:
        mask, centres = main_component(layout, radius, cell)
        masks.append(mask)
        cells.append(centres[mask])
    n = max(len(c) for c in cells)
    h = max(m.shape[0] for m in masks)
    w = max(m.shape[1] for m in masks)
    pad_cells = [np.concatenate([c, np.repeat(c[:1], n - len(c), 0)]) for c in cells]
    pad_masks = [np.pad(m, ((0, h - m.shape[0]), (0, w - m.shape[1]))) for m in masks]
    goals = [room.goal_pos if room.goal_pos is not None else (0.0, 0.0) for room in layouts]
    return GoalCells(
        goal=jnp.asarray(np.array(goals, np.float32)),
        has_goal=jnp.asarray([room.goal_pos is not None for room in layouts]),
        cells=jnp.asarray(np.stack(pad_cells).astype(np.float32)),
        count=jnp.asarray([len(c) for c in cells], jnp.int32),
        main=jnp.asarray(np.stack(pad_masks)),
        shape=jnp.asarray([m.shape for m in masks], jnp.int32),
    )


# ------------------------------------------------------------------------------
# Traced draws


def _first_or_best(ok: jax.Array, score: jax.Array) -> jax.Array:
    """Index of the first True of `ok` [T], or of the highest `score` [T] if none is."""
    return jnp.where(ok.any(), jnp.argmax(ok), jnp.argmax(score))


def _on_main(g: GoalCells, half: jax.Array, xy: jax.Array) -> jax.Array:
    """[] bool: the grid cell containing `xy` is on the main component of layout `g`."""
    cols_rows = g.shape[::-1]  # [2] cells along x, y
    ij = jnp.floor((xy + half) / (2 * half) * cols_rows).astype(jnp.int32)
    col, row = jnp.clip(ij, 0, cols_rows - 1)
    return g.main[row, col]


def _layout_goal(d: Draws, params: SceneParams, goals: GoalCells, radius, clearance, min_distance):
    """(params with the spawn on the main component, [2] goal) in a layout room."""
    g = jax.tree_util.tree_map(lambda x: x[jnp.maximum(params.layout_id, 0)], goals)
    draw = lambda: g.cells[d.randint((TRIES,), 0, g.count)]  # noqa: E731
    # Spawn: kept if on the main component, else the first of TRIES uniform main cells that keeps
    # `clearance` from everything (or the one with the most clearance).
    cand = draw()  # [TRIES, 2]
    gap = signed_distance(params, cand) - radius
    moved = cand[_first_or_best(gap >= clearance, gap)]
    spawn_xy = jnp.where(_on_main(g, params.room_half, params.spawn[:2]), params.spawn[:2], moved)
    # Goal: the layout's, else the first of TRIES uniform main cells at least min_distance from
    # the spawn (straight line), or the farthest of them.
    cand = draw()
    dist = jnp.linalg.norm(cand - spawn_xy, axis=-1)
    goal = jnp.where(g.has_goal, g.goal, cand[_first_or_best(dist >= min_distance, dist)])
    return params.replace(spawn=params.spawn.at[:2].set(spawn_xy)), goal


def grid_steps(free: jax.Array, seed: jax.Array, sweeps: int = SWEEPS) -> jax.Array:
    """[..., H, W] float32 4-connected steps from the `seed` cells to every `free` cell (inf
    where unreached), for grids [..., H, W] with any leading batch axes. Each round scans east,
    west, north and south: along a scan a free cell takes min(its own, its predecessor's + 1) and
    a blocked one stays unreached.

    Under `jax.vmap`, a rule of its own (`jax.custom_batching.custom_vmap`) hands the whole batch
    to one flood: on the CPU one that loops over the rows with the batch on the arrays' minor axis
    (`_flood_rows`; docs/results.md, "What was decided and why"), on GPUs a Pallas kernel that
    runs every scan of a block of grids in one program (`flood_kernel`), on each GPU's own part
    of the batch where the devices it is split between are known (`xla.spanned`) and each part
    is large enough (`_gpu_flood`). Elsewhere (smaller batches; several devices whose part of the
    batch is not known; other accelerators) every scan is a log-depth `associative_scan`
    (`_flood_scans`). All give the same steps, bit for bit."""
    backend = jax.default_backend()
    devices = xla.spanned() if backend == "gpu" and _fits_kernel(free.shape) else None
    if backend != "cpu" and devices is None:
        return _flood_scans(free, seed, sweeps)
    free, seed = jnp.broadcast_arrays(free, seed)
    return _batched_steps(sweeps, devices)(free, seed)


def _fits_kernel(shape) -> bool:
    """Whether `flood_kernel` takes grids of `shape` [..., H, W]."""
    return shape[-2] * shape[-1] < flood_kernel.MAX_CELLS


@functools.cache
def _batched_steps(sweeps: int, devices: tuple | None):
    """`grid_steps` with `sweeps` rounds, whose vmap passes the batch to one flood: the GPUs'
    (`devices`, `_gpu_flood`) or, with None, the CPU's `_flood_rows`."""

    @jax.custom_batching.custom_vmap
    def steps(free, seed):
        if devices is None:
            return _flood_rows(free, seed, sweeps)
        return _gpu_flood(free, seed, sweeps, devices)

    @steps.def_vmap
    def _batched(axis_size, in_batched, free, seed):
        free, seed = (
            x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))
            for x, batched in zip((free, seed), in_batched, strict=True)
        )
        return steps(free, seed), True  # an outer vmap batches this call in turn

    return steps


def _gpu_flood(free, seed, sweeps: int, devices: tuple, interpret: bool = False) -> jax.Array:
    """`grid_steps` of grids [B, ..., H, W] whose first axis is split between `devices` in equal
    consecutive parts: the kernel on each device's part (`jax.shard_map` over several: no device
    waits for another) where each holds at least `flood_kernel.MIN_BATCH` grids, else the
    associative scans. `interpret`: the kernel through Pallas' interpreter (tests, on the CPU)."""
    n, batch = len(devices), math.prod(free.shape[:-2])
    if free.ndim < 3 or free.shape[0] % n or batch // n < flood_kernel.MIN_BATCH:
        return _flood_scans(free, seed, sweeps)
    kernel = functools.partial(flood_kernel.flood, sweeps=sweeps, interpret=interpret)
    if n == 1:
        return kernel(free, seed)
    part = PartitionSpec("grids")  # the first axis, one part a device
    mesh = Mesh(np.array(devices), ("grids",))
    split = jax.shard_map(kernel, mesh=mesh, in_specs=(part, part), out_specs=part, check_vma=False)
    return split(free, seed)


def _flood_scans(free: jax.Array, seed: jax.Array, sweeps: int) -> jax.Array:
    """`grid_steps` of grids [..., H, W]: each scan is a min-plus recurrence that
    `associative_scan` solves in log(length) passes (a blocked cell has infinite cost)."""
    step = jnp.where(free, 1.0, jnp.inf)

    def combine(earlier, later):  # compose x -> min(a, x + b) maps, earlier cells first
        (a1, b1), (a2, b2) = earlier, later
        return jnp.minimum(a2, a1 + b2), b1 + b2

    def sweep(steps, axis, reverse):
        steps = jnp.where(free, steps, jnp.inf)
        return jax.lax.associative_scan(combine, (steps, step), reverse, axis)[0]

    def round_(_, steps):
        for axis in (steps.ndim - 1, steps.ndim - 2):  # along the rows, then the columns
            steps = sweep(sweep(steps, axis, False), axis, True)
        return steps

    return jax.lax.fori_loop(0, sweeps, round_, jnp.where(seed & free, 0.0, jnp.inf))


def _flood_rows(free: jax.Array, seed: jax.Array, sweeps: int) -> jax.Array:
    """`grid_steps` of grids [..., H, W], computed as [H, W, batch], a scan a loop over rows."""
    lead, (h, w) = free.shape[:-2], free.shape[-2:]
    free, seed = (jnp.moveaxis(x.reshape(-1, h, w), 0, -1) for x in (free, seed))  # [H, W, B]
    # Unreached cells hold `far` or up to a row's length more (a scan starts from `far` and adds
    # one a cell), and every reachable count (< h * w) stays below it: int16 where both fit.
    small = h * w < 30_000 and max(h, w) < 2_000
    dtype, far = (jnp.int16, 30_000) if small else (jnp.int32, 2**30)

    def scan(steps, free, reverse):  # along axis 0 of [L, M, B]
        length = steps.shape[0]

        def cell(i, carry):
            out, run = carry
            j = length - 1 - i if reverse else i
            here = jax.lax.dynamic_index_in_dim(out, j, 0, keepdims=False)  # [M, B]
            ok = jax.lax.dynamic_index_in_dim(free, j, 0, keepdims=False)
            run = jnp.where(ok, jnp.minimum(here, run + 1), far).astype(dtype)
            return jax.lax.dynamic_update_index_in_dim(out, run, j, 0), run

        start = jnp.full(steps.shape[1:], far, dtype)
        return jax.lax.fori_loop(0, length, cell, (steps, start))[0]

    free_t = jnp.swapaxes(free, 0, 1)  # [W, H, B]: the columns' scans run along its rows

    def round_(_, steps):
        across = scan(scan(jnp.swapaxes(steps, 0, 1), free_t, False), free_t, True)
        steps = jnp.swapaxes(across, 0, 1)
        return scan(scan(steps, free, False), free, True)

    steps = jax.lax.fori_loop(0, sweeps, round_, jnp.where(seed & free, 0, far).astype(dtype))
    steps = jnp.where(steps >= far, jnp.inf, steps.astype(jnp.float32))
    return jnp.moveaxis(steps, -1, 0).reshape(*lead, h, w)


def grid_shape(extent: tuple[float, float]) -> tuple[int, int]:
    """(rows, columns) of the traced grid covering half extents `extent` = (long, short) m: an
    even number of `GRID_CELL` cells along each axis, the columns along the long one."""
    long, short = (2 * int(np.ceil(h / GRID_CELL)) for h in extent)
    return short, long


def _grid(extent: tuple[float, float]):
    """[rows, cols, 2] centres of the traced grid's cells in its own frame (x along the
    columns: the long axis)."""
    rows, cols = grid_shape(extent)
    axis = lambda n: (np.arange(n) - 0.5 * (n - 1)) * GRID_CELL  # noqa: E731
    return jnp.asarray(np.stack(np.meshgrid(axis(cols), axis(rows)), -1), jnp.float32)


def _transposed(shape: tuple[int, int], room_half: jax.Array | None):
    """[] bool: the grid of `shape` lies on the room transposed (the room is longer in y than in
    x); None for a square grid, which is never transposed."""
    if shape[0] == shape[1]:
        return None
    if room_half is None:
        raise ValueError(f"a traced grid of shape {shape} needs the room's half extents")
    return room_half[1] > room_half[0]


def _swap(xy: jax.Array, transposed) -> jax.Array:
    """[..., 2] points between the room's frame and the grid's (the same map both ways);
    `transposed`: `_transposed`'s [] bool, or None (a square grid: `xy` as it is)."""
    return xy if transposed is None else jnp.where(transposed, xy[..., ::-1], xy)


def _room_centres(extent: tuple[float, float], room_half: jax.Array) -> jax.Array:
    """[rows, cols, 2] centres of the traced grid's cells in the frame of the room `room_half`."""
    centres = _grid(extent)
    return _swap(centres, _transposed(centres.shape[:2], room_half))


def grid_clearance(params: SceneParams, extent: tuple[float, float]) -> jax.Array:
    """[rows, cols] m from the centre of every cell of the traced grid (`_room_centres`) to the
    nearest wall or active obstacle of the room `params` (`geometry.signed_distance`).

    Computed in `GRID_BLOCKS` blocks of rows, in a loop: a loop's operands are computed once,
    where XLA's CPU backend otherwise fuses the room sampler that drew `params` into the
    per-cell computation and repeats it for every cell (docs/results.md, "What was
    decided and why").
    """
    centres = _room_centres(extent, params.room_half)
    blocks = centres.reshape(GRID_BLOCKS, -1, *centres.shape[1:])  # [B, rows/B, cols, 2]
    per_block = jax.lax.map(lambda c: signed_distance(params, c), blocks)
    return per_block.reshape(centres.shape[:2])


def _free(params: SceneParams, extent: tuple[float, float], radius: float):
    """([rows, cols] clearance beyond the robot m, [rows, cols] bool free) of the room `params`
    on the traced grid: a cell is free where the robot clears everything by half a cell (module
    doc)."""
    gap = grid_clearance(params, extent) - radius
    return gap, gap >= 0.5 * GRID_CELL


def _free_where(need: jax.Array, room: SceneParams, free: jax.Array, extent, radius: float):
    """[rows, cols] `_free`'s cells of `room` where `need` [] bool, else `free` (those of a room
    with the same obstacles active). Under `jax.vmap`, however deeply nested
    (`jax.custom_batching`), a batch computes `room`'s grid only when one of its elements needs
    it, and then for all of them: a `lax.cond` on a batched predicate would compute it for every
    element always, and it is rarely needed (a spawn with no goal cell far enough,
    `sample_goal`). With the batch sharded over devices, that test is one reduction over them per
    batch of resets."""

    @jax.custom_batching.custom_vmap
    def batch(need, room, free):  # a batch [B] of rooms
        def some(room):
            grids = jax.vmap(lambda r: _free(r, extent, radius)[1])(room)  # [B, rows, cols]
            return jnp.where(need[:, None, None], grids, free)

        return jax.lax.cond(need.any(), some, lambda _: free, room)

    @batch.def_vmap
    def _outer(axis_size, in_batched, need, room, free):  # [A, B, ...] as one batch [A * B]
        grow = lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))  # noqa: E731
        args = jax.tree_util.tree_map(grow, (need, room, free), tuple(in_batched))
        size = args[0].shape[1]  # B (explicit: a leaf may have no elements, e.g. paths of 0 points)
        merged = jax.tree_util.tree_map(lambda x: x.reshape(axis_size * size, *x.shape[2:]), args)
        return batch(*merged).reshape(axis_size, size, *free.shape[-2:]), True

    one = lambda x: x[None]  # noqa: E731
    return batch(one(need), jax.tree_util.tree_map(one, room), one(free))[0]


def _uniform(d: Draws, ok: jax.Array) -> jax.Array:
    """Flat index of a uniform True cell of `ok` [rows, cols] (arbitrary where none is), from one
    random number rather than one per cell."""
    count = jnp.cumsum(ok.ravel())  # [rows * cols]
    return jnp.argmax(count > d.randint((), 0, jnp.maximum(count[-1], 1)))


def _half_extents(shape: tuple[int, int]) -> np.ndarray:
    """[2] m, the half extents (x, y) of the traced grid of `shape` (rows, cols), in its frame."""
    return 0.5 * np.array(shape[::-1]) * GRID_CELL


def _grid_cell(shape: tuple[int, int], xy: jax.Array, transposed) -> jax.Array:
    """[..., 2] int32 (col, row) of the cells of the traced grid of `shape` containing the room's
    points `xy` [..., 2] (outside the grid's range beyond it)."""
    half = _half_extents(shape)
    return jnp.round((_swap(xy, transposed) + half) / GRID_CELL - 0.5).astype(jnp.int32)


def _flood(free: jax.Array, centres: jax.Array, goal: jax.Array) -> jax.Array:
    """[rows, cols] grid steps from the cell nearest `goal` to every `free` cell (`grid_steps`)."""
    straight = planar_distance(centres, goal)
    return grid_steps(free, straight == straight.min())


def goal_field(params: SceneParams, extent: tuple[float, float], goal: jax.Array, radius: float):
    """[rows, cols] float32 grid steps from every cell of the traced grid (`grid_shape(extent)`)
    to the goal's cell (inf where the robot cannot reach it): the geodesic distance `geodesic`
    reads."""
    centres = _room_centres(extent, params.room_half)
    return _flood(_free(params, extent, radius)[1], centres, goal)


FIELD_FAR = np.iinfo(np.int16).max  # a packed field's unreached cells


def pack_field(field: jax.Array) -> jax.Array:
    """`goal_field`'s [rows, cols] steps as int16 (FIELD_FAR where unreached) where every count
    fits, as an episode's state keeps them: the same values in half the bytes, which the
    auto-reset moves every step. `geodesics` reads either form."""
    if field.shape[-2] * field.shape[-1] >= FIELD_FAR:
        return field
    return jnp.where(jnp.isfinite(field), field, FIELD_FAR).astype(jnp.int16)


def _unpack(steps: jax.Array) -> jax.Array:
    """float32 steps (inf where unreached) of a field or part of one, packed or not."""
    if steps.dtype != jnp.int16:
        return steps
    return jnp.where(steps == FIELD_FAR, jnp.inf, steps.astype(jnp.float32))


def geodesic(
    field: jax.Array, goal: jax.Array, xy: jax.Array, blocked=None, room_half=None
) -> jax.Array:
    """[] m from `xy` [2] to the goal along the grid of `goal_field`: the least of (a cell's
    steps x GRID_CELL + the straight line to its centre) over the 3 x 3 cells around `xy`;
    where none of them reaches the goal (a robot pressed against a wall, a point inside one),
    `blocked` [], or by default the straight line. `room_half` [2]: the room's half extents,
    needed where the grid is not square (it may lie on the room transposed)."""
    best = geodesics(field, xy, xy[None], 0.0, room_half)[0]
    fallback = jnp.linalg.norm(goal - xy) if blocked is None else blocked
    return jnp.where(jnp.isfinite(best), best, fallback)


def geodesics(field, centre, points, reach: float, room_half=None) -> jax.Array:
    """[P] `geodesic`'s least value for each of `points` [P, 2], all within `reach` m (static) of
    `centre` [2], inf where none of a point's 3 x 3 cells reaches the goal (no fallback). Every
    cell they read lies in one window of the field around `centre`'s cell, read with one slice:
    a point's cells are those of the window between its cell -1 and +1, clipped to the grid, and
    a point within `reach` > 0 lies at most floor(reach / GRID_CELL + 1) cells from `centre`'s.
    The values of reading each point's nine cells on their own, to float32 rounding
    (`tests/test_goal.py`). `field`: `goal_field`'s, or `pack_field`'s, as it is or `Banked`."""
    shape = field.shape  # rows, cols
    transposed = _transposed(shape, room_half)
    k = 1 + (int(np.floor(reach / GRID_CELL + 1)) if reach > 0 else 0)  # to a point's neighbour
    size = np.minimum(2 * k + 1, shape)  # [2] the window's rows, cols
    last = np.array(shape[::-1]) - 1  # [2] the last col, row
    start = jnp.clip(_grid_cell(shape, centre, transposed) - k, 0, last + 1 - size[::-1])
    window = _unpack(types.window(field, (start[1], start[0]), tuple(size)))  # [h, w]
    half = _half_extents(shape)
    cols = start[0] + jnp.arange(size[1])  # [w]
    rows = start[1] + jnp.arange(size[0])  # [h]
    cells = _grid_cell(shape, points, transposed)  # [P, 2] col, row
    lo, hi = jnp.clip(cells - 1, 0, last), jnp.clip(cells + 1, 0, last)  # [P, 2]
    near_col = (cols >= lo[:, :1]) & (cols <= hi[:, :1])  # [P, w]
    near_row = (rows >= lo[:, 1:]) & (rows <= hi[:, 1:])  # [P, h]
    grid_xy = _swap(points, transposed)  # [P, 2] in the grid's frame
    dx = (cols + 0.5) * GRID_CELL - half[0] - grid_xy[:, :1]  # [P, w]
    dy = (rows + 0.5) * GRID_CELL - half[1] - grid_xy[:, 1:]  # [P, h]
    line = jnp.sqrt(jnp.square(dx[:, None, :]) + jnp.square(dy[:, :, None]))  # [P, h, w]
    via = window * GRID_CELL + line
    near = near_row[:, :, None] & near_col[:, None, :]
    return jnp.where(near, via, jnp.inf).min((1, 2))


def _interior_goal(d: Draws, params: SceneParams, radius, clearance, min_distance):
    """[2] the first of TRIES uniform points of the room's interior (shrunk by the robot and
    `clearance`) at least min_distance from the spawn, or the farthest of them."""
    limit = jnp.maximum(params.room_half - radius - clearance, 0.0)
    cand = d.uniform((TRIES, 2), -1.0, 1.0) * limit
    dist = jnp.linalg.norm(cand - params.spawn[:2], axis=-1)
    return cand[_first_or_best(dist >= min_distance, dist)]


def _clear_path(d: Draws, params: SceneParams, goal, radius, path_clearance) -> SceneParams:
    """The room with every obstacle removed that blocks an L-shaped path spawn -> corner -> goal
    (half-width radius + path_clearance); the corner (spawn x, goal y) or (goal x, spawn y)."""
    spawn = params.spawn[:2]
    corner = jnp.where(
        d.bernoulli(),
        jnp.stack([spawn[0], goal[1]]),
        jnp.stack([goal[0], spawn[1]]),
    )
    t = jnp.linspace(0.0, 1.0, PATH_POINTS)[:, None]
    points = jnp.concatenate([spawn + t * (corner - spawn), corner + t * (goal - corner)])
    legs = jnp.stack([jnp.linalg.norm(corner - spawn), jnp.linalg.norm(goal - corner)])
    # Clearance is 1-Lipschitz: points `spacing` apart that keep r + spacing/2 keep r in between.
    keep = radius + path_clearance + 0.5 * legs.max() / (PATH_POINTS - 1)
    return families.clear_around(params, points, jnp.full(points.shape[0], keep))


def sample_goal(
    key: jax.Array,
    params: SceneParams,
    extent: tuple[float, float],
    goals: GoalCells,
    radius: float,
    clearance: float,
    min_distance: float,
    path_clearance: float,
) -> tuple[SceneParams, jax.Array, jax.Array]:
    """(the episode's params, [2] goal m, [rows, cols] its `goal_field`) for the room `params`
    drew (`episode.sample`), with one flood of the traced grid (`grid_shape(extent)`; `extent`
    static: half extents (long, short) that cover every room, the room's long axis along the long
    one).

    Layout rooms (layout_id >= 0) take their goal from `goals` (`_layout_goal`). Sampled rooms:
    the goal is a uniform cell at least `min_distance` from the spawn that keeps `clearance` from
    everything, and the field is flooded from it. A spawn it does not reach (a pocket) moves to a
    uniform reached cell at least `min_distance` from the goal that keeps `clearance`. Where no
    cell is far enough, the goal is a point of the interior and the obstacles on an L-shaped path
    to it are removed (`_clear_path`) before the flood; where the goal's part of the room holds no
    cell for the spawn, too (rare), after it: the field then reaches the goal's part only, and
    `geodesic` takes the straight line elsewhere.
    """
    d = Draws(key)
    centres = _room_centres(extent, params.room_half)  # [rows, cols, 2] in the room's frame
    spawn = params.spawn[:2]  # [2]
    pick = lambda ok: centres.reshape(-1, 2)[_uniform(d, ok)]  # noqa: E731
    where = lambda c, a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)  # noqa: E731
    # Sampled rooms: the goal is a uniform far cell that keeps `clearance`, else (none is far
    # enough) a point of the interior, the path to it cleared before the flood.
    gap, free = _free(params, extent, radius)
    roomy = free & (gap >= clearance)  # [rows, cols] cells a goal or a moved spawn may take
    far = roomy & (planar_distance(centres, spawn) >= min_distance)
    found = far.any()
    interior = _interior_goal(d, params, radius, clearance, min_distance)
    room_goal = jnp.where(found, pick(far), interior)
    cleared = _clear_path(d, params, room_goal, radius, path_clearance)
    layout_room, layout_goal = _layout_goal(d, params, goals, radius, clearance, min_distance)
    sampled = params.layout_id < 0
    room = where(sampled, where(found, params, cleared), layout_room)
    goal = jnp.where(sampled, room_goal, layout_goal)
    # The one flood, of `room`'s free cells: those of `params` but where the path was cleared.
    field = _flood(_free_where(sampled & ~found, cleared, free, extent, radius), centres, goal)
    # A sampled spawn the flood does not reach moves to a reached cell far from the goal that
    # keeps `clearance`; where there is none (rare), the path is cleared after the flood.
    reached = jnp.isfinite(field)
    shape = centres.shape[:2]
    cell = _grid_cell(shape, spawn, _transposed(shape, params.room_half))
    col, row = jnp.clip(cell, 0, np.array(shape[::-1]) - 1)
    spots = reached & roomy & (planar_distance(centres, goal) >= min_distance)
    move = sampled & found & ~reached[row, col]
    moved = room.spawn.at[:2].set(pick(spots))
    room = room.replace(spawn=jnp.where(move & spots.any(), moved, room.spawn))
    return where(move & ~spots.any(), cleared, room), goal, field


# ------------------------------------------------------------------------------
# Shortest paths (numpy, on the host)


def grid_graph(free: np.ndarray, step: tuple[float, float]):
    """The 8-connected graph of the free cells [H, W] (sparse [HW, HW], edge weights in m).

    `step` is the cell's (x, y) size. Orthogonal steps join free neighbours; a diagonal step
    needs all four cells of its 2 x 2 block free.
    """
    h, w = free.shape
    ids = np.arange(h * w).reshape(h, w)
    dx, dy = step
    rows, cols, costs = [], [], []

    def link(a, b, ok, cost):
        rows.append(a[ok]), cols.append(b[ok]), costs.append(np.full(int(ok.sum()), cost))

    link(ids[:, :-1], ids[:, 1:], free[:, :-1] & free[:, 1:], dx)
    link(ids[:-1, :], ids[1:, :], free[:-1, :] & free[1:, :], dy)
    block = free[:-1, :-1] & free[:-1, 1:] & free[1:, :-1] & free[1:, 1:]
    link(ids[:-1, :-1], ids[1:, 1:], block, np.hypot(dx, dy))
    link(ids[:-1, 1:], ids[1:, :-1], block, np.hypot(dx, dy))
    r, c, v = (np.concatenate(x) for x in (rows, cols, costs))
    return coo_matrix((v, (r, c)), shape=(h * w, h * w)).tocsr()


class ShortestPaths:
    """Shortest path lengths in one room, its grid and graph built once (see `shortest_paths`)."""

    def __init__(self, layout: lay.RoomLayout, radius: float = lay.ROBOT_RADIUS, cell=CELL):
        self.free, self.centres = families.free_cells(layout, radius, cell)
        size = np.asarray(layout.size, np.float64)
        step = (size[0] / self.free.shape[1], size[1] / self.free.shape[0])
        self.graph = grid_graph(self.free, step)

    def __call__(self, starts, goals) -> np.ndarray:
        """[E] m from starts [E, 2] to goals [E, 2]."""
        starts, goals = np.asarray(starts, np.float64), np.asarray(goals, np.float64)
        src = np.array([_nearest(self.free, self.centres, g) for g in goals])
        dst = np.array([_nearest(self.free, self.centres, s) for s in starts])
        if (src < 0).any():
            return np.full(len(starts), np.inf)
        unique, inverse = np.unique(src, return_inverse=True)
        table = dijkstra(self.graph, directed=False, indices=unique)  # [U, H * W]
        return np.maximum(table[inverse.ravel(), dst], np.linalg.norm(goals - starts, axis=-1))


def shortest_paths(
    layout: lay.RoomLayout, starts, goals, radius: float = lay.ROBOT_RADIUS, cell: float = CELL
) -> np.ndarray:
    """[E] shortest path lengths (m) for a robot of `radius` from starts [E, 2] to goals [E, 2].

    On the occupancy grid of `families.free_cells` (`cell` m, obstacles inflated by the radius),
    8-connected (`grid_graph`), between the free cells nearest each start and goal; never less
    than the straight line. inf where no path exists. Grid paths run up to 8 % longer than the
    true shortest path (octile vs. Euclidean), the grid rounds inflated obstacles out by up to a
    cell, and each end may be off by half a cell.
    """
    return ShortestPaths(layout, radius, cell)(starts, goals)
