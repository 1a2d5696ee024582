"""BARN worlds as jaxnav layouts, and the BARN Challenge's score.

BARN (Perille, Truong, Xiao and Stone, "Benchmarking Metric Ground Navigation", SSRR 2020) is 300
static worlds used by the ICRA BARN Challenge (github.com/Daffan/the-barn-challenge, MIT licence):
`jackal_helper/worlds/BARN/world_N.world` (SDF) and `path_files/path_N.npy` (the optimal path on
the world's 30 x 30 cell map). Every world holds only upright cylinders, 0.075 m in radius and 1 m
long, centred on the floor (0.5 m stand above it), on a grid of 0.15 m, so neighbours touch: a full
column down each side and a full back row (the field's walls) around the obstacles of the map.
The challenge's `run.py` starts the robot at `START` facing +y and counts a success when it comes
within `SUCCESS_RADIUS` of `GOAL` (10 m ahead) in `TIME_LIMIT_S` without a collision.

`world_layout` converts one world (BARN's frame: x east, y north, metres) into a layout dict:

- The side columns and the back row become the room's walls, placed at their inner faces (tangent
  to the cylinders). Between two touching cylinders the robot's disc (radius 0.177 m) reaches
  0.011 m further than it can towards the flat wall, so no gap between the wall and an obstacle
  opens or closes by more than that.
- BARN is open beyond the field's end (y = 9.6 m) and behind the goal. The room's front wall is
  `FRONT_MARGIN` beyond the goal, and its side walls continue the columns there, 2.1 m either side
  of the goal. The free region between the field and the goal is convex and holds the goal, so
  every path to it, and its shortest length, is the same as in BARN. The robot cannot go around the
  outside of a column, which never leads to the goal.
- The rest of the cylinders are obstacles, with their radius and the height above the floor.
- The frame is only translated (both have x east, y north): the room's interior is centred on the
  origin, so BARN's (x, y) becomes (x - cx, y - cy), where (cx, cy) is the centre of the interior
  in BARN's frame, (-2.25, 7.575) m for every BARN world.

Numpy and the standard library only: no jax.
"""

from __future__ import annotations

import gzip
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

# From the challenge's run.py (static worlds, indices 0-299).
START = (-2.25, 3.0)  # m, BARN's frame
START_YAW = math.pi / 2  # facing +y (run.py writes 1.57)
GOAL = (-2.25, 13.0)  # m: START + (0, 10)
SUCCESS_RADIUS = 1.0  # m from GOAL
TIME_LIMIT_S = 100.0
OPTIMAL_SPEED = 2.0  # m/s: optimal time = optimal path length / 2
# From run.py's path_coord_to_gazebo_coord: map cell (i, j) -> (0.15 i - 4.575, 0.15 j + 5.075) m.
CELL = 0.15  # m
CELL_ORIGIN = (-0.075 - 30 * 0.15, 0.075 + 5.0)  # m, centre of cell (0, 0) as run.py places it

FRONT_MARGIN = 2.0  # m from GOAL to the room's front wall, where BARN is open
_GRID_TOL = 1e-6  # m; SDF poses are written with 6 decimals


def _open_text(path: Path) -> str:
    """The text of a file, gunzipped when its name ends in .gz."""
    if path.suffix == ".gz":
        with gzip.open(path, "rt", encoding="utf-8") as f:
            return f.read()
    return path.read_text(encoding="utf-8")


def _pose(text: str | None, where: str) -> np.ndarray:
    """An SDF pose "x y z roll pitch yaw" -> [6] floats (zeros when absent)."""
    values = np.zeros(6) if text is None else np.array(text.split(), float)
    if values.shape != (6,):
        raise ValueError(f"{where}: pose must have 6 numbers, got {text!r}")
    return values


def _model_cylinder(model: ET.Element, pose: np.ndarray, where: str) -> list[float] | None:
    """[x, y, radius, height above the floor] of a one-cylinder model; None for the ground plane."""
    shapes = [shape for geom in model.iter("geometry") for shape in geom]
    if shapes and all(s.tag == "plane" for s in shapes):
        return None
    collisions = [c.find("geometry/cylinder") for c in model.iter("collision")]
    if len(collisions) != 1 or collisions[0] is None:
        kinds = sorted({s.tag for s in shapes})
        raise ValueError(f"{where}: expected one cylinder collision geometry, found {kinds}")
    if np.abs(pose[3:5]).max() > _GRID_TOL:  # a tilted cylinder has no layout equivalent
        raise ValueError(f"{where}: cylinder is not upright (roll, pitch {pose[3:5].tolist()})")
    radius = float(collisions[0].findtext("radius"))
    length = float(collisions[0].findtext("length"))
    # The SDF cylinder is centred on its pose: what stands above the floor is z + length / 2.
    return [pose[0], pose[1], radius, pose[2] + 0.5 * length]


def read_world(path: str | os.PathLike) -> np.ndarray:
    """[N, 4] cylinders (x, y, radius, height above the floor), m, of a BARN world file (SDF, or
    SDF gzipped as .gz) in BARN's frame, in the file's order."""
    path = Path(path)
    world = ET.fromstring(_open_text(path)).find("world")
    if world is None:
        raise ValueError(f"{path}: no <world> element")
    # Gazebo applies the saved <state> over the models' own poses.
    state = {m.get("name"): m.findtext("pose") for m in world.findall("state/model")}
    rows = []
    for model in world.findall("model"):
        name = model.get("name")
        where = f"{path}: model {name!r}"
        pose = _pose(state.get(name) or model.findtext("pose"), where)
        row = _model_cylinder(model, pose, where)
        if row is not None:
            rows.append(row)
    return np.array(rows, float).reshape(-1, 4)


