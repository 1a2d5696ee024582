"""People who walk: goal-directed walkers in cylinder slots, some of them giving way to the robot.

A walker is an upright cylinder (a person) walking at its preferred speed towards its goal; on
arrival its goal becomes the point it came from, so it crosses the room back and forth (a
layout's walker may instead stay at its goal). Every control step each walker picks its
velocity from candidates around the preferred one by the sampling rule of Reciprocal Velocity
Obstacles (van den Berg, Lin and Manocha 2008): the candidate of least penalty
|v - v_pref| + AVOID_WEIGHT * (1 / time to collision - 1 / HORIZON), the time to collision
taken over the other walkers (each taking half of the avoiding: RVO's reciprocity) and, for a
reactive walker, the robot (taken to keep its velocity); a candidate that touches one of them
within the step, or takes it towards a wall or a still obstacle within LOOKAHEAD, is ruled out.
So a reactive walker slows, stops or sidesteps for the robot and for the others; a non-reactive
one gives way to the other people only and walks through the robot's position
(CrowdNav's "invisible robot", Chen et al. 2019).

Where people meet from every side (a circle crossing's centre) or face to face, every candidate
but standing can close on someone or turn back, and all of them could stand for good. So a
walker that has stood for the other people (not for the robot) for PATIENCE s turns bold for
BOLD s: it heeds the others only as far as not touching them, and stands no more where it can
move, so it slips past them or steps aside and the meeting dissolves. (The robot is heeded as
before.) And whatever the candidates' costs, a walker whose step would take it into another
person, where that one stands or where one in an earlier slot goes, stands instead (`_apart`):
of two whose steps clash one still moves, so they do not stand and pick the same steps again.

The state is traced data (`Walkers`, in `SceneParams.motion.walkers`; None where nobody walks),
so new walkers never recompile. `add_walkers` draws the sampler's walkers at the reset
(`WalkerConfig`), in cylinder slots of their own; a layout's walkers are its cylinders with a
`"goal"` motion (`from_layouts`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxnav.core.draws import Draws
from jaxnav.core.geometry import signed_distance
from jaxnav.core.layout import MAX_WALKER_SPEED

ANGLES = (0.0, 25.0, -25.0, 50.0, -50.0, 80.0, -80.0, 115.0, -115.0)  # deg from the preferred
SCALES = (1.0, 0.5)  # of the preferred speed; with ANGLES and standing, the candidates
AVOID_WEIGHT = 1.0  # m/s * s: the penalty of a collision 1 s ahead, against a change of velocity
HORIZON = 3.0  # s; a collision further ahead costs nothing
MIN_TIME = 0.05  # s; times to collision below this cost as much as this one
SOCIAL_GAP = 0.1  # m a walker keeps between its edge and another person's or the robot's
PATIENCE = 1.0  # s a walker stands for people, short of its goal, before it turns bold
BOLD = 1.0  # s it then heeds the other people only as far as not touching them
LOOKAHEAD = 0.5  # s ahead at which a candidate must keep STATIC_GAP from walls and still obstacles
STATIC_GAP = 0.05  # m
BLOCKED = 100.0  # penalty of a candidate that touches someone or heads into a wall or obstacle
ARRIVE = 0.05  # m from its goal at which a walker has arrived
TRIES = 16  # candidate crossings per added walker; a walker whose candidates all fail is left out
FREE_GAP = 0.05  # m an added walker keeps from the walls and obstacles along its crossing
SEGMENT_POINTS = 8  # points of a crossing checked against the still obstacles
_DX = 1e-3  # m, step of the finite differences that give a still obstacle's normal
STOPPED_SPEED = 0.05  # m/s: a robot slower than this stands (`hit_by_walker`)
TOUCH = 1e-3  # m of tolerance on the robot touching a walker
MAX_WALKERS = 16  # most walkers added per room
AIM_AHEAD = (1.0, 4.0)  # m, radius of an aimed walker's circle where the robot has no goal
AIM_NOISE = 0.5  # m, the most an aimed walker's start lies off its circle per axis (CrowdNav's)
CROWD_ROOM = -2  # `SceneParams.layout_id` of a room of the `crowd` family (sampled, < 0)


@dataclasses.dataclass(frozen=True)
class WalkerConfig:
    """People the sampler adds to rooms (`RandomizeConfig.walkers`, 'field=value,...'). Pairs are
    inclusive [low, high] ranges, drawn uniformly per walker."""

    count: tuple[int, int] = (0, 0)
    """Walkers in every room, sampled or layout, count uniform over the range; (0, 0): none,
    at no cost (a layout's own walkers come on top)."""
    crowd_count: tuple[int, int] = (3, 6)
    """Walkers in a room of the `crowd` family, count uniform over the range (instead of
    `count`); used where the families include `crowd`."""
    speed: tuple[float, float] = (0.3, 1.4)
    """Preferred walking speed, m/s (people walk at about 1.3 m/s)."""
    radius: tuple[float, float] = (0.2, 0.3)
    """Radius of the cylinder a walker is, m."""
    reactive: float = 0.5
    """Share of the walkers that give way to the robot; the others walk through its position."""
    height: tuple[float, float] = (1.5, 1.9)
    """Height of a walker, m."""
    clearance: float = 1.0
    """Least gap between a walker and the robot's edge at the reset, m."""
    aimed: float = 0.0
    """Share of the walkers that cross the robot's way as CrowdNav's circle crossing has them
    (`_aimed`): from a point of the circle whose diameter is the straight way from the spawn to
    the goal (ahead of the spawn where there is no goal) to the opposite point, where it stays;
    where no such crossing fits, and for the others, a crossing of the room back and forth
    (`_crossings`). 0: none, and the draws of a room are those of before."""

    def __post_init__(self):
        for name in ("count", "crowd_count", "speed", "radius", "height"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"WalkerConfig.{name}: need 0 <= low <= high, got ({lo}, {hi})")
        for name in ("count", "crowd_count"):
            if getattr(self, name)[1] > MAX_WALKERS:
                raise ValueError(
                    f"WalkerConfig.{name}: at most {MAX_WALKERS} per room, got {getattr(self, name)}"
                )
        if not (0 < self.speed[0] and self.speed[1] <= MAX_WALKER_SPEED):
            raise ValueError(
                f"WalkerConfig.speed: need 0 < low <= high <= {MAX_WALKER_SPEED:g} m/s, "
                f"got {self.speed}"
            )
        for name in ("radius", "height"):
            if getattr(self, name)[0] <= 0:
                raise ValueError(
                    f"WalkerConfig.{name}: low must be > 0 m, got {getattr(self, name)}"
                )
        for name in ("reactive", "aimed"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(
                    f"WalkerConfig.{name}: must be in [0, 1], got {getattr(self, name)}"
                )
        if self.clearance < 0:
            raise ValueError(f"WalkerConfig.clearance: must be >= 0 m, got {self.clearance}")

    @property
    def slots(self) -> int:
        """Cylinder slots the added walkers take."""
        return max(self.count[1], self.crowd_count[1])

    @classmethod
    def parse(cls, spec: str) -> WalkerConfig:
        """The config of a 'field=value,...' spec, ranges as 'low:high' ('count=2:6,reactive=1');
        errors name `RandomizeConfig.walkers` and the field."""
        kinds = {f.name: f.type for f in dataclasses.fields(cls)}
        values = {}
        for part in filter(None, (p.strip() for p in spec.split(","))):
            name, _, text = part.partition("=")
            name = name.strip()
            if name not in kinds:
                valid = ", ".join(kinds)
                raise ValueError(f"RandomizeConfig.walkers: unknown field {name!r}; valid: {valid}")
            number = int if "int" in str(kinds[name]) else float
            try:
                items = [number(x) for x in text.split(":")]
            except ValueError:
                raise ValueError(
                    f"RandomizeConfig.walkers: {name} must be numbers, got {text!r}"
                ) from None
            if "tuple" in str(kinds[name]):
                values[name] = (items[0], items[-1]) if len(items) in (1, 2) else None
            else:
                values[name] = items[0] if len(items) == 1 else None
            if values[name] is None:
                shape = "a number or low:high" if "tuple" in str(kinds[name]) else "a number"
                raise ValueError(f"RandomizeConfig.walkers: {name} must be {shape}, got {text!r}")
        try:
            return cls(**values)
        except ValueError as err:
            raise ValueError(f"RandomizeConfig.walkers: {err}") from None


@struct.dataclass
class Walkers:
    """The people walking in a room's cylinder slots. C = cylinder slots."""

    goal: jax.Array  # [C, 2] m, where each walker is heading
    back: jax.Array  # [C, 2] m, its next goal on arrival (where it came from; = goal: it stays)
    speed: jax.Array  # [C] m/s, preferred speed; 0: the slot does not walk
    reactive: jax.Array  # [C] bool: it gives way to the robot
    velocity: jax.Array  # [C, 2] m/s over the last control step
    waited: jax.Array  # [C] s it has stood for people short of its goal; >= PATIENCE: bold


def idle(slots: int) -> Walkers:
    """`Walkers` in which none of `slots` cylinder slots walks (numpy)."""
    f32 = np.float32
    return Walkers(
        goal=np.zeros((slots, 2), f32),
        back=np.zeros((slots, 2), f32),
        speed=np.zeros(slots, f32),
        reactive=np.zeros(slots, bool),
        velocity=np.zeros((slots, 2), f32),
        waited=np.zeros(slots, f32),
    )


def from_layouts(layouts, nc: int) -> Walkers | None:
    """[K, ...] the walkers of each layout's cylinders (slot i: its i-th cylinder) with a
    `"goal"` motion, stacked (numpy); None where no layout has one."""
    if not any(c.motion is not None and c.motion.goal for lay in layouts for c in lay.cylinders):
        return None
    rooms = []
    for lay in layouts:
        w = idle(nc)
        for i, c in enumerate(lay.cylinders):
            if c.motion is not None and c.motion.goal is not None:
                w.goal[i] = c.motion.goal
                w.back[i] = c.pos if c.motion.repeat else c.motion.goal
                w.speed[i] = c.motion.speed
                w.reactive[i] = c.motion.reactive
        rooms.append(w)
    return jax.tree_util.tree_map(lambda *x: np.stack(x), *rooms)


# ------------------------------------------------------------------------------
# One control step


def _avoidance(px, py, wx, wy, reach, dt: float, weight=AVOID_WEIGHT):
    """[...] the avoidance cost of discs at relative position (px, py) [...] (from the walker to
    the other) closing at relative velocity (wx, wy) [...] (the walker's minus the other's) whose
    centres touch at `reach` [...]: `weight` [...] times the penalty of the time until they come
    within reach + SOCIAL_GAP (RVO's), plus BLOCKED where they touch within `dt` s. Components,
    not [..., 2] arrays: XLA on the CPU runs these [C, K, C] arrays about 4x faster so."""
    a = wx * wx + wy * wy
    b = px * wx + py * wy  # > 0: closing
    near = px * px + py * py  # squared distance now
    c = near - (reach + SOCIAL_GAP) ** 2
    disc = b * b - a * c
    t = (b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(a, 1e-12)  # time to collision, s
    t = jnp.where(
        c <= 0, jnp.where(b > 0, 0.0, jnp.inf), jnp.where((b > 0) & (disc > 0), t, jnp.inf)
    )
    penalty = weight * jnp.maximum(1.0 / jnp.maximum(t, MIN_TIME) - 1.0 / HORIZON, 0.0)
    closest = jnp.clip(b / jnp.maximum(a, 1e-12), 0.0, dt)  # s into the step of the least gap
    touch = (b > 0) & (near - 2 * b * closest + a * closest**2 < reach**2)
    return penalty + BLOCKED * touch


def _candidates(desired):
    """([C, K], [C, K]) x and y of velocities around `desired` [C, 2]: turned by ANGLES, scaled
    by SCALES, and 0."""
    a = jnp.deg2rad(jnp.array(ANGLES))  # [A]
    g = jnp.array(SCALES)[:, None]  # [G, 1]
    c, s = (g * jnp.cos(a)).reshape(-1), (g * jnp.sin(a)).reshape(-1)  # [G * A]
    c, s = jnp.append(c, 0.0), jnp.append(s, 0.0)  # [K]: and standing
    x, y = desired[:, None, 0], desired[:, None, 1]  # [C, 1]
    return c * x - s * y, s * x + c * y


def _heading(w: Walkers, pos, walking, dt: float):
    """([C, 2] goal, [C, 2] back, [C, 2] preferred velocity): arrived walkers turn to their next
    goal; the preferred velocity reaches the goal within the step where it is that near."""
    arrived = walking & (jnp.linalg.norm(w.goal - pos, axis=-1) < ARRIVE)
    goal = jnp.where(arrived[:, None], w.back, w.goal)
    back = jnp.where(arrived[:, None], w.goal, w.back)
    delta = goal - pos
    dist = jnp.linalg.norm(delta, axis=-1)  # [C]
    speed = jnp.minimum(w.speed, dist / dt)
    return goal, back, delta / jnp.maximum(dist, 1e-9)[:, None] * speed[:, None]


def _still_ahead(still, pos, cx, cy):
    """[C, K] the clearance from walls and still obstacles (`still`: the room without the
    walkers) of each walker at `pos` [C, 2] after LOOKAHEAD s at velocity (cx, cy) [C, K],
    linearised at its position (a planar face is exact), and [C] the clearance now."""
    steps = jnp.array([[0.0, 0.0], [_DX, 0.0], [0.0, _DX]])
    d = signed_distance(still, pos[None] + steps[:, None])  # [3, C]
    gx, gy = (d[1] - d[0]) / _DX, (d[2] - d[0]) / _DX  # [C]
    return d[0][:, None] + LOOKAHEAD * (cx * gx[:, None] + cy * gy[:, None]), d[0]


def _people(w: Walkers, pos, radius, walking, bold, cx, cy, dt: float):
    """[C, K] the cost of each walker's candidates (cx, cy) [C, K] among the other people, each
    taking half of the avoiding (reciprocal: the relative velocity of a candidate v is
    2 v - v_i - v_j, last velocities); a `bold` [C] walker heeds touching only."""
    vel = w.velocity  # [C, 2]
    px, py = (pos[None, :, k] - pos[:, None, k] for k in (0, 1))  # [C, C] from i to j
    wx, wy = (
        (2 * c - vel[:, None, k])[:, :, None] - vel[None, None, :, k] for k, c in ((0, cx), (1, cy))
    )  # [C, K, C]: walker i, candidate, j
    reach = radius[:, None] + radius[None, :]  # [C, C]
    weight = jnp.where(bold, 0.0, AVOID_WEIGHT)[:, None, None]  # [C, 1, 1]
    people = _avoidance(px[:, None], py[:, None], wx, wy, reach[:, None], dt, weight)
    others = walking[None, :] & ~jnp.eye(pos.shape[0], dtype=bool)  # [C, C]
    return jnp.where(others[:, None], people, 0.0).max(-1)


def _waited(waited, bold, stood, dt: float):
    """[C] `Walkers.waited` after a step from `waited` [C] (`bold` [C]: at least PATIENCE) in
    which the walkers `stood` [C] short of their goals for the other people: it counts up while
    they stand, on through BOLD, then starts over."""
    waited = jnp.where(bold | stood, waited + dt, 0.0)
    return jnp.where(waited >= PATIENCE + BOLD - 1e-6, 0.0, waited)


def _apart(pos, new, radius, walking):
    """[C] bool: the walkers whose step from `pos` to `new` [C, 2] comes within touch ([C]
    `radius`; closer than they were, so people who touch may still part) of where another
    walker stands, or of where one in an earlier slot goes. Those stand instead. Whoever still
    moves keeps clear of where everyone stands and of where the earlier ones go, and a later
    one that stands instead stays where it stood: no one steps into another, and of two whose
    steps clash one still moves (both standing, they would choose the same steps again)."""
    reach = radius[:, None] + radius[None, :]  # [C, C]
    now = jnp.linalg.norm(pos[:, None] - pos[None], axis=-1)  # [C, C]
    earlier = jnp.tri(pos.shape[0], k=-1, dtype=bool)  # [C, C]: slot j before slot i
    near = jnp.zeros(pos.shape[0], bool)
    for there, heed in ((pos, walking[None, :]), (new, walking[None, :] & earlier)):
        gap = jnp.linalg.norm(new[:, None] - there[None], axis=-1)  # [C, C]
        near |= ((gap < reach) & (gap < now) & heed).any(-1)
    return near


def _walking(room):
    """[C] bool: the cylinder slots of `room` (SceneParams) in which someone walks."""
    return (room.motion.walkers.speed > 0) & room.cyl_active


def walk(room, dt: float, robot=None):
    """`room` (SceneParams whose `motion.walkers` is set) after the walkers' step of `dt` s.
    `robot`: (xy [2], velocity [2], radius) of the robot the reactive walkers give way to
    (None: no robot)."""
    w = room.motion.walkers
    pos, radius = room.cyl_pos, room.cyl_radius  # [C, 2], [C]
    walking = _walking(room)
    goal, back, desired = _heading(w, pos, walking, dt)
    bold = w.waited >= PATIENCE  # [C]
    cx, cy = _candidates(desired)  # [C, K], the last one standing
    cost = jnp.hypot(cx - desired[:, :1], cy - desired[:, 1:])  # [C, K]
    cost += _people(w, pos, radius, walking, bold, cx, cy, dt)
    # Walls and still obstacles: no candidate that comes too near them, unless it moves away.
    still = room.replace(cyl_active=room.cyl_active & ~walking)
    ahead, now = _still_ahead(still, pos, cx, cy)  # [C, K], [C]
    cost += jnp.where((ahead < (radius + STATIC_GAP)[:, None]) & (ahead < now[:, None]), BLOCKED, 0)
    wants = jnp.linalg.norm(desired, axis=-1)  # [C] m/s
    cost = cost.at[:, -1].add(jnp.where(bold, wants, 0.0))  # bold: not standing
    stood = walking & (jnp.argmin(cost, -1) == cost.shape[1] - 1) & (wants > 0)  # for people
    if robot is not None:  # the reactive walkers give way to the robot too: [C, K]
        xy, velocity, r = robot
        rx, ry = (xy[k] - pos[:, k : k + 1] for k in (0, 1))  # [C, 1] from walker to robot
        them = _avoidance(rx, ry, cx - velocity[0], cy - velocity[1], radius[:, None] + r, dt)
        cost += jnp.where(w.reactive[:, None], them, 0.0)
    best = jnp.argmin(cost, -1)  # [C]
    pick = lambda x: jnp.take_along_axis(x, best[:, None], 1)[:, 0]  # noqa: E731
    velocity = jnp.where(walking[:, None], jnp.stack([pick(cx), pick(cy)], -1), 0.0)
    limit = jnp.maximum(room.room_half - radius[:, None], 0.0)  # [C, 2]
    new = jnp.where(walking[:, None], jnp.clip(pos + velocity * dt, -limit, limit), pos)
    stop = walking & _apart(pos, new, radius, walking)  # [C]
    velocity = jnp.where(stop[:, None], 0.0, velocity)
    new = jnp.where(stop[:, None], pos, new)
    waited = _waited(w.waited, bold, stood | (stop & (wants > 0)), dt)
    walkers = w.replace(goal=goal, back=back, velocity=velocity, waited=waited)
    return room.replace(cyl_pos=new, motion=room.motion.replace(walkers=walkers))


def hit_by_walker(room, xy, velocity, radius: float, z=None):
    """[] bool: a robot at `xy` [2] moving at `velocity` [2] (below STOPPED_SPEED: it stands)
    with a collision disc of `radius` touches a non-reactive walker that is walking towards it,
    and nothing else (`z`: the robot's vertical span, as `signed_distance` takes it)."""
    w = room.motion.walkers
    walking = _walking(room)  # [C]
    gap = jnp.linalg.norm(room.cyl_pos - xy, axis=-1) - room.cyl_radius  # [C]
    towards = jnp.sum(w.velocity * (xy - room.cyl_pos), -1) > 0
    by = walking & ~w.reactive & towards & (gap < radius + TOUCH)
    still = room.replace(cyl_active=room.cyl_active & ~walking)
    clear = signed_distance(still, xy, z) >= radius
    return by.any() & clear & (jnp.linalg.norm(velocity) < STOPPED_SPEED)


# ------------------------------------------------------------------------------
# The sampler's walkers


def _crossings(d: Draws, half, r):
    """[TRIES, 2] starts and [TRIES, 2] goals of crossings of a room of interior `half` [2] by a
    walker of radius `r`: the axis uniform (x or y), the direction uniform, the start within the
    outer 40 % of one side and the goal within that of the other, across uniform."""
    limit = jnp.maximum(half - r - FREE_GAP, 0.0)  # [2]
    along = d.uniform((2, TRIES), 0.6, 1.0)
    along = along * jnp.where(d.bernoulli(0.5, (TRIES,)), 1.0, -1.0)
    across = d.uniform((2, TRIES), -1.0, 1.0)
    on_x = d.bernoulli(0.5, (TRIES,))  # the crossing runs along x
    start = jnp.where(
        on_x[:, None], jnp.stack([-along[0], across[0]], -1), jnp.stack([across[0], -along[0]], -1)
    )
    goal = jnp.where(
        on_x[:, None], jnp.stack([along[1], across[1]], -1), jnp.stack([across[1], along[1]], -1)
    )
    return start * limit, goal * limit


def _aimed(d: Draws, half, r, spawn, goal):
    """[TRIES, 2] starts and [TRIES, 2] goals of CrowdNav's circle crossing around the robot's
    way: on the circle through `spawn` [3] (x, y, yaw) and `goal` [2] whose diameter is the
    straight line between them or, where `goal` is None, the circle of radius AIM_AHEAD m centred
    that far ahead of the spawn along its heading; the start at a uniform angle on it plus
    uniform noise of up to AIM_NOISE m per axis, the goal opposite it across the centre. And
    [TRIES] bool: both ends lie inside the room of interior `half` [2] for a walker of radius
    `r`."""
    if goal is None:
        reach = d.uniform((TRIES, 1), *AIM_AHEAD)
        centre = spawn[:2] + reach * jnp.stack([jnp.cos(spawn[2]), jnp.sin(spawn[2])])
    else:
        centre, reach = (spawn[:2] + goal) / 2, jnp.linalg.norm(goal - spawn[:2]) / 2
    angle = d.uniform((TRIES,), -jnp.pi, jnp.pi)
    offset = reach * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)  # [TRIES, 2]
    offset += d.uniform((TRIES, 2), -AIM_NOISE, AIM_NOISE)
    start, end = centre + offset, centre - offset
    limit = half - r - FREE_GAP
    inside = (jnp.abs(start) <= limit).all(-1) & (jnp.abs(end) <= limit).all(-1)
    return start, end, inside


def _clear_of_ends(points, r, room):
    """[N] bool: points [N, 2] where a walker of radius `r` keeps FREE_GAP from where each walker
    of `room` (SceneParams) turns or stays (its goal and its next goal): as CrowdNav's people, no
    one's goal is where another stands for good, nor another's turning point."""
    w = room.motion.walkers
    ends = jnp.concatenate([w.goal, w.back])  # [2C, 2]
    reach = r + jnp.tile(room.cyl_radius, 2) + FREE_GAP  # [2C]
    walking = jnp.tile(_walking(room), 2)  # [2C]
    near = jnp.linalg.norm(points[:, None] - ends[None], axis=-1) < reach  # [N, 2C]
    return ~(near & walking).any(-1)


def add_walkers(key, room, cfg: WalkerConfig, first: int, robot_radius: float, goal=None):
    """`room` (SceneParams with `motion.walkers`) with up to `cfg.slots` walkers in cylinder slots
    `first`... : count uniform in cfg.count (cfg.crowd_count in a `crowd` room), radius, speed and
    height uniform in their ranges, reactive with probability cfg.reactive, aimed across the
    robot's way with probability cfg.aimed. Each takes the first of `TRIES` crossings of the room
    (`_crossings`; an aimed walker first tries `TRIES` of `_aimed`) whose start keeps FREE_GAP
    from everything placed so far and `cfg.clearance` from the robot's edge at the spawn, off the
    robot's disc at `goal` [2] (if given), and whose straight line keeps FREE_GAP from the walls
    and the still obstacles; a walker with no such crossing is left out."""
    m = cfg.slots
    d = Draws(key)
    crowd = room.layout_id == CROWD_ROOM
    lo = jnp.where(crowd, cfg.crowd_count[0], cfg.count[0])
    hi = jnp.where(crowd, cfg.crowd_count[1], cfg.count[1])
    count = d.randint((), lo, hi + 1)
    radius, speed, height = (d.uniform((m,), *b) for b in (cfg.radius, cfg.speed, cfg.height))
    reactive = d.bernoulli(cfg.reactive, (m,))
    aimed = d.bernoulli(cfg.aimed, (m,)) if cfg.aimed else None
    still, spawn = room, room.spawn[:2]
    along = jnp.linspace(0.0, 1.0, SEGMENT_POINTS)[:, None, None]  # [P, 1, 1]
    for j in range(m):
        slot, r = first + j, radius[j]
        start, end = _crossings(d, room.room_half, r)  # [N, 2] each, N = TRIES
        ok = True
        if aimed is not None:  # the aimed crossings first, where they fit: N = 2 TRIES
            at, to, inside = _aimed(d, room.room_half, r, room.spawn, goal)
            start, end = jnp.concatenate([at, start]), jnp.concatenate([to, end])
            ok = jnp.concatenate([inside & aimed[j], jnp.ones(TRIES, bool)])
        ok &= signed_distance(room, start) > r + FREE_GAP
        line = signed_distance(still, start + along * (end - start))  # [P, N]
        ok &= (line > r + FREE_GAP).all(0)
        ok &= jnp.linalg.norm(start - spawn, axis=-1) > robot_radius + cfg.clearance + r
        if goal is not None:
            ok &= jnp.linalg.norm(start - goal, axis=-1) > robot_radius + r
        ok &= _clear_of_ends(start, r, room) & _clear_of_ends(end, r, room)  # the walkers so far
        on = ok.any() & (j < count)
        pick = jnp.argmax(ok)
        put = lambda x, v, on=on, slot=slot: x.at[slot].set(jnp.where(on, v, x[slot]))  # noqa: E731
        stays = False if aimed is None else aimed[j] & (pick < TRIES)  # as CrowdNav's people
        w = room.motion.walkers
        w = w.replace(
            goal=put(w.goal, end[pick]),
            back=put(w.back, jnp.where(stays, end[pick], start[pick])),
            speed=put(w.speed, speed[j]),
            reactive=put(w.reactive, reactive[j]),
        )
        room = room.replace(
            cyl_pos=put(room.cyl_pos, start[pick]),
            cyl_radius=put(room.cyl_radius, r),
            cyl_height=put(room.cyl_height, height[j]),
            cyl_bottom=put(room.cyl_bottom, 0.0),
            cyl_active=put(room.cyl_active, True),
            motion=room.motion.replace(walkers=w),
        )
    return room
