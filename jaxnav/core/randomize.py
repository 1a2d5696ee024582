"""Domain randomisation: a pure `sample(key) -> SceneParams`, vmapped over keys, drawn at every reset.

Each episode gets a room (one of the given layouts, or a procedurally sampled one), a spawn pose, floor
traction, an actuator speed gain and sensor noise. Everything here is traced data, so a new draw never
recompiles anything.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxnav.core import crowd, motion
from jaxnav.core import grid as occupancy
from jaxnav.core.checks import require_finite
from jaxnav.core.draws import Draws, draws
from jaxnav.core.geometry import UNUSED_HEIGHT, UNUSED_SIZE, signed_distance
from jaxnav.core.layout import MAX_OBSTACLE_SPEED, RoomLayout


@struct.dataclass
class SceneParams:
    """Everything that differs between episodes. Shapes are per env; a batch adds a leading axis."""

    room_half: jax.Array  # [2] half interior extents, m
    box_pos: jax.Array  # [Sb, 2] box centres, m
    box_yaw: jax.Array  # [Sb] rad
    box_half: jax.Array  # [Sb, 2] half extents along the box's own axes, m
    box_height: jax.Array  # [Sb] m, top above the floor
    box_bottom: jax.Array  # [Sb] m, underside above the floor (0: standing on it)
    box_active: jax.Array  # [Sb] bool; inactive slots are parked
    cyl_pos: jax.Array  # [Sc, 2] m
    cyl_radius: jax.Array  # [Sc] m
    cyl_height: jax.Array  # [Sc] m, top above the floor
    cyl_bottom: jax.Array  # [Sc] m, underside above the floor
    cyl_active: jax.Array  # [Sc] bool
    spawn: jax.Array  # [3] x, y, yaw of the robot at reset
    layout_id: jax.Array  # [] int32 index into the layouts, -1 for a sampled room
    friction: jax.Array  # [] floor traction coefficient: bounds the robot's acceleration
    speed_gain: jax.Array  # [] actual / commanded speed of the drive
    noise_std: jax.Array  # [] m, std of the additive depth noise per ray
    dropout: jax.Array  # [] probability that a ray returns nothing
    noise_quad: jax.Array  # [] m per m^2: depth noise std grows with distance^2
    dark: jax.Array  # [Sb + Sc] bool: the obstacle returns no depth (black, glossy, glass)
    camera: jax.Array  # [5] mount error: height m, pitch rad (down +), yaw rad (left +); then the
    # floor rule's error about the true mount (its calibration): height m, pitch rad
    accel: jax.Array  # [2] acceleration limits of the velocity smoother: m/s^2, rad/s^2
    latency: jax.Array  # [] int32 control steps between a command and the motors
    wheel_gain: jax.Array  # [2] actual / commanded speed of the left and right wheels
    margin: jax.Array  # [] m the collision test adds to the robot's collision volume (training)
    motion: Any = None  # `motion.MotionState` of the moving obstacles; None: nothing moves
    grid: Any = None  # `grid.OccupancyGrid` [G, G] of cell obstacles; None: the room has none


MAX_MOVERS = 16  # most moving obstacles added per room (each is placed by its own draw)
RANDOM = "random"  # the family of `RandomizeConfig.families` that is `sample_room` with that config
FAMILY_NAMES = (
    RANDOM,
    *("open", "clutter", "pillars", "corridor", "ltu", "joined", "furniture", "low_overhang"),
    "crowd",
    "long_hall",
    "dense_field",
)
"""Names of `RandomizeConfig.families`: 'random' and the room families of `jaxnav.core.families`."""
LARGE_FAMILIES = ("long_hall",)
"""Families of rooms over 10 m that 'all' leaves out (by name only): with one in the mix the goal
task's traced grid grows from 10.8 m square to cover them (`families.LARGE_EXTENTS`), which every
room of the batch pays, and 'all' stays the benchmark suite's families."""
GRID_FAMILIES = ("dense_field",)
"""Families on an occupancy grid (`jaxnav.core.families.GRID_FAMILIES`) that 'all' leaves out
(by name only): a grid layer costs every room of the batch, and 'all' stays the suite's families."""
WALKER_FAMILIES = ("crowd",)
"""Families with people walking (`jaxnav.core.crowd`) that 'all' leaves out (by name only):
walkers cost every room of the batch, and 'all' stays the suite's families."""


