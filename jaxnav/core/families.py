"""Room families: pure, vmappable samplers `family(key, nb, nc, radius) -> SceneParams`.

Each family draws one room of a kind (open, clutter, pillar grid, corridor, L/T/U, joined rooms,
furniture, low obstacles and overhangs) into `nb` box and `nc` cylinder slots. All draws are traced
data: `sample_family(key, index, ...)` picks a family by a traced index, so mixing families never
recompiles. Interior walls are boxes. Every room leaves the robot's spawn free by `SPAWN_CLEARANCE`
(obstacles that would come nearer are deactivated), keeps every obstacle inside the walls and leaves
doorways and corridors at least `MIN_DOOR` / `MIN_CORRIDOR` wide. `GRID_FAMILIES` (dense_field,
BARN-like clutter) put their obstacles on an occupancy grid (`jaxnav.core.grid`) instead of slots;
`sample_weighted` draws them by name, with an empty grid in every other room of the batch.

The free-space tools at the end (`free_cells`, `reachable`, `coverage`) work on `RoomLayout`s in
numpy: a 0.1 m occupancy grid inflated by the robot radius, flood-filled from the spawn.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxnav.core import grid as occupancy
from jaxnav.core import layout as lay
from jaxnav.core.crowd import CROWD_ROOM
from jaxnav.core.draws import Draws, draws
from jaxnav.core.geometry import UNUSED_HEIGHT, UNUSED_SIZE, box_distance
from jaxnav.core.randomize import (
    RANDOM,
    RandomizeConfig,
    SceneParams,
    empty_room,
    family_weights,
    sample_room,
)

SPAWN_CLEARANCE = 0.3  # m between the robot's edge and anything at the spawn (RandomizeConfig's)
WALL = 0.1  # m, thickness of interior walls
MIN_DOOR = 0.8  # m, narrowest doorway between joined rooms
MIN_CORRIDOR = 1.2  # m, narrowest corridor, arm of an L/T/U room or U-turn
FAMILY_BOXES = 16  # box slots the families need (pillar grid 4 x 4, furniture 3 x 5)
FAMILY_CYLINDERS = 4  # cylinder slots the families use at most
CELL = 0.1  # m, occupancy grid cell of `free_cells`
_BLOCK = 4096  # grid points per clearance call in `free_cells`
COVER_REACH = 1.0  # m, the robot "covers" free space within this distance of its path
FIELD_CELLS = 40  # G, the grid side of `dense_field` in cells (rooms up to 40 x 0.2 = 8 m)
FIELD_MARGIN = 0.2  # m, least gap between the robot's edge and a cell along `dense_field`'s path
FIELD_WAYPOINTS = 4  # points of `dense_field`'s path, south wall to north wall
HALL_LENGTH = (8.0, 30.0)  # m, range of `long_hall`'s length
HALL_WIDTH = (MIN_CORRIDOR, 4.0)  # m, range of a hall's width
FLOOR_WIDTH = (6.0, 12.0)  # m, range of the width of `long_hall`'s open floors (one in four)
LARGE_EXTENTS = {"long_hall": (0.5 * HALL_LENGTH[1], 0.5 * FLOOR_WIDTH[1])}
"""Half extents (long, short) m of the largest room of each family whose rooms do not fit a
square of 2 x `goals.GRID_HALF` (`randomize.LARGE_FAMILIES`): what the goal task's grid covers."""


@struct.dataclass
class Boxes:
    """Box obstacles of one room before they are padded into slots. N = boxes."""

    pos: jax.Array  # [N, 2] centres, m
    half: jax.Array  # [N, 2] half extents along the box's own axes, m
    yaw: jax.Array  # [N] rad
    height: jax.Array  # [N] top above the floor, m
    bottom: jax.Array  # [N] underside above the floor, m
    active: jax.Array  # [N] bool


def _walls(pos, half, d: Draws, active=True) -> Boxes:
    """Axis-aligned standing wall boxes [N]; top uniform in [0.5, 1.0] m."""
    n = pos.shape[0]
    return Boxes(
        pos=pos,
        half=half,
        yaw=jnp.zeros(n),
        height=d.uniform((n,), 0.5, 1.0),
        bottom=jnp.zeros(n),
        active=jnp.broadcast_to(jnp.asarray(active), (n,)),
    )


def _join(*groups: Boxes) -> Boxes:
    return jax.tree_util.tree_map(lambda *x: jnp.concatenate(x), *groups)


