"""Room families: valid rooms over many keys, no recompilation when they mix, coverage, the suite."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import XLA_CPU_CODE

from jaxnav.core import families
from jaxnav.core import grid as occupancy
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import RandomizeConfig, family_weights
from jaxnav.io.layouts import Box, RoomLayout

NB, NC, RADIUS = families.FAMILY_BOXES, families.FAMILY_CYLINDERS, 0.177
KEYS = 24  # rooms per family
NAMES = list(families.FAMILIES)
# Families whose free space must be one connected piece: walls, doorways and corridors are laid
# out so that the robot can reach every part (clutter may wall off a pocket, and that is allowed).
CONNECTED = ("pillars", "corridor", "ltu", "joined", "furniture", "open")


@jax.jit
@chex.assert_max_traces(n=1)
def _draw(keys, index):
    return jax.vmap(lambda k, i: families.sample_family(k, i, NB, NC, RADIUS))(keys, index)


@pytest.fixture(scope="module")
def rooms():
    """KEYS rooms of every family, drawn in one compiled call: {name: [SceneParams]}."""
    keys = jax.random.split(jax.random.PRNGKey(0), KEYS * len(NAMES))
    index = jnp.repeat(jnp.arange(len(NAMES)), KEYS)
    batch = jax.device_get(_draw(keys, index))
    one = lambda i: jax.tree_util.tree_map(lambda x: x[i], batch)  # noqa: E731
    return {n: [one(f * KEYS + i) for i in range(KEYS)] for f, n in enumerate(NAMES)}


def _box_corners(room):
    """[Sb, 4, 2] footprint corners of every box slot."""
    c, s = np.cos(room.box_yaw), np.sin(room.box_yaw)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [Sb, 2, 2]
    signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]])
    local = signs[None] * room.box_half[:, None]  # [Sb, 4, 2]
    return room.box_pos[:, None] + np.einsum("bij,bkj->bki", rot, local)


@pytest.mark.parametrize("name", NAMES)
def test_family_rooms_are_valid(rooms, name):
    for room in rooms[name]:
        # A free spawn: the robot and its clearance touch nothing.
        gap = float(signed_distance(room, room.spawn[:2])) - RADIUS
        assert gap >= families.SPAWN_CLEARANCE - 1e-4, (name, gap)
        # Nothing outside the walls.
        corners = _box_corners(room)[room.box_active]
        assert (np.abs(corners) <= room.room_half + 1e-4).all(), name
        cyl = np.abs(room.cyl_pos[room.cyl_active]) + room.cyl_radius[room.cyl_active, None]
        assert (cyl <= room.room_half + 1e-4).all(), name
        assert room.box_active.sum() + room.cyl_active.sum() <= NB + NC


@pytest.mark.parametrize("name", CONNECTED)
def test_doorways_and_corridors_are_passable(rooms, name):
    """The robot can reach (nearly) all free space from its spawn: a closed doorway, a blocked
    corridor or a shut U-turn would cut off a whole room or lane (>= 20 % of the area)."""
    for i, room in enumerate(rooms[name]):
        layout = families.to_layout(room, f"{name}-{i}")  # validates spawn and walls again
        free, _ = families.free_cells(layout)
        reach, _ = families.reachable(layout)
        assert reach.sum() >= 0.95 * free.sum(), (name, i, reach.sum() / free.sum())


def test_joined_rooms_doors_are_wide_enough(rooms):
    """Each doorway is a gap of >= MIN_DOOR between two wall boxes on the same divider."""
    for room in rooms["joined"]:
        walls = [i for i in range(4) if room.box_active[i]]
        assert len(walls) in (2, 4)
        for south in walls[: len(walls) // 2]:
            north = south + 2  # the two boxes of one divider lie on one line, the door between
            along = np.linalg.norm(room.box_pos[north] - room.box_pos[south])
            gap = along - room.box_half[south, 1] - room.box_half[north, 1]
            assert gap >= families.MIN_DOOR - 1e-4


def test_families_mix_without_recompiling(rooms):
    """`rooms` compiled `_draw` once; other keys and another mix of families reuse it."""
    keys = jax.random.split(jax.random.PRNGKey(7), KEYS * len(NAMES))
    index = jax.random.randint(jax.random.PRNGKey(8), (KEYS * len(NAMES),), 0, len(NAMES))
    out = _draw(keys, index)  # a second trace would raise
    assert out.box_pos.shape == (KEYS * len(NAMES), NB, 2)


@pytest.mark.slow
def test_pick_is_the_room_lax_switch_draws():
    """`families.pick` keeps the room `lax.switch` would: the same bits for every key and family,
    in a batch (as resets run) and for one robot alone. Slow: every family's sampler compiled
    three times (picked and switched in a batch, picked alone) for this check."""
    branches = [lambda k, f=f: f(k, NB, NC, RADIUS) for f in families.FAMILIES.values()]
    keys = jax.random.split(jax.random.PRNGKey(5), 3 * len(NAMES))
    index = jnp.arange(3 * len(NAMES)) % len(NAMES)
    jit = functools.partial(jax.jit, compiler_options=XLA_CPU_CODE)
    picked = jit(jax.vmap(lambda i, k: families.pick(i, branches, k)))(index, keys)
    switched = jit(jax.vmap(lambda i, k: jax.lax.switch(i, branches, k)))(index, keys)
    chex.assert_trees_all_equal(picked, switched)
    one = jit(lambda i, k: families.pick(i, branches, k))(index[4], keys[4])
    chex.assert_trees_all_equal(one, jax.tree_util.tree_map(lambda x: x[4], switched))


def test_coverage_of_a_straight_path_in_an_empty_room():
    """A 4 x 4 m room, a path along y = 0 from x = -1 to 1: the reachable area is the square of
    side 4 - 2 r; the covered part is the stadium of radius 1 around the path, clipped by it."""
    room = RoomLayout(name="empty", size=(4.0, 4.0), robot_pos=(0.0, 0.0))
    path = np.stack([np.linspace(-1, 1, 201), np.zeros(201)], -1)
    d = 2.0 - RADIUS - 1.0  # the stadium's caps reach beyond the reachable square by 1 - d
    cap_cut = np.arccos(d) - d * np.sqrt(1 - d * d)  # area of a disc segment beyond x = d
    expected = (4.0 + np.pi - 2 * cap_cut) / (4 - 2 * RADIUS) ** 2
    got = families.coverage(room, [path])
    assert got.shape == (1,) and got[0] == pytest.approx(expected, abs=0.03)


def test_coverage_counts_only_reachable_space():
    """A wall cuts the east metre off: it is neither reachable nor in the denominator."""
    wall = Box(pos=(1.0, 0.0), size=(0.1, 4.0))
    room = RoomLayout(name="cut", size=(4.0, 4.0), robot_pos=(-1.0, 0.0), obstacles=(wall,))
    reach, centres = families.reachable(room)
    assert (centres[reach][:, 0] < 1.0 - 0.05 - RADIUS).all()
    free, _ = families.free_cells(room)
    assert free[centres[..., 0] > 1.3].any()  # free, but behind the wall
    everywhere = centres[reach].reshape(-1, 1, 2)  # a "path" through every reachable cell
    assert families.coverage(room, [everywhere.reshape(-1, 2)])[0] == pytest.approx(1.0)
    # Straight-line distance (through the wall): 1.9 m is 1.13 m from the nearest reachable cell.
    assert families.coverage(room, [np.array([[1.9, 0.0]])])[0] == 0.0


# ------------------------------------------------------------------------------
# dense_field: a cellular-automaton field on the occupancy grid

GRID_MIX = RandomizeConfig(families="dense_field:3,clutter:1")
MIXED = 24  # rooms per draw of GRID_MIX


@jax.jit
@chex.assert_max_traces(n=1)
def _draw_mixed(keys):
    return jax.vmap(lambda k: families.sample_weighted(k, GRID_MIX, NB, NC, RADIUS))(keys)


@pytest.fixture(scope="module")
def fields():
    """The dense_field rooms among MIXED draws of GRID_MIX (one compile): [SceneParams]."""
    batch = jax.device_get(_draw_mixed(jax.random.split(jax.random.PRNGKey(3), MIXED)))
    one = lambda i: jax.tree_util.tree_map(lambda x: x[i], batch)  # noqa: E731
    return [one(i) for i in range(MIXED) if batch.grid.cells[i].any()]


_clearance = jax.jit(signed_distance)


def _fill(room) -> float:
    """Share of the room's cells that are occupied."""
    n = np.round(2 * np.asarray(room.room_half) / float(room.grid.cell)).astype(int)
    return float(room.grid.cells[: n[1], : n[0]].mean())


