"""An occupancy-grid obstacle layer: a room's clutter as square cells instead of obstacle slots.

Each occupied cell is an axis-aligned box from the floor to the grid's `height`. A ray is cast on
the grid in one pass over the grid lines: every crossing of a grid line (and of the top and bottom
planes) where the ray enters an occupied cell is a candidate, and the nearest is where it first
meets the union of the cells' boxes, exactly as if each cell were a box slot (`geometry.ray_cast`'s
slab test; tested to 1e-5 m). So a field of hundreds of cells costs about 2 G + 2 gathers a ray,
whatever the number of occupied cells. Distances read the cells within `REACH` cells of the point:
exact wherever the nearest cell lies within that reach (at least 0.5 m with 0.1 m cells), +inf
where none does.

Cells are never dark (`SceneParams.dark` is per slot) and moving obstacles pass through them (they
bounce off walls and slots only). A room without a grid has `SceneParams.grid` None (nothing is
computed); a batch that mixes rooms with and without one gives the others an `empty` grid of the
same shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# Cells on each side of a point's own cell that `distance` reads: 0.5 m at the families' smallest
# cell (0.1 m), beyond a spawn's clearance (robot radius + 0.3 m).
REACH = 5


@struct.dataclass
class OccupancyGrid:
    """One room's occupancy grid (a batch adds a leading axis to every array)."""

    # [G, G] bool, occupied: cell (row i, column j) spans x in ox + [j, j + 1] c, y in oy + [i, i + 1] c
    cells: jax.Array
    origin: jax.Array  # [2] m, (ox, oy): the south-west corner of cell (0, 0)
    cell: jax.Array  # [] m, c: the side of a cell
    height: jax.Array  # [] m, the top of every occupied cell (each stands on the floor)


def empty(g: int) -> OccupancyGrid:
    """A [g, g] grid with no occupied cell (numpy: for banks and placeholders)."""
    f32 = np.float32
    return OccupancyGrid(
        cells=np.zeros((g, g), bool), origin=np.zeros(2, f32), cell=f32(0.1), height=f32(1.0)
    )


def size(grid) -> int:
    """G, the static side of `grid` in cells (0 for None)."""
    return 0 if grid is None else int(grid.cells.shape[-1])


def _lookup(grid: OccupancyGrid):
    """A function (row, col) [...] int32 -> [...] bool: the cell lies on the grid and is occupied."""
    g = grid.cells.shape[-1]
    flat = grid.cells.reshape(-1)  # [G * G]

    def occupied(row, col):
        inside = (row >= 0) & (row < g) & (col >= 0) & (col < g)
        return inside & flat[jnp.clip(row, 0, g - 1) * g + jnp.clip(col, 0, g - 1)]

    return occupied


def _safe(x):
    """x with zeros moved to a tiny signed value, for 1 / x."""
    return jnp.where(jnp.abs(x) < 1e-12, jnp.where(x < 0, -1e-12, 1e-12), x)


def _side_hits(grid, occupied, o, dz, moving, t, row, col) -> jax.Array:
    """[...] the nearest of the crossings at `t` [..., L] (m) into cells (row, col) [..., L]
    that are `occupied`, ahead, and between the floor and the cells' top there."""
    z = o[2] + t * dz
    ok = moving & (t >= 0) & (z >= 0) & (z <= grid.height) & occupied(row, col)
    return jnp.where(ok, t, jnp.inf).min(-1)


