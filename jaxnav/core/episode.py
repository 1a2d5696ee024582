"""One episode's draw: a room (a layout of the bank, a sampled room or a room family), a free
spawn, moving-obstacle slots, and the drive and sensor parameters (`sample`, what `env.reset`
calls). It composes `randomize` (the configs and samplers) with `families` (the room families)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnav.core import crowd, motion
from jaxnav.core import grid as occupancy
from jaxnav.core.draws import Draws
from jaxnav.core.families import sample_weighted
from jaxnav.core.randomize import (
    LayoutBank,
    RandomizeConfig,
    SceneParams,
    family_weights,
    free_spawn,
    sample_room,
)


def walker_config(cfg: RandomizeConfig) -> crowd.WalkerConfig:
    """The walkers `cfg.walkers` adds; rooms of the `crowd` family get theirs only where the
    families include it (crowd_count is (0, 0) otherwise)."""
    walkers = crowd.WalkerConfig.parse(cfg.walkers)
    if not cfg.families or not family_weights(cfg.families).get("crowd"):
        walkers = dataclasses.replace(walkers, crowd_count=(0, 0))
    return walkers


def sample(key: jax.Array, cfg: RandomizeConfig, bank: LayoutBank, radius: float) -> SceneParams:
    """One episode's scene for a robot of `radius`: a room, a free spawn, physics and sensing.

    With moving obstacles (`cfg.moving_count`, walkers, or a layout's `motion`s) it has a
    `motion` in which nothing moves yet, and its last moving_count[1] cylinder slots are left
    empty for `motion.add_movers`, the walkers' slots (`walker_config`) before them for
    `crowd.add_walkers`."""
    d = Draws(key)
    nb, nc = bank.rooms.box_pos.shape[1], bank.rooms.cyl_pos.shape[1]
    walkers = walker_config(cfg).slots
    reserved = cfg.moving_count[1] + walkers
    g = occupancy.size(bank.rooms.grid)  # the bank has a grid wherever a sampled room may
    # Room: a sampled room with probability sampled_room_prob, otherwise a uniform pick of the layouts.
    if cfg.families:
        sampled = sample_weighted(d.key(), cfg, nb, nc - reserved, radius, grid=g)
    else:
        sampled = occupancy.with_grid(sample_room(d, cfg, nb, nc - reserved, radius), g)
    idx = d.randint((), 0, bank.size)
    layout = jax.tree_util.tree_map(lambda x: x[idx], bank.rooms).replace(layout_id=idx)
    if reserved or layout.motion is not None:
        if reserved:
            sampled = motion.reserve(sampled, reserved)
        points = 0 if layout.motion is None else layout.motion.path.shape[-2]
        still = jax.tree_util.tree_map(jnp.asarray, motion.still(nb + nc, points))
        kept = still if layout.motion is None else layout.motion
        if walkers or kept.walkers is not None:  # one structure for every room
            idle = jax.tree_util.tree_map(jnp.asarray, crowd.idle(nc))
            still = still.replace(walkers=idle)
            kept = kept.replace(walkers=idle if kept.walkers is None else kept.walkers)
        sampled = sampled.replace(motion=still)
        layout = layout.replace(motion=kept)
    # Spawn in a layout: its own pose, or with probability random_spawn_prob (always if it has none)
    # a uniform free pose.
    use_random = ~bank.has_spawn[idx] | d.bernoulli(cfg.random_spawn_prob)
    spawn = jnp.where(use_random, free_spawn(d, layout, radius, cfg.spawn_clearance), layout.spawn)
    layout = layout.replace(spawn=spawn)
    use_sampled = d.bernoulli(cfg.sampled_room_prob)
    room = jax.tree_util.tree_map(lambda a, b: jnp.where(use_sampled, a, b), sampled, layout)
    return _physics_and_sensing(d, cfg, room)


def _symmetric(d: Draws, bounds: jax.Array) -> jax.Array:
    """[n] uniform in +-bounds [n]."""
    return d.uniform(bounds.shape, -1.0, 1.0) * bounds


def _physics_and_sensing(d: Draws, cfg: RandomizeConfig, room: SceneParams) -> SceneParams:
    """The episode's drive and sensor parameters, each uniform in its configured range."""
    n = room.dark.shape[0]
    errors = jnp.array([cfg.camera_height_error, cfg.camera_pitch_error, cfg.camera_yaw_error])
    # The floor rule's height (m) and pitch (rad) error about the true mount.
    calibration = jnp.array([cfg.calibration_height_error, cfg.calibration_pitch_error])
    # Wheel mismatch: gains (1 - a/2, 1 + a/2), a uniform in wheel_asymmetry, which wheel at random.
    a = d.uniform((), *cfg.wheel_asymmetry) * jnp.where(d.bernoulli(), 1.0, -1.0)
    room = room.replace(
        friction=d.uniform((), *cfg.friction),
        speed_gain=d.uniform((), *cfg.speed_gain),
        noise_std=d.uniform((), *cfg.sensor_noise),
        dropout=d.uniform((), *cfg.sensor_dropout),
        noise_quad=d.uniform((), *cfg.sensor_noise_quadratic),
        camera=jnp.concatenate([_symmetric(d, errors), _symmetric(d, calibration)]),
        accel=jnp.stack([d.uniform((), *cfg.accel_limit), d.uniform((), *cfg.angular_accel_limit)]),
        latency=d.randint((), cfg.latency_steps[0], cfg.latency_steps[1] + 1),
        wheel_gain=jnp.stack([1.0 - 0.5 * a, 1.0 + 0.5 * a]),
    )
    if cfg.collision_margin[1] > 0:  # drawn only where asked, so other envs draw as before
        room = room.replace(margin=d.uniform((), *cfg.collision_margin))
    # Last, as its size counts the slots reserved for movers and walkers: the draws before it are
    # those of an env without them.
    return room.replace(dark=d.bernoulli(cfg.dark_prob, (n,)))
