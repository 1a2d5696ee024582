"""The room layout data model: rooms, obstacles and their motions, the bounds they obey and the
geometry that checks them (clearance, a free spawn). The JSON format and its files are
`jaxnav.io.layouts`, which reads and writes these types.

The dataclasses check themselves on construction, so a `RoomLayout` built in code obeys the same
rules as one read from a file: sizes within bounds, obstacles inside the room, a spawn where the
robot fits. Every mistake raises `LayoutError`, whose one-line message names the file (where
there is one), the room and the field in JSON path style (`obstacles[2].size`). The bounds are
listed in `jaxnav.io.layouts`' docstring.
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import numbers
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from jaxnav.core import geometry
from jaxnav.core.robot import TURTLEBOT2I

ROBOT_RADIUS = TURTLEBOT2I.radius  # m; spawns in layout files must fit the default robot
ROOM_SIZE = (0.5, 100.0)  # m, smallest and largest side of a room's interior
MAX_HEIGHT = 10.0  # m, tallest wall or obstacle
MIN_OBSTACLE = 0.01  # m, thinnest box side or cylinder radius
MAX_WAYPOINTS = 8  # waypoints of a path motion (after the obstacle's own `pos`)
MAX_OBSTACLE_SPEED = 1.0  # m/s: 0.1 m per control step, so a moving obstacle cannot skip the robot
MAX_WALKER_SPEED = 1.5  # m/s of a walker (a cylinder walking to a goal): people walk at ~1.3 m/s
SPAWN_GRID = 0.05  # m between points of the free-spawn search (sides over 20 m: 400 steps a side)
# Every room of a batch simulates as many obstacle slots as its fullest one, every step.
MAX_OBSTACLES = 256  # per room; shipped rooms hold at most 18, sampled ones 20 (+16 movers)
MAX_ROOMS = 1024  # in a file, and in all the files of one batch (the benchmark suite has 32)
MAX_GRID = 64  # cells per side of a grid obstacle (every room of a batch casts rays on as many)

# m; a spawn the search finds clears by this much more, so that float32 round-off (a few ulp of
# 50 m coordinates) in its own evaluation cannot make it touch as `is_free` evaluates it.
_SPAWN_MARGIN = 1e-4
_TOL = (
    1e-9  # m; obstacles may touch a wall exactly, float round-off must not turn that into an error
)
_WALLS = ("east", "west", "north", "south")  # order of the columns of `_wall_distances`


class LayoutError(ValueError):
    """A bad layout; the one-line message names the file, the room and the field."""

    def __init__(
        self,
        field: str | None,
        detail: str,
        *,
        source: str | None = None,
        room: str | None = None,
        index: int | None = None,
    ):
        self.field = field  # JSON path of the bad value, e.g. "obstacles[2].size"; None: the file
        self.detail = detail  # what is wrong with it
        self.source = source  # file name (or "<layout>" for objects built in code)
        self.room = room  # room name; None for unnamed rooms, which are named by index only
        self.index = index  # position of the room in the file
        super().__init__(self._message())

    def _message(self) -> str:
        parts = [self.source] if self.source else []
        if self.room is not None and self.index is not None:
            parts.append(f"room {self.room!r} (#{self.index})")
        elif self.room is not None:
            parts.append(f"room {self.room!r}")
        elif self.index is not None:
            parts.append(f"room #{self.index}")
        if self.field:
            parts.append(self.field)
        return ": ".join([*parts, self.detail])

    def located(
        self, *, source: str | None, room: str | None, index: int | None = None
    ) -> LayoutError:
        """The same error, placed in a file and a room."""
        return LayoutError(self.field, self.detail, source=source, room=room, index=index)

    def under(self, prefix: str) -> LayoutError:
        """The same error with its field nested under `prefix` (e.g. "obstacles[2]")."""
        field = f"{prefix}.{self.field}" if self.field else prefix
        return LayoutError(field, self.detail, source=self.source, room=self.room, index=self.index)


# ------------------------------------------------------------------------------
# Value checks shared by the dataclasses and the parser


def _show(value, limit: int = 60) -> str:
    """A short one-line rendering of a (JSON) value for error messages."""
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _kind(value) -> str:
    """The JSON type of a value, with an article: 'a string', 'an object'."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, numbers.Real):
        return "a number"
    kinds = {
        str: "a string",
        dict: "an object",
        list: "a list",
        tuple: "a list",
        type(None): "null",
    }
    return next((k for t, k in kinds.items() if isinstance(value, t)), type(value).__name__)


