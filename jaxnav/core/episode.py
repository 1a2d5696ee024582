"""One episode's draw: a room (a layout of the bank, a sampled room or a room family), a free
spawn, moving-obstacle slots, and the drive and sensor parameters (`sample`, what `env.reset`
calls). It composes `randomize` (the configs and samplers) with `families` (the room families)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnav.core import crowd, motion
from jaxnav.core import grid as occupancy
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


def _in(key, bounds):
    return jax.random.uniform(key, (), minval=bounds[0], maxval=bounds[1])


def sample(key: jax.Array, cfg: RandomizeConfig, bank: LayoutBank, radius: float) -> SceneParams:
    """One episode's scene for a robot of `radius`: a room, a free spawn, physics and sensing.

    With moving obstacles (`cfg.moving_count`, walkers, or a layout's `motion`s) it has a
    `motion` in which nothing moves yet, and its last moving_count[1] cylinder slots are left
    empty for `motion.add_movers`, the walkers' slots (`walker_config`) before them for
    `crowd.add_walkers`."""
    k_pick, k_room, k_layout, k_spawn, k_rand, k_phys = jax.random.split(key, 6)
    nb, nc = bank.rooms.box_pos.shape[1], bank.rooms.cyl_pos.shape[1]
    walkers = walker_config(cfg).slots
    reserved = cfg.moving_count[1] + walkers
    g = occupancy.size(bank.rooms.grid)  # the bank has a grid wherever a sampled room may
    # Room: a sampled room with probability sampled_room_prob, otherwise a uniform pick of the layouts.
    if cfg.families:
        sampled = sample_weighted(k_room, cfg, nb, nc - reserved, radius, grid=g)
    else:
        sampled = occupancy.with_grid(sample_room(k_room, cfg, nb, nc - reserved, radius), g)
    idx = jax.random.randint(k_layout, (), 0, bank.size)
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
    use_random = ~bank.has_spawn[idx] | jax.random.bernoulli(k_rand, cfg.random_spawn_prob)
    spawn = jnp.where(
        use_random, free_spawn(k_spawn, layout, radius, cfg.spawn_clearance), layout.spawn
    )
    layout = layout.replace(spawn=spawn)
    use_sampled = jax.random.bernoulli(k_pick, cfg.sampled_room_prob)
    room = jax.tree_util.tree_map(lambda a, b: jnp.where(use_sampled, a, b), sampled, layout)
    return _physics_and_sensing(k_phys, cfg, room)


def _symmetric(key, bounds: jax.Array) -> jax.Array:
    """[n] uniform in +-bounds [n]."""
    return jax.random.uniform(key, bounds.shape, minval=-1.0, maxval=1.0) * bounds


def _calibration(key, cfg: RandomizeConfig) -> jax.Array:
    """[2] the floor rule's height (m) and pitch (rad) error about the true mount; from a key of
    its own, so the other draws stay as they were."""
    bounds = jnp.array([cfg.calibration_height_error, cfg.calibration_pitch_error])
    return _symmetric(jax.random.fold_in(key, 1), bounds)


def _physics_and_sensing(key, cfg: RandomizeConfig, room: SceneParams) -> SceneParams:
    """The episode's drive and sensor parameters, each uniform in its configured range."""
    ks = jax.random.split(key, 10)
    n = room.dark.shape[0]
    errors = jnp.array([cfg.camera_height_error, cfg.camera_pitch_error, cfg.camera_yaw_error])
    # Wheel mismatch: gains (1 - a/2, 1 + a/2), a uniform in wheel_asymmetry, which wheel at random.
    a = _in(ks[8], cfg.wheel_asymmetry) * jnp.where(jax.random.bernoulli(ks[9]), 1.0, -1.0)
    return room.replace(
        friction=_in(ks[0], cfg.friction),
        speed_gain=_in(ks[1], cfg.speed_gain),
        noise_std=_in(ks[2], cfg.sensor_noise),
        dropout=_in(ks[3], cfg.sensor_dropout),
        noise_quad=_in(ks[4], cfg.sensor_noise_quadratic),
        dark=jax.random.bernoulli(ks[5], cfg.dark_prob, (n,)),
        camera=jnp.concatenate([_symmetric(ks[6], errors), _calibration(ks[6], cfg)]),
        accel=jnp.stack(
            [
                _in(jax.random.fold_in(ks[7], 0), cfg.accel_limit),
                _in(jax.random.fold_in(ks[7], 1), cfg.angular_accel_limit),
            ]
        ),
        latency=jax.random.randint(ks[7], (), cfg.latency_steps[0], cfg.latency_steps[1] + 1),
        wheel_gain=jnp.stack([1.0 - 0.5 * a, 1.0 + 0.5 * a]),
    )
