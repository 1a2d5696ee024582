"""The occupancy-grid obstacle layer: rays and distances exact against its cells cast as boxes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnav
from jaxnav.core import grid as occupancy
from jaxnav.core.geometry import ray_cast, signed_distance
from jaxnav.core.layout import Grid, RoomLayout
from jaxnav.core.randomize import RandomizeConfig, make_bank, sample_room
from jaxnav.core.scene import SceneConfig

G, HEIGHT, RAYS = 16, 0.7, 4096
cast, distance = jax.jit(ray_cast), jax.jit(signed_distance)


def _rooms(seed: int):
    """(room with a random grid, the same room with the grid's cells in box slots)."""
    rng = np.random.default_rng(seed)
    cell = rng.uniform(0.1, 0.2)
    grid = occupancy.OccupancyGrid(
        cells=jnp.asarray(rng.random((G, G)) < 0.3),
        origin=jnp.asarray(rng.uniform(-2.0, -1.0, 2), jnp.float32),
        cell=jnp.float32(cell),
        height=jnp.float32(HEIGHT),
    )
    centres, half = occupancy.cell_boxes(grid)
    n, slots = len(centres), G * G  # as many slots in every room: one compile
    pad = lambda x: np.concatenate([x, np.full((slots - n, 2), 0.05)])  # noqa: E731
    empty = RandomizeConfig(num_boxes=(0, 0), num_cylinders=(0, 0))
    base = sample_room(jax.random.PRNGKey(seed), empty, 0, 0, 0.177)
    base = base.replace(room_half=jnp.array([6.0, 6.0]))
    boxes = sample_room(jax.random.PRNGKey(seed), empty, slots, 0, 0.177).replace(
        room_half=base.room_half,
        box_pos=jnp.asarray(pad(centres), jnp.float32),
        box_half=jnp.asarray(pad(half), jnp.float32),
        box_yaw=jnp.zeros(slots),
        box_height=jnp.full(slots, HEIGHT),
        box_bottom=jnp.zeros(slots),
        box_active=jnp.arange(slots) < n,
    )
    return base.replace(grid=grid), boxes


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_rays_match_its_cells_as_boxes(seed):
    """Random rays from above, below the top and inside the field: the same first hit to 1e-5 m
    (walls included), and a cell reads slot -1 (no obstacle slot)."""
    with_grid, as_boxes = _rooms(seed)
    rng = np.random.default_rng(100 + seed)
    for _ in range(4):
        xy = np.asarray(with_grid.grid.origin) + rng.uniform(-0.5, 1.2, 2) * G * 0.1
        origin = jnp.asarray(np.r_[xy, rng.uniform(0.05, 1.2)], jnp.float32)
        d = rng.normal(size=(RAYS, 3)) * [1.0, 1.0, 0.4]
        d = jnp.asarray(d / np.linalg.norm(d, axis=1, keepdims=True), jnp.float32)
        got, slot = cast(with_grid, origin, d)
        want, want_slot = cast(as_boxes, origin, d)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-5, rtol=0)
        on_cell = np.asarray(want_slot) >= 0
        assert on_cell.mean() > 0.05  # many rays meet a cell
        assert (np.asarray(slot)[on_cell] == -1).all()


@pytest.mark.parametrize("z", [None, (0.1, 0.4), (0.75, 0.9)])
def test_grid_clearance_matches_its_cells_as_boxes(z):
    """2-D and 3-D signed distances (above the cells too): exact wherever the nearest cell is
    within `REACH` cells, never nearer than the truth beyond."""
    with_grid, as_boxes = _rooms(3)
    span = G * float(with_grid.grid.cell)
    p = (
        np.asarray(with_grid.grid.origin)
        + np.random.default_rng(4).uniform(-0.5, 1.5, (8000, 2)) * span
    )
    p = jnp.asarray(p, jnp.float32)
    zz = None if z is None else tuple(jnp.full(len(p), v) for v in z)
    got = np.asarray(distance(with_grid, p, zz))
    want = np.asarray(distance(as_boxes, p, zz))
    near = want < occupancy.REACH * float(with_grid.grid.cell)
    assert near.mean() > 0.3 and (want < 0).any() == (z is None or z[0] < HEIGHT)
    np.testing.assert_allclose(got[near], want[near], atol=1e-5, rtol=0)
    assert (got[~near] >= want[~near] - 1e-5).all()


def test_layout_grid_reaches_the_bank_south_to_north():
    """A layout's grid rows run north to south in the file; in the bank the occupied cells are
    where the file draws them, and rooms without a grid get an empty one."""
    rows = ("#...", "....", "..#.")  # north-west and south-east-ish cells
    room = RoomLayout(
        name="g", size=(4.0, 4.0), obstacles=(Grid(origin=(-1.0, -1.0), cell=0.5, rows=rows),)
    )
    bank = make_bank([room, RoomLayout(name="plain", size=(4.0, 4.0))], 2, 1)
    assert bank.rooms.grid.cells.shape == (2, 4, 4)
    one = jax.tree_util.tree_map(lambda x: x[0], bank.rooms)
    # The north-west and south-east occupied cells' centres, then a free cell's.
    points = jnp.array([[-0.75, 0.25], [0.25, -0.75], [0.25, 0.25]])
    gap = np.asarray(signed_distance(one, points))
    assert gap[0] < 0 and gap[1] < 0 and gap[2] > 0
    assert not bank.rooms.grid.cells[1].any()


@pytest.mark.parametrize(
    ("scene", "flag"),
    [
        (SceneConfig(fast_contacts=True), "--scene.fast-contacts"),
        (SceneConfig(physics="wheeled"), "--physics wheeled"),
    ],
)
def test_grid_rooms_refuse_mjx_contacts_in_one_line(scene, flag):
    """Grid cells are not MJX geoms: the physics that collide through MJX refuse grid rooms."""
    randomize = RandomizeConfig(sampled_room_prob=1.0, families="dense_field")
    with pytest.raises(ValueError, match=f"^{flag}: rooms with grid obstacles") as info:
        jaxnav.make_env("avoid", layouts=[], randomize=randomize, scene=scene)
    assert "\n" not in str(info.value)


def test_twin_builds_grid_cells_as_boxes():
    """The classic-MuJoCo twin's room has one box geom per occupied cell, where the cell is."""
    import mujoco

    from jaxnav import twin

    cells = Grid(origin=(-1.0, -1.0), cell=0.2, rows=["#..#", "....", ".##."], height=0.8)
    plain = RoomLayout(name="plain", size=(4.0, 4.0))
    model = twin.room_model(
        RoomLayout(name="g", size=(4.0, 4.0), obstacles=(cells,)), twin.TwinConfig()
    )
    boxes = model.geom_type == mujoco.mjtGeom.mjGEOM_BOX
    before = twin.room_model(plain, twin.TwinConfig()).geom_type == mujoco.mjtGeom.mjGEOM_BOX
    assert boxes.sum() - before.sum() == 4
    centres = {tuple(np.round(p[:2], 3)) for p in model.geom_pos[boxes]}
    assert {(-0.9, -0.5), (-0.3, -0.5), (-0.7, -0.9), (-0.5, -0.9)} <= centres
