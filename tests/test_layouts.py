"""Layout format: shipped rooms, round trip, geometry helpers and one test per kind of bad input."""

import copy
import dataclasses
import json
import math
import os
import time
import types
from pathlib import Path

import numpy as np
import pytest

from jaxnav.io import layouts
from jaxnav.io.layouts import (
    MAX_OBSTACLES,
    MAX_ROOMS,
    Box,
    Cylinder,
    LayoutError,
    RoomLayout,
    box_corners,
    clearance,
    free_spawn,
    is_free,
    layout_to_dict,
    load_layout,
    load_layouts,
    parse_layouts,
    save_layouts,
)
from jaxnav.io.layouts import ROBOT_RADIUS as BASE_RADIUS

SCENES = Path(__file__).resolve().parent.parent / "scenes"

# A valid 4 m x 4 m room; the bad-input cases each break one thing in a copy of it.
GOOD = {
    "name": "office-a",
    "room": {"size": [4.0, 4.0], "wall_height": 0.5},
    "robot": {"pos": [0.0, 0.0], "yaw": 0.0},
    "obstacles": [
        {"type": "box", "pos": [1.2, 0.5], "size": [0.6, 0.4], "yaw": 0.3, "height": 0.5},
        {"type": "cylinder", "pos": [-1.0, 1.0], "radius": 0.15, "height": 0.8},
    ],
}


def _grid(**fields) -> dict:
    """A grid obstacle object: 0.2 m cells south-west of the robot, `fields` over it."""
    return {"type": "grid", "origin": [-1.5, -1.5], "cell": 0.2, "rows": ["#.", ".#"], **fields}


def write(tmp_path: Path, obj, name: str = "rooms.json") -> Path:
    path = tmp_path / name
    path.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return path


# ------------------------------------------------------------------------------
# Shipped layouts


