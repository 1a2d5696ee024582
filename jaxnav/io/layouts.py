"""Room layouts: the JSON format, its parser and validator, and the geometry used to check it.

A layout file holds one room object or a JSON list of them. Units are metres and radians; the room's
interior is centred on the origin, x to the east, y to the north, and walls are added around it::

    {
      "name": "office-a",
      "room": {"size": [6.0, 5.0], "wall_height": 0.5},
      "robot": {"pos": [0.0, 0.0], "yaw": 0.0},
      "obstacles": [
        {"type": "box", "pos": [1.2, 0.5], "size": [0.6, 0.4], "yaw": 0.3, "height": 0.5},
        {"type": "cylinder", "pos": [-1.0, 1.0], "radius": 0.15, "height": 0.8}
      ]
    }

`name`, `room.wall_height`, `robot`, `goal`, `obstacles` and each obstacle's `yaw`/`height` are
optional. A room without `name` is named `<file stem>-<index>` (`room-<index>` when parsed from
an object); names are unique across all the files read together (`load_layouts`). Without `robot` the spawn is sampled in free space every episode; with it, `robot.pos` is
required. `"goal": {"pos": [x, y]}` fixes the target of goal-reaching tasks (`jaxnav.tasks.goal`;
other tasks ignore it); without it a reachable goal is sampled every episode.
`box.size` is the full extent along the box's own axes. An obstacle may move (`motion`, see
`Motion`): `{"velocity": [vx, vy]}` bounces off the walls and the other obstacles, and
`{"path": [[x, y], ...], "speed": s}` goes back and forth from its `pos` through the waypoints;
a cylinder with `{"goal": [x, y], "speed": s}` (optional `"reactive"`, `"repeat"`, both true by
default) is a person walking to the goal (`jaxnav.core.crowd`).
A `{"type": "grid", "origin": [x, y], "cell": c, "rows": ["#..", ...], "height": h}` obstacle
is dense clutter on an occupancy grid (`Grid`; rows north to south, each west to east, "#"
occupied), at most one per room and `MAX_GRID` cells a side. Every mistake raises
`LayoutError`, whose one-line message names the file, the room and the field in JSON path style
(`obstacles[2].size`).

Bounds (what the float32 simulator handles exactly enough; anything else is refused):

- `room.size`: each side 0.5 m to 100 m (`ROOM_SIZE`); `wall_height` and obstacle `height` up to
  10 m (`MAX_HEIGHT`).
- Obstacles: each `size` side, `radius` and grid `cell` at least 0.01 m (`MIN_OBSTACLE`), the
  whole footprint inside the room (so positions are within it too; a grid's occupied cells); at
  most `MAX_OBSTACLES` per room.
- Rooms: at most `MAX_ROOMS` in a file, and in all the files read together (`load_layouts`).
- Angles (`yaw`) are any finite number, reduced modulo 2 pi to [-pi, pi] when read.
- A room with `robot` must have the robot's disc (`ROBOT_RADIUS`) clear of every wall and obstacle
  at `robot.pos`; a room without it must have some free spawn, found at load time by a grid search
  over the interior (`SPAWN_GRID`, centred on the room: its centre lines are searched), else it is
  refused: every episode would start in a collision.
- `motion`: a velocity or a speed above 0 and at most `MAX_OBSTACLE_SPEED` (a walker's:
  `MAX_WALKER_SPEED`); a path of 1 to `MAX_WAYPOINTS` waypoints, at each of which, and at a
  walker's goal, the footprint lies inside the room; only a cylinder walks.
- A `goal.pos` must have the robot's disc clear of every wall and obstacle too (a goal inside an
  obstacle could never be reached). That it is reachable from the spawn (not in a closed-off part)
  is checked where the goal task builds its rooms (`jaxnav.core.goals`), on the occupancy grid;
  that it lies beyond a goal task's success radius from a fixed spawn, by `check_goal_distance`.

Clearances are computed by `jaxnav.core.geometry` in float32, the simulator's precision. The file
must be a regular file of at most 16 MB.

The dataclasses check themselves on construction, so a `RoomLayout` built in code obeys the same
rules as one read from a file: sizes within bounds, obstacles inside the room, a spawn where the
robot fits.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from collections.abc import Sequence

from jaxnav.core.layout import (  # noqa: F401 (the model's names are this module's API too)
    _OBSTACLE_TYPES,
    MAX_GRID,
    MAX_HEIGHT,
    MAX_OBSTACLE_SPEED,
    MAX_OBSTACLES,
    MAX_ROOMS,
    MAX_WALKER_SPEED,
    MAX_WAYPOINTS,
    MIN_OBSTACLE,
    ROBOT_RADIUS,
    ROOM_SIZE,
    SPAWN_GRID,
    Box,
    Cylinder,
    Grid,
    LayoutError,
    Motion,
    Obstacle,
    RoomLayout,
    _check_count,
    _check_keys,
    _JsonObject,
    _kind,
    _path,
    _show,
    box_corners,
    clearance,
    free_spawn,
    is_free,
)
from jaxnav.io.files import FileProblem, parse_json, read_text, write_atomic

# ------------------------------------------------------------------------------
# Parsing

_TOP_KEYS = ("name", "room", "robot", "goal", "obstacles")
_ROOM_KEYS = ("size", "wall_height")
_ROBOT_KEYS = ("pos", "yaw")
_GOAL_KEYS = ("pos",)


def _require(obj: dict, key: str, prefix: str):
    if key not in obj:
        raise LayoutError(_path(prefix, key), "missing required field")
    return obj[key]


def _section(entry: dict, key: str, allowed: Sequence[str], hint: str) -> dict | None:
    """The sub-object entry[key] after checking its type and keys; None when absent."""
    if key not in entry:
        return None
    obj = entry[key]
    if not isinstance(obj, dict):
        raise LayoutError(key, f"must be an object {hint}, got {_kind(obj)}")
    _check_keys(obj, allowed, key)
    return obj


def _parse_obstacle(item, prefix: str) -> Obstacle:
    if not isinstance(item, dict):
        raise LayoutError(prefix, f"must be an obstacle object, got {_kind(item)}")
    kind = _require(item, "type", prefix)
    cls = _OBSTACLE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        valid = ", ".join(repr(k) for k in _OBSTACLE_TYPES)
        shown = repr(kind) if isinstance(kind, str) else _show(kind)
        raise LayoutError(f"{prefix}.type", f"unknown obstacle type {shown} (valid: {valid})")
    fields = dataclasses.fields(cls)
    _check_keys(item, ("type", *(f.name for f in fields)), prefix)
    for f in fields:
        if f.default is dataclasses.MISSING:
            _require(item, f.name, prefix)
    try:
        return cls(**{k: v for k, v in item.items() if k != "type"})
    except LayoutError as err:
        raise err.under(prefix) from None


def _parse_room(entry, index: int, unnamed: str) -> RoomLayout:
    """One room object -> RoomLayout (named `<unnamed>-<index>` if the object has no name); errors
    carry the field but not yet the file or room."""
    if not isinstance(entry, dict):
        raise LayoutError(None, f"must be a room object, got {_kind(entry)}")
    _check_keys(entry, _TOP_KEYS, "")
    room = _section(entry, "room", _ROOM_KEYS, 'with "size" (and "wall_height")')
    if room is None:
        raise LayoutError("room", 'missing required field (an object with "size")')
    robot = _section(entry, "robot", _ROBOT_KEYS, 'with "pos" (and "yaw"); omit it to sample')
    name = entry.get("name", f"{unnamed}-{index}")
    kwargs = {"name": name, "size": _require(room, "size", "room")}
    if "wall_height" in room:
        kwargs["wall_height"] = room["wall_height"]
    if robot is not None:
        kwargs["robot_pos"] = _require(robot, "pos", "robot")
        kwargs["robot_yaw"] = robot.get("yaw", 0.0)
    goal = _section(entry, "goal", _GOAL_KEYS, 'with "pos"; omit it to sample a goal')
    if goal is not None:
        kwargs["goal_pos"] = _require(goal, "pos", "goal")
    raw = entry.get("obstacles", [])
    if not isinstance(raw, list):
        raise LayoutError("obstacles", f"must be a list of obstacle objects, got {_kind(raw)}")
    _check_count(raw)
    obstacles = tuple(_parse_obstacle(item, f"obstacles[{i}]") for i, item in enumerate(raw))
    return RoomLayout(**kwargs, obstacles=obstacles)


def _check_unique_names(layouts: Sequence[RoomLayout], source: str) -> None:
    first: dict[str, int] = {}
    for i, layout in enumerate(layouts):
        if layout.name in first:
            detail = f"duplicate room name, also used by room #{first[layout.name]}"
            raise LayoutError("name", detail, source=source, room=layout.name, index=i)
        first[layout.name] = i


def _parse_rooms(obj, source: str, unnamed: str) -> list[tuple[RoomLayout, bool]]:
    """(layout, whether its object gave a name) for each room of parsed JSON `obj`."""
    rooms = [obj] if isinstance(obj, dict) else obj
    if not isinstance(rooms, list):
        detail = f"expected a room object or a list of rooms, got {_kind(obj)}"
        raise LayoutError(None, detail, source=source)
    if not rooms:
        raise LayoutError(None, "empty list: expected at least one room", source=source)
    if len(rooms) > MAX_ROOMS:
        detail = f"{len(rooms)} rooms: at most {MAX_ROOMS} (they run as one batch)"
        raise LayoutError(None, detail, source=source)
    out = []
    for i, entry in enumerate(rooms):
        name = entry.get("name") if isinstance(entry, dict) else None
        try:
            out.append((_parse_room(entry, i, unnamed), "name" in entry))
        except LayoutError as err:
            label = name if isinstance(name, str) and name else None
            raise err.located(source=source, room=label, index=i) from None
    return out


def parse_layouts(obj, source: str = "<layout>") -> list[RoomLayout]:
    """Parsed JSON (one room object or a list of them) -> validated layouts.

    `source` names the origin (usually the file) in error messages. Unnamed rooms are named
    `room-<index>`.
    """
    layouts = [layout for layout, _ in _parse_rooms(obj, source, "room")]
    _check_unique_names(layouts, source)
    return layouts


def _read_rooms(path, source: str) -> list[tuple[RoomLayout, bool]]:
    """`_parse_rooms` of a layout file; unnamed rooms are named `<file stem>-<index>`."""
    try:
        obj = parse_json(read_text(path), path, object_pairs_hook=_JsonObject.from_pairs)
    except FileProblem as err:
        raise LayoutError(None, err.detail, source=source) from None
    return _parse_rooms(obj, source, os.path.splitext(os.path.basename(source))[0] or "room")


def load_layouts(
    paths: Sequence[str | os.PathLike], *, success_radius: float | None = None
) -> list[RoomLayout]:
    """The rooms of layout files, in order, as one set (one batch of a run or an evaluation).

    Unnamed rooms are named `<file stem>-<index>` (with `-2`, `-3`... where that is taken). Two
    rooms given the same name, one file given twice, or more than MAX_ROOMS rooms in all raise a
    LayoutError naming the files. With `success_radius` (a goal task's, m), a fixed goal that
    near its fixed spawn is refused too (`check_goal_distance`).
    """
    rooms: list[tuple[RoomLayout, str, int, bool]] = []  # (layout, file, index, named in it)
    given: dict[str, str] = {}  # real path -> the path as given
    for path in paths:
        source = os.fspath(path)
        real = os.path.realpath(source)
        if real in given:
            also = "" if given[real] == source else f" (as {given[real]})"
            raise LayoutError(None, f"given twice{also}; give each file once", source=source)
        given[real] = source
        parsed = _read_rooms(path, source)
        rooms += [(layout, source, i, named) for i, (layout, named) in enumerate(parsed)]
        if len(rooms) > MAX_ROOMS:
            detail = f"{len(rooms)} rooms with the files before it: at most {MAX_ROOMS} in all"
            raise LayoutError(None, detail, source=source)
    if success_radius is not None:
        for layout, source, i, _ in rooms:
            try:
                check_goal_distance(layout, success_radius)
            except LayoutError as err:
                raise err.located(source=source, room=layout.name, index=i) from None
    return _named(rooms)


def load_layout(path: str | os.PathLike) -> list[RoomLayout]:
    """Read a layout file (one room object or a list of them) -> validated layouts."""
    return load_layouts([path])


def _named(rooms: list[tuple[RoomLayout, str, int, bool]]) -> list[RoomLayout]:
    """The layouts of `load_layouts`, an unnamed one renamed where its name is taken; a name
    given to two rooms is a LayoutError naming both (file and index)."""
    owner: dict[str, tuple[str, int]] = {}
    for layout, source, i, named in rooms:
        if named and layout.name in owner:
            first, j = owner[layout.name]
            where = f"room #{j}" + ("" if first == source else f" of {first}")
            detail = f"duplicate room name, also used by {where}"
            raise LayoutError("name", detail, source=source, room=layout.name, index=i)
        if named:
            owner[layout.name] = (source, i)
    taken, out = set(owner), []
    for layout, _, _, named in rooms:
        if not named and layout.name in taken:
            k = 2
            while f"{layout.name}-{k}" in taken:
                k += 1
            layout = dataclasses.replace(layout, name=f"{layout.name}-{k}")
        taken.add(layout.name)
        out.append(layout)
    return out


def check_goal_distance(layout: RoomLayout, success_radius: float) -> None:
    """A fixed goal lies farther than `success_radius` (a goal task's, m) from a fixed spawn:
    nearer, every episode succeeds on its first step and measures nothing (SPL 0)."""
    if layout.goal_pos is None or layout.robot_pos is None:
        return
    gap = math.dist(layout.goal_pos, layout.robot_pos)
    if gap <= success_radius:
        raise LayoutError(
            "goal.pos",
            f"{gap:.3f} m from robot.pos {_show(list(layout.robot_pos))}, within the goal task's "
            f"success radius ({success_radius:g} m): every episode would succeed at once; place "
            "it farther from the spawn",
            room=layout.name,
        )


# ------------------------------------------------------------------------------
# Writing


def _obstacle_to_dict(ob: Obstacle) -> dict:
    out: dict = {"type": ob.kind}
    for f in dataclasses.fields(ob):
        value = getattr(ob, f.name)
        if f.name == "motion":
            if value is not None:  # a still obstacle is written as before motions existed
                out["motion"] = value.to_dict()
        else:
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def layout_to_dict(layout: RoomLayout) -> dict:
    """The layout as a JSON-ready room object (all optional fields written out)."""
    out: dict = {
        "name": layout.name,
        "room": {"size": list(layout.size), "wall_height": layout.wall_height},
    }
    if layout.robot_pos is not None:
        out["robot"] = {"pos": list(layout.robot_pos), "yaw": layout.robot_yaw}
    if layout.goal_pos is not None:
        out["goal"] = {"pos": list(layout.goal_pos)}
    out["obstacles"] = [_obstacle_to_dict(ob) for ob in layout.obstacles]
    return out


def _dump_room(room: dict, indent: str = "") -> str:
    """A room object as JSON text: one line per section and per obstacle."""
    dump = functools.partial(json.dumps, ensure_ascii=False, allow_nan=False)
    lines = []
    for key, value in room.items():
        if key == "obstacles" and value:
            items = ",\n".join(f"{indent}    {dump(ob)}" for ob in value)
            lines.append(f'{indent}  "obstacles": [\n{items}\n{indent}  ]')
        else:
            lines.append(f"{indent}  {dump(key)}: {dump(value)}")
    return f"{indent}{{\n" + ",\n".join(lines) + f"\n{indent}}}"


def save_layouts(path: str | os.PathLike, layouts: RoomLayout | Sequence[RoomLayout]) -> None:
    """Write layouts in the format `load_layout` reads, atomically.

    A single `RoomLayout` is written as one room object, a sequence as a JSON list.
    """
    source = os.fspath(path)
    single = isinstance(layouts, RoomLayout)
    rooms = [layouts] if single else list(layouts)
    if not rooms:
        raise LayoutError(None, "nothing to save: empty list of layouts", source=source)
    for i, layout in enumerate(rooms):
        if not isinstance(layout, RoomLayout):
            detail = f"must be a RoomLayout, got {type(layout).__name__}"
            raise LayoutError(None, detail, source=source, index=i)
    _check_unique_names(rooms, source)
    if single:
        text = _dump_room(layout_to_dict(layouts))
    else:
        text = "[\n" + ",\n".join(_dump_room(layout_to_dict(r), "  ") for r in rooms) + "\n]"
    write_atomic(path, text + "\n")