def _assemble(
    d: Draws, half, spawn_xy, boxes: Boxes, nb: int, nc: int, radius: float
) -> SceneParams:
    """A room of interior `half` [2] with `boxes` in the first slots and a spawn at `spawn_xy` [2]."""
    n = boxes.pos.shape[0]
    if n > nb:
        raise ValueError(f"room families: need {n} box slots, got num_boxes={nb}")
    room = empty_room(nb, nc)
    pad = lambda x, fill: jnp.concatenate([x, jnp.full((nb - n, *x.shape[1:]), fill, x.dtype)])  # noqa: E731
    # Heading at the spawn: uniform in [-pi, pi).
    spawn = jnp.append(spawn_xy, d.uniform((), -jnp.pi, jnp.pi))
    room = room.replace(
        room_half=half,
        box_pos=pad(boxes.pos, 0.0),
        box_half=pad(boxes.half, UNUSED_SIZE),
        box_yaw=pad(boxes.yaw, 0.0),
        box_height=pad(boxes.height, UNUSED_HEIGHT),
        box_bottom=pad(boxes.bottom, 0.0),
        box_active=pad(boxes.active, False),
        spawn=spawn,
    )
    return clear_around(room, spawn_xy[None], jnp.array([radius + SPAWN_CLEARANCE]))


def clear_around(room: SceneParams, points, keep, first_box: int = 0) -> SceneParams:
    """Deactivates every obstacle nearer than `keep` [P] m to one of `points` [P, 2] (of the
    boxes, only slots from `first_box` on: the ones before are walls placed clear by design)."""
    box = box_distance(points, room.box_pos, room.box_yaw, room.box_half)  # [P, Sb]
    cyl = jnp.linalg.norm(points[:, None] - room.cyl_pos, axis=-1) - room.cyl_radius  # [P, Sc]
    spare = jnp.arange(box.shape[1]) < first_box
    return room.replace(
        box_active=room.box_active & ((box >= keep[:, None]).all(0) | spare),
        cyl_active=room.cyl_active & (cyl >= keep[:, None]).all(0),
    )


def _mirror(d: Draws, room: SceneParams) -> SceneParams:
    """The room flipped in x and in y (each with probability 1/2) and transposed (probability 1/2)."""
    sign = jnp.where(d.bernoulli(0.5, (2,)), -1.0, 1.0)  # [2]
    yaw_sign = sign[0] * sign[1]  # a box is symmetric under a half turn: a flip negates its yaw
    swap = d.bernoulli()
    perm = lambda xy: jnp.where(swap, xy[..., ::-1], xy)  # noqa: E731
    yaw = lambda a: jnp.where(swap, 0.5 * jnp.pi - yaw_sign * a, yaw_sign * a)  # noqa: E731
    return room.replace(
        room_half=perm(room.room_half),
        box_pos=perm(room.box_pos * sign),
        box_yaw=yaw(room.box_yaw),
        cyl_pos=perm(room.cyl_pos * sign),
        spawn=jnp.append(perm(room.spawn[:2] * sign), room.spawn[2]),
    )


def _room_half(d: Draws, lo, hi):
    """[2] half interior extents, full extents uniform per axis in [lo, hi] m."""
    return 0.5 * d.uniform((2,), lo, hi)


# ------------------------------------------------------------------------------
# The families