def _is_number(value) -> bool:
    # JSON booleans are Python ints: `true` must not pass as 1.
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _finite(value) -> float | None:
    """`value` as a float, or None if it is not finite (an integer of 400 digits included)."""
    try:
        out = float(value)
    except OverflowError:
        return None
    return out if math.isfinite(out) else None


def _number(value, field: str, *, positive: bool = False, bounds=None) -> float:
    """`value` as a finite float (positive, within [lo, hi] `bounds` if asked), or a LayoutError
    naming `field`."""
    what = "a positive number" if positive else "a number"
    if not _is_number(value):
        raise LayoutError(field, f"must be {what}, got {_show(value)}")
    out = _finite(value)
    if out is None:
        raise LayoutError(field, f"must be a finite number, got {_show(value)}")
    if positive and out <= 0:
        raise LayoutError(field, f"must be {what}, got {_show(value)}")
    if bounds is not None and not bounds[0] <= out <= bounds[1]:
        raise LayoutError(field, f"must be {bounds[0]:g} to {bounds[1]:g} m, got {_show(value)}")
    return out


def _pair(value, field: str, *, positive: bool = False, bounds=None) -> tuple[float, float]:
    """`value` as two finite floats (positive, within [lo, hi] `bounds` if asked), or a
    LayoutError naming `field`."""
    what = "two positive numbers" if positive else "two numbers [x, y]"
    ok = isinstance(value, (list, tuple, np.ndarray)) and len(value) == 2
    if not ok or not all(_is_number(v) for v in value):
        raise LayoutError(field, f"must be {what}, got {_show(value)}")
    out = [_finite(v) for v in value]
    if None in out:
        raise LayoutError(field, f"must be two finite numbers, got {_show(value)}")
    if positive and min(out) <= 0:
        raise LayoutError(field, f"must be {what}, got {_show(value)}")
    if bounds is not None and not (bounds[0] <= min(out) and max(out) <= bounds[1]):
        raise LayoutError(
            field, f"each must be {bounds[0]:g} to {bounds[1]:g} m, got {_show(value)}"
        )
    return out[0], out[1]


def _height(value, field: str) -> float:
    """A positive height of at most MAX_HEIGHT, m."""
    out = _number(value, field, positive=True)
    if out > MAX_HEIGHT:
        raise LayoutError(field, f"must be at most {MAX_HEIGHT:g} m, got {_show(value)}")
    return out


def _angle(value, field: str) -> float:
    """A finite angle, rad, reduced modulo 2 pi to [-pi, pi] (as float32 would see it)."""
    return math.remainder(_number(value, field), 2 * math.pi)


# ------------------------------------------------------------------------------
# The dataclasses


_MOTION_KEYS = ("velocity", "path", "speed", "goal", "reactive", "repeat")


def _speed(value, field: str, what: str = "must be", top: float = MAX_OBSTACLE_SPEED) -> float:
    """A speed above 0 and at most `top` (MAX_OBSTACLE_SPEED), m/s."""
    out = _number(value, field)
    if not 0 < out <= top:
        detail = f"{what} > 0 and <= {top:g} m/s, got {out:.4g}"
        raise LayoutError(field, detail)
    return out


def _flag(value, field: str) -> bool:
    """A JSON boolean."""
    if not isinstance(value, bool):
        raise LayoutError(field, f"must be true or false, got {_show(value)}")
    return value


