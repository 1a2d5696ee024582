"""Pictures: top-down rooms with episode paths (the paper's Fig. 6/7) and training curves (Fig. 5).

Figures are built on `matplotlib.figure.Figure` with the Agg canvas, never through pyplot, so nothing
is left open in pyplot's global state and no display is needed.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence

import numpy as np
from matplotlib import patches
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from jaxnav.core import robot
from jaxnav.io.layouts import Box, RoomLayout, box_corners

MAX_PATHS = 20  # paths drawn per picture; beyond that they hide each other and the room
WALL_THICKNESS = 0.1  # m, as drawn (the simulated walls have no thickness that matters here)
METRICS_HEADER = (
    "update,env_steps,episode_reward,episode_length,collision_rate,total_loss,policy_loss,"
    "value_loss,entropy,approx_kl,steps_per_second,elapsed_s"
).split(",")

_OBSTACLE = {"facecolor": "0.55", "edgecolor": "0.25", "linewidth": 0.8, "zorder": 2}


def draw_room(ax: Axes, layout: RoomLayout) -> None:
    """Walls, boxes, cylinders and the layout's spawn (if any), top-down, in metres."""
    hx, hy = 0.5 * layout.size[0], 0.5 * layout.size[1]
    t = WALL_THICKNESS
    # Walls as a dark frame around the interior outline.
    ax.add_patch(patches.Rectangle((-hx - t, -hy - t), 2 * (hx + t), 2 * (hy + t), color="0.2"))
    ax.add_patch(patches.Rectangle((-hx, -hy), 2 * hx, 2 * hy, color="white", zorder=1))
    for ob in layout.obstacles:
        if isinstance(ob, Box):
            ax.add_patch(patches.Polygon(box_corners(ob), closed=True, **_OBSTACLE))
        else:
            ax.add_patch(patches.Circle(ob.pos, ob.radius, **_OBSTACLE))
    if layout.robot_pos is not None:
        draw_robot(ax, layout.robot_pos, layout.robot_yaw, color="tab:blue")
    ax.set_xlim(-hx - 3 * t, hx + 3 * t)
    ax.set_ylim(-hy - 3 * t, hy + 3 * t)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def draw_robot(ax: Axes, xy, yaw: float, color="tab:blue") -> None:
    """The Kobuki base as a disc of robot.BASE_RADIUS with a tick along its heading."""
    r = robot.BASE_RADIUS
    ax.add_patch(patches.Circle(xy, r, fill=False, edgecolor=color, linewidth=1.5, zorder=4))
    tip = (xy[0] + r * math.cos(yaw), xy[1] + r * math.sin(yaw))
    ax.plot([xy[0], tip[0]], [xy[1], tip[1]], color=color, linewidth=1.5, zorder=4)


def plot_trajectories(
    layout: RoomLayout,
    trajectories: Sequence[np.ndarray],
    collided: Sequence[bool],
    path: str | os.PathLike,
    title: str | None = None,
) -> None:
    """Writes a top-down PNG: the room, each episode's path ([T_i, 2] xy arrays, one colour each),
    a start marker and a red X where an episode collided. Draws the first `MAX_PATHS` only.
    """
    trajectories = list(trajectories)[:MAX_PATHS]
    fig = Figure(figsize=(6, 6 * layout.size[1] / layout.size[0] + 0.6), layout="constrained")
    ax = fig.add_subplot()
    draw_room(ax, layout)
    colors = _path_colors(len(trajectories))
    for xy, hit, color in zip(trajectories, collided, colors, strict=False):
        xy = np.asarray(xy)  # [T, 2]
        ax.plot(xy[:, 0], xy[:, 1], color=color, linewidth=1.2, alpha=0.8, zorder=3)
        ax.plot(*xy[0], marker="o", markersize=4, color=color, zorder=5)
        if hit:
            ax.plot(*xy[-1], marker="X", markersize=9, color="red", markeredgecolor="k", zorder=6)
    handles = _legend_handles(spawn=layout.robot_pos is not None)
    # Below the axes, so it never hides part of the room.
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.08),
        ncol=len(handles),
        fontsize=8,
        frameon=False,
    )
    ax.set_title(title or f"{layout.name}: {len(trajectories)} episodes", fontsize=10)
    fig.savefig(path, dpi=120)


def _path_colors(n: int) -> list:
    """n distinct colours (tab20 holds exactly MAX_PATHS)."""
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _legend_handles(spawn: bool) -> list[Line2D]:
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
    return {c: np.array([_float(r.get(c)) for r in rows], np.float64) for c in METRICS_HEADER}


def _float(cell) -> float:
    try:
        return float(cell)
    except (TypeError, ValueError):  # empty cell: no episode has finished yet
        return math.nan


def plot_reward_curve(csv_path: str | os.PathLike, png_path: str | os.PathLike) -> None:
    """Writes a PNG of mean episode reward and collision rate vs env steps from a metrics CSV.

    Rows whose episode_reward is empty or nan (no episode finished yet) are skipped.
    """
    cols = read_metrics(csv_path)
    keep = np.isfinite(cols["episode_reward"]) & np.isfinite(cols["env_steps"])
    steps = cols["env_steps"][keep]
    fig = Figure(figsize=(7, 5.5), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(steps, cols["episode_reward"][keep], color="tab:blue", linewidth=1.5)
    top.set_ylabel("mean episode reward")
    top.set_title("Training")
    rate = cols["collision_rate"][keep]
    bottom.plot(steps, rate, color="tab:red", linewidth=1.5)
    bottom.set_ylabel("collision rate")
    bottom.set_ylim(-0.02, 1.02)
    bottom.set_xlabel("env steps")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    if not keep.any():
        top.text(0.5, 0.5, "no finished episodes yet", transform=top.transAxes, ha="center")
    fig.savefig(png_path, dpi=120)
