"""Pictures: top-down rooms with episode paths (the paper's Fig. 6/7) and training curves (Fig. 5).

Figures are built on `matplotlib.figure.Figure` with the Agg canvas, never through pyplot, so nothing
is left open in pyplot's global state and no display is needed.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import textwrap
from collections.abc import Sequence

import jax
import numpy as np
from matplotlib import patches
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from jaxnav.core import grid
from jaxnav.core.randomize import SceneParams
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.io.layouts import Box, Cylinder, RoomLayout, box_corners

ROBOT_RADIUS = TURTLEBOT2I.radius  # m, as drawn
MAX_PATHS = 20  # paths drawn per picture; beyond that they hide each other and the room
WALL_THICKNESS = (
    0.1  # m, as drawn (the simulated walls are planes: their thickness does not matter)
)
FLOOR_MARGIN = 0.2  # m of floor shown beyond the walls
METRICS_HEADER = ("update", "env_steps", "episode_reward", "episode_length")  # always present

_OBSTACLE = {"facecolor": "0.55", "edgecolor": "0.25", "linewidth": 0.8, "zorder": 2}
_MOVER = {"facecolor": "none", "edgecolor": "tab:orange", "linewidth": 1.2, "linestyle": "--"}
ARROW_SECONDS = 2.0  # a bouncing obstacle's arrow shows where it heads in this many seconds


@dataclasses.dataclass(frozen=True)
class RoomShapes:
    """A room from above as plain shapes, in metres: what `draw_room` and `jaxnav.viz.render` draw."""

    walls: np.ndarray  # [4, 2, 2] east, west, north, south wall: centre (x, y), half extents (x, y)
    boxes: np.ndarray  # [Nb, 4, 2] corners of each box, counter-clockwise
    circles: np.ndarray  # [Nc, 3] centre x, y and radius of each cylinder
    spawn: np.ndarray | None  # [3] robot x, y, yaw; None when the spawn is sampled per episode

    @property
    def outer_half(self) -> np.ndarray:
        """[2] half extents of the room with its walls."""
        return (np.abs(self.walls[:, 0]) + self.walls[:, 1]).max(axis=0)


def room_shapes(room: RoomLayout | SceneParams) -> RoomShapes:
    """The shapes of a layout, or of one env's `SceneParams` (active obstacle slots only); the
    occupied cells of a grid obstacle are boxes."""
    if isinstance(room, RoomLayout):
        spawn = None if room.robot_pos is None else np.array([*room.robot_pos, room.robot_yaw])
        cells = room.grid.cell_boxes() if room.grid is not None else (np.zeros((0, 2)),) * 2
        boxes = [*room.boxes, *(Box(c, size) for c, size in zip(*cells, strict=True))]
        return _shapes(0.5 * np.asarray(room.size), boxes, room.cylinders, spawn)
    if not isinstance(room, SceneParams):
        raise TypeError(f"room: must be a RoomLayout or SceneParams, got {type(room).__name__}")
    p = jax.device_get(room)
    if np.shape(p.room_half) != (2,):
        raise ValueError(
            f"room: one env's SceneParams (no batch axis), got room_half of shape {p.room_half.shape}"
        )
    boxes = [
        Box(pos, 2 * half, yaw)
        for pos, half, yaw, on in zip(p.box_pos, p.box_half, p.box_yaw, p.box_active, strict=True)
        if on
    ]
    if p.grid is not None:
        boxes += [Box(c, 2 * half) for c, half in zip(*grid.cell_boxes(p.grid), strict=True)]
    cylinders = [
        Cylinder(pos, radius)
        for pos, radius, on in zip(p.cyl_pos, p.cyl_radius, p.cyl_active, strict=True)
        if on
    ]
    return _shapes(np.asarray(p.room_half), boxes, cylinders, np.asarray(p.spawn))


def _shapes(half, boxes: Sequence[Box], cylinders: Sequence[Cylinder], spawn) -> RoomShapes:
    """Walls of `WALL_THICKNESS` just outside the interior of half extents `half` [2], and the
    obstacles' footprints."""
    hx, hy = half
    t = 0.5 * WALL_THICKNESS
    walls = [
        [(hx + t, 0.0), (t, hy + 2 * t)],
        [(-hx - t, 0.0), (t, hy + 2 * t)],
        [(0.0, hy + t), (hx + 2 * t, t)],
        [(0.0, -hy - t), (hx + 2 * t, t)],
    ]
    return RoomShapes(
        walls=np.array(walls, np.float64),
        boxes=np.array([box_corners(b) for b in boxes], np.float64).reshape(-1, 4, 2),
        circles=np.array([[*c.pos, c.radius] for c in cylinders], np.float64).reshape(-1, 3),
        spawn=spawn,
    )