def open_room(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A nearly empty room: 3-9 m a side, 0-2 boxes, 0-1 cylinder."""
    cfg = RandomizeConfig(
        room_size_min=(3.0, 3.0),
        room_size_max=(9.0, 9.0),
        num_boxes=(0, min(2, nb)),
        num_cylinders=(0, min(1, nc)),
    )
    return sample_room(key, cfg, nb, nc, radius)


def crowd_room(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A 5-10 m room with 1-3 boxes and 0-2 cylinders, for people to cross: its walkers are
    added at the reset (`crowd.add_walkers`, `crowd.WalkerConfig.crowd_count`), which knows the
    room by its `layout_id` (`crowd.CROWD_ROOM`)."""
    cfg = RandomizeConfig(
        room_size_min=(5.0, 5.0),
        room_size_max=(10.0, 10.0),
        num_boxes=(min(1, nb), min(3, nb)),
        num_cylinders=(0, min(2, nc)),
    )
    return sample_room(key, cfg, nb, nc, radius).replace(layout_id=jnp.int32(CROWD_ROOM))


def clutter(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A 4-8 m room with nb/2-nb boxes and nc/2-nc cylinders (sample_room's distributions)."""
    cfg = RandomizeConfig(num_boxes=(nb // 2, nb), num_cylinders=(nc // 2, nc))
    return sample_room(key, cfg, nb, nc, radius)


def low_and_overhang(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A 4-8 m room of 4-10 obstacles, 40 % low (below the camera), 40 % overhangs (tables)."""
    cfg = RandomizeConfig(
        num_boxes=(min(4, nb), min(10, nb)),
        num_cylinders=(0, nc),
        low_prob=0.4,
        overhang_prob=0.4,
    )
    return sample_room(key, cfg, nb, nc, radius)


def pillars(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A grid of square pillars (a car park, a hall): up to 4 x 4, the spawn between four."""
    d = draws(key)
    g = min(4, int(np.sqrt(nb)))
    # Interior: uniform 5-9 m per axis. Spacing: uniform 1.2-2.0 m. Pillar side: uniform 0.2-0.4 m.
    half = _room_half(d, 5.0, 9.0)
    spacing = d.uniform((), 1.2, 2.0)
    side = d.uniform((), 0.2, 0.4)
    # Grid offset: uniform in +-spacing/2 per axis; the spawn is the midpoint of the central four.
    offset = d.uniform((2,), -0.5, 0.5) * spacing
    idx = jnp.arange(g) - 0.5 * (g - 1)
    grid = jnp.stack(jnp.meshgrid(idx, idx), -1).reshape(-1, 2) * spacing + offset  # [g*g, 2]
    # A pillar stays only if a robot still passes between it and the walls (0.4 m).
    inside = (jnp.abs(grid) + 0.5 * side + 0.4 <= half).all(-1)
    boxes = _walls(grid, jnp.full((g * g, 2), 0.5) * side, d, inside)
    room = _assemble(d, half, offset, boxes, nb, nc, radius)
    return _mirror(d, room)


def corridor(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A serpentine corridor: 2-4 lanes 1.2-2.5 m wide, joined by U-turns at alternate ends."""
    d = draws(key)
    # Lanes: uniform in {2, 3, 4}; width uniform 1.2-2.5 m; length uniform 5-9 m;
    # U-turn opening uniform 1.2-2.0 m.
    lanes = d.randint((), 2, 5)
    width = d.uniform((), MIN_CORRIDOR, 2.5)
    hx = 0.5 * d.uniform((), 5.0, 9.0)
    gap = d.uniform((), MIN_CORRIDOR, 2.0)
    hy = 0.5 * (lanes * width + (lanes - 1) * WALL)
    k = jnp.arange(3)  # interior wall k separates lanes k and k + 1
    side = jnp.where(k % 2 == 0, -1.0, 1.0)  # even walls start at the west wall, odd at the east
    pos = jnp.stack([-side * 0.5 * gap, -hy + (k + 1) * width + (k + 0.5) * WALL], -1)
    wall_half = jnp.stack([jnp.full(3, hx - 0.5 * gap), jnp.full(3, 0.5 * WALL)], -1)
    boxes = _walls(pos, wall_half, d, k < lanes - 1)
    # Spawn: the middle of the first lane, uniform along it.
    x = d.uniform((), -1.0, 1.0) * (hx - radius - SPAWN_CLEARANCE)
    spawn = jnp.stack([x, -hy + 0.5 * width])
    room = _assemble(d, jnp.stack([hx, hy]), spawn, boxes, nb, nc, radius)
    return _mirror(d, room)


def ltu_room(key, nb: int, nc: int, radius: float) -> SceneParams:
    """An L, T (upside down) or U room: a 5-9 m rectangle with solid blocks along one wall."""
    d = draws(key)
    # Shape: L, T or U uniformly; interior uniform 5-9 m per axis; the open strip along the south
    # wall and the arms uniform 1.2-2.0 m wide.
    shape = d.randint((), 0, 3)
    hx, hy = _room_half(d, 5.0, 9.0)
    strip = d.uniform((), MIN_CORRIDOR, 2.0)
    arm = d.uniform((), MIN_CORRIDOR, 2.0)
    block_hy = 0.5 * (2 * hy - strip)
    y = hy - block_hy
    # [2] blocks as west and east edges: L blocks the east, T both sides of a stem, U the middle.
    zero = jnp.zeros(())
    west = jnp.where(shape == 1, jnp.stack([-hx, 0.5 * arm]), jnp.stack([-hx + arm, zero]))
    east_l_u = jnp.stack([jnp.where(shape == 0, hx, hx - arm), zero])
    east = jnp.where(shape == 1, jnp.stack([-0.5 * arm, hx]), east_l_u)  # [2]
    centre = jnp.stack([0.5 * (west + east), jnp.full(2, y)], -1)  # [2, 2]
    half = jnp.stack([0.5 * (east - west), jnp.full(2, block_hy)], -1)  # [2, 2]
    active = jnp.array([True, False]) | (shape == 1)
    boxes = _walls(centre, jnp.maximum(half, 0.05), d, active)
    # Spawn: the middle of the south strip, uniform along it.
    x = d.uniform((), -1.0, 1.0) * (hx - radius - SPAWN_CLEARANCE)
    spawn = jnp.stack([x, -hy + 0.5 * strip])
    room = _assemble(d, jnp.stack([hx, hy]), spawn, boxes, nb, nc, radius)
    return _mirror(d, room)


def _scatter(d: Draws, half, bound, n: int):
    """[n, 2] uniform centres whose bounding circles (radius `bound` [n]) lie inside the room."""
    limit = jnp.maximum(half - bound[:, None], 0.0)  # [n, 2]
    return d.uniform((n, 2), -1.0, 1.0) * limit


def _furniture_boxes(d: Draws, half, n: int) -> Boxes:
    """[n] standing boxes: full extents uniform 0.3-1.0 m, yaw uniform, top uniform 0.4-1.0 m."""
    box_half = 0.5 * d.uniform((n, 2), 0.3, 1.0)
    pos = _scatter(d, half, jnp.linalg.norm(box_half, axis=-1), n)
    return Boxes(
        pos=pos,
        half=box_half,
        yaw=d.uniform((n,), -jnp.pi, jnp.pi),
        height=d.uniform((n,), 0.4, 1.0),
        bottom=jnp.zeros(n),
        active=jnp.ones(n, bool),
    )


def joined_rooms(key, nb: int, nc: int, radius: float) -> SceneParams:
    """Two or three rooms side by side, each pair joined by a doorway 0.8-1.2 m wide, with up
    to 6 pieces of furniture kept out of the doorways."""
    d = draws(key)
    # Rooms: 2 or 3 uniformly; interior 7-10 m along x, 3.5-6 m along y.
    rooms = d.randint((), 2, 4)
    hx = 0.5 * d.uniform((), 7.0, 10.0)
    hy = 0.5 * d.uniform((), 3.5, 6.0)
    # Dividers: evenly spaced, each moved uniformly by +-0.3 m; doors uniform 0.8-1.2 m wide,
    # centred uniformly with 0.3 m of wall kept on either side.
    k = jnp.arange(2)
    x = -hx + (k + 1) * 2 * hx / rooms + d.uniform((2,), -0.3, 0.3)  # [2]
    door = d.uniform((2,), MIN_DOOR, 1.2)
    door_y = d.uniform((2,), -1.0, 1.0) * (hy - 0.5 * door - 0.3)
    south, north = door_y - 0.5 * door + hy, hy - door_y - 0.5 * door  # [2] wall lengths
    pos = jnp.concatenate(
        [jnp.stack([x, -hy + 0.5 * south], -1), jnp.stack([x, hy - 0.5 * north], -1)]
    )
    wall_half = jnp.stack([jnp.full(4, 0.5 * WALL), 0.5 * jnp.concatenate([south, north])], -1)
    used = jnp.tile(k < rooms - 1, 2)
    walls = _walls(pos, wall_half, d, used)
    n_furniture = min(6, nb - 4)
    # Furniture: 0-6 pieces (count uniform), none within a robot's width of a doorway.
    furniture = _furniture_boxes(d, jnp.stack([hx, hy]), n_furniture)
    count = d.randint((), 0, n_furniture + 1)
    furniture = furniture.replace(active=jnp.arange(n_furniture) < count)
    # Spawn: the middle of the west room.
    spawn = jnp.stack([0.5 * (-hx + x[0]), 0.0])
    half = jnp.stack([hx, hy])
    room = _assemble(d, half, spawn, _join(walls, furniture), nb, nc, radius)
    doors = jnp.stack([x, door_y], -1)  # [2, 2]
    room = clear_around(room, doors, 0.5 * door + 2 * radius + 0.1, first_box=4)
    return _mirror(d, room)


def furniture(key, nb: int, nc: int, radius: float) -> SceneParams:
    """1-3 tables in a 5-9 m room, each with up to 4 chairs around it."""
    d = draws(key)
    c = min(3, nb // 5)
    # Interior uniform 5-9 m per axis; clusters: 1-c uniformly; table extents uniform
    # 0.8-1.6 m x 0.6-1.0 m, yaw uniform; chair 0.4 x 0.4 m; each chair there with probability 0.7.
    half = _room_half(d, 5.0, 9.0)
    count = d.randint((), 1, c + 1)
    table = 0.5 * jnp.stack([d.uniform((c,), 0.8, 1.6), d.uniform((c,), 0.6, 1.0)], -1)
    yaw = d.uniform((c,), -jnp.pi, jnp.pi)
    reach = jnp.linalg.norm(table + 0.55, axis=-1)  # [c] bounding circle of table and chairs
    centre = _scatter(d, half, reach, c)  # [c, 2]
    # Chairs 0.15 m beyond each side of the table, in the table's frame: +x, -x, +y, -y.
    unit = jnp.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])  # [4, 2]
    local = unit[None] * (table[:, None] + 0.35)  # [c, 4, 2]
    rot = jnp.stack([jnp.cos(yaw), -jnp.sin(yaw), jnp.sin(yaw), jnp.cos(yaw)], -1).reshape(c, 2, 2)
    turned = jnp.einsum("cij,ckj->cki", rot, local, precision="highest")  # float32 on a GPU too
    chairs = centre[:, None] + turned  # [c, 4, 2]
    chair_on = d.bernoulli(0.7, (c, 4))
    used = jnp.arange(c) < count  # [c]
    boxes = Boxes(
        pos=jnp.concatenate([centre, chairs.reshape(-1, 2)]),
        half=jnp.concatenate([table, jnp.full((4 * c, 2), 0.2)]),
        yaw=jnp.concatenate([yaw, jnp.repeat(yaw, 4)]),
        # Tops: tables 0.7-0.8 m, chairs 0.45-0.9 m (seat or back), uniform.
        height=jnp.concatenate([d.uniform((c,), 0.7, 0.8), d.uniform((4 * c,), 0.45, 0.9)]),
        bottom=jnp.zeros(5 * c),
        active=jnp.concatenate([used, (chair_on & used[:, None]).reshape(-1)]),
    )
    # Spawn: uniform over the room, away from the walls.
    spawn = d.uniform((2,), -1.0, 1.0) * (half - radius - SPAWN_CLEARANCE)
    return _assemble(d, half, spawn, boxes, nb, nc, radius)


def long_hall(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A hall 8-30 m long and 1.2-4 m wide (one in four: an open floor 6-12 m wide), with up to
    4 cabinets along one side wall, so the far end often lies beyond the camera's 8 m."""
    d = draws(key)
    # Length uniform 8-30 m; width uniform 1.2-4 m, or (probability 1/4) 6-12 m.
    length = d.uniform((), *HALL_LENGTH)
    wide = d.bernoulli(0.25)
    width = jnp.where(wide, d.uniform((), *FLOOR_WIDTH), d.uniform((), *HALL_WIDTH))
    half = 0.5 * jnp.stack([length, width])
    n = min(4, nb)
    # Cabinets: 0-n (count uniform), along x uniform, 0.3-1.0 m long; all against one side wall
    # (side uniform), each 0.2-0.6 m deep but leaving MIN_DOOR beside it; top uniform 0.4-1.0 m.
    count = d.randint((), 0, n + 1)
    long_half = 0.5 * d.uniform((n,), 0.3, 1.0)
    depth = jnp.minimum(d.uniform((n,), 0.2, 0.6), jnp.maximum(width - MIN_DOOR, 0.1))
    side = jnp.where(d.bernoulli(), 1.0, -1.0)
    x = d.uniform((n,), -1.0, 1.0) * (half[0] - long_half)
    pos = jnp.stack([x, side * (half[1] - 0.5 * depth)], -1)  # [n, 2]
    boxes = _walls(pos, jnp.stack([long_half, 0.5 * depth], -1), d, jnp.arange(n) < count)
    # Spawn: uniform along the hall, on its centre line.
    spawn = jnp.stack([d.uniform((), -1.0, 1.0) * (half[0] - radius - SPAWN_CLEARANCE), 0.0])
    room = _assemble(d, half, spawn, boxes, nb, nc, radius)
    return _mirror(d, room)


FAMILIES = {
    "open": open_room,
    "clutter": clutter,
    "pillars": pillars,
    "corridor": corridor,
    "ltu": ltu_room,
    "joined": joined_rooms,
    "furniture": furniture,
    "low_overhang": low_and_overhang,
    "crowd": crowd_room,
    "long_hall": long_hall,
}
"""Name -> sampler `(key, nb, nc, radius) -> SceneParams`; `sample_family` indexes them in order.
The names are `randomize.FAMILY_NAMES` after 'random' (tests/test_families.py checks)."""


# ------------------------------------------------------------------------------
# Families on an occupancy grid (`jaxnav.core.grid`): not in `FAMILIES`, whose rooms have none


def _neighbours(cells: jax.Array) -> jax.Array:
    """[H, W] int32 count of the 8 neighbours of each cell that are occupied (none beyond)."""
    h, w = cells.shape
    padded = jnp.pad(cells.astype(jnp.int32), 1)
    shifts = [(i, j) for i in range(3) for j in range(3) if (i, j) != (1, 1)]
    return sum(padded[i : i + h, j : j + w] for i, j in shifts)


def _automaton(d: Draws, inside: jax.Array, fill, rounds) -> jax.Array:
    """[G, G] bool: a cellular-automaton field on the `inside` cells [G, G]: each occupied with
    probability `fill`, then `rounds` (traced, at most 4) rounds in which a free cell becomes
    occupied with at least 5 occupied neighbours and an occupied one stays with at least 2: lone
    cells vanish and clusters grow into blobs, as in BARN's generator."""
    cells = d.bernoulli(fill, inside.shape) & inside

    def round_(i, cells):
        n = _neighbours(cells)
        grown = jnp.where(cells, n >= 2, n >= 5) & inside
        return jnp.where(i < rounds, grown, cells)

    return jax.lax.fori_loop(0, 4, round_, cells)


def _polyline_distance(p: jax.Array, path: jax.Array) -> jax.Array:
    """[...] distance from points p [..., 2] to the polyline through `path` [K, 2], m."""
    a, b = path[:-1], path[1:]  # [K - 1, 2] each
    ab = b - a
    ap = p[..., None, :] - a  # [..., K - 1, 2]
    t = jnp.clip((ap * ab).sum(-1) / jnp.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return jnp.linalg.norm(ap - t[..., None] * ab, axis=-1).min(-1)


def dense_field(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A field of square cells like BARN's worlds (`jaxnav.core.grid`), 3-8 m a side, with a path
    for the robot from the spawn by the south wall to the north wall; no obstacle slots used."""
    d = draws(key)
    g = FIELD_CELLS
    # Cell side uniform 0.1-0.2 m; field uniform 30-40 cells per axis (the room is the field).
    cell = d.uniform((), 0.1, 0.2)
    n = d.randint((2,), 30, g + 1)  # [2] cells along x, y
    half = 0.5 * n * cell
    # Initial fill uniform 0.15-0.35; smoothing rounds uniform in {2, 3, 4} (BARN's ranges).
    fill = d.uniform((), 0.15, 0.35)
    rounds = d.randint((), 2, 5)
    idx = jnp.arange(g)
    inside = (idx[:, None] < n[1]) & (idx[None, :] < n[0])  # [G, G] rows along y, columns x
    cells = _automaton(d, inside, fill, rounds)
    # Path: FIELD_WAYPOINTS points evenly spaced from the south to the north wall, x uniform,
    # each keeping the robot and its spawn clearance from the walls; the spawn is its first.
    keep = radius + SPAWN_CLEARANCE
    ys = jnp.linspace(-1.0, 1.0, FIELD_WAYPOINTS) * (half[1] - keep)
    xs = d.uniform((FIELD_WAYPOINTS,), -1.0, 1.0) * (half[0] - keep)
    path = jnp.stack([xs, ys], -1)  # [K, 2]
    # Cleared: every cell whose box comes within the robot and FIELD_MARGIN of the path (its
    # centre within that and half its diagonal), or within the spawn clearance of the spawn.
    centres = -half + (jnp.stack(jnp.meshgrid(idx, idx), -1) + 0.5) * cell  # [G, G, 2]
    diagonal = cell * np.sqrt(0.5)
    near_path = _polyline_distance(centres, path) < radius + FIELD_MARGIN + diagonal
    near_spawn = jnp.linalg.norm(centres - path[0], axis=-1) < keep + diagonal
    cells = cells & ~near_path & ~near_spawn
    field = occupancy.OccupancyGrid(
        # Height of the cells uniform 0.5-1.0 m (BARN's are 1 m).
        cells=cells,
        origin=-half,
        cell=cell,
        height=d.uniform((), 0.5, 1.0),
    )
    spawn = jnp.append(path[0], d.uniform((), -jnp.pi, jnp.pi))  # heading uniform
    return empty_room(nb, nc).replace(room_half=half, spawn=spawn, grid=field)


GRID_FAMILIES = {"dense_field": dense_field}
"""Name -> sampler of the families whose rooms have an occupancy grid of `FIELD_CELLS` a side;
`RandomizeConfig.families` draws them by name (not in 'all'), `sample_weighted` gives every other
room of the batch an empty grid."""


def grid_size(weights) -> int:
    """G of the rooms that the families of `weights` (names) draw: 0 if none has a grid."""
    return FIELD_CELLS if set(weights) & set(GRID_FAMILIES) else 0


def pick(index: jax.Array, branches, key: jax.Array) -> SceneParams:
    """The room of `branches[index](key)`, `index` a traced int32 in range: every branch computed
    and the room of `index` kept, which is what `lax.switch` does under vmap (a batched index),
    traced once under the batch rather than once alone and again to batch it."""
    rooms = [branch(key) for branch in branches]
    return jax.tree_util.tree_map(lambda *xs: jax.lax.select_n(index, *xs), *rooms)


def sample_family(key, index, nb: int, nc: int, radius: float) -> SceneParams:
    """A room of family `index` (traced int32: families mix without recompiling)."""
    branches = [lambda k, f=f: f(k, nb, nc, radius) for f in FAMILIES.values()]
    return pick(index, branches, key)


def sample_weighted(
    key, cfg: RandomizeConfig, nb: int, nc: int, radius: float, grid: int = 0
) -> SceneParams:
    """A room of a family drawn with the weights of `cfg.families` ('random': `sample_room(cfg)`).

    Only families of positive weight are traced; each of them is computed for every env and one
    kept (`pick`), so the cost grows with their number (see benchmarks/env_rollout.py). With
    a grid family among them, or `grid` > 0, every room has an occupancy grid of
    max(`grid`, its `grid_size`) cells a side (empty where the family has none)."""
    weights = family_weights(cfg.families)
    g = max(grid, grid_size(weights))
    samplers = {RANDOM: lambda k: sample_room(k, cfg, nb, nc, radius)}
    samplers.update({n: lambda k, f=f: f(k, nb, nc, radius) for n, f in FAMILIES.items()})
    samplers.update({n: lambda k, f=f: f(k, nb, nc, radius) for n, f in GRID_FAMILIES.items()})
    branches = [lambda k, f=samplers[n]: _grown(f(k), g) for n in weights]
    d = Draws(key)
    # Family: drawn with the given weights.
    index = d.choice(jnp.asarray(list(weights.values()), jnp.float32))
    return pick(index, branches, d.key()) if len(branches) > 1 else branches[0](d)


def _grown(room: SceneParams, g: int) -> SceneParams:
    """`room` with a [g, g] occupancy grid: its own, padded, or an empty one (g = 0: as it is)."""
    if g == 0:
        return room
    if room.grid is None:
        return occupancy.with_grid(room, g)
    return room.replace(grid=occupancy.pad(room.grid, g))


def mixture(key, nb: int, nc: int, radius: float) -> SceneParams:
    """A room of a family drawn uniformly from `FAMILIES`."""
    d = Draws(key)
    # Family: uniform over FAMILIES.
    return sample_family(d.key(), d.randint((), 0, len(FAMILIES)), nb, nc, radius)


# ------------------------------------------------------------------------------
# Rooms as layouts, and their free space


def to_layout(room: SceneParams, name: str) -> lay.RoomLayout:
    """One room (no batch axis) as a `RoomLayout` with its spawn, active obstacles only; a
    walker (`crowd.Walkers`) is its cylinder with a `"goal"` motion, walking back and forth.

    Positions are rounded to the millimetre, obstacle sizes down to it less 2 mm and the interior
    up to it, so a box that touches a wall in float32 stays inside it in the file.
    """
    r = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), room)
    walkers = None if room.motion is None else r.motion.walkers
    mm = lambda v: [round(float(x), 3) for x in np.atleast_1d(v)]  # noqa: E731
    shrink = lambda v: [float(np.floor(x * 1000) / 1000 - 0.002) for x in np.atleast_1d(v)]  # noqa: E731
    obstacles = [
        lay.Box(
            pos=mm(r.box_pos[i]),
            size=shrink(2 * r.box_half[i]),
            yaw=round(float(r.box_yaw[i]), 4),
            height=round(float(r.box_height[i]), 3),
            bottom=round(float(r.box_bottom[i]), 3),
        )
        for i in np.flatnonzero(np.asarray(room.box_active))
    ]
    obstacles += [
        lay.Cylinder(
            pos=mm(r.cyl_pos[i]),
            radius=shrink(r.cyl_radius[i])[0],
            height=round(float(r.cyl_height[i]), 3),
            bottom=round(float(r.cyl_bottom[i]), 3),
            motion=_walking(walkers, i),
        )
        for i in np.flatnonzero(np.asarray(room.cyl_active))
    ]
    obstacles += _grid_obstacle(room.grid)
    # A grid's cells may reach 1 mm beyond the interior rounded up (its origin rounds up too).
    extra = 0.002 if obstacles and isinstance(obstacles[-1], lay.Grid) else 0.0
    return lay.RoomLayout(
        name=name,
        size=mm(np.ceil(2000 * r.room_half) / 1000 + extra),
        robot_pos=mm(r.spawn[:2]),
        robot_yaw=round(float(r.spawn[2]), 4),
        obstacles=tuple(obstacles),
    )


def _walking(walkers, i: int) -> lay.Motion | None:
    """The layout motion of cylinder slot `i` where `walkers` (numpy) has it walk, else None."""
    if walkers is None or walkers.speed[i] <= 0:
        return None
    goal = [round(float(x), 3) for x in walkers.goal[i]]
    speed, reactive = round(float(walkers.speed[i]), 3), bool(walkers.reactive[i])
    return lay.Motion(goal=goal, speed=speed, reactive=reactive, repeat=True)


def _grid_obstacle(grid) -> list:
    """[] or [the `lay.Grid` of an occupancy grid with occupied cells]: origin rounded up to the
    millimetre, cell down to the micrometre (its cells stay inside the room)."""
    if grid is None or not np.asarray(grid.cells).any():
        return []
    cells = np.asarray(grid.cells)
    used = np.flatnonzero(cells.any(0)).max() + 1, np.flatnonzero(cells.any(1)).max() + 1
    rows = ["".join("#" if c else "." for c in row[: used[0]]) for row in cells[: used[1]][::-1]]
    origin = [float(np.ceil(float(v) * 1000) / 1000) for v in np.asarray(grid.origin)]
    cell = float(np.floor(float(grid.cell) * 1e6) / 1e6)
    return [lay.Grid(origin=origin, cell=cell, rows=rows, height=round(float(grid.height), 3))]


def free_cells(room: lay.RoomLayout, radius: float = lay.ROBOT_RADIUS, cell: float = CELL):
    """The occupancy grid of `room`: ([H, W] bool free, [H, W, 2] cell centres m).

    Cells of `cell` m cover the interior; a cell is free where a robot disc of `radius` centred
    on it touches nothing (obstacles inflated by the robot radius; walls count, overhangs too).
    """
    half = 0.5 * np.asarray(room.size)
    n = np.maximum(np.round(2 * half / cell).astype(int), 1)  # [2] cells along x, y
    xs, ys = ((np.arange(k) + 0.5) * (2 * h / k) - h for k, h in zip(n, half, strict=True))
    centres = np.stack(np.meshgrid(xs, ys), -1)  # [H, W, 2]
    # Blocks of a fixed size: the clearance's jnp ops compile once per obstacle count, not per
    # room size.
    flat = np.concatenate([centres.reshape(-1, 2), np.zeros((_BLOCK, 2))])
    gap = [lay.clearance(room, flat[i : i + _BLOCK]) for i in range(0, len(flat) - _BLOCK, _BLOCK)]
    gap = np.concatenate(gap)[: centres[..., 0].size].reshape(centres.shape[:2])
    return gap > radius, centres


def reachable(room: lay.RoomLayout, radius: float = lay.ROBOT_RADIUS, cell: float = CELL):
    """([H, W] bool, [H, W, 2] centres): the free cells 4-connected to the spawn's cell (the
    one nearest `room.robot_pos`, or the first free cell when the room has no spawn)."""
    free, centres = free_cells(room, radius, cell)
    start = room.robot_pos if room.robot_pos is not None else lay.free_spawn(room, radius)
    seed = np.zeros_like(free)
    if start is not None:
        dist = np.linalg.norm(centres - np.asarray(start), axis=-1)
        seed.flat[np.argmin(np.where(free, dist, np.inf))] = True
    seed &= free
    while True:  # flood fill: grow by one cell in each direction until nothing changes
        grown = seed.copy()
        grown[1:] |= seed[:-1]
        grown[:-1] |= seed[1:]
        grown[:, 1:] |= seed[:, :-1]
        grown[:, :-1] |= seed[:, 1:]
        grown &= free
        if (grown == seed).all():
            return seed, centres
        seed = grown


def coverage(room: lay.RoomLayout, paths, reach: float = COVER_REACH, cell: float = CELL):
    """[E] share of the room's reachable free area (`reachable`) within `reach` m of each path.

    `paths` is [E, T, 2] positions (m), or a list of [T_i, 2]. A cell counts as covered when its
    centre is within `reach` of the centre of a cell the path visited, so the result is exact to
    one cell (0.1 m). 0 where nothing is reachable.
    """
    mask, _ = reachable(room, cell=cell)
    h, w = mask.shape
    r = int(np.floor(reach / cell))
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = (np.hypot(dx, dy) * cell <= reach + 1e-9).astype(np.float64)  # [2r+1, 2r+1]
    shape = (h + 2 * r, w + 2 * r)  # zero-padded: no wrap-around in the FFT convolution
    kernel = np.fft.rfft2(disc, shape)
    half = 0.5 * np.asarray(room.size)
    out = []
    for path in paths:
        ij = np.floor((np.asarray(path)[:, ::-1] + half[::-1]) / (2 * half[::-1]) * [h, w])
        ij = np.clip(ij.astype(int), 0, [h - 1, w - 1])
        visited = np.zeros((h, w))
        visited[ij[:, 0], ij[:, 1]] = 1.0
        near = np.fft.irfft2(np.fft.rfft2(visited, shape) * kernel, shape)[r : r + h, r : r + w]
        out.append((near > 0.5)[mask].sum() / max(mask.sum(), 1))
    return np.asarray(out, np.float64)