def _boundary(ob, n: int = 400) -> np.ndarray:
    """[n, 2] points along an obstacle's footprint outline."""
    if isinstance(ob, Cylinder):
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.asarray(ob.pos) + ob.radius * np.stack([np.cos(t), np.sin(t)], -1)
    c = box_corners(ob)
    t = np.linspace(0, 1, n // 4, endpoint=False)[:, None]
    return np.concatenate([a + t * (b - a) for a, b in zip(c, np.roll(c, -1, axis=0), strict=True)])


def _passage_widths(layout: RoomLayout) -> list[float]:
    """Gap from each obstacle to its nearest neighbour (another obstacle or a wall)."""
    widths = []
    for i, ob in enumerate(layout.obstacles):
        others = layout.obstacles[:i] + layout.obstacles[i + 1 :]
        rest = dataclasses.replace(layout, robot_pos=None, robot_yaw=0.0, obstacles=others)
        widths.append(float(clearance(rest, _boundary(ob)).min()))
    return widths


def test_train_room_loads():
    (room,) = load_layout(SCENES / "train_room.json")
    assert room.name == "train-room"
    assert room.size == (6.0, 6.0)
    assert room.robot_pos == (0.0, 0.0) and room.robot_yaw == 0.0
    assert 6 <= len(room.obstacles) <= 8
    assert room.boxes and room.cylinders
    assert len(room.boxes) + len(room.cylinders) == len(room.obstacles)
    assert all(isinstance(b, Box) for b in room.boxes)
    # At least 0.8 m of free driving straight ahead (+x) of the spawn.
    ahead = np.stack([np.linspace(0.0, 0.8, 17), np.zeros(17)], axis=-1)
    assert is_free(room, ahead, BASE_RADIUS).all()


def test_inference_room_loads_and_differs():
    (room,) = load_layout(SCENES / "inference_room.json")
    (train,) = load_layout(SCENES / "train_room.json")
    assert room.name == "inference-room"
    assert room.size == (5.0, 7.0)
    assert 6 <= len(room.obstacles) <= 8
    assert room.boxes and room.cylinders
    assert {ob.pos for ob in room.obstacles}.isdisjoint({ob.pos for ob in train.obstacles})
    # Spawn near the south wall, facing into the room.
    assert room.robot_pos[1] < -0.5 * room.size[1] + 1.0
    assert math.isclose(room.robot_yaw, math.pi / 2)


@pytest.mark.parametrize("name", ["train_room.json", "inference_room.json"])
def test_shipped_passages_fit_the_robot(name):
    """Obstacles either touch a wall/neighbour or leave >= 0.9 m for the 0.354 m robot."""
    (room,) = load_layout(SCENES / name)
    for i, width in enumerate(_passage_widths(room)):
        assert width < 1e-6 or width >= 0.9, f"obstacles[{i}]: gap {width:.3f} m"


# ------------------------------------------------------------------------------
# Round trip


def test_round_trip_dict():
    (layout,) = parse_layouts(GOOD)
    assert parse_layouts([layout_to_dict(layout)]) == [layout]
    assert json.loads(json.dumps(layout_to_dict(layout))) == layout_to_dict(layout)


def test_round_trip_files(tmp_path):
    layouts = load_layout(SCENES / "train_room.json") + load_layout(SCENES / "inference_room.json")
    unnamed = dict(GOOD, name="sampled-spawn")
    del unnamed["robot"]
    layouts += parse_layouts(unnamed)
    path = tmp_path / "set.json"
    save_layouts(path, layouts)
    assert load_layout(path) == layouts
    assert isinstance(json.loads(path.read_text()), list)
    save_layouts(path, layouts[0])  # a single layout is written as one room object
    assert isinstance(json.loads(path.read_text()), dict)
    assert load_layout(path) == layouts[:1]
    assert [p.name for p in tmp_path.iterdir()] == ["set.json"]  # no temp file left behind


def test_grid_round_trip_and_clearance(tmp_path):
    """A grid obstacle reads, writes and reads back the same; its clearance is that of its
    occupied cells as boxes (rows north first: the "#" of the top row is the north-west cell)."""
    room = dict(GOOD, obstacles=[*GOOD["obstacles"], _grid(rows=["#..", "...", "..#"])])
    (layout,) = parse_layouts(room)
    path = tmp_path / "grid.json"
    save_layouts(path, layout)
    assert load_layout(path) == [layout] and layout.grid is layout.obstacles[2]
    north_west, south_east = (-1.4, -1.0), (-1.0, -1.4)  # centres of the two occupied cells
    assert clearance(layout, north_west) == pytest.approx(-0.1, abs=1e-6)
    assert clearance(layout, south_east) == pytest.approx(-0.1, abs=1e-6)
    assert clearance(layout, (-1.2, -1.2)) == pytest.approx(0.1 * math.sqrt(2), abs=1e-6)


def test_defaults_and_optional_fields():
    minimal = {
        "room": {"size": [3, 2]},
        "obstacles": [{"type": "cylinder", "pos": [0, 0.5], "radius": 0.1}],
    }
    (layout,) = parse_layouts([minimal, {"room": {"size": [2, 2]}}])[:1]
    assert layout.name == "room-0"
    assert layout.size == (3.0, 2.0) and isinstance(layout.size[0], float)
    assert layout.wall_height == 0.5 and layout.robot_pos is None
    assert layout.obstacles == (Cylinder(pos=(0.0, 0.5), radius=0.1, height=0.5),)
    assert parse_layouts({"room": {"size": [2, 2]}})[0].obstacles == ()


def test_programmatic_layout_is_validated():
    with pytest.raises(LayoutError, match=r"room 'x': obstacles\[0\]: box .* east wall"):
        RoomLayout(name="x", size=(2.0, 2.0), obstacles=(Box(pos=(0.9, 0.0), size=(0.4, 0.4)),))
    with pytest.raises(LayoutError, match="size: must be two positive numbers"):
        Box(pos=(0, 0), size=(0.0, 1.0))


# ------------------------------------------------------------------------------
# Geometry


def test_clearance_one_metre_from_a_box_face():
    room = RoomLayout(
        name="g", size=(10.0, 10.0), obstacles=(Box(pos=(0.0, 0.0), size=(1.0, 1.0)),)
    )
    assert clearance(room, [1.5, 0.0]) == pytest.approx(1.0)
    assert clearance(room, [0.0, -1.5]) == pytest.approx(1.0)
    assert clearance(room, [0.0, 0.0]) == pytest.approx(-0.5)  # centre: 0.5 m deep inside
    assert clearance(room, [4.5, 0.0]) == pytest.approx(0.5)  # nearer to the east wall


def test_clearance_inside_a_cylinder_is_negative():
    room = RoomLayout(
        name="g", size=(10.0, 10.0), obstacles=(Cylinder(pos=(2.0, 2.0), radius=0.5),)
    )
    assert clearance(room, (2.2, 2.0)) == pytest.approx(-0.3)
    assert clearance(room, (2.0, 3.0)) == pytest.approx(0.5)


def test_yawed_box_corners_and_corner_distance():
    box = Box(pos=(1.0, 1.0), size=(2.0, 1.0), yaw=math.pi / 2)
    corners = box_corners(box)
    assert corners.shape == (4, 2)
    expected = {(1.5, 0.0), (1.5, 2.0), (0.5, 2.0), (0.5, 0.0)}
    assert {tuple(np.round(c, 9) + 0.0) for c in corners} == expected
    room = RoomLayout(name="g", size=(10.0, 10.0), obstacles=(box,))
    # Diagonally off the (1.5, 2.0) corner by (0.3, 0.4): 0.5 m to the corner.
    assert clearance(room, (1.8, 2.4)) == pytest.approx(0.5)


def test_is_free_and_batches():
    room = RoomLayout(name="g", size=(4.0, 4.0), obstacles=(Box(pos=(0.0, 0.0), size=(1.0, 1.0)),))
    assert is_free(room, (1.0, 0.0), 0.4) is True
    assert is_free(room, (1.0, 0.0), 0.5) is False  # touching is not free
    assert is_free(room, (1.85, -1.0), BASE_RADIUS) is False  # into the east wall
    pts = np.array([[[1.5, 0.0], [0.0, 0.0]], [[1.0, 1.0], [-1.9, 1.9]]])
    dist = clearance(room, pts)
    assert dist.shape == (2, 2)
    np.testing.assert_allclose(dist, [[0.5, -0.5], [math.sqrt(0.5), 0.1]], rtol=1e-6)  # float32
    np.testing.assert_array_equal(is_free(room, pts, 0.2), [[True, False], [True, False]])


# ------------------------------------------------------------------------------
# Bad input: each error names the file, the room and the field


def _set(path: str, value):
    """A mutation of GOOD setting a dotted path (obstacles[i] indexes; value None deletes)."""

    def mutate(room):
        *parents, last = path.replace("[", ".").replace("]", "").split(".")
        node = room
        for key in parents:
            node = node[int(key)] if key.isdigit() else node[key]
        key = int(last) if last.isdigit() else last
        if value is None:
            del node[key]
        else:
            node[key] = value
        return room

    return mutate


BAD = [
    # id, mutation, field named, further fragments
    ("unknown-type", _set("obstacles[1].type", "sphere"), "obstacles[1].type",
     ["'sphere'", "'box', 'cylinder'"]),
    ("negative-size", _set("obstacles[0].size", [-1.0, 0.3]), "obstacles[0].size",
     ["must be two positive numbers, got [-1.0, 0.3]"]),
    ("zero-radius", _set("obstacles[1].radius", 0), "obstacles[1].radius", ["positive"]),
    ("zero-height", _set("obstacles[1].height", 0.0), "obstacles[1].height", ["positive"]),
    ("negative-room", _set("room.size", [4.0, -4.0]), "room.size", ["positive"]),
    ("zero-wall-height", _set("room.wall_height", 0), "room.wall_height", ["positive"]),
    ("box-outside", _set("obstacles[0].pos", [1.9, 0.5]), "obstacles[0]", ["east wall"]),
    ("cylinder-outside", _set("obstacles[1].pos", [-1.0, -1.9]), "obstacles[1]", ["south wall"]),
    # 0.7 m square at x=1.6 fits (x <= 1.95) unrotated, its 45-degree corner reaches x = 2.095.
    ("box-outside-after-yaw", _set("obstacles[0]", {"type": "box", "pos": [1.6, 0.0],
     "size": [0.7, 0.7], "yaw": math.pi / 4}), "obstacles[0]", ["east wall", "0.095 m"]),
    ("spawn-in-box", _set("robot.pos", [1.2, 0.5]), "robot.pos", ["obstacles[0] (box)"]),
    ("spawn-near-cylinder", _set("robot.pos", [-0.75, 1.0]), "robot.pos",
     ["obstacles[1] (cylinder)"]),
    ("spawn-in-wall", _set("robot.pos", [1.9, -1.5]), "robot.pos", ["east wall"]),
    ("spawn-outside", _set("robot.pos", [0.0, 5.0]), "robot.pos", ["north wall"]),
    ("unknown-key", _set("obstacles[1].radus", 0.2), "obstacles[1].radus",
     ["did you mean 'radius'?"]),
    ("unknown-top-key", _set("obstacle", []), "obstacle", ["did you mean 'obstacles'?"]),
    ("unknown-room-key", _set("room.wall_heigth", 1), "room.wall_heigth",
     ["did you mean 'wall_height'?"]),
    ("yaw-on-cylinder", _set("obstacles[1].yaw", 0.1), "obstacles[1].yaw", ["valid keys"]),
    ("string-size", _set("room.size", "6x5"), "room.size", ['got "6x5"']),
    ("three-element-pos", _set("robot.pos", [0, 0, 0]), "robot.pos", ["two numbers"]),
    ("bool-as-number", _set("obstacles[0].yaw", True), "obstacles[0].yaw", ["got true"]),
    ("bool-in-pair", _set("obstacles[0].pos", [1, False]), "obstacles[0].pos", ["two numbers"]),
    ("nan", _set("obstacles[1].height", float("nan")), "obstacles[1].height", ["finite"]),
    ("infinity", _set("robot.yaw", float("inf")), "robot.yaw", ["finite"]),
    ("obstacles-not-list", _set("obstacles", {"type": "box"}), "obstacles", ["list"]),
    ("obstacle-not-object", _set("obstacles[0]", [1, 2]), "obstacles[0]", ["object"]),
    ("room-not-object", _set("room", [4, 4]), "room", ["object"]),
    ("name-not-string", _set("name", 7), "name", ["string"]),
    ("missing-room", _set("room", None), "room", ["missing"]),
    ("missing-room-size", _set("room.size", None), "room.size", ["missing"]),
    ("missing-type", _set("obstacles[0].type", None), "obstacles[0].type", ["missing"]),
    ("missing-pos", _set("obstacles[1].pos", None), "obstacles[1].pos", ["missing"]),
    ("missing-box-size", _set("obstacles[0].size", None), "obstacles[0].size", ["missing"]),
    ("missing-radius", _set("obstacles[1].radius", None), "obstacles[1].radius", ["missing"]),
    ("missing-robot-pos", _set("robot.pos", None), "robot.pos", ["missing"]),
    # Bounds: what the float32 simulator handles (module docstring).
    ("tiny-room", _set("room.size", [0.1, 0.1]), "room.size", ["0.5 to 100 m"]),
    ("huge-room", _set("room.size", [1e30, 1e30]), "room.size", ["0.5 to 100 m"]),
    ("tall-wall", _set("room.wall_height", 20.0), "room.wall_height", ["at most 10 m"]),
    ("thin-box", _set("obstacles[0].size", [0.001, 0.4]), "obstacles[0].size", ["0.01 to 100 m"]),
    ("400-digit-integer", _set("room.size", [10**400, 4]), "room.size", ["finite"]),
    # Grid obstacles (obstacles[0] replaced by one).
    ("grid-bad-character", _set("obstacles[0]", _grid(rows=["#.", "x."])),
     "obstacles[0].rows[1]", ['"#" or "."', '"x."']),
    ("grid-ragged", _set("obstacles[0]", _grid(rows=["#..", "#."])), "obstacles[0].rows[1]",
     ["3 characters"]),
    ("grid-not-strings", _set("obstacles[0]", _grid(rows="#.")), "obstacles[0].rows",
     ["list of 1 to 64 strings"]),
    ("grid-zero-cell", _set("obstacles[0]", _grid(cell=0)), "obstacles[0].cell", ["positive"]),
    ("grid-outside", _set("obstacles[0]", _grid(origin=[1.5, 1.5], rows=["##"], cell=0.3)),
     "obstacles[0]", ["east wall"]),
    ("two-grids", _set("obstacles", [_grid(), _grid(origin=[0.5, 0.5])]), "obstacles[1]",
     ["at most one grid"]),
    ("spawn-in-grid-cell", _set("obstacles[0]", _grid(origin=[-0.1, -0.1])), "robot.pos",
     ["obstacles[0] (grid)"]),
]  # fmt: skip


@pytest.mark.parametrize(
    ("mutate", "field", "fragments"), [b[1:] for b in BAD], ids=[b[0] for b in BAD]
)
def test_bad_room(tmp_path, mutate, field, fragments):
    # The bad room is the second of the file, so the index in the message is checked too.
    other = dict(copy.deepcopy(GOOD), name="lobby")
    bad = mutate(copy.deepcopy(GOOD))
    path = write(tmp_path, [other, bad])
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    msg = str(info.value)
    named = isinstance(bad.get("name"), str)
    room = "room 'office-a' (#1)" if named else "room #1"
    assert msg.startswith(f"{path}: {room}: {field}: "), msg
    for fragment in fragments:
        assert fragment in msg, msg
    assert "\n" not in msg
    assert info.value.field == field and info.value.index == 1


def test_unnamed_room_is_named_by_index(tmp_path):
    bad = _set("obstacles[0].size", [0.0, 1.0])(copy.deepcopy(GOOD))
    del bad["name"]
    path = write(tmp_path, bad)
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    assert str(info.value).startswith(f"{path}: room #0: obstacles[0].size: must be two positive")
    assert "room-0" not in str(info.value)


def test_box_fits_before_yaw(tmp_path):
    """Control for the box-outside-after-yaw case: the same box unrotated is accepted."""
    ok = _set("obstacles[0]", {"type": "box", "pos": [1.6, 0.0], "size": [0.7, 0.7]})
    assert load_layout(write(tmp_path, ok(copy.deepcopy(GOOD))))[0].boxes[0].yaw == 0.0


@pytest.mark.parametrize(
    ("rooms", "field", "room", "fragment"),
    [
        ([GOOD, 5], None, "room #1", "must be a room object, got a number"),
        ([GOOD, GOOD], "name", "room 'office-a' (#1)", "duplicate room name"),
    ],
    ids=["entry-not-object", "duplicate-name"],
)
def test_bad_room_list(tmp_path, rooms, field, room, fragment):
    path = write(tmp_path, rooms)
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    parts = [str(path), room] + ([field] if field else [])
    assert str(info.value).startswith(": ".join(parts) + ": "), str(info.value)
    assert fragment in str(info.value)


def test_duplicate_key(tmp_path):
    text = json.dumps(GOOD).replace('"radius": 0.15', '"radius": 0.15, "radius": 0.2')
    path = write(tmp_path, text)
    with pytest.raises(
        LayoutError, match=r"room 'office-a' \(#0\): obstacles\[1\]\.radius: key given"
    ):
        load_layout(path)


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        ('{"name": "a",\n  "room": {"size": [4, 4]]}', "invalid JSON at line 2, column 26"),
        ("", "invalid JSON at line 1, column 1"),
        ("[]", "empty list"),
        ('"room"', "expected a room object or a list of rooms, got a string"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ('{"room": {"size": [' + "9" * 5000 + ", 4]}}", "invalid JSON: Exceeds the limit"),
    ],
    ids=["invalid-json", "empty-file", "empty-list", "not-a-room", "deep", "5000-digits"],
)
def test_bad_file(tmp_path, content, fragment):
    path = write(tmp_path, content)
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    assert str(info.value).startswith(f"{path}: "), str(info.value)
    assert fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.json"
    with pytest.raises(LayoutError, match=r"nope\.json: no such file"):
        load_layout(path)
    with pytest.raises(LayoutError, match="is a directory"):
        load_layout(tmp_path)


