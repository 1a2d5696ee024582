"""Moving obstacles: their state, their motion over one control step, and the ones the sampler adds.

An obstacle slot moves in one of three ways, all traced data in `SceneParams.motion` (a
`MotionState`; None where nothing in the env can move, which costs nothing and changes nothing):

- bouncing: a constant velocity, reflected off the walls (the footprint's extent along x and y
  mirrored at the interior's edge) and off the other active obstacles (the footprint's bounding
  circle against their exact shapes: the velocity is mirrored about the normal of the nearest
  one and the obstacle waits that step where it was);
- along a path: back and forth at a constant speed along a polyline (a layout's `pos`, then its
  waypoints), ignoring everything else (the layout's author drew it);
- walking: a person walking to a goal (`jaxnav.core.crowd`, in `MotionState.walkers`), some of
  them giving way to the robot.

Bouncing and path obstacles do not react to the robot: a mover that drives into it is the robot's
collision (it is the robot's job to keep out of the way). `advance` moves every slot once per
control step, before the physics, so the MJX geoms, the depth rays and the collision test all see
the new positions.
`add_movers` puts the sampler's bouncing cylinders (`RandomizeConfig.moving_*`) into the last
cylinder slots, which `make_env` reserves for them (the sampler's walkers, `crowd.add_walkers`,
take the slots before those).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxnav.core import crowd
from jaxnav.core.draws import Draws
from jaxnav.core.geometry import (
    UNUSED_HEIGHT,
    UNUSED_SIZE,
    box_distance,
    disc_distance,
    signed_distance,
)

TRIES = 16  # uniform candidates per added mover; a mover whose candidates all fail is left out
FREE_GAP = 0.05  # m an added mover keeps from the walls and the other obstacles at the reset
_DX = 1e-3  # m, step of the finite differences that give an obstacle's normal


@struct.dataclass
class MotionState:
    """How each obstacle slot moves. S = Sb + Sc slots (boxes, then cylinders, as in `dark`)."""

    velocity: jax.Array  # [S, 2] m/s of a bouncing slot; 0: it does not bounce
    path: jax.Array  # [S, K, 2] m: a path slot's polyline from its start, padded with its last
    # point (K: the most points of any path in the env; 0 when there is none)
    speed: jax.Array  # [S] m/s along the path; 0: no path
    travelled: jax.Array  # [S] m along the path's there-and-back cycle, in [0, 2 x its length)
    walkers: Any = None  # `crowd.Walkers` of the cylinder slots; None: nobody walks


def still(slots: int, points: int = 0) -> MotionState:
    """A `MotionState` in which none of `slots` slots moves (numpy; paths of `points` points)."""
    f32 = np.float32
    return MotionState(
        velocity=np.zeros((slots, 2), f32),
        path=np.zeros((slots, points, 2), f32),
        speed=np.zeros(slots, f32),
        travelled=np.zeros(slots, f32),
    )


def reserve(room, m: int):
    """`room` (SceneParams) with `m` inactive cylinder slots appended (for `add_movers`)."""
    f32, pad = jnp.float32, lambda x, fill: jnp.concatenate([x, jnp.full((m, *x.shape[1:]), fill)])
    return room.replace(
        cyl_pos=pad(room.cyl_pos, f32(0)),
        cyl_radius=pad(room.cyl_radius, f32(UNUSED_SIZE)),
        cyl_height=pad(room.cyl_height, f32(UNUSED_HEIGHT)),
        cyl_bottom=pad(room.cyl_bottom, f32(0)),
        cyl_active=pad(room.cyl_active, False),
        dark=pad(room.dark, False),
    )


def _slots(room):
    """([S, 2] positions, [S] active, [S, 2] footprint half extents along x and y, [S] bounding
    radius) of every slot, boxes then cylinders."""
    c, s = jnp.abs(jnp.cos(room.box_yaw)), jnp.abs(jnp.sin(room.box_yaw))  # [Sb]
    hx, hy = room.box_half[:, 0], room.box_half[:, 1]
    box_extent = jnp.stack([c * hx + s * hy, s * hx + c * hy], -1)  # [Sb, 2]
    return (
        jnp.concatenate([room.box_pos, room.cyl_pos]),
        jnp.concatenate([room.box_active, room.cyl_active]),
        jnp.concatenate([box_extent, jnp.repeat(room.cyl_radius[:, None], 2, -1)]),
        jnp.concatenate([jnp.linalg.norm(room.box_half, axis=-1), room.cyl_radius]),
    )


def _others(room, points, active):
    """[..., S] floor-plane distance from points [..., S, 2] (one per slot) to the nearest active
    obstacle other than that slot (inf: none)."""
    box = box_distance(points, room.box_pos, room.box_yaw, room.box_half)  # [..., S, Sb]
    cyl = disc_distance(points, room.cyl_pos, room.cyl_radius)  # [..., S, Sc]
    dist = jnp.concatenate([box, cyl], -1)  # [..., S, S]
    n = active.shape[0]
    other = ~jnp.eye(n, dtype=bool) & active[None, :]
    return jnp.where(other, dist, jnp.inf).min(-1)


def _bounce(room, motion: MotionState, dt: float):
    """([S, 2] positions, [S, 2] velocities) of the bouncing slots after `dt` s (others kept)."""
    pos, active, extent, radius = _slots(room)
    vel = motion.velocity
    moves = active & (vel != 0).any(-1)  # [S]
    # Walls: mirror what went beyond the interior less the footprint's extent.
    limit = jnp.maximum(room.room_half - extent, 0.0)  # [S, 2]
    cand = pos + vel * dt
    over, under = cand > limit, cand < -limit
    cand = jnp.where(over, 2 * limit - cand, jnp.where(under, -2 * limit - cand, cand))
    cand = jnp.clip(cand, -limit, limit)
    vel = jnp.where(over, -jnp.abs(vel), jnp.where(under, jnp.abs(vel), vel))
    # Obstacles: within the bounding radius of the nearest other one and heading into it.
    steps = jnp.array([[0.0, 0.0], [_DX, 0.0], [-_DX, 0.0], [0.0, _DX], [0.0, -_DX]])
    dist = _others(room, cand[None] + steps[:, None], active)  # [5, S]
    normal = jnp.stack([dist[1] - dist[2], dist[3] - dist[4]], -1)  # [S, 2]
    length = jnp.linalg.norm(normal, axis=-1, keepdims=True)
    normal = jnp.where(length > 0, normal / jnp.where(length > 0, length, 1.0), 0.0)
    into = jnp.sum(vel * normal, -1)  # [S] < 0: towards it
    hit = (dist[0] < radius) & (into < 0) & jnp.isfinite(into)
    vel = jnp.where(hit[:, None], vel - 2 * into[:, None] * normal, vel)
    cand = jnp.where(hit[:, None], pos, cand)
    return jnp.where(moves[:, None], cand, pos), jnp.where(moves[:, None], vel, motion.velocity)


def path_point(path: jax.Array, travelled: jax.Array) -> jax.Array:
    """[S, 2] where each slot is after `travelled` [S] m of the there-and-back cycle of its
    polyline `path` [S, K, 2] (K >= 2)."""
    seg = path[:, 1:] - path[:, :-1]  # [S, K - 1, 2]
    length = jnp.linalg.norm(seg, axis=-1)  # [S, K - 1]
    cum = jnp.concatenate([jnp.zeros_like(length[:, :1]), jnp.cumsum(length, -1)], -1)  # [S, K]
    total = cum[:, -1]
    s = total - jnp.abs(total - travelled)  # [S] arc length: out, then back
    i = jnp.clip(jnp.sum(cum[:, 1:-1] <= s[:, None], -1), 0, seg.shape[1] - 1)  # [S] segment
    take = lambda x: x[jnp.arange(x.shape[0]), i]  # noqa: E731  [S, ...] slot s's entry i[s]
    t = jnp.clip((s - take(cum)) / jnp.maximum(take(length), 1e-9), 0.0, 1.0)
    return take(path) + t[:, None] * take(seg)


def advance(room, dt: float, robot=None):
    """`room` (SceneParams with a `motion`) after `dt` s: bouncing and path slots moved, then the
    walkers (`crowd.walk`, giving way to `robot`: (xy [2], velocity [2], radius), or None)."""
    motion = room.motion
    pos, vel = _bounce(room, motion, dt)
    travelled = motion.travelled
    if motion.path.shape[-2] >= 2:  # static: some layout of the env has a path
        cycle = 2 * jnp.linalg.norm(motion.path[:, 1:] - motion.path[:, :-1], axis=-1).sum(-1)
        travelled = jnp.where(cycle > 0, jnp.mod(travelled + motion.speed * dt, cycle), 0.0)
        active = jnp.concatenate([room.box_active, room.cyl_active])
        on_path = (motion.speed > 0) & active
        pos = jnp.where(on_path[:, None], path_point(motion.path, travelled), pos)
    nb = room.box_pos.shape[0]
    room = room.replace(
        box_pos=pos[:nb],
        cyl_pos=pos[nb:],
        motion=motion.replace(velocity=vel, travelled=travelled),
    )
    return room if motion.walkers is None else crowd.walk(room, dt, robot)


def add_movers(key, room, cfg, robot_radius: float, goal=None):
    """`room` with up to `cfg.moving_count` bouncing cylinders in its last moving_count[1]
    cylinder slots (`reserve`): count uniform in moving_count, radius uniform in moving_radius,
    top uniform in obstacle_height, speed uniform in moving_speed, heading uniform. Each is the
    first of `TRIES` uniform positions that keeps `FREE_GAP` from the walls and the obstacles
    placed so far, `cfg.moving_clearance` from the robot's edge at the spawn and clear of the
    robot's disc at `goal` [2] (if given); a mover with no such position is left out."""
    m = cfg.moving_count[1]
    nb, nc = room.box_pos.shape[0], room.cyl_pos.shape[0]
    d = Draws(key)
    count = d.randint((), cfg.moving_count[0], m + 1)
    radius = d.uniform((m,), *cfg.moving_radius)
    height = d.uniform((m,), *cfg.obstacle_height)
    speed = d.uniform((m,), *cfg.moving_speed)
    heading = d.uniform((m,), -jnp.pi, jnp.pi)
    spawn = room.spawn[:2]
    velocity = room.motion.velocity
    for j in range(m):
        slot, r = nc - m + j, radius[j]
        limit = jnp.maximum(room.room_half - r - FREE_GAP, 0.0)
        cand = d.uniform((TRIES, 2), -1.0, 1.0) * limit
        ok = signed_distance(room, cand) > r + FREE_GAP
        ok &= jnp.linalg.norm(cand - spawn, axis=-1) > robot_radius + cfg.moving_clearance + r
        if goal is not None:
            ok &= jnp.linalg.norm(cand - goal, axis=-1) > robot_radius + r
        on = ok.any() & (j < count)
        put = lambda x, v, on=on, slot=slot: x.at[slot].set(jnp.where(on, v, x[slot]))  # noqa: E731
        room = room.replace(
            cyl_pos=put(room.cyl_pos, cand[jnp.argmax(ok)]),
            cyl_radius=put(room.cyl_radius, r),
            cyl_height=put(room.cyl_height, height[j]),
            cyl_bottom=put(room.cyl_bottom, 0.0),
            cyl_active=put(room.cyl_active, True),
        )
        direction = jnp.stack([jnp.cos(heading[j]), jnp.sin(heading[j])])
        velocity = velocity.at[nb + slot].set(jnp.where(on, speed[j] * direction, 0.0))
    return room.replace(motion=room.motion.replace(velocity=velocity))