def _line_complete(values: np.ndarray, lo: float, hi: float, step: float) -> bool:
    """Whether `values` hold every multiple of `step` from lo to hi (touching cylinders)."""
    want = np.arange(round((hi - lo) / step) + 1)
    have = np.unique(np.round((values - lo) / step).astype(int))
    return np.array_equal(have, want)


def split_walls(cylinders: np.ndarray, where: str = "world") -> tuple[np.ndarray, dict]:
    """(obstacles [M, 4], walls {x_lo, x_hi, y_lo, y_top, height} in BARN's frame, m) of a BARN
    world's cylinders: the side columns (least and greatest x) and the back row (least y) are
    walls; the interior starts at their inner faces, the columns end at y_top, and `height` is
    theirs above the floor. Raises ValueError if a wall line has a gap."""
    x, y, radius = cylinders[:, 0], cylinders[:, 1], cylinders[:, 2]
    x_lo, x_hi, y_lo, y_hi = x.min(), x.max(), y.min(), y.max()
    west, east, back = (np.abs(v - at) < _GRID_TOL for v, at in ((x, x_lo), (x, x_hi), (y, y_lo)))
    wall = west | east | back
    r = radius[wall]
    if np.ptp(r) > _GRID_TOL:
        raise ValueError(f"{where}: wall cylinders differ in radius ({r.min()} to {r.max()} m)")
    step = 2 * r[0]  # touching cylinders
    lines = {"west column": (y[west], y_lo, y_hi), "east column": (y[east], y_lo, y_hi)}
    lines["back row"] = (x[back], x_lo, x_hi)
    for line, (values, lo, hi) in lines.items():
        if not _line_complete(values, lo, hi, step):
            raise ValueError(f"{where}: the {line} has gaps; not a BARN field")
    bounds = {"x_lo": x_lo + r[0], "x_hi": x_hi - r[0], "y_lo": y_lo + r[0], "y_top": y_hi + r[0]}
    bounds["height"] = float(cylinders[wall, 3].max())
    return cylinders[~wall], bounds


def _point(xy, centre) -> list[float]:
    """A BARN-frame point in the room's frame, rounded off float noise (1 um)."""
    return [round(float(v - c), 6) for v, c in zip(xy, centre, strict=True)]


def world_layout(path: str | os.PathLike, name: str | None = None) -> dict:
    """The layout dict (jaxnav's layout JSON format) of a BARN world file: walls, obstacles, the
    challenge's start and goal, in the room's frame (see the module doc). `name` defaults to the
    file's stem without suffixes (`world_N`)."""
    path = Path(path)
    name = name or path.name.split(".")[0]
    obstacles, b = split_walls(read_world(path), str(path))
    y_hi = max(GOAL[1] + FRONT_MARGIN, b["y_top"])
    size = (b["x_hi"] - b["x_lo"], y_hi - b["y_lo"])
    centre = (0.5 * (b["x_lo"] + b["x_hi"]), 0.5 * (b["y_lo"] + y_hi))
    return {
        "name": name,
        "room": {"size": [round(float(s), 6) for s in size], "wall_height": b["height"]},
        "robot": {"pos": _point(START, centre), "yaw": round(START_YAW, 4)},
        "goal": {"pos": _point(GOAL, centre)},
        "obstacles": [
            {
                "type": "cylinder",
                "pos": _point(c[:2], centre),
                "radius": float(c[2]),
                "height": float(c[3]),
            }
            for c in obstacles
        ],
    }


def path_to_world(path: np.ndarray) -> np.ndarray:
    """[N, 2] map cells (i, j) of a BARN path file -> [N, 2] points, m, in BARN's frame, exactly as
    the challenge's run.py places them (its cell centres sit 0.15 m west and 0.1 m south of the
    cylinder grid's; kept, since its score is defined with them)."""
    return np.asarray(path, float) * CELL + np.asarray(CELL_ORIGIN)


def optimal_path_length(path: np.ndarray) -> float:
    """The optimal path length, m, of a BARN path file's cells, as run.py measures it: the
    polyline START -> the path's points -> GOAL."""
    points = np.vstack([START, path_to_world(path), GOAL])
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def optimal_time(path_length_m):
    """The challenge's optimal time, s: the optimal path length at `OPTIMAL_SPEED`."""
    return np.asarray(path_length_m, float) / OPTIMAL_SPEED


def barn_score(success, time_s, optimal_time_s):
    """The challenge's navigation metric (run.py): success x optimal_time / clip(time, 2 x
    optimal_time, 8 x optimal_time), in [0, 0.5]; 0 where not successful (whatever the time).
    Numbers or arrays (broadcast); a float for scalars."""
    opt = np.asarray(optimal_time_s, float)
    clipped = np.clip(np.asarray(time_s, float), 2 * opt, 8 * opt)
    score = np.where(np.asarray(success, bool), opt / clipped, 0.0)
    return float(score) if score.ndim == 0 else score