def test_parse_layouts_source_and_save_errors(tmp_path):
    with pytest.raises(LayoutError, match=r"^<layout>: room 'office-a' \(#0\): room\.size"):
        parse_layouts(_set("room.size", "big")(copy.deepcopy(GOOD)))
    with pytest.raises(LayoutError, match="nothing to save"):
        save_layouts(tmp_path / "x.json", [])
    (layout,) = parse_layouts(GOOD)
    with pytest.raises(LayoutError, match="duplicate room name"):
        save_layouts(tmp_path / "x.json", [layout, layout])
    assert not any(tmp_path.iterdir())
    assert issubclass(LayoutError, ValueError)


def test_special_and_huge_files_are_refused_at_once(tmp_path):
    import os

    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)  # would block forever if opened for reading
    (tmp_path / "huge.json").write_bytes(b" " * (16 * 2**20 + 1))
    cases = {fifo: "a FIFO", "/dev/zero": "a character device", tmp_path / "huge.json": "16 MB"}
    for path, fragment in cases.items():
        with pytest.raises(LayoutError, match=f"^{path}: .*{fragment}"):
            load_layout(path)


def test_room_without_a_free_spawn_is_refused(tmp_path):
    """A 2 m room filled by four 1 m boxes validated before, and every episode then started in a
    collision; the grid search over the interior finds that no spawn exists."""
    boxes = [
        {"type": "box", "pos": [x, y], "size": [1.0, 1.0]} for x in (-0.5, 0.5) for y in (-0.5, 0.5)
    ]
    full = {"name": "full", "room": {"size": [2.0, 2.0]}, "obstacles": boxes}
    with pytest.raises(LayoutError, match=r"room 'full' \(#0\): no free spawn"):
        load_layout(write(tmp_path, full))
    roomy = dict(full, room={"size": [3.0, 3.0]})  # a 0.5 m ring around them: free
    assert load_layout(write(tmp_path, roomy))[0].robot_pos is None