@dataclass(frozen=True)
class Motion:
    """How an obstacle moves: `velocity` (it bounces off the walls and the other obstacles), back
    and forth along `path` at `speed` (its own `pos`, then the waypoints, and back), or, a
    cylinder only, walking to `goal` at `speed` as a person (`jaxnav.core.crowd`)."""

    velocity: tuple[float, float] | None = None  # [vx, vy] m/s at the start
    path: tuple[tuple[float, float], ...] | None = None  # 1 to MAX_WAYPOINTS waypoints [x, y], m
    speed: float | None = None  # m/s along the path, or a walker's preferred speed
    goal: tuple[float, float] | None = None  # [x, y] m a walker walks to
    reactive: bool = True  # a walker gives way to the robot (else only to the other people)
    repeat: bool = True  # a walker walks back to its `pos` on arrival, and so on (else it stays)

    def __post_init__(self):
        if sum(x is not None for x in (self.velocity, self.path, self.goal)) != 1:
            raise LayoutError(
                None, 'must have either "velocity", "path" (with "speed") or "goal" (with "speed")'
            )
        if self.goal is None and (self.reactive is not True or self.repeat is not True):
            raise LayoutError(
                "reactive" if self.reactive is not True else "repeat", 'only with "goal"'
            )
        if self.goal is not None:
            object.__setattr__(self, "goal", _pair(self.goal, "goal"))
            if self.speed is None:
                raise LayoutError("speed", "missing required field (a walker's speed, m/s)")
            object.__setattr__(self, "speed", _speed(self.speed, "speed", top=MAX_WALKER_SPEED))
            object.__setattr__(self, "reactive", _flag(self.reactive, "reactive"))
            object.__setattr__(self, "repeat", _flag(self.repeat, "repeat"))
            return
        if self.velocity is not None:
            vx, vy = _pair(self.velocity, "velocity")
            _speed(math.hypot(vx, vy), "velocity", "its speed (length) must be")
            if self.speed is not None:
                raise LayoutError("speed", 'only with "path" (a velocity carries its speed)')
            object.__setattr__(self, "velocity", (vx, vy))
            return
        path = self.path
        if not isinstance(path, (list, tuple)) or not 1 <= len(path) <= MAX_WAYPOINTS:
            raise LayoutError(
                "path",
                f"must be a list of 1 to {MAX_WAYPOINTS} waypoints [x, y], got {_show(path)}",
            )
        object.__setattr__(self, "path", tuple(_pair(p, f"path[{i}]") for i, p in enumerate(path)))
        if self.speed is None:
            raise LayoutError("speed", 'missing required field (m/s along the "path")')
        object.__setattr__(self, "speed", _speed(self.speed, "speed"))

    @classmethod
    def parse(cls, value) -> Motion | None:
        """A `Motion` from itself, None or its JSON object (keys checked)."""
        if value is None or isinstance(value, Motion):
            return value
        if not isinstance(value, dict):
            raise LayoutError(
                None,
                f'must be an object with "velocity", "path" and "speed" or "goal" and "speed", '
                f"got {_kind(value)}",
            )
        _check_keys(value, _MOTION_KEYS, "")
        return cls(**value)

    def to_dict(self) -> dict:
        """The JSON object of this motion."""
        if self.velocity is not None:
            return {"velocity": list(self.velocity)}
        if self.goal is not None:
            walk = {"goal": list(self.goal), "speed": self.speed}
            return walk | {"reactive": self.reactive, "repeat": self.repeat}
        return {"path": [list(p) for p in self.path], "speed": self.speed}


def _set_motion(ob) -> None:
    """Checks and stores the obstacle's `motion` (None: it stands still)."""
    try:
        object.__setattr__(ob, "motion", Motion.parse(ob.motion))
    except LayoutError as err:
        raise err.under("motion") from None