def ray_cast(o: jax.Array, d: jax.Array, grid: OccupancyGrid) -> jax.Array:
    """[...] distance along unit `d` [..., 3] from `o` [3] to the first occupied cell's box (inf:
    none). A ray starting inside a cell does not see that cell (as the slab test of a box)."""
    g, c, h = grid.cells.shape[-1], grid.cell, grid.height
    lx, ly = (o[0] - grid.origin[0]) / c, (o[1] - grid.origin[1]) / c  # [] origin, in cells
    dx, dy, dz = d[..., 0, None], d[..., 1, None], d[..., 2, None]  # [..., 1] each
    occupied = _lookup(grid)
    k = jnp.arange(g + 1)  # [G + 1] grid lines, in cells
    # Lines x = k: the ray enters column k going east, k - 1 going west.
    tx = (k - lx) * c / _safe(dx)  # [..., G + 1] m
    row = jnp.floor(ly + tx * dy / c).astype(jnp.int32)
    hits = [_side_hits(grid, occupied, o, dz, dx != 0, tx, row, k - (dx < 0))]
    # Lines y = k: the ray enters row k going north, k - 1 going south.
    ty = (k - ly) * c / _safe(dy)
    col = jnp.floor(lx + ty * dx / c).astype(jnp.int32)
    hits.append(_side_hits(grid, occupied, o, dz, dy != 0, ty, k - (dy < 0), col))
    # The top (downwards) and bottom (upwards) planes: enters the cell below or above the point.
    for plane, sign in ((h, -1.0), (0.0, 1.0)):
        t = (plane - o[2]) / _safe(dz[..., 0])  # [...]
        col = jnp.floor(lx + t * dx[..., 0] / c).astype(jnp.int32)
        row = jnp.floor(ly + t * dy[..., 0] / c).astype(jnp.int32)
        ok = (dz[..., 0] * sign > 0) & (t >= 0) & occupied(row, col)
        hits.append(jnp.where(ok, t, jnp.inf))
    return jnp.minimum(jnp.minimum(hits[0], hits[1]), jnp.minimum(hits[2], hits[3]))


def distance(p, grid: OccupancyGrid, z=None, reach: int = REACH) -> jax.Array:
    """[...] signed distance from points p [..., 2] to the nearest occupied cell's box within
    `reach` cells of the point's own cell (<0 inside; inf where none is). Each cell is a box
    like `geometry.box_distance`'s; with z = (low, high) [...], 3-D from the vertical segment at p
    between those heights, as `geometry.signed_distance` measures boxes."""
    p = jnp.asarray(p)
    c = grid.cell
    lx, ly = (p[..., 0] - grid.origin[0]) / c, (p[..., 1] - grid.origin[1]) / c  # [...] cells
    offsets = jnp.arange(-reach, reach + 1)  # [W]
    col = jnp.floor(lx).astype(jnp.int32)[..., None, None] + offsets  # [..., 1, W]
    row = jnp.floor(ly).astype(jnp.int32)[..., None, None] + offsets[:, None]  # [..., W, 1]
    # Per-axis distance beyond each cell's faces, m (cells are unrotated boxes of half side c/2).
    qx = (jnp.abs(lx[..., None, None] - (col + 0.5)) - 0.5) * c  # [..., 1, W]
    qy = (jnp.abs(ly[..., None, None] - (row + 0.5)) - 0.5) * c  # [..., W, 1]
    outside = jnp.sqrt(jnp.maximum(qx, 0.0) ** 2 + jnp.maximum(qy, 0.0) ** 2)
    flat = outside + jnp.minimum(jnp.maximum(qx, qy), 0.0)  # [..., W, W]
    if z is not None:
        low, high = (jnp.asarray(v)[..., None, None] for v in z)
        dz = jnp.maximum(low - grid.height, -high)  # to the span [0, height]
        corner = (flat > 0) & (dz > 0)
        flat = jnp.where(corner, jnp.hypot(flat, dz), jnp.maximum(flat, dz))
    return jnp.where(_lookup(grid)(row, col), flat, jnp.inf).min((-2, -1))


def cell_boxes(grid) -> tuple[np.ndarray, np.ndarray]:
    """([N, 2] centres, [N, 2] half extents), m, of the occupied cells of one grid (numpy)."""
    cells = np.asarray(grid.cells)
    rows, cols = np.nonzero(cells)
    c = float(np.asarray(grid.cell))
    centres = np.asarray(grid.origin, np.float64) + (np.stack([cols, rows], -1) + 0.5) * c
    return centres, np.full_like(centres, 0.5 * c)


def with_grid(room, g: int):
    """`room` (SceneParams) with an empty [g, g] grid if it has none and g > 0."""
    if g == 0 or room.grid is not None:
        return room
    return room.replace(grid=jax.tree_util.tree_map(jnp.asarray, empty(g)))


def pad(grid: OccupancyGrid, g: int) -> OccupancyGrid:
    """`grid` [G0, G0] grown to [g, g] with free cells to the north and east (g >= G0)."""
    g0 = grid.cells.shape[-1]
    if g0 == g:
        return grid
    cells = jnp.zeros((g, g), bool).at[:g0, :g0].set(grid.cells)
    return grid.replace(cells=cells)
