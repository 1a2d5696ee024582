"""A short memory of what the camera saw, read back all round the robot.

A depth camera sees 60 degrees ahead and nothing nearer than its range_min (the Astra's 0.6 m): a
robot that drives past an obstacle loses it from view just before it could touch it, and cannot
tell 0.3 m from 0.6 m. The memory keeps each sector's reading of the last `steps` control steps as
a point in the odometry frame (at the reading's depth along the sector's central bearing, from the
camera's position) and reads back, in each of `bins` equal directions round the robot, the
distance from the robot's centre to the nearest remembered point, at most `reach`.

A reading at range_min (the sector the camera cannot read: too near, or no return) or at
range_max (nothing within range) leaves no point. Bin b holds the bearings from
-pi + b * 2 pi / bins to -pi + (b + 1) * 2 pi / bins (rad from the heading, positive = left), so
the first bin is straight behind, turning right, and the middle ones are ahead.

numpy only here; the simulator runs the same functions with `xp` = jax.numpy
(`jaxnav.tasks.goal`), the robot's loop through `Memory`, so both read the same memory from the
same readings and poses.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class MemorySpec:
    """How readings are remembered and read back (stored in the exported .npz as memory_*)."""

    bins: int
    """Directions round the robot, each one observation entry (0: no memory)."""
    steps: int
    """Control steps a sector's reading is remembered, the newest included."""
    reach: float
    """m; a bin with no remembered point nearer reads this."""
    camera_forward: float = 0.0
    """m the camera sits ahead of the robot's centre, along the heading (negative: behind)."""

    def __post_init__(self):
        if self.bins < 0 or (self.bins and self.steps < 1):
            raise ValueError(
                f"memory: need bins >= 0 and steps >= 1, got bins {self.bins}, steps {self.steps}"
            )
        if not 0 < self.reach < math.inf or not math.isfinite(self.camera_forward):
            raise ValueError(
                f"memory: need a finite reach > 0 and camera_forward, got {self.reach}, "
                f"{self.camera_forward}"
            )


def sector_points(sectors, pose, fov: float, range_min: float, range_max: float, forward, xp=np):
    """The points of one frame's sector readings `sectors` [S] (camera depth, m, right to left)
    seen from `pose` (x, y, yaw) in the odometry frame: ([S, 2] x, y; [S] bool, the readings that
    leave a point). A camera of horizontal field of view `fov` (rad) sits `forward` m ahead of the
    robot's centre."""
    n = sectors.shape[-1]
    bearing = ((xp.arange(n) + 0.5) * (fov / n) - 0.5 * fov).astype(sectors.dtype)  # [S] centres
    lateral = sectors * xp.tan(bearing)  # depth along the axis -> the point's side offset
    cos, sin = xp.cos(pose[2]), xp.sin(pose[2])
    x = pose[0] + (forward + sectors) * cos - lateral * sin
    y = pose[1] + (forward + sectors) * sin + lateral * cos
    seen = (sectors > range_min) & (sectors < range_max)
    return xp.stack([x, y], -1), seen


def remember_frame(kept, frame, xp=np):
    """The memory `kept` = (points [steps, S, 2], seen [steps, S], newest first) with `frame`
    = (points [S, 2], seen [S]) (`sector_points`) added first and the oldest frame let go."""
    return tuple(
        xp.concatenate([new[None], old[:-1]]) for new, old in zip(frame, kept, strict=True)
    )


def recall(points, seen, pose, bins: int, reach: float, xp=np):
    """[bins] the distance (m) from the robot at `pose` (x, y, yaw) to the nearest of `points`
    [N, 2] whose `seen` [N] is true in each direction bin (module docstring), `reach` where
    there is none that near."""
    dx, dy = points[:, 0] - pose[0], points[:, 1] - pose[1]
    distance = xp.sqrt(dx * dx + dy * dy)  # [N]
    cos, sin = xp.cos(pose[2]), xp.sin(pose[2])
    ahead, left = cos * dx + sin * dy, cos * dy - sin * dx  # [N] in the robot's frame
    # The bin: how many of its inner edges the bearing has passed, compared as `_turn` values
    # (XLA's CPU backend spent most of the memory's time on an arctangent per point).
    which = (_turn(ahead, left, xp)[:, None] >= _edges(bins)[None, :]).sum(-1)  # [N] 0 .. bins - 1
    # [bins, N]: the points along the minor axis, which XLA's CPU backend reduces in vector lanes
    member = (which[None, :] == xp.arange(bins)[:, None]) & seen[None, :]
    near = xp.where(member, distance[None, :], reach).min(1)
    return xp.minimum(near, reach)


@functools.cache
def _edges(bins: int) -> np.ndarray:
    """[bins - 1] float32 `_turn` values of the bins' inner edges (made once per bin count: the
    robot reads its memory every control step)."""
    edges = -math.pi + (2 * math.pi / bins) * np.arange(1, bins)  # rad
    edges = _turn(np.cos(edges), np.sin(edges), np).astype(np.float32)
    edges.flags.writeable = False  # shared by every call
    return edges


def _turn(ahead, left, xp=np):
    """[...] a value in [0, 4] that grows with the bearing atan2(left, ahead) from -pi (0,
    straight behind, turning right) through 0 (2) to pi (4), from the forward component over
    the sum of both components' sizes: no arctangent."""
    ratio = ahead / xp.maximum(xp.abs(ahead) + xp.abs(left), 1e-30)  # [-1, 1]
    return xp.where(left < 0, 1 + ratio, 3 - ratio)


class Memory:
    """The robot's memory (numpy): `__call__(sectors, pose)` adds a frame and returns the
    [bins] observation, as the simulator computes it (`jaxnav.tasks.goal`), one frame a control
    step."""

    def __init__(self, spec: MemorySpec, fov: float, range_min: float, range_max: float):
        self.spec, self._sensor = spec, (fov, range_min, range_max)
        self._points: np.ndarray | None = None  # [steps, S, 2], newest first
        self._seen: np.ndarray | None = None  # [steps, S]

    def reset(self) -> None:
        """Forget everything (a new goal, an odometry jump, a stop longer than it remembers)."""
        self._points = self._seen = None

    def __call__(self, sectors, pose, remember: bool = True, taken_at=None) -> np.ndarray:
        """[bins] float32 read back at `pose` (x, y, yaw) after remembering `sectors` [S] (m)
        as read from `taken_at` (the pose the frame was taken at; default `pose`); `remember`
        False: a frame already remembered (the camera sent no newer one this step), read back
        from the new pose without adding it again."""
        spec = self.spec
        sectors = np.asarray(sectors, np.float32)
        pose = np.asarray(pose, np.float32)
        if self._points is None:
            self._points = np.zeros((spec.steps, sectors.size, 2), np.float32)
            self._seen = np.zeros((spec.steps, sectors.size), bool)
            remember = True
        if remember:
            seen_from = pose if taken_at is None else np.asarray(taken_at, np.float32)
            forward = np.float32(spec.camera_forward)
            frame = sector_points(sectors, seen_from, *self._sensor, forward)
            self._points, self._seen = remember_frame((self._points, self._seen), frame)
        flat = self._points.reshape(-1, 2)
        out = recall(flat, self._seen.reshape(-1), pose, spec.bins, np.float32(spec.reach))
        return out.astype(np.float32)