def _set_span(ob) -> None:
    """Checks and stores the obstacle's vertical span [bottom, height]."""
    object.__setattr__(ob, "height", _height(ob.height, "height"))
    object.__setattr__(ob, "bottom", _number(ob.bottom, "bottom"))
    if not 0 <= ob.bottom < ob.height:
        raise LayoutError("bottom", f"must be in [0, height = {ob.height:g}) m, got {ob.bottom:g}")


@dataclass(frozen=True)
class Box:
    """A box standing on the floor, possibly rotated about the vertical axis."""

    kind: ClassVar[str] = "box"  # the obstacle's "type" in JSON

    pos: tuple[float, float]  # centre [x, y], m
    size: tuple[float, float]  # full extents along the box's own x and y, m
    yaw: float = 0.0  # rad, counter-clockwise from the room's x axis
    height: float = 0.5  # m, of its top above the floor
    bottom: float = 0.0  # m, of its underside above the floor (tables, shelves); below `height`
    motion: Motion | None = None  # None: it stands still

    def __post_init__(self):
        object.__setattr__(self, "pos", _pair(self.pos, "pos"))
        size = _pair(self.size, "size", positive=True, bounds=(MIN_OBSTACLE, ROOM_SIZE[1]))
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "yaw", _angle(self.yaw, "yaw"))
        _set_span(self)
        _set_motion(self)
        if self.motion is not None and self.motion.goal is not None:
            raise LayoutError("motion.goal", "only a cylinder walks to a goal (a person)")


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder standing on the floor."""

    kind: ClassVar[str] = "cylinder"  # the obstacle's "type" in JSON

    pos: tuple[float, float]  # centre [x, y], m
    radius: float  # m
    height: float = 0.5  # m, of its top above the floor
    bottom: float = 0.0  # m, of its underside above the floor; below `height`
    motion: Motion | None = None  # None: it stands still

    def __post_init__(self):
        object.__setattr__(self, "pos", _pair(self.pos, "pos"))
        radius = _number(self.radius, "radius", positive=True, bounds=(MIN_OBSTACLE, ROOM_SIZE[1]))
        object.__setattr__(self, "radius", radius)
        _set_span(self)
        _set_motion(self)


@dataclass(frozen=True)
class Grid:
    """Square cells standing on the floor, on an axis-aligned occupancy grid (`jaxnav.core.grid`):
    dense clutter that costs the simulator one grid pass, not one obstacle slot per cell."""

    kind: ClassVar[str] = "grid"  # the obstacle's "type" in JSON
    bottom: ClassVar[float] = 0.0  # every cell stands on the floor
    motion: ClassVar[None] = None  # a grid stands still

    origin: tuple[float, float]  # [x, y] of the grid's south-west corner, m
    cell: float  # m, the side of a cell
    rows: tuple[str, ...]  # north to south, each west to east: "#" occupied, "." free
    height: float = 0.5  # m, of the cells' top above the floor

    def __post_init__(self):
        object.__setattr__(self, "origin", _pair(self.origin, "origin"))
        cell = _number(self.cell, "cell", positive=True, bounds=(MIN_OBSTACLE, ROOM_SIZE[1]))
        object.__setattr__(self, "cell", cell)
        object.__setattr__(self, "height", _height(self.height, "height"))
        rows = self.rows
        ok = isinstance(rows, (list, tuple)) and 1 <= len(rows) <= MAX_GRID
        if not ok or not all(isinstance(r, str) for r in rows):
            detail = f'must be a list of 1 to {MAX_GRID} strings of "#" and ".", got {_show(rows)}'
            raise LayoutError("rows", detail)
        for i, row in enumerate(rows):
            if len(row) != len(rows[0]) or not 1 <= len(row) <= MAX_GRID or set(row) - {"#", "."}:
                detail = (
                    f'must be {len(rows[0])} characters "#" or "." (1 to {MAX_GRID}, as '
                    f"rows[0]), got {_show(row)}"
                )
                raise LayoutError(f"rows[{i}]", detail)
        object.__setattr__(self, "rows", tuple(rows))

    @property
    def pos(self) -> tuple[float, float]:
        """The south-west corner (where `_check_inside` measures from)."""
        return self.origin

    def cell_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """([N, 2] centres, [N, 2] full sizes), m, of the occupied cells."""
        occupied = np.array([[ch == "#" for ch in row] for row in self.rows[::-1]], bool)
        rows, cols = np.nonzero(occupied.reshape(len(self.rows), -1))
        centres = np.asarray(self.origin) + (np.stack([cols, rows], -1) + 0.5) * self.cell
        return centres.reshape(-1, 2), np.full((len(rows), 2), self.cell)


Obstacle = Box | Cylinder | Grid
_OBSTACLE_TYPES = {cls.kind: cls for cls in (Box, Cylinder, Grid)}


def _check_count(obstacles: Sequence) -> None:
    """At most MAX_OBSTACLES obstacles (checked before any of them is looked at)."""
    if len(obstacles) > MAX_OBSTACLES:
        raise LayoutError(
            "obstacles",
            f"{len(obstacles)} obstacles: at most {MAX_OBSTACLES} per room (every room of a batch "
            "simulates as many obstacle slots as the fullest one)",
        )


@dataclass(frozen=True)
class RoomLayout:
    """One room: interior size, optional fixed spawn pose, static obstacles; checked on creation."""

    name: str  # unique in a set of rooms; "<file stem>-<index>" when the JSON gives none
    size: tuple[float, float]  # interior extents [x, y], m, centred on the origin
    wall_height: float = 0.5  # m
    robot_pos: tuple[float, float] | None = None  # None -> spawn sampled in free space each episode
    robot_yaw: float = 0.0  # rad; only meaningful with robot_pos
    obstacles: tuple[Obstacle, ...] = ()  # in file order; error messages index into it
    goal_pos: tuple[float, float] | None = None  # goal tasks' target; None -> sampled each episode

    def __post_init__(self):
        try:
            self._coerce()
            _check_inside(self)
            _check_spawn(self)
            _check_goal(self)
        except LayoutError as err:
            name = self.name if isinstance(self.name, str) else None
            raise err.located(source=None, room=name) from None

    def _coerce(self):
        if not isinstance(self.name, str) or not self.name:
            raise LayoutError("name", f"must be a non-empty string, got {_show(self.name)}")
        set_ = functools.partial(object.__setattr__, self)
        set_("size", _pair(self.size, "room.size", positive=True, bounds=ROOM_SIZE))
        set_("wall_height", _height(self.wall_height, "room.wall_height"))
        if self.robot_pos is not None:
            set_("robot_pos", _pair(self.robot_pos, "robot.pos"))
        set_("robot_yaw", _angle(self.robot_yaw, "robot.yaw"))
        if self.goal_pos is not None:
            set_("goal_pos", _pair(self.goal_pos, "goal.pos"))
        if self.robot_pos is None and self.robot_yaw != 0.0:
            raise LayoutError("robot.yaw", "a spawn yaw needs robot.pos (None: sampled spawn)")
        if not isinstance(self.obstacles, (list, tuple)):
            raise LayoutError("obstacles", f"must be a sequence, got {_kind(self.obstacles)}")
        _check_count(self.obstacles)
        for i, ob in enumerate(self.obstacles):
            if not isinstance(ob, (Box, Cylinder, Grid)):
                raise LayoutError(f"obstacles[{i}]", f"must be a Box, Cylinder or Grid, got {ob!r}")
        grids = [i for i, ob in enumerate(self.obstacles) if isinstance(ob, Grid)]
        if len(grids) > 1:
            raise LayoutError(f"obstacles[{grids[1]}]", "at most one grid per room")
        set_("obstacles", tuple(self.obstacles))

    @property
    def boxes(self) -> tuple[Box, ...]:
        """The box obstacles, in file order."""
        return tuple(ob for ob in self.obstacles if isinstance(ob, Box))

    @property
    def cylinders(self) -> tuple[Cylinder, ...]:
        """The cylinder obstacles, in file order."""
        return tuple(ob for ob in self.obstacles if isinstance(ob, Cylinder))

    @property
    def grid(self) -> Grid | None:
        """The room's grid obstacle, None if it has none."""
        return next((ob for ob in self.obstacles if isinstance(ob, Grid)), None)