def family_weights(spec: str) -> dict[str, float]:
    """{name: probability} of a `RandomizeConfig.families` spec ('name:weight,...', 'name' alone
    weighs 1, 'all' is every family but `LARGE_FAMILIES` and 'random' equally). Errors name the
    field and the part."""
    names, where = FAMILY_NAMES, "RandomizeConfig.families"
    weights: dict[str, float] = {}
    for part in spec.split(","):
        name, _, value = part.strip().partition(":")
        if name == "all" and not value:
            left_out = (*LARGE_FAMILIES, *GRID_FAMILIES, *WALKER_FAMILIES)
            weights.update(dict.fromkeys([n for n in names if n not in left_out], 1.0))
            continue
        if name not in names:
            raise ValueError(f"{where}: unknown family {name!r}; valid: all, {', '.join(names)}")
        try:
            weights[name] = float(value) if value else 1.0
        except ValueError:
            raise ValueError(
                f"{where}: weight of {name!r} must be a number, got {value!r}"
            ) from None
        if not np.isfinite(weights[name]) or weights[name] < 0:
            raise ValueError(f"{where}: weight of {name!r} must be >= 0, got {value!r}")
    total = sum(weights.values())
    if total <= 0:
        raise ValueError(f"{where}: the weights must not all be 0, got {spec!r}")
    return {k: w / total for k, w in weights.items() if w > 0}