def test_yaw_is_reduced_modulo_two_pi(tmp_path):
    """A yaw of 1e9 + 0.5 was checked in float64 and simulated in float32 (where it is another
    angle); reduced when read, both see the same box."""
    room = copy.deepcopy(GOOD)
    room["obstacles"][0]["yaw"] = 1_000_000_000.5
    room["robot"]["yaw"] = -7.0
    (layout,) = load_layout(write(tmp_path, room))
    yaw = layout.boxes[0].yaw
    assert -math.pi <= yaw <= math.pi and yaw == pytest.approx(
        math.remainder(1e9 + 0.5, 2 * math.pi)
    )
    assert layout.robot_yaw == pytest.approx(-7.0 + 2 * math.pi)
    f32 = clearance(layout, [0.0, 0.0])  # float32, as simulated
    box = layout.boxes[0]
    local = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]]) @ (
        -np.asarray(box.pos)
    )
    q = np.abs(local) - 0.5 * np.asarray(box.size)
    f64 = np.linalg.norm(np.maximum(q, 0)) + min(q.max(), 0)
    assert f32 == pytest.approx(min(f64, 1.5), abs=1e-5)  # the box, or the cylinder at 1.27 m


@pytest.mark.parametrize("size", [(100.0, 0.5), (0.5, 100.0)])
def test_long_narrow_room_has_a_free_spawn(size):
    """A 0.5 m wide room leaves the 0.177 m robot 0.073 m either side of its centre line; the
    search grid, coarser than that along 100 m, refused it until it was centred on the room."""
    assert 2 * BASE_RADIUS < 0.5
    room = RoomLayout(name="hall", size=size)  # no robot: it needs a free spawn
    spawn = free_spawn(room)
    assert spawn is not None and is_free(room, spawn, BASE_RADIUS)
    assert abs(spawn[int(np.argmin(size))]) < 0.25 - BASE_RADIUS