# ------------------------------------------------------------------------------
# Geometry


def box_corners(box: Box) -> np.ndarray:
    """[4, 2] world (x, y) corners of a box, counter-clockwise from its own (-x, -y) corner."""
    half = 0.5 * np.asarray(box.size)
    local = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * half
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(box.pos)  # rows times R(yaw)^T


def _distances(layout: RoomLayout, p: np.ndarray) -> np.ndarray:
    """[..., 4 + N] signed distance (float32, as simulated) from points p [..., 2] to the east,
    west, north, south walls and then each obstacle in layout order; negative inside or beyond."""
    cols = [geometry.wall_distance(p, 0.5 * np.asarray(layout.size, np.float32), np)]
    for ob in layout.obstacles:
        pos = np.asarray([ob.pos], np.float32)
        if isinstance(ob, Grid):
            centres, sizes = (np.asarray(a, np.float32) for a in ob.cell_boxes())
            yaw = np.zeros(len(centres), np.float32)
            d = geometry.box_distance(p, centres, yaw, 0.5 * sizes, np)  # [..., N]
            cols.append(np.min(d, axis=-1, initial=np.inf)[..., None])
        elif isinstance(ob, Cylinder):
            cols.append(geometry.disc_distance(p, pos, np.float32(ob.radius), np))
        else:
            half = 0.5 * np.asarray([ob.size], np.float32)
            cols.append(geometry.box_distance(p, pos, np.float32(ob.yaw), half, np))
    return np.concatenate([np.asarray(c) for c in cols], axis=-1)