def draw_room(ax: Axes, room: RoomLayout | SceneParams) -> None:
    """Walls, boxes, cylinders and the robot's spawn (if fixed), top-down, in metres.

    `room` is a layout or one env's `SceneParams` (see `room_shapes`).
    """
    shapes = room_shapes(room)
    for centre, half in shapes.walls:
        ax.add_patch(patches.Rectangle(centre - half, *(2 * half), color="0.2"))
    for corners in shapes.boxes:
        ax.add_patch(patches.Polygon(corners, closed=True, **_OBSTACLE))
    for x, y, radius in shapes.circles:
        ax.add_patch(patches.Circle((x, y), radius, **_OBSTACLE))
    if shapes.spawn is not None:
        draw_robot(ax, shapes.spawn[:2], float(shapes.spawn[2]), color="tab:blue")
    lim = shapes.outer_half + FLOOR_MARGIN
    ax.set_xlim(-lim[0], lim[0])
    ax.set_ylim(-lim[1], lim[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def draw_robot(ax: Axes, xy, yaw: float, color="tab:blue", radius: float = ROBOT_RADIUS) -> None:
    """The robot's base as a disc of `radius` (the Kobuki's) with a tick along its heading."""
    r = radius
    ax.add_patch(patches.Circle(xy, r, fill=False, edgecolor=color, linewidth=1.5, zorder=4))
    tip = (xy[0] + r * math.cos(yaw), xy[1] + r * math.sin(yaw))
    ax.plot([xy[0], tip[0]], [xy[1], tip[1]], color=color, linewidth=1.5, zorder=4)


def draw_movers(ax: Axes, params: SceneParams) -> bool:
    """The moving obstacles of one env's `params` at their positions there (dashed orange
    outlines): a bouncing one with an arrow to where it heads in `ARROW_SECONDS`, one on a path
    with its path, a walker with its line to its goal. Returns whether there was any."""
    p = jax.device_get(params)
    if p.motion is None:
        return False
    nb = len(p.box_pos)
    pos = np.concatenate([p.box_pos, p.cyl_pos])
    active = np.concatenate([p.box_active, p.cyl_active])
    bouncing = active & (np.abs(p.motion.velocity) > 0).any(-1)
    on_path = active & (p.motion.speed > 0)
    if p.motion.walkers is not None:  # people walking to their goals (cylinder slots)
        walking = np.concatenate([np.zeros(nb, bool), p.motion.walkers.speed > 0]) & active
        goal = np.concatenate([np.zeros((nb, 2)), p.motion.walkers.goal])
        on_path = on_path | walking
    for i in np.flatnonzero(bouncing | on_path):
        if i < nb:
            corners = box_corners(Box(pos[i], 2 * p.box_half[i], p.box_yaw[i]))
            ax.add_patch(patches.Polygon(corners, closed=True, zorder=4, **_MOVER))
        else:
            ax.add_patch(patches.Circle(pos[i], p.cyl_radius[i - nb], zorder=4, **_MOVER))
        if bouncing[i]:
            dx, dy = ARROW_SECONDS * p.motion.velocity[i]
            ax.arrow(*pos[i], dx, dy, color="tab:orange", width=0.02, zorder=4)
        else:
            line = p.motion.path[i] if p.motion.speed[i] > 0 else np.stack([pos[i], goal[i]])
            ax.plot(line[:, 0], line[:, 1], color="tab:orange", linestyle=":", zorder=4)
    return bool((bouncing | on_path).any())


def plot_trajectories(
    layout: RoomLayout,
    trajectories: Sequence[np.ndarray],
    collided: Sequence[bool],
    path: str | os.PathLike,
    title: str | None = None,
    goals: Sequence | None = None,
    movers: SceneParams | None = None,
) -> None:
    """Writes a top-down PNG: the room, each episode's path ([T_i, 2] xy arrays, one colour each),
    a start marker and a red X where an episode collided; with `goals` ([2] per episode, the goal
    task), a star in the path's colour at each episode's goal; with `movers` (one episode's
    `SceneParams` at its reset), that episode's moving obstacles where they started
    (`draw_movers`). Draws the first `MAX_PATHS` paths only.
    """
    trajectories = list(trajectories)[:MAX_PATHS]
    fig = Figure(figsize=(6, 6 * layout.size[1] / layout.size[0] + 0.6), layout="constrained")
    ax = fig.add_subplot()
    draw_room(ax, layout)
    moving = movers is not None and draw_movers(ax, movers)
    colors = _path_colors(len(trajectories))
    for xy, hit, color in zip(trajectories, collided, colors, strict=False):
        xy = np.asarray(xy)  # [T, 2]
        ax.plot(xy[:, 0], xy[:, 1], color=color, linewidth=1.2, alpha=0.8, zorder=3)
        ax.plot(*xy[0], marker="o", markersize=4, color=color, zorder=5)
        if hit:
            ax.plot(*xy[-1], marker="X", markersize=9, color="red", markeredgecolor="k", zorder=6)
    for goal, color in zip(goals if goals is not None else [], colors, strict=False):
        ax.plot(*goal, marker="*", markersize=12, color=color, markeredgecolor="k", zorder=6)
    handles = _legend_handles(layout.robot_pos is not None, goals is not None, moving)
    # Below the axes, so it never hides part of the room.
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.08),
        ncol=len(handles),
        fontsize=8,
        frameon=False,
    )
    title = title or f"{layout.name}: {len(trajectories)} episodes"
    ax.set_title(fit_title(title, fig.get_figwidth(), 10), fontsize=10)
    fig.savefig(path, dpi=120)