def _grid_of_boxes(n: int, side: float = 100.0) -> list[dict]:
    """n boxes of 1 m tiling a side x side room from its south-west corner."""
    per_row = int(side)
    return [
        {"type": "box", "pos": [-side / 2 + 0.5 + i % per_row, -side / 2 + 0.5 + i // per_row],
         "size": [1.0, 1.0]}
        for i in range(n)
    ]  # fmt: skip


def test_spawn_search_is_fast_on_many_obstacles():
    """10,000 boxes filling a 100 m room: no free spawn, found in seconds (each obstacle is
    measured only near its footprint), not minutes."""
    boxes = tuple(Box(pos=tuple(b["pos"]), size=(1.0, 1.0)) for b in _grid_of_boxes(10_000))
    full = types.SimpleNamespace(size=(100.0, 100.0), obstacles=boxes)  # beyond MAX_OBSTACLES
    start = time.perf_counter()
    assert free_spawn(full) is None
    one_gap = types.SimpleNamespace(size=(100.0, 100.0), obstacles=boxes[:-1])  # the last box
    assert free_spawn(one_gap) == pytest.approx((49.5, 49.5), abs=0.5 - BASE_RADIUS)
    assert time.perf_counter() - start < 30


def test_too_many_obstacles_or_rooms_are_refused_before_they_are_checked(tmp_path, monkeypatch):
    many = {"room": {"size": [100, 100]}, "obstacles": _grid_of_boxes(10_000)}
    start = time.perf_counter()
    with pytest.raises(LayoutError) as info:
        load_layout(write(tmp_path, many))
    assert str(info.value) == (
        f"{tmp_path / 'rooms.json'}: room #0: obstacles: 10000 obstacles: at most "
        f"{MAX_OBSTACLES} per room (every room of a batch simulates as many obstacle slots as "
        "the fullest one)"
    )
    with pytest.raises(LayoutError, match=f"^{tmp_path / 'rooms.json'}: 5000 rooms: at most"):
        load_layout(write(tmp_path, [{"room": {"size": [4, 4]}}] * 5000))
    assert time.perf_counter() - start < 10
    with pytest.raises(LayoutError, match=f"obstacles: {MAX_OBSTACLES + 1} obstacles: at most"):
        RoomLayout(name="x", size=(100.0, 100.0), obstacles=(Box(pos=(0, 0), size=(1, 1)),) * 257)
    assert MAX_ROOMS >= 1000  # 30 times the benchmark suite
    monkeypatch.setattr(layouts, "MAX_ROOMS", 3)  # in all the files read together
    a = write(tmp_path, [{"room": {"size": [4, 4]}}] * 2, "a.json")
    b = write(tmp_path, [{"room": {"size": [4, 4]}}] * 2, "b.json")
    with pytest.raises(LayoutError, match=f"^{b}: 4 rooms with the files before it: at most 3"):
        load_layouts([a, b])


def test_rooms_of_several_files_are_named_by_file_and_index(tmp_path):
    """Unnamed rooms get `<file stem>-<index>` (`-2` where that is taken), so two files of
    unnamed rooms make one set; a name given twice names both files and rooms."""
    (tmp_path / "other").mkdir()
    a = write(tmp_path, [{"room": {"size": [4, 4]}}] * 2, "a.json")
    b = write(tmp_path, {"room": {"size": [4, 4]}}, "b.json")
    a2 = write(tmp_path / "other", {"room": {"size": [4, 4]}}, "a.json")
    taken = write(tmp_path, {"name": "a-0", "room": {"size": [4, 4]}}, "c.json")
    names = [room.name for room in load_layouts([a, b, a2, taken])]
    assert names == ["a-0-2", "a-1", "b-0", "a-0-3", "a-0"]  # a given name keeps it
    assert [r.name for r in load_layout(a)] == ["a-0", "a-1"]
    office = {"name": "office", "room": {"size": [4, 4]}}
    one = write(tmp_path, office, "one.json")
    two = write(tmp_path, [{"room": {"size": [4, 4]}}, office], "two.json")
    with pytest.raises(LayoutError) as info:
        load_layouts([one, two])
    assert str(info.value) == (
        f"{two}: room 'office' (#1): name: duplicate room name, also used by room #0 of {one}"
    )
    with pytest.raises(LayoutError, match=f"^{a}: given twice; give each file once$"):
        load_layouts([a, b, a])
    same = os.path.join(tmp_path, "other", "..", "a.json")
    with pytest.raises(LayoutError, match=rf"^{same}: given twice \(as {a}\)"):
        load_layouts([a, same])


def test_goal_within_the_success_radius_of_the_spawn_is_refused(tmp_path):
    """A goal on the spawn: every goal-task episode succeeds at once (100 %, SPL 0)."""
    room = {"name": "on-spawn", "room": {"size": [4, 4]}, "robot": {"pos": [0.5, 0.0]}}
    room["goal"] = {"pos": [0.5, 0.2]}
    path = write(tmp_path, room)
    assert load_layouts([path])[0].goal_pos == (0.5, 0.2)  # the avoid task ignores goals
    with pytest.raises(LayoutError) as info:
        load_layouts([path], success_radius=0.3)
    assert str(info.value) == (
        f"{path}: room 'on-spawn' (#0): goal.pos: 0.200 m from robot.pos [0.5, 0.0], within the "
        "goal task's success radius (0.3 m): every episode would succeed at once; place it "
        "farther from the spawn"
    )
    assert load_layouts([path], success_radius=0.1)[0].name == "on-spawn"


def test_unreadable_file_is_one_line(tmp_path, monkeypatch):
    """Root reads files whatever their mode: the refusal is simulated where the file is opened."""
    path = write(tmp_path, GOOD)
    real_open = os.open

    def refuse(file, *args, **kwargs):
        if os.fspath(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    assert str(info.value) == f"{path}: cannot read (Permission denied)"