def _points(xy) -> np.ndarray:
    p = np.asarray(xy, dtype=float)
    if p.ndim == 0 or p.shape[-1] != 2:
        raise ValueError(f"xy must have shape [2] or [..., 2], got {p.shape}")
    return p


def clearance(layout: RoomLayout, xy) -> float | np.ndarray:
    """Distance from xy to the nearest obstacle surface or wall, m.

    Negative inside an obstacle or beyond a wall. `xy` is one point [2] (returns a float) or a batch
    [..., 2] (returns an array [...]).
    """
    out = _distances(layout, _points(xy)).min(axis=-1)
    return float(out) if out.ndim == 0 else out


def is_free(layout: RoomLayout, xy, radius: float) -> bool | np.ndarray:
    """Whether a disc of `radius` centred at xy touches no obstacle and no wall.

    Touching counts as not free. Batches like `clearance`: xy [..., 2] gives a bool array [...].
    """
    free = np.asarray(clearance(layout, xy)) > radius
    return bool(free) if free.ndim == 0 else free


def _footprint_bounds(ob: Obstacle) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper [x, y] corners of the obstacle's axis-aligned footprint bounding box."""
    if isinstance(ob, Cylinder):
        return np.asarray(ob.pos) - ob.radius, np.asarray(ob.pos) + ob.radius
    if isinstance(ob, Grid):  # its occupied cells' (free cells may lie beyond the walls)
        centres, sizes = ob.cell_boxes()
        if not len(centres):
            return np.asarray(ob.origin), np.asarray(ob.origin)
        return (centres - 0.5 * sizes).min(0), (centres + 0.5 * sizes).max(0)
    corners = box_corners(ob)
    return corners.min(axis=0), corners.max(axis=0)