def fit_title(title: str, width_in: float, fontsize: float) -> str:
    """`title` broken into lines that fit a figure `width_in` inches wide at `fontsize` points
    (a character of the default font is at most ~0.62 em wide), at most 3 lines, then cut."""
    per_line = max(10, int(0.95 * width_in * 72 / (0.62 * fontsize)))
    lines = textwrap.wrap(title, per_line, break_long_words=True) or [""]
    if len(lines) > 3:
        lines = [*lines[:2], textwrap.shorten(" ".join(lines[2:]), per_line, placeholder=" ...")]
    return "\n".join(lines)


def _path_colors(n: int) -> list:
    """n distinct colours (tab20 holds exactly MAX_PATHS)."""
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _legend_handles(spawn: bool, goal: bool = False, moving: bool = False) -> list[Line2D]:
    handles = [
        Line2D([], [], color="0.3", linewidth=1.2, label="path"),
        Line2D([], [], color="0.3", marker="o", linestyle="", markersize=4, label="start"),
        Line2D(
            [],
            [],
            color="red",
            marker="X",
            linestyle="",
            markersize=8,
            markeredgecolor="k",
            label="collision",
        ),
    ]
    if goal:
        handles.append(
            Line2D([], [], color="0.3", marker="*", linestyle="", markersize=10, label="goal")
        )
    if moving:
        handles.append(
            Line2D([], [], color="tab:orange", linestyle="--", label="moving (1st episode)")
        )
    if spawn:
        handles.append(
            Line2D(
                [],
                [],
                color="tab:blue",
                marker="o",
                markerfacecolor="none",
                linestyle="",
                markersize=8,
                label="layout spawn",
            )
        )
    return handles


def read_metrics(csv_path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The training metrics CSV as columns [N] of floats; empty cells read as nan.

    Raises ValueError naming the file if a column of `METRICS_HEADER` is missing.
    """
    with open(csv_path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in METRICS_HEADER if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{os.fspath(csv_path)}: missing columns {', '.join(missing)}")
        rows = list(reader)
    return {c: np.array([_float(r.get(c)) for r in rows], np.float64) for c in reader.fieldnames}


def _float(cell) -> float:
    try:
        return float(cell)
    except (TypeError, ValueError):  # empty cell: no episode has finished yet
        return math.nan


def plot_reward_curve(
    csv_path: str | os.PathLike, png_path: str | os.PathLike, metric: str = "collision"
) -> None:
    """Writes a PNG of mean episode reward and a task metric (default: the collision rate) vs
    env steps from a metrics CSV; without that column, the episode length.

    Rows whose episode_reward is empty or nan (no episode finished yet) are skipped.
    """
    cols = read_metrics(csv_path)
    keep = np.isfinite(cols["episode_reward"]) & np.isfinite(cols["env_steps"])
    steps = cols["env_steps"][keep]
    fig = Figure(figsize=(7, 5.5))  # fixed margins: a layout engine would double the time
    fig.subplots_adjust(left=0.12, right=0.97, bottom=0.09, top=0.94, hspace=0.08)
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(steps, cols["episode_reward"][keep], color="tab:blue", linewidth=1.5)
    top.set_ylabel("mean episode reward")
    top.set_title("Training")
    metric = metric if metric in cols else "episode_length"
    bottom.plot(steps, cols[metric][keep], color="tab:red", linewidth=1.5)
    bottom.set_ylabel("collision rate" if metric == "collision" else metric.replace("_", " "))
    if metric == "collision":
        bottom.set_ylim(-0.02, 1.02)
    bottom.set_xlabel("env steps")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    if not keep.any():
        top.text(0.5, 0.5, "no finished episodes yet", transform=top.transAxes, ha="center")
    fig.savefig(png_path, dpi=120)