@dataclasses.dataclass(frozen=True)
class RandomizeConfig:
    """Ranges of the per-episode randomisation. Pairs are inclusive [low, high] ranges.

    The defaults simulate exactly the given rooms from their own spawns; `TRAINING` is the
    training distribution of `python -m jaxnav.train`, which mixes in sampled rooms and spawns.
    """

    sampled_room_prob: float = 0.0
    """Probability that an episode uses a sampled room instead of one of the layouts (must be 1 if
    there are no layouts; `make_env` sees to that)."""
    random_spawn_prob: float = 0.0
    """Probability that a layout with a fixed spawn starts the robot at a random free pose instead."""
    spawn_clearance: float = 0.3
    """Minimum gap between the robot's edge and any obstacle or wall at a sampled spawn, m."""
    room_size_min: tuple[float, float] = (4.0, 4.0)
    """Smallest sampled interior [x, y], m."""
    room_size_max: tuple[float, float] = (8.0, 8.0)
    """Largest sampled interior [x, y], m."""
    num_boxes: tuple[int, int] = (2, 8)
    """Number of boxes in a sampled room, uniform over the range."""
    num_cylinders: tuple[int, int] = (0, 4)
    """Number of cylinders in a sampled room, uniform over the range."""
    box_size: tuple[float, float] = (0.2, 1.0)
    """Full extent of a sampled box along each of its axes, m."""
    cylinder_radius: tuple[float, float] = (0.08, 0.3)
    """Radius of a sampled cylinder, m."""
    families: str = ""
    """Kinds of room the sampled rooms are, as 'name:weight,...': names of
    `jaxnav.core.families.FAMILIES` (open, clutter, pillars, corridor, ltu, joined, furniture,
    low_overhang, crowd: people crossing, see `walkers`, long_hall), `GRID_FAMILIES` (dense_field:
    a BARN-like field of cells on an occupancy grid) and 'random' (the sampler configured by the
    fields below); 'all' is every one but those of `LARGE_FAMILIES`, `GRID_FAMILIES` and
    `WALKER_FAMILIES`, equally weighted. Empty: 'random' only."""
    moving_count: tuple[int, int] = (0, 0)
    """Moving obstacles added to every room, sampled or layout, count uniform over the range:
    cylinders bouncing off the walls and the other obstacles at a constant speed, in cylinder
    slots of their own (`jaxnav.core.motion`); a layout's own `motion`s come on top. (0, 0):
    none, at no cost."""
    moving_speed: tuple[float, float] = (0.2, 0.5)
    """Speed of an added moving obstacle, m/s, uniform (at most 1); its heading is uniform."""
    moving_radius: tuple[float, float] = (0.15, 0.3)
    """Radius of an added moving obstacle, m, uniform (a person, a trolley); its height is
    drawn from obstacle_height."""
    moving_clearance: float = 1.0
    """Least gap between an added moving obstacle and the robot's edge at the reset, m, so that
    the first steps are fair."""
    walkers: str = ""
    """People walking across the rooms (`jaxnav.core.crowd`): fields of `crowd.WalkerConfig` as
    'name=value,...', ranges as low:high, e.g. 'count=2:6,reactive=0.5' (count: in every room;
    speed, radius, reactive share, height, clearance). Empty: its defaults, which add walkers to
    the rooms of the `crowd` family only."""
    obstacle_height: tuple[float, float] = (0.4, 1.0)
    """Height of a sampled obstacle, m; the TurtleBot 2i's camera sits at 0.30 m."""
    low_prob: float = 0.0
    """Probability that a sampled obstacle is low (height in low_height): below the camera.
    The ranges from here to wheel_asymmetry are off in a bare config; `FIDELITY` has them on."""
    low_height: tuple[float, float] = (0.05, 0.25)
    """Height of a low obstacle, m."""
    overhang_prob: float = 0.0
    """Probability that a sampled obstacle hangs: underside in overhang_bottom (a table, a shelf)."""
    overhang_bottom: tuple[float, float] = (0.3, 0.45)
    """Underside of an overhang, m: above the Kobuki's shell, below the 2i's top deck (0.47 m)."""
    friction: tuple[float, float] = (0.5, 1.0)
    """Floor traction coefficient (rubber wheels on office floors)."""
    speed_gain: tuple[float, float] = (0.8, 1.2)
    """Actual / commanded speed: the paper had to recalibrate speeds on the real robot."""
    sensor_noise: tuple[float, float] = (0.0, 0.02)
    """Std of the additive per-ray depth noise, m."""
    sensor_dropout: tuple[float, float] = (0.0, 0.02)
    """Probability that a ray returns nothing (the camera reports 0 there)."""
    sensor_noise_quadratic: tuple[float, float] = (0.0, 0.0)
    """Depth noise std per distance^2, m/m^2 (structured light: ~4 cm at 5 m is 0.0016)."""
    dark_prob: float = 0.0
    """Probability that an obstacle returns no depth at all (black, glossy or glass surfaces)."""
    camera_height_error: float = 0.0
    """Camera height error, m: uniform in +-this."""
    camera_pitch_error: float = 0.0
    """Camera pitch error, rad: uniform in +-this (3 deg)."""
    camera_yaw_error: float = 0.0
    """Camera yaw error, rad: uniform in +-this (2 deg)."""
    calibration_height_error: float = 0.0
    """Error of the camera height the floor rule uses, m: uniform in +-this about the true
    (mount-error included) height. On the robot the rule uses the calibrated mount
    (`jaxnav.robot_side.calibrate`: within 0.01 m on synthetic frames); 0: the true one."""
    calibration_pitch_error: float = 0.0
    """Error of the camera pitch the floor rule uses, rad: uniform in +-this about the true pitch
    (the calibration: within 0.2 deg, 0.0035 rad, on synthetic frames); 0: the true one."""
    accel_limit: tuple[float, float] = (0.0, 0.0)
    """Linear acceleration limit of the velocity smoother, m/s^2 (kobuki_velocity_smoother: 0.3;
    0: no smoother, commanded speeds within one step)."""
    angular_accel_limit: tuple[float, float] = (0.0, 0.0)
    """Angular acceleration limit, rad/s^2 (Kobuki: 3.5)."""
    coupled_smoother: bool = False
    """The velocity smoother's rule: True shrinks the forward and the turn change of a step by one
    factor, so the (m/s, rad/s) change keeps its direction, as kobuki_velocity_smoother does
    (`jaxnav.twin.smoother_step`); False limits each on its own."""
    latency_steps: tuple[int, int] = (0, 0)
    """Command latency in control steps, uniform over the range (0.1 s each)."""
    wheel_asymmetry: tuple[float, float] = (0.0, 0.0)
    """Left/right wheel gain mismatch: gains 1 -+ a/2 with a uniform here, the sign at random."""
    collision_margin: tuple[float, float] = (0.0, 0.0)
    """m the collision test adds to the robot's collision volume, uniform over the range per
    episode: a policy that must keep this much clear of everything passes things with room to
    spare for what it misjudges (how near its path passes an obstacle out of view, its drift). For
    training: evaluation's ranges (`jaxnav.evaluation.eval_randomize`) leave it 0, the robot's true
    size (docs/results.md, "A collision margin in training")."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple) and len(value) != 2:
                raise ValueError(f"RandomizeConfig.{f.name}: must be two numbers, got {value}")
        require_finite(self)
        for name in (
            "sampled_room_prob",
            "random_spawn_prob",
            "low_prob",
            "overhang_prob",
            "dark_prob",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"RandomizeConfig.{name}: must be in [0, 1], got {getattr(self, name)}"
                )
        for name in ("spawn_clearance", "moving_clearance"):
            if getattr(self, name) < 0:
                raise ValueError(
                    f"RandomizeConfig.{name}: must be >= 0 m, got {getattr(self, name)}"
                )
        if 0 < self.collision_margin[1] and self.collision_margin[1] >= self.spawn_clearance:
            raise ValueError(
                f"RandomizeConfig.collision_margin: must stay below spawn_clearance "
                f"({self.spawn_clearance} m), or a spawn would count as a collision, got "
                f"{self.collision_margin}"
            )
        if self.moving_count[1] > MAX_MOVERS:
            raise ValueError(
                f"RandomizeConfig.moving_count: at most {MAX_MOVERS} per room, got {self.moving_count}"
            )
        if not 0 < self.moving_speed[0] <= self.moving_speed[1] <= MAX_OBSTACLE_SPEED:
            raise ValueError(
                f"RandomizeConfig.moving_speed: need 0 < low <= high <= {MAX_OBSTACLE_SPEED:g} "
                f"m/s, got {self.moving_speed}"
            )
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple) and f.name not in ("room_size_min", "room_size_max"):
                lo, hi = value
                if lo > hi or lo < 0:
                    raise ValueError(
                        f"RandomizeConfig.{f.name}: need 0 <= low <= high, got {value}"
                    )
        for name in (
            "camera_height_error",
            "camera_pitch_error",
            "camera_yaw_error",
            "calibration_height_error",
            "calibration_pitch_error",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"RandomizeConfig.{name}: must be >= 0, got {getattr(self, name)}")
        if self.low_prob + self.overhang_prob > 1:
            raise ValueError(
                f"RandomizeConfig.low_prob: low_prob + overhang_prob must be <= 1, got "
                f"{self.low_prob} + {self.overhang_prob}"
            )
        for name in (
            "box_size",
            "cylinder_radius",
            "obstacle_height",
            "low_height",
            "moving_radius",
        ):
            if getattr(self, name)[0] <= 0:
                raise ValueError(
                    f"RandomizeConfig.{name}: low must be > 0 m, got {getattr(self, name)}"
                )
        if any(lo > hi for lo, hi in zip(self.room_size_min, self.room_size_max, strict=True)):
            raise ValueError(
                f"RandomizeConfig.room_size_min: must not exceed room_size_max per axis, got "
                f"{self.room_size_min} > {self.room_size_max}"
            )

        if self.families:
            family_weights(self.families)
        crowd.WalkerConfig.parse(self.walkers)

    def check_robot(self, radius: float) -> None:
        """Sampled rooms must fit a robot of `radius` with its spawn clearance."""
        smallest = 2 * (radius + self.spawn_clearance)
        if min(self.room_size_min) < smallest:
            raise ValueError(
                f"RandomizeConfig.room_size_min: must be >= {smallest:.3f} m per axis (the robot "
                f"and spawn_clearance on both sides), got {self.room_size_min}"
            )


FIDELITY = dict(
    low_prob=0.2,
    overhang_prob=0.1,
    sensor_noise=(0.0, 0.01),
    sensor_noise_quadratic=(0.0, 0.0016),
    dark_prob=0.05,
    camera_height_error=0.02,
    camera_pitch_error=0.052,
    camera_yaw_error=0.035,
    accel_limit=(0.25, 0.35),
    angular_accel_limit=(3.0, 4.0),
    latency_steps=(0, 2),
    wheel_asymmetry=(0.0, 0.05),
)
"""The sim-to-real ranges around the TurtleBot 2i's figures: low obstacles and overhangs, the
Kobuki's velocity smoother (0.3 m/s^2, 3.5 rad/s^2), 0-2 steps of command latency, wheel mismatch,
structured-light depth noise, dark obstacles and camera mount error. On in `TRAINING` and in
evaluation; a bare `RandomizeConfig()` has them off (exact physics and sensing)."""

TRAINING = RandomizeConfig(sampled_room_prob=0.75, random_spawn_prob=0.5, **FIDELITY)
"""The training distribution of `python -m jaxnav.train`: three episodes in four in a sampled room
(the 'random' family, with low obstacles and overhangs), the rest in the given layouts, half of
those from a random spawn; the sim-to-real ranges of `FIDELITY` on. The room families of
`jaxnav.core.families` stay out of it by default, so the benchmark suite, built from them, is
rooms the policy never saw (`families="all"` mixes them in; docs/results.md compares)."""


@struct.dataclass
class LayoutBank:
    """The given layouts as stacked arrays padded to the slot counts ([K, ...] SceneParams fields)."""

    rooms: SceneParams  # room fields of K layouts; spawn/physics fields are placeholders
    has_spawn: jax.Array  # [K] bool: the layout fixes the robot's spawn
    goals: Any = None  # goal tasks only: the layouts' goals and free cells (`goals.GoalCells`)

    @property
    def size(self) -> int:
        return int(self.has_spawn.shape[0])


def make_bank(
    layouts: Sequence[RoomLayout], num_boxes: int, num_cylinders: int, grid: int = 0
) -> LayoutBank:
    """Stacks layouts into a bank with `num_boxes`/`num_cylinders` slots (inactive beyond their own).

    Where an obstacle of some layout moves, every room gets a `motion.MotionState` (its paths
    padded to the longest); otherwise `rooms.motion` is None. With `grid` > 0 (at least the
    largest layout grid's side, `layout_grid_size`), every room gets a [grid, grid] occupancy
    grid: its layout's own, or an empty one; otherwise `rooms.grid` is None."""
    points = None
    if any(ob.motion is not None for lay in layouts for ob in lay.obstacles):
        paths = [ob.motion.path for lay in layouts for ob in lay.obstacles if ob.motion]
        points = max([1 + len(p) for p in paths if p] or [0])
    need = layout_grid_size(layouts)
    if grid and grid < need:
        raise ValueError(
            f"make_bank: grid must be >= {need} cells (the largest layout's), got {grid}"
        )
    grid = grid or need
    rooms = [_layout_params(lay, num_boxes, num_cylinders, points, grid) for lay in layouts]
    if not rooms:  # an empty bank keeps shapes static: one dummy room, never drawn
        none = RoomLayout(name="none", size=(4.0, 4.0))
        rooms = [_layout_params(none, num_boxes, num_cylinders, None, grid)]
    stacked = jax.tree_util.tree_map(lambda *x: np.stack(x), *rooms)
    if (walkers := crowd.from_layouts(layouts, num_cylinders)) is not None:
        stacked = stacked.replace(motion=stacked.motion.replace(walkers=walkers))
    has_spawn = np.array([lay.robot_pos is not None for lay in layouts] or [False])
    return LayoutBank(
        rooms=jax.tree_util.tree_map(jnp.asarray, stacked), has_spawn=jnp.asarray(has_spawn)
    )


def _layout_motion(layout: RoomLayout, nb: int, nc: int, points: int) -> motion.MotionState:
    """The layout's obstacle motions in slots (boxes, then cylinders from slot `nb`), paths of
    `points` points: the obstacle's `pos`, its waypoints, then its last one repeated."""
    state = motion.still(nb + nc, points)
    slots = [(i, b) for i, b in enumerate(layout.boxes)]
    slots += [(nb + i, c) for i, c in enumerate(layout.cylinders)]
    for slot, ob in slots:
        move = ob.motion
        if move is None:
            continue
        if move.velocity is not None:
            state.velocity[slot] = move.velocity
        elif move.path is not None:  # a walker's goal: `crowd.from_layouts`
            line = [ob.pos, *move.path]
            state.path[slot] = line + [line[-1]] * (points - len(line))
            state.speed[slot] = move.speed
    return state


def layout_grid_size(layouts: Sequence[RoomLayout]) -> int:
    """G, the side in cells of the largest occupancy grid of `layouts` (0: none has one)."""
    sides = [max(len(lay.grid.rows), len(lay.grid.rows[0])) for lay in layouts if lay.grid]
    return max(sides, default=0)


def _layout_grid(layout: RoomLayout, g: int) -> occupancy.OccupancyGrid | None:
    """The layout's grid as a [g, g] `OccupancyGrid` (numpy; empty where it has none), or None
    for g = 0. Its rows run north to south in the file, south to north here."""
    if g == 0:
        return None
    out = occupancy.empty(g)
    ob = layout.grid
    if ob is None:
        return out
    rows = np.array([[ch == "#" for ch in row] for row in ob.rows[::-1]], bool)
    out.cells[: rows.shape[0], : rows.shape[1]] = rows
    f32 = np.float32
    return out.replace(origin=np.asarray(ob.origin, f32), cell=f32(ob.cell), height=f32(ob.height))


def _layout_params(
    layout: RoomLayout, nb: int, nc: int, points: int | None = None, grid: int = 0
) -> SceneParams:
    boxes, cyls = layout.boxes, layout.cylinders
    if len(boxes) > nb or len(cyls) > nc:
        raise ValueError(
            f"layout '{layout.name}': {len(boxes)} boxes and {len(cyls)} cylinders "
            f"do not fit {nb} box and {nc} cylinder slots"
        )
    f32 = np.float32
    pad = lambda rows, n, width: np.array(  # noqa: E731
        list(rows) + [[0.0] * width] * (n - len(rows)), f32
    ).reshape(n, width)
    active = lambda k, n: np.arange(n) < k  # noqa: E731
    spawn = (*(layout.robot_pos or (0.0, 0.0)), layout.robot_yaw)
    return SceneParams(
        room_half=0.5 * np.array(layout.size, f32),
        box_pos=pad([b.pos for b in boxes], nb, 2),
        box_yaw=pad([[b.yaw] for b in boxes], nb, 1)[:, 0],
        box_half=0.5 * pad([b.size for b in boxes], nb, 2)
        + UNUSED_SIZE * ~active(len(boxes), nb)[:, None],
        box_height=pad([[b.height] for b in boxes], nb, 1)[:, 0]
        + UNUSED_HEIGHT * ~active(len(boxes), nb),
        box_bottom=pad([[b.bottom] for b in boxes], nb, 1)[:, 0],
        box_active=active(len(boxes), nb),
        cyl_pos=pad([c.pos for c in cyls], nc, 2),
        cyl_radius=pad([[c.radius] for c in cyls], nc, 1)[:, 0]
        + UNUSED_SIZE * ~active(len(cyls), nc),
        cyl_height=pad([[c.height] for c in cyls], nc, 1)[:, 0]
        + UNUSED_HEIGHT * ~active(len(cyls), nc),
        cyl_bottom=pad([[c.bottom] for c in cyls], nc, 1)[:, 0],
        cyl_active=active(len(cyls), nc),
        spawn=np.array(spawn, f32),
        layout_id=np.int32(0),
        friction=f32(1),
        speed_gain=f32(1),
        noise_std=f32(0),
        dropout=f32(0),
        **_episode_placeholders(nb, nc),
        motion=None if points is None else _layout_motion(layout, nb, nc, points),
        grid=_layout_grid(layout, grid),
    )


def empty_room(nb: int, nc: int) -> SceneParams:
    """A room of `nb` box and `nc` cylinder slots, every one inactive (the placeholders of a
    layout's unused slots), the per-episode fields zero: what a room family fills in."""
    f32, zeros = np.float32, lambda *shape: np.zeros(shape, np.float32)  # noqa: E731
    room = SceneParams(
        room_half=np.ones(2, f32),
        box_pos=zeros(nb, 2),
        box_yaw=zeros(nb),
        box_half=np.full((nb, 2), UNUSED_SIZE, f32),
        box_height=np.full(nb, UNUSED_HEIGHT, f32),
        box_bottom=zeros(nb),
        box_active=np.zeros(nb, bool),
        cyl_pos=zeros(nc, 2),
        cyl_radius=np.full(nc, UNUSED_SIZE, f32),
        cyl_height=np.full(nc, UNUSED_HEIGHT, f32),
        cyl_bottom=zeros(nc),
        cyl_active=np.zeros(nc, bool),
        spawn=zeros(3),
        layout_id=np.int32(-1),
        friction=f32(0),
        speed_gain=f32(0),
        noise_std=f32(0),
        dropout=f32(0),
        **_episode_placeholders(nb, nc),
    )
    return jax.tree_util.tree_map(jnp.asarray, room)


def _episode_placeholders(nb: int, nc: int) -> dict:
    """Zeros for the per-episode physics and sensor fields; `sample` draws them."""
    f32 = np.float32
    return dict(
        noise_quad=f32(0),
        dark=np.zeros(nb + nc, bool),
        camera=np.zeros(5, f32),
        accel=np.zeros(2, f32),
        latency=np.int32(0),
        wheel_gain=np.ones(2, f32),
        margin=f32(0),
    )


def clearance(params: SceneParams, xy: jax.Array) -> jax.Array:
    """Distance from point `xy` [2] to the nearest wall or active obstacle surface (< 0 inside one)."""
    return signed_distance(params, xy)


def _place(d: Draws, half, bound, spawn_xy, keep_out, count, n, tries=8):
    """[n, 2] positions inside the room (margin `bound` [n]) and [n] active flags.

    Slot i is active if i < count and one of `tries` uniform candidates keeps its bounding circle
    `keep_out` away from the spawn; otherwise it stays parked, so the spawn is always free.
    """
    limit = jnp.maximum(half - bound[:, None], 0.0)  # [n, 2]
    cand = d.uniform((n, tries, 2), -1.0, 1.0) * limit[:, None]
    free = jnp.linalg.norm(cand - spawn_xy, axis=-1) > bound[:, None] + keep_out  # [n, tries]
    first = jnp.argmax(free, axis=1)
    pos = jnp.take_along_axis(cand, first[:, None, None], axis=1)[:, 0]
    return pos, free.any(axis=1) & (jnp.arange(n) < count)


def sample_room(
    key: jax.Array | Draws, cfg: RandomizeConfig, nb: int, nc: int, radius: float
) -> SceneParams:
    """A procedural room with `nb`/`nc` slots; the spawn of a robot of `radius` is free by
    construction. `key`: a PRNG key or the `Draws` to take the numbers from."""
    d = draws(key)
    # Interior extents: uniform per axis in [room_size_min, room_size_max].
    half = 0.5 * d.uniform((2,), jnp.array(cfg.room_size_min), jnp.array(cfg.room_size_max))
    keep_out = radius + cfg.spawn_clearance
    # Spawn: uniform over the interior shrunk by the robot and its clearance; heading uniform.
    spawn_xy = d.uniform((2,), -1.0, 1.0) * (half - keep_out)
    spawn = jnp.append(spawn_xy, d.uniform((), -jnp.pi, jnp.pi))
    # Boxes: count uniform in num_boxes; full extents uniform in box_size; yaw uniform.
    box_half = 0.5 * d.uniform((nb, 2), *cfg.box_size)
    box_yaw = d.uniform((nb,), -jnp.pi, jnp.pi)
    n_box = d.randint((), cfg.num_boxes[0], cfg.num_boxes[1] + 1)
    box_pos, box_active = _place(
        d, half, jnp.linalg.norm(box_half, axis=-1), spawn_xy, keep_out, n_box, nb
    )
    # Cylinders: count uniform in num_cylinders; radius uniform in cylinder_radius.
    radius = d.uniform((nc,), *cfg.cylinder_radius)
    n_cyl = d.randint((), cfg.num_cylinders[0], cfg.num_cylinders[1] + 1)
    cyl_pos, cyl_active = _place(d, half, radius, spawn_xy, keep_out, n_cyl, nc)
    bottom, top = _vertical_spans(d, cfg, nb + nc)
    zero = jnp.float32(0)
    return SceneParams(
        room_half=half,
        box_pos=box_pos,
        box_yaw=box_yaw,
        box_half=box_half,
        box_height=top[:nb],
        box_bottom=bottom[:nb],
        box_active=box_active,
        cyl_pos=cyl_pos,
        cyl_radius=radius,
        cyl_height=top[nb:],
        cyl_bottom=bottom[nb:],
        cyl_active=cyl_active,
        spawn=spawn,
        layout_id=jnp.int32(-1),
        friction=zero,
        speed_gain=zero,
        noise_std=zero,
        dropout=zero,
        **jax.tree_util.tree_map(jnp.asarray, _episode_placeholders(nb, nc)),
    )


def _vertical_spans(d: Draws, cfg: RandomizeConfig, n: int):
    """[n] undersides and [n] tops of sampled obstacles: standing, low or overhanging."""
    # Kind: low with low_prob, overhang with overhang_prob, else standing.
    u = d.uniform((n,))
    low, hang = u < cfg.low_prob, (u >= cfg.low_prob) & (u < cfg.low_prob + cfg.overhang_prob)
    # Standing: top uniform in obstacle_height; low: top uniform in low_height.
    top = jnp.where(low, d.uniform((n,), *cfg.low_height), d.uniform((n,), *cfg.obstacle_height))
    # Overhang: underside uniform in overhang_bottom, 0.05-0.5 m thick.
    bottom = jnp.where(hang, d.uniform((n,), *cfg.overhang_bottom), 0.0)
    top = jnp.where(hang, bottom + d.uniform((n,), 0.05, 0.5), top)
    return bottom, top


def free_spawn(
    key: jax.Array | Draws, room: SceneParams, radius: float, clearance_margin: float, tries=64
):
    """[3] a uniform pose whose robot disc (`radius`) keeps `clearance_margin` from everything.

    Takes the first of `tries` uniform candidates that is free; if none is (a crowded room), the one
    with the most clearance. `key`: a PRNG key or the `Draws` to take the numbers from.
    """
    d = draws(key)
    half = jnp.maximum(room.room_half - radius, 0.0)
    cand = d.uniform((tries, 2), -1.0, 1.0) * half  # [tries, 2]
    gap = signed_distance(room, cand) - radius  # [tries]
    ok = gap >= clearance_margin
    best = jnp.where(ok.any(), jnp.argmax(ok), jnp.argmax(gap))
    return jnp.append(cand[best], d.uniform((), -jnp.pi, jnp.pi))