def _check_inside(layout: RoomLayout) -> None:
    """Every obstacle's footprint (yawed box corners, cylinder disc) lies within the interior, at
    its `pos` and at every waypoint of its path."""
    half = 0.5 * np.asarray(layout.size)
    for i, ob in enumerate(layout.obstacles):
        lo, hi = _footprint_bounds(ob)
        path = ob.motion.path if ob.motion is not None and ob.motion.path else ()
        stops = [(f"obstacles[{i}]", ob.pos)]
        stops += [(f"obstacles[{i}].motion.path[{j}]", p) for j, p in enumerate(path)]
        if ob.motion is not None and ob.motion.goal is not None:
            stops.append((f"obstacles[{i}].motion.goal", ob.motion.goal))
        for field, at in stops:
            shift = np.asarray(at) - np.asarray(ob.pos)
            a, b = lo + shift, hi + shift
            beyond = np.array([b[0] - half[0], -half[0] - a[0], b[1] - half[1], -half[1] - a[1]])
            k = int(beyond.argmax())
            if beyond[k] > _TOL:
                raise LayoutError(
                    field,
                    f"{ob.kind} at {_show(list(at))} reaches {beyond[k]:.3f} m beyond the "
                    f"{_WALLS[k]} wall (interior x in [{-half[0]:g}, {half[0]:g}], "
                    f"y in [{-half[1]:g}, {half[1]:g}])",
                )


def _spawn_axis(half: float, side: float) -> np.ndarray:
    """Coordinates of the spawn search along one axis: from -half to half, at most SPAWN_GRID
    apart (side / 400 on sides over 20 m), and always 0, so a room one robot wide is searched
    along its centre line."""
    n = math.ceil(half / max(SPAWN_GRID, side / 400))
    return np.linspace(-half, half, 2 * n + 1)


def _near_distance(kind: str, p, pos, yaw, size):
    """[H, W] signed distance (float32) from points p [H, W, 2] to one box or cylinder of `kind`
    (a cylinder's `size` is [radius, radius])."""
    if kind == Cylinder.kind:
        return geometry.disc_distance(p, pos[None], size[0], np)[..., 0]
    return geometry.box_distance(p, pos[None], yaw[None], 0.5 * size[None], np)[..., 0]


def _window(lo: float, hi: float, axis: np.ndarray) -> slice | None:
    """The points of `axis` from lo to hi (None: none), widened to a power-of-two count so that
    few shapes of `_near_distance` compile."""
    a, b = (int(i) for i in np.searchsorted(axis, [lo, hi]))
    if a == b:
        return None
    n = min(1 << (b - a - 1).bit_length(), len(axis))
    a = min(a, len(axis) - n)
    return slice(a, a + n)


def _touched(layout: RoomLayout, grid: np.ndarray, radius: float) -> np.ndarray:
    """[H, W] bool: where a disc of `radius` at a point of `grid` [H, W, 2] touches an obstacle.
    Each obstacle is measured only near its footprint: thousands of small ones take a second."""
    touched = np.zeros(grid.shape[:2], bool)
    reach = radius + 1e-3  # beyond this from the footprint's box nothing touches (round-off too)
    for ob in expand_grids(layout.obstacles):
        lo, hi = _footprint_bounds(ob)
        rows = _window(lo[1] - reach, hi[1] + reach, grid[:, 0, 1])
        cols = _window(lo[0] - reach, hi[0] + reach, grid[0, :, 0])
        if rows is None or cols is None:
            continue
        size = (ob.radius, ob.radius) if isinstance(ob, Cylinder) else ob.size
        args = (np.float32(ob.pos), np.float32(getattr(ob, "yaw", 0.0)), np.float32(size))
        touched[rows, cols] |= (
            np.asarray(_near_distance(ob.kind, grid[rows, cols], *args)) <= radius
        )
    return touched


def expand_grids(obstacles):
    """The obstacles, each grid replaced by its occupied cells as standing boxes (in order)."""
    for ob in obstacles:
        if isinstance(ob, Grid):
            centres, sizes = ob.cell_boxes()
            boxes = zip(centres, sizes, strict=True)
            yield from (Box(pos=p, size=s, height=ob.height) for p, s in boxes)
        else:
            yield ob