def test_dense_fields_are_barn_like(fields):
    """Cells 0.1-0.2 m in rooms 3-8 m a side, every cell inside, no obstacle slot used, a free
    spawn; the smoothed fields cover from a few per cent to about a quarter of the floor."""
    assert len(fields) >= MIXED // 2
    fills = [_fill(room) for room in fields]
    assert 0.0 < min(fills) < 0.08 and 0.15 < max(fills) < 0.4, fills
    for room in fields:
        assert 0.1 <= float(room.grid.cell) <= 0.2
        assert (2.99 <= 2 * room.room_half).all() and (2 * room.room_half <= 8.01).all()
        centres, half = occupancy.cell_boxes(room.grid)
        assert (np.abs(centres) + half <= np.asarray(room.room_half) + 1e-4).all()
        assert not room.box_active.any() and not room.cyl_active.any()
        gap = float(_clearance(room, room.spawn[:2])) - RADIUS
        assert gap >= families.SPAWN_CLEARANCE - 1e-4, gap


def test_dense_fields_have_a_path_for_the_robot(fields):
    """On the occupancy grid of the layout (cells inflated by the robot's radius), the spawn's
    free component reaches the north wall."""
    for i, room in enumerate(fields[:8]):
        layout = families.to_layout(room, f"dense-{i}")  # validates the cells and spawn again
        reach, centres = families.reachable(layout)
        north = centres[..., 1] > float(room.room_half[1]) - RADIUS - families.SPAWN_CLEARANCE
        assert (reach & north).any(), i


def test_dense_field_mixes_without_recompiling(fields):
    """`fields` compiled `_draw_mixed` once; other keys reuse it, and the clutter rooms of the
    mix carry an empty grid of the same shape."""
    out = _draw_mixed(jax.random.split(jax.random.PRNGKey(9), MIXED))  # a second trace raises
    g = families.FIELD_CELLS
    assert out.grid.cells.shape == (MIXED, g, g)
    plain = ~np.asarray(out.grid.cells).any((1, 2))
    assert plain.any() and np.asarray(out.box_active)[plain].any()


def test_dense_field_is_drawn_by_name_only():
    """'all' stays the suite's families (a grid costs every room of a batch); by name it mixes."""
    assert "dense_field" not in family_weights("all")
    assert family_weights("random:3,dense_field:1")["dense_field"] == pytest.approx(0.25)
    assert families.grid_size(family_weights("all")) == 0
    assert families.grid_size(["dense_field"]) == families.FIELD_CELLS
