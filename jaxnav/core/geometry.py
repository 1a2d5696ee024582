"""The one signed distance of jaxnav: from points to the walls and obstacles of a room.

Used for spawns and free-space checks (2-D, in the floor plane), for collision detection (3-D, the
robot's bumper sphere against boxes, upright capsules and the wall planes: the shapes the MJX scene
collides, cross-checked against MuJoCo's own collision in the tests) and for layout validation.
Everything is `jax.numpy` in float32, the simulator's precision; numpy inputs are accepted.
"""

from __future__ import annotations

import jax.numpy as jnp


def box_distance(p, pos, yaw, half):
    """[..., N] signed floor-plane distance from points p [..., 2] to N boxes (<0 inside).

    pos [N, 2] centres, yaw [N] rad, half [N, 2] half extents along each box's own axes.
    """
    d = jnp.asarray(p)[..., None, :] - pos  # [..., N, 2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    local = jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
    q = jnp.abs(local) - half  # per-axis distance beyond each face
    return jnp.linalg.norm(jnp.maximum(q, 0.0), axis=-1) + jnp.minimum(q.max(-1), 0.0)


def disc_distance(p, pos, radius):
    """[..., N] signed floor-plane distance from points p [..., 2] to N discs (<0 inside)."""
    return jnp.linalg.norm(jnp.asarray(p)[..., None, :] - pos, axis=-1) - radius


def wall_distance(p, room_half):
    """[..., 4] distance from points p [..., 2] to the east, west, north, south walls (<0 beyond)."""
    x, y = jnp.asarray(p)[..., 0], jnp.asarray(p)[..., 1]
    hx, hy = room_half[0], room_half[1]
    return jnp.stack([hx - x, hx + x, hy - y, hy + y], axis=-1)


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
    widened by their radius (the capsules the scene collides).
    """
    walls = wall_distance(p, room.room_half).min(-1)
    box = box_distance(p, room.box_pos, room.box_yaw, room.box_half)  # [..., Sb]
    cyl = jnp.linalg.norm(jnp.asarray(p)[..., None, :] - room.cyl_pos, axis=-1)  # [..., Sc]
    if z is None:
        cyl = cyl - room.cyl_radius
    else:
        dz = _vertical(z, room.box_bottom, room.box_height)
        corner = (box > 0) & (dz > 0)  # beyond an edge: distance to it; else the nearer face
        box = jnp.where(corner, jnp.hypot(box, dz), jnp.maximum(box, dz))
        dz = jnp.maximum(_vertical(z, room.cyl_bottom, room.cyl_height), 0.0)
        cyl = jnp.hypot(cyl, dz) - room.cyl_radius
    box = jnp.where(room.box_active, box, jnp.inf).min(-1, initial=jnp.inf)
    cyl = jnp.where(room.cyl_active, cyl, jnp.inf).min(-1, initial=jnp.inf)
    return jnp.minimum(walls, jnp.minimum(box, cyl))