def free_spawn(layout: RoomLayout, radius: float = ROBOT_RADIUS) -> tuple[float, float] | None:
    """A point where a disc of `radius` touches nothing (float32 clearance, as `is_free` sees
    it, with `_SPAWN_MARGIN` to spare), by a grid search over the interior centred on the room
    (`_spawn_axis`); None if there is none."""
    half = 0.5 * np.asarray(layout.size) - radius  # centres nearer a wall cannot be free
    if min(half) <= 0:
        return None
    xs, ys = (_spawn_axis(h, side) for h, side in zip(half, layout.size, strict=True))
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).astype(np.float32)  # [len(ys), len(xs), 2]
    walls = np.asarray(geometry.wall_distance(grid, 0.5 * np.asarray(layout.size, np.float32), np))
    clear = radius + _SPAWN_MARGIN
    free = (walls.min(axis=-1) > clear) & ~_touched(layout, grid, clear)
    if not free.any():
        return None
    row, col = np.argwhere(free)[0]
    return float(grid[row, col, 0]), float(grid[row, col, 1])


def _check_spawn(layout: RoomLayout) -> None:
    """The robot's disc at the spawn position touches no obstacle and no wall; without a spawn
    position, there is at least one place where it would not."""
    if layout.robot_pos is None:
        if free_spawn(layout) is None:
            raise LayoutError(
                None,
                f"no free spawn: nowhere in the {layout.size[0]:g} x {layout.size[1]:g} m room "
                f"does the robot (radius {ROBOT_RADIUS} m) clear every wall and obstacle; "
                "give robot.pos or make room",
            )
        return
    if is_free(layout, layout.robot_pos, ROBOT_RADIUS):
        return
    name, gap = _nearest(layout, layout.robot_pos)
    raise LayoutError(
        "robot.pos",
        f"the robot (radius {ROBOT_RADIUS} m) at {_show(list(layout.robot_pos))} overlaps "
        f"{name}: clearance {gap:.3f} m",
    )


def _nearest(layout: RoomLayout, pos) -> tuple[str, float]:
    """The wall or obstacle nearest `pos` [2] (as an error names it) and its clearance, m."""
    dist = _distances(layout, np.asarray(pos))
    names = [f"the {w} wall" for w in _WALLS]
    names += [f"obstacles[{i}] ({ob.kind})" for i, ob in enumerate(layout.obstacles)]
    k = int(dist.argmin())
    return names[k], float(dist[k])


def _check_goal(layout: RoomLayout) -> None:
    """A goal position leaves the robot's disc clear of every wall and obstacle."""
    if layout.goal_pos is None or is_free(layout, layout.goal_pos, ROBOT_RADIUS):
        return
    name, gap = _nearest(layout, layout.goal_pos)
    raise LayoutError(
        "goal.pos",
        f"the robot (radius {ROBOT_RADIUS} m) at the goal {_show(list(layout.goal_pos))} would "
        f"overlap {name}: clearance {gap:.3f} m",
    )


class _JsonObject(dict):
    """A JSON object that remembers which keys appeared more than once (json keeps the last)."""

    duplicates: tuple[str, ...] = ()

    @classmethod
    def from_pairs(cls, pairs: list[tuple[str, object]]) -> _JsonObject:
        obj = cls(pairs)
        obj.duplicates = tuple(k for k, n in Counter(k for k, _ in pairs).items() if n > 1)
        return obj


def _path(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_keys(obj: dict, allowed: Sequence[str], prefix: str) -> None:
    """Reject duplicate and unknown keys, suggesting the closest allowed one."""
    for key in getattr(obj, "duplicates", ()):
        raise LayoutError(_path(prefix, key), "key given more than once")
    for key in obj:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            valid = ", ".join(allowed)
            raise LayoutError(_path(prefix, key), f"unknown key{hint} (valid keys: {valid})")
