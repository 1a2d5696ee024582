"""The one signed distance of jaxnav: from points to the walls and obstacles of a room.

Used for spawns and free-space checks (2-D, in the floor plane), for collision detection (3-D, the
robot's bumper sphere against boxes, upright capsules and the wall planes: the shapes the MJX scene
collides, cross-checked against MuJoCo's own collision in the tests) and for layout validation.
Everything is `jax.numpy` in float32, the simulator's precision; numpy inputs are accepted. The
2-D distances also run in numpy (`xp=np`, float32 inputs stay float32): layout validation checks
rooms of varied shapes one by one, where jax would dispatch every operation (and on an
accelerator, copy every array) eagerly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnav.core import grid as occupancy

# An unused obstacle slot (inactive: it never collides and reflects no ray) holds these, so that
# its MJX geom stays a valid shape: a box's half extents or a cylinder's radius, and its height.
UNUSED_SIZE = 0.05  # m
UNUSED_HEIGHT = 0.1  # m


def planar_distance(a, b, xp=jnp):
    """[...] floor-plane distance between points a [..., 2] and b [..., 2] (broadcast), per
    component: over a grid of points, a reduction over an axis of 2 costs XLA's CPU backend
    several times the arithmetic (docs/results.md)."""
    a, b = xp.asarray(a), xp.asarray(b)
    return xp.sqrt(xp.square(a[..., 0] - b[..., 0]) + xp.square(a[..., 1] - b[..., 1]))


def box_distance(p, pos, yaw, half, xp=jnp):
    """[..., N] signed floor-plane distance from points p [..., 2] to N boxes (<0 inside).

    pos [N, 2] centres, yaw [N] rad, half [N, 2] half extents along each box's own axes.
    """
    p = xp.asarray(p)
    dx, dy = p[..., 0, None] - pos[:, 0], p[..., 1, None] - pos[:, 1]  # [..., N] each
    c, s = xp.cos(yaw), xp.sin(yaw)
    # Per-axis distance beyond each face, in the box's own frame. Each axis its own array: over
    # a grid of points a stacked [..., N, 2] costs XLA's CPU backend three times the time.
    qx = xp.abs(c * dx + s * dy) - half[:, 0]
    qy = xp.abs(c * dy - s * dx) - half[:, 1]
    outside = xp.sqrt(xp.maximum(qx, 0.0) ** 2 + xp.maximum(qy, 0.0) ** 2)
    return outside + xp.minimum(xp.maximum(qx, qy), 0.0)


def disc_distance(p, pos, radius, xp=jnp):
    """[..., N] signed floor-plane distance from points p [..., 2] to N discs (<0 inside)."""
    return planar_distance(xp.asarray(p)[..., None, :], pos, xp) - radius


def wall_distance(p, room_half, xp=jnp):
    """[..., 4] distance from points p [..., 2] to the east, west, north, south walls (<0 beyond)."""
    x, y = xp.asarray(p)[..., 0], xp.asarray(p)[..., 1]
    hx, hy = room_half[0], room_half[1]
    return xp.stack([hx - x, hx + x, hy - y, hy + y], axis=-1)


def _vertical(z, bottom, top):
    """[..., N] signed vertical distance from the segment z = (low, high) [...] to the spans
    [bottom, top] [N] (<0 where they overlap)."""
    low, high = (jnp.asarray(v)[..., None] for v in z)
    return jnp.maximum(low - top, bottom - high)


def signed_distance(room, p, z=None):
    """[...] distance from points to the nearest wall or active obstacle of `room` (<0 inside).

    `room` has the `SceneParams` room fields (room_half, box_*, cyl_*). p [..., 2] is in the floor
    plane; with z = (low, high) heights [...], the distance is 3-D, from the vertical segment at p
    between those heights (low == high: a point; widen by a radius for a capsule or sphere): boxes
    span [box_bottom, box_height] and cylinders are upright segments of [cyl_bottom, cyl_height]
    widened by their radius (the capsules the scene collides). A room with an occupancy grid
    (`room.grid`) adds its cells' boxes within `grid.REACH` cells of p (`grid.distance`).
    """
    out = nearest(room, *shape_distances(room, p, z))
    if getattr(room, "grid", None) is None:
        return out
    return jnp.minimum(out, occupancy.distance(p, room.grid, z))


def shape_distances(room, p, z=None):
    """(walls [...], boxes [..., Sb], cylinders [..., Sc]): the distances `signed_distance` takes
    the least of (the nearest wall, and every obstacle slot, active or not)."""
    walls = wall_distance(p, room.room_half).min(-1)
    box = box_distance(p, room.box_pos, room.box_yaw, room.box_half)  # [..., Sb]
    cyl = planar_distance(jnp.asarray(p)[..., None, :], room.cyl_pos)  # [..., Sc]
    if z is None:
        return walls, box, cyl - room.cyl_radius
    dz = _vertical(z, room.box_bottom, room.box_height)
    corner = (box > 0) & (dz > 0)  # beyond an edge: distance to it; else the nearer face
    box = jnp.where(corner, jnp.hypot(box, dz), jnp.maximum(box, dz))
    dz = jnp.maximum(_vertical(z, room.cyl_bottom, room.cyl_height), 0.0)
    return walls, box, jnp.hypot(cyl, dz) - room.cyl_radius


def nearest(room, walls, box, cyl):
    """[...] the least of `shape_distances` over the walls and the obstacles active in `room`: a
    room that differs only in which obstacles are active (`families.clear_around`) reuses them."""
    box = jnp.where(room.box_active, box, jnp.inf).min(-1, initial=jnp.inf)
    cyl = jnp.where(room.cyl_active, cyl, jnp.inf).min(-1, initial=jnp.inf)
    return jnp.minimum(walls, jnp.minimum(box, cyl))


def ray_cast(room, origin, dirs):
    """Where rays from `origin` [3] along unit `dirs` [..., 3] first meet a wall or an active
    obstacle of `room`: (distance [...] m, inf where none; slot [...] int32, the obstacle's index
    in boxes-then-cylinders order, -1 for a wall or none).

    The shapes are the ones the MJX scene has (cross-checked against `mjx.ray` in the tests): wall
    planes at +-room_half, boxes spanning [box_bottom, box_height], cylinders as upright capsules
    (the segment [cyl_bottom, cyl_height] widened by the radius). A ray starting inside a shape
    does not see it. The floor is not a shape here: the sensor tests it itself. A room with an
    occupancy grid (`room.grid`) adds its cells (`grid.ray_cast`; slot -1, as a wall).
    """
    o, d = jnp.asarray(origin, jnp.float32), jnp.asarray(dirs, jnp.float32)
    walls = _ray_walls(o, d, room.room_half)  # [...]
    box = _ray_boxes(o, d, room)  # [..., Sb]
    cyl = _ray_capsules(o, d, room)  # [..., Sc]
    hits = jnp.concatenate([walls[..., None], box, cyl], -1)  # [..., 1 + Sb + Sc]
    dist, first = least(hits)
    slot = jnp.where(jnp.isfinite(dist), first - 1, -1).astype(jnp.int32)
    if getattr(room, "grid", None) is None:
        return dist, slot
    cells = occupancy.ray_cast(o, d, room.grid)  # [...]
    return jnp.minimum(dist, cells), jnp.where(cells < dist, -1, slot)


def least(x):
    """([...] the least of `x` [..., K] along its last axis, [...] its first index, as
    `jnp.argmin`). On the CPU the value is read back at the index; on a GPU it is a reduction of
    its own beside the index's, which XLA fuses into one pass over `x` where the read-back was a
    second pass (the rays' hits: one H200's env step 64.6 -> 68.8 M env-steps/s, PPO `avoid`
    40.4 -> 42.0 M); on the 2-core CPU that form ran the env step about 3x slower
    (docs/results.md)."""
    first = jnp.argmin(x, -1)
    if jax.default_backend() == "cpu":
        return jnp.take_along_axis(x, first[..., None], -1)[..., 0], first
    return x.min(-1), first


def _safe(x):
    """x with zeros moved to a tiny signed value, for 1 / x."""
    return jnp.where(jnp.abs(x) < 1e-12, jnp.where(x < 0, -1e-12, 1e-12), x)


def _ray_walls(o, d, half):
    """[...] distance along d [..., 3] from o (inside) to the first of the 4 wall planes."""
    t = (jnp.sign(d[..., :2]) * half - o[:2]) / _safe(d[..., :2])  # [..., 2]
    t = jnp.where(d[..., :2] == 0, jnp.inf, t)
    return t.min(-1)


def _ray_boxes(o, d, room):
    """[..., Sb] slab test of each ray against each yawed box (inf: missed or inactive)."""
    c, s = jnp.cos(room.box_yaw), jnp.sin(room.box_yaw)  # [Sb]
    rx, ry = o[0] - room.box_pos[:, 0], o[1] - room.box_pos[:, 1]  # [Sb]
    centre_z = 0.5 * (room.box_bottom + room.box_height)  # [Sb]
    dx, dy, dz = d[..., 0, None], d[..., 1, None], d[..., 2, None]  # [..., 1] each
    # One slab per axis of the box's frame: (origin [Sb], direction [..., Sb], half extent [Sb]).
    # Each axis its own array, no stacked [..., Sb, 3]: reductions over an axis of 3 cost XLA's
    # CPU backend several times the arithmetic (docs/results.md).
    slabs = (
        (c * rx + s * ry, c * dx + s * dy, room.box_half[:, 0]),
        (c * ry - s * rx, c * dy - s * dx, room.box_half[:, 1]),
        (o[2] - centre_z, dz, centre_z - room.box_bottom),
    )
    near, far = -jnp.inf, jnp.inf
    for ol, dl, half in slabs:
        inv = 1.0 / _safe(dl)
        t1, t2 = (-half - ol) * inv, (half - ol) * inv
        near, far = jnp.maximum(near, jnp.minimum(t1, t2)), jnp.minimum(far, jnp.maximum(t1, t2))
    hit = (far >= near) & (near >= 0) & room.box_active
    return jnp.where(hit, near, jnp.inf)


def _ray_capsules(o, d, room):
    """[..., Sc] first hit of each ray on each upright capsule (inf: missed or inactive)."""
    r = room.cyl_radius  # [Sc]
    rx, ry = o[0] - room.cyl_pos[:, 0], o[1] - room.cyl_pos[:, 1]  # [Sc] each
    dx, dy, dz = d[..., 0, None], d[..., 1, None], d[..., 2, None]  # [..., 1] each
    # Side: |rel + t d_xy| = r, the nearer root, where it lies between the two ends.
    a = dx * dx + dy * dy  # [..., 1]
    b = rx * dx + ry * dy  # [..., Sc]
    disc = b * b - a * (rx * rx + ry * ry - r * r)
    t_side = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / _safe(a)
    z = o[2] + t_side * dz
    side_ok = (disc >= 0) & (t_side >= 0) & (z >= room.cyl_bottom) & (z <= room.cyl_height)
    best = jnp.where(side_ok, t_side, jnp.inf)
    # Ends: spheres of radius r at the segment's two end points.
    for end in (room.cyl_bottom, room.cyl_height):
        rz = o[2] - end  # [Sc]
        md = b + rz * dz  # [..., Sc]: (rel, rz) . d
        disc = md * md - (rx * rx + ry * ry + rz * rz - r * r)
        t = -md - jnp.sqrt(jnp.maximum(disc, 0.0))
        best = jnp.minimum(best, jnp.where((disc >= 0) & (t >= 0), t, jnp.inf))
    return jnp.where(room.cyl_active, best, jnp.inf)
