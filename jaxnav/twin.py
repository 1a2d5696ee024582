"""`python -m jaxnav.twin`: an exported policy on the robot's own code, in classic MuJoCo, no JAX.

    python -m jaxnav.twin --policy policy.npz --layouts scenes/inference_room.json --json twin.json
    python -m jaxnav.twin --policy policy.npz --suite benchmark --episodes 5 --video videos/

A digital twin of the TurtleBot 2i for the last check before the robot: the ROS node's own control
loop (`jaxnav.robot_side.ros_node.ControlLoop`, built by `make_loop` from the node's default
parameters, as `python -m jaxnav.replay` builds it) drives the wheeled Kobuki model
(`scenes/turtlebot2i_wheeled.xml`) in a room built from the layout file, on the CPU. Nothing of
the simulator's own code runs in the loop: the room is MuJoCo geoms made from the layout (true
cylinders, box walls), the depth images are rasterised by MuJoCo's renderer, and the policy reads
them through the robot side as it reads the Astra's.

What is simulated, and how often (the physics timestep is the wheeled model's 5 ms):
- the camera: 30 frames a second, at a phase drawn per episode (the camera and the node's timer
  are not in step), rendered at the Astra's 640x480 with its calibration (fx = fy = 570.3 px;
  other sizes scale it) from the mount the policy was trained with, off by a mount error drawn
  per episode (height +-2 cm, pitch +-3 deg, yaw +-2 deg, uniform: the simulator's ranges; the
  node is given the true mount, or calibrates it at start-up: `TwinConfig.mount`). Depth
  nearer than 0.6 m (the blind zone) or beyond 8 m reads 0, as the Astra reports it; images go to
  the loop as sensor_msgs/Image (16UC1, millimetres, as the Astra driver's image_raw) with a
  CameraInfo, stamped with the twin's clock. The loop keeps only the newest image, so a frame
  that a newer one replaces before any tick reads it changes nothing: those are not rendered
  (`TwinConfig.every_frame` renders and sends them all; the results are the same);
- the node: `ControlLoop.tick` at the policy's rate (its control period, 10 Hz), as the node's
  timer calls it; goal policies get the goal (geometry_msgs/PoseStamped) at the start and
  nav_msgs/Odometry from the simulated pose at 50 Hz (the Kobuki's sensor stream), both in frame
  `odom`, through the node's own handlers;
- the command path (`Drive`): each command reaches the velocity smoother after a latency of 0-2
  control periods drawn per episode; the smoother (kobuki_velocity_smoother at its 20 Hz, with the
  Kobuki's nominal 0.3 m/s^2 and 3.5 rad/s^2, the centre of the simulator's ranges) ramps towards
  it, both components by one factor as that smoother does (the simulator limits each on its own:
  `TwinConfig.smoother_coupled`), and zeroes a target whose input fell silent; the driver applies
  the smoother's last command to the wheels' speed loops, and stops them when none came for 0.6 s
  (cmd_vel_timeout);
- a collision: the robot's disc (the bumper's radius) touching a wall or an obstacle it can meet
  (`jaxnav.core.layout.is_free`, after every physics step; obstacles whose underside is above the
  robot's top are passed under). The simulator tests its 3-D bumper, which meets low obstacles
  and overhangs up to 2-3 cm later than the disc does. An episode ends at its first collision,
  after `steps` control steps, or (goal policies) once the robot's centre is within the
  policy's success radius of the goal.

Metrics are `python -m jaxnav.evaluate`'s (`jaxnav.evaluation.metrics`, coverage and the goal
task's declared metrics), per room, per family (suites) and overall, in the same JSON keys, with
the twin's settings under "twin".
The CPU cost is mostly rendering: `benchmarks/twin.py` measures it and compares the twin with
`jaxnav.evaluate` on the same rooms (docs/deployment.md).

Rendering needs OpenGL (EGL or OSMesa, see `jaxnav.viz.render`); the ROS messages are the ROS 2
Humble definitions of the `rosbags` package (`pip install rosbags`), the types the replay reads.
User mistakes (flags, files, a missing package) end with one `error: ...` line, exit status 2
(the command line: `jaxnav.cli.twin`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections import Counter, deque
from pathlib import Path

import mujoco
import numpy as np

from jaxnav.core.assets import scenes_dir
from jaxnav.core.layout import Cylinder, LayoutError, RoomLayout, expand_grids, is_free
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.io.layouts import check_goal_distance
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import make_loop
from jaxnav.robot_side.ros_node import parse_args as node_args

CLOCK0 = 1000.0  # s on the twin's clock at an episode's start (a zero stamp reads as unset)
WALL_THICKNESS = 0.1  # m of the box walls around the interior
SPAWN_CLEARANCE = 0.3  # m between a drawn spawn's disc and anything (RandomizeConfig's default)
FLOOR_GROUP, SOLID_GROUP = 2, 1  # geom groups the depth camera sees: the floor, walls/obstacles
VIDEO_SIZE = (320, 240)  # px of each of the two views of a video frame
SMOOTHER_SILENCE = 0.5  # s: the smoother's longest wait for input (3 input periods, at most this)
MOUNTS = ("true", "calibrate", "check", "policy")  # `TwinConfig.mount`


class TwinError(ValueError):
    """A user mistake (flag, file, a missing package or OpenGL); one line naming it."""


@dataclasses.dataclass(frozen=True)
class TwinConfig:
    """The twin's settings: episodes, the camera, the command path and the per-episode draws."""

    episodes: int = 5
    """Episodes per room."""
    steps: int = 600
    """Control steps per episode at most (600: 60 s at 10 Hz, evaluate's default)."""
    seed: int = 0
    """Seed of the per-episode draws (episode e of room r draws from (seed, r, e))."""
    width: int = 640
    """Depth image width, px (the Astra's 640x480)."""
    height: int = 480
    """Depth image height, px."""
    focal_px: float = 570.3
    """Focal length at 640 px wide (the Astra's common calibration); scaled with `width`."""
    frame_rate: float = 30.0
    """Depth frames per second."""
    blind_zone: float = 0.6
    """m; nearer depth reads 0 (the Astra's minimum range)."""
    max_depth: float = 8.0
    """m; farther depth reads 0 (no return)."""
    every_frame: bool = False
    """Render and send every frame, also those no tick reads (the same results, 3x the work)."""
    latency_steps: tuple[int, int] = (0, 2)
    """Command latency, control periods, uniform over the range per episode."""
    camera_height_error: float = 0.02
    """Camera height error, m: uniform in +-this per episode."""
    camera_pitch_error: float = math.radians(3.0)
    """Camera pitch error, rad: uniform in +-this per episode."""
    camera_pitch_bias: float = 0.0
    """rad (down +) added to every episode's pitch error: a stand tilted the same way throughout."""
    camera_yaw_error: float = math.radians(2.0)
    """Camera yaw error, rad: uniform in +-this per episode."""
    accel_limit: float = 0.3
    """The velocity smoother's linear acceleration limit, m/s^2 (kobuki_velocity_smoother)."""
    angular_accel_limit: float = 3.5
    """The velocity smoother's angular acceleration limit, rad/s^2."""
    smoother_rate: float = 20.0
    """The velocity smoother's cycles per second (its `frequency`)."""
    smoother_coupled: bool = True
    """kobuki_velocity_smoother's rule: both components' changes shrink by one factor, so going
    from driving to turning takes as long as braking (0.3 m/s^2); False: each component within
    its own limit, as the simulator's drive does (`NavTask.actuate`)."""
    command_timeout: float = 0.6
    """s without a command after which the Kobuki driver stops the wheels (cmd_vel_timeout)."""
    odom_rate: float = 50.0
    """Odometry messages per second (goal policies)."""
    floor_friction: float = 1.0
    """Traction coefficient of the floor (MuJoCo's default)."""
    wall_height: float = 2.5
    """m, at least, of the room's walls: a real room's reach the ceiling, and the simulator's are
    unbounded planes (a layout's `wall_height`, 0.5 m by default, is what pictures draw; the
    camera's upper rays pass over a 0.5 m wall beyond 1.2 m)."""
    mount: str = "true"
    """The camera mount the node reads depth with (its `camera_height`, `tilt_deg`, `calibration`
    parameters): "true": the episode's true height and pitch, as the simulator assumes, no start-up
    calibration; "calibrate": the node's start-up calibration from its first frames, its estimate
    used (`calibration:=use`); "check": the node's default, the policy file's mount checked
    against that estimate (off by more than the tolerance: it refuses to drive); "policy": the
    policy file's mount, off by the mount error, unchecked. The yaw error stays unknown to it."""
    node_flags: tuple[str, ...] = ()
    """Flags of the node (`python -m jaxnav_robot.ros_node`) its loop is built with, as a lab
    would pass them, e.g. ("--blind-hold", "0"); () : the node's defaults."""
    goal_min_distance: float = 1.5
    """Goal policies in rooms without a goal: a goal is drawn at least this far (m) from the spawn
    (the goal task's default), on the free cells the spawn can reach."""

    def __post_init__(self):
        for name in ("episodes", "steps", "width", "height"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        positive = ("focal_px", "frame_rate", "smoother_rate", "command_timeout", "odom_rate")
        for name in (*positive, "max_depth", "floor_friction", "wall_height"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        for name in ("blind_zone", "accel_limit", "angular_accel_limit", "goal_min_distance"):
            if not 0 <= getattr(self, name) < math.inf:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        errors = ("camera_height_error", "camera_pitch_error", "camera_yaw_error")
        for name in errors:
            if not 0 <= getattr(self, name) < 0.5:
                raise ValueError(f"{name}: must be in [0, 0.5), got {getattr(self, name)}")
        if self.mount not in MOUNTS:
            raise ValueError(f"mount: must be one of {', '.join(MOUNTS)}, got {self.mount!r}")
        if not abs(self.camera_pitch_bias) < 0.5:
            raise ValueError(
                f"camera_pitch_bias: must be in (-0.5, 0.5), got {self.camera_pitch_bias}"
            )
        lo, hi = self.latency_steps
        if not 0 <= lo <= hi:
            raise ValueError(f"latency_steps: need 0 <= low <= high, got {self.latency_steps}")

    @property
    def focal(self) -> float:
        """px at this image width."""
        return self.focal_px * self.width / 640


# ------------------------------------------------------------------------------
# The room


def room_model(layout: RoomLayout, cfg: TwinConfig) -> mujoco.MjModel:
    """The wheeled TurtleBot 2i in `layout`'s room: floor, box walls `wall_height` tall around
    the interior, and each obstacle as a box or a cylinder over [bottom, height]. Only the wheels
    and castors touch anything (the floor); collisions are tested on the layout (`is_free`)."""
    spec = mujoco.MjSpec.from_file(str(scenes_dir() / TURTLEBOT2I.wheeled_mjcf))
    spec.visual.global_.offwidth = max(cfg.width, VIDEO_SIZE[0])
    spec.visual.global_.offheight = max(cfg.height, VIDEO_SIZE[1])
    world = spec.worldbody
    world.add_light(pos=[0, 0, 6], dir=[0, 0, -1], diffuse=[0.5] * 3)
    floor = dict(size=[0, 0, 0.05], rgba=[0.85, 0.85, 0.8, 1], group=FLOOR_GROUP)
    world.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, conaffinity=2, **floor)
    world.geoms[-1].friction[0] = cfg.floor_friction
    solid = dict(contype=0, conaffinity=0, group=SOLID_GROUP)
    half = 0.5 * np.asarray(layout.size)
    t, h = WALL_THICKNESS / 2, max(layout.wall_height, cfg.wall_height) / 2
    for axis in (0, 1):
        for side in (-1, 1):
            pos, size = [0.0, 0.0, h], [half[0] + 2 * t, half[1] + 2 * t, h]
            pos[axis], size[axis] = side * (half[axis] + t), t
            world.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, size=size, **solid)
            world.geoms[-1].rgba = [0.7, 0.6, 0.5, 1]
    for ob in expand_grids(layout.obstacles):  # a grid's cells as boxes
        half_h, z = 0.5 * (ob.height - ob.bottom), 0.5 * (ob.height + ob.bottom)
        if isinstance(ob, Cylinder):
            kind, size, quat = mujoco.mjtGeom.mjGEOM_CYLINDER, [ob.radius, half_h, 0], [1, 0, 0, 0]
        else:
            kind, size = mujoco.mjtGeom.mjGEOM_BOX, [ob.size[0] / 2, ob.size[1] / 2, half_h]
            quat = [math.cos(ob.yaw / 2), 0, 0, math.sin(ob.yaw / 2)]
        world.add_geom(type=kind, pos=[*ob.pos, z], size=size, quat=quat, **solid)
        world.geoms[-1].rgba = [0.3, 0.5, 0.8, 1]
    model = spec.compile()
    model.vis.map.znear = 0.05 / model.stat.extent  # nothing is nearer the camera than 5 cm
    model.vis.map.zfar = 50.0 / model.stat.extent
    return model


def camera_quat(pitch: float, yaw: float) -> np.ndarray:
    """[4] MuJoCo camera orientation in the base's frame: looking along +x turned by `yaw` (left
    +) and tilted down by `pitch`; MuJoCo cameras look along their -z with +y up."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    up = np.array([np.sin(pitch) * np.cos(yaw), np.sin(pitch) * np.sin(yaw), np.cos(pitch)])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([np.cross(forward, up), up, -forward]).ravel())
    return quat


def solid_for(layout: RoomLayout, top: float) -> RoomLayout:
    """`layout` without the obstacles whose underside is at or above `top` (m): the robot passes
    under them."""
    kept = tuple(ob for ob in layout.obstacles if ob.bottom < top)
    if len(kept) == len(layout.obstacles):
        return layout
    return dataclasses.replace(layout, obstacles=kept)


# ------------------------------------------------------------------------------
# The command path


def smoother_step(last, target, accel, period: float, coupled: bool = True) -> np.ndarray:
    """One cycle of kobuki_velocity_smoother (decel_factor 1, no robot feedback): [2] the command
    (m/s, rad/s) after `period` s from `last` [2] towards `target` [2], each component changing by
    at most accel [2] x period. `coupled`: both changes shrink by the same factor, so the (v, w)
    change keeps its direction (the smoother's rule); else each is clipped on its own."""
    last, target = np.asarray(last, np.float64), np.asarray(target, np.float64)
    change = target - last
    bound = np.asarray(accel, np.float64) * period
    if not coupled:
        return last + np.clip(change, -bound, bound)
    moving = change != 0
    scale = min([1.0, *(bound[moving] / np.abs(change[moving]))])  # 1 where nothing changes
    return last + scale * change


class Drive:
    """The path of the node's commands to the wheels: `latency` s on the way, the velocity
    smoother's cycles (`cycle`, every `period` s; `coupled`: see `smoother_step`), and the Kobuki
    driver (`wheels`).

    The smoother takes the newest command that has arrived as its target, and a zero target once
    its input has been silent for `silence` s; each cycle it moves its output towards the target
    (`smoother_step`) and publishes it while its input is active or it is still moving. The driver
    holds the last published command, and stops the wheels once none came for `timeout` s."""

    def __init__(self, latency, accel, period, silence, timeout, coupled: bool = True):
        self.latency, self.accel, self.period = latency, np.asarray(accel, np.float64), period
        self.silence, self.timeout, self.coupled = silence, timeout, coupled
        self.queue: deque = deque()  # (arrival s, [2] command) on their way to the smoother
        self.target, self.heard = np.zeros(2), -math.inf  # the smoother's input, when it came
        self.output = np.zeros(2)  # the smoother's last command
        self.sent, self.sent_at = np.zeros(2), -math.inf  # what the driver got last, when

    def command(self, now: float, twist) -> None:
        """The node sends `twist` (forward m/s, yaw rad/s) at `now` s."""
        self.queue.append((now + self.latency, np.asarray(twist, np.float64)))

    def cycle(self, now: float) -> None:
        """One cycle of the smoother at `now` s."""
        while self.queue and self.queue[0][0] <= now + 1e-9:
            self.heard, self.target = self.queue.popleft()
        active = now - self.heard <= self.silence
        if not active:
            self.target = np.zeros(2)
        moving = bool((self.output != self.target).any())
        if moving:
            step = smoother_step(self.output, self.target, self.accel, self.period, self.coupled)
            self.output = step
        if active or moving:
            self.sent, self.sent_at = self.output.copy(), now

    def wheels(self, now: float) -> np.ndarray:
        """[2] the (forward m/s, yaw rad/s) the driver sets the wheels to at `now` s."""
        return self.sent if now - self.sent_at <= self.timeout + 1e-9 else np.zeros(2)


# ------------------------------------------------------------------------------
# Messages


def _typestore():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise TwinError(
            "python -m jaxnav.twin needs the 'rosbags' package for its ROS messages "
            "(pip install rosbags)"
        ) from None
    return get_typestore(Stores.ROS2_HUMBLE)


class Messages:
    """The ROS 2 messages the robot's drivers publish (rosbags' Humble definitions)."""

    def __init__(self):
        self.t = _typestore().types

    def header(self, stamp: float, frame: str):
        sec = math.floor(stamp)
        time_ = self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((stamp - sec) * 1e9))
        return self.t["std_msgs/msg/Header"](stamp=time_, frame_id=frame)

    def image(self, depth_mm: np.ndarray, stamp: float):
        """sensor_msgs/Image of a [H, W] uint16 depth image, millimetres (16UC1)."""
        h, w = depth_mm.shape
        data = np.frombuffer(depth_mm.astype("<u2").tobytes(), np.uint8)
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(stamp, "camera_depth_optical_frame"), height=h, width=w,
            encoding="16UC1", is_bigendian=0, step=2 * w, data=data,
        )  # fmt: skip

    def camera_info(self, focal: float, width: int, height: int, stamp: float):
        """sensor_msgs/CameraInfo of a pinhole camera, principal point at the image's centre."""
        cx, cy = (width - 1) / 2, (height - 1) / 2
        k = np.array([focal, 0, cx, 0, focal, cy, 0, 0, 1], np.float64)
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp, "camera_depth_optical_frame"), height=height, width=width,
            distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).ravel(),
            p=np.concatenate([k.reshape(3, 3), np.zeros((3, 1))], 1).ravel(), binning_x=0,
            binning_y=0, roi=roi,
        )  # fmt: skip

    def pose(self, x: float, y: float, yaw: float):
        t = self.t
        q = t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        )
        point = t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0)
        return t["geometry_msgs/msg/Pose"](position=point, orientation=q)

    def odometry(self, pose, twist, stamp: float):
        """nav_msgs/Odometry in frame odom: pose (x, y, yaw), twist (forward m/s, yaw rad/s)."""
        t, cov = self.t, np.zeros(36)
        vector = t["geometry_msgs/msg/Vector3"]
        moving = t["geometry_msgs/msg/Twist"](
            linear=vector(x=float(twist[0]), y=0.0, z=0.0),
            angular=vector(x=0.0, y=0.0, z=float(twist[1])),
        )
        return t["nav_msgs/msg/Odometry"](
            header=self.header(stamp, "odom"), child_frame_id="base_footprint",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(*pose), covariance=cov),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=moving, covariance=cov),
        )  # fmt: skip

    def goal(self, xy, stamp: float):
        """geometry_msgs/PoseStamped at `xy` in frame odom (what RViz's goal tool sends)."""
        pose = self.pose(xy[0], xy[1], 0.0)
        return self.t["geometry_msgs/msg/PoseStamped"](header=self.header(stamp, "odom"), pose=pose)


# ------------------------------------------------------------------------------
# Episodes


@dataclasses.dataclass(frozen=True)
class Draw:
    """What one episode draws."""

    latency: int
    """Control periods between a command leaving the node and reaching the smoother."""
    camera: tuple[float, float, float]
    """The camera mount's error: height m, pitch rad (+ down), yaw rad (+ left)."""
    phase: float
    """s from the episode's start to the camera's first frame."""
    spawn: tuple[float, float, float]
    """The robot's start: x, y m, yaw rad."""
    goal: tuple[float, float] | None = None
    """Goal policies: the goal, m."""


def draw_episode(layout: RoomLayout, cfg: TwinConfig, rng, radius: float, goals: bool) -> Draw:
    """One episode's latency, mount error, camera phase and spawn (the layout's, else a free
    pose), and with `goals` its goal (the layout's, else drawn, `_goal`)."""
    lo, hi = cfg.latency_steps
    latency = int(rng.integers(lo, hi + 1))
    errors = np.array([cfg.camera_height_error, cfg.camera_pitch_error, cfg.camera_yaw_error])
    camera = rng.uniform(-1.0, 1.0, 3) * errors + (0.0, cfg.camera_pitch_bias, 0.0)
    camera = tuple(float(x) for x in camera)
    phase = float(rng.uniform(0.0, 1.0 / cfg.frame_rate))
    spawn = _spawn(layout, rng, radius)
    goal = _goal(layout, spawn[:2], cfg, rng, radius) if goals else None
    return Draw(latency, camera, phase, spawn, goal)


def _spawn(layout: RoomLayout, rng, radius: float) -> tuple[float, float, float]:
    """The layout's spawn, else a uniform pose whose disc clears everything by SPAWN_CLEARANCE."""
    if layout.robot_pos is not None:
        return (*layout.robot_pos, layout.robot_yaw)
    half = 0.5 * np.asarray(layout.size)
    points = rng.uniform(-half, half, (1024, 2))
    free = np.flatnonzero(is_free(layout, points, radius + SPAWN_CLEARANCE))
    if free.size == 0:
        raise LayoutError(None, "no free spawn for the robot found", room=layout.name)
    return (*points[free[0]].tolist(), float(rng.uniform(-math.pi, math.pi)))


def _goal(layout: RoomLayout, start, cfg: TwinConfig, rng, radius: float):
    """The layout's goal, else a uniform free cell the start can reach at least
    `goal_min_distance` from it (the farthest where none is that far)."""
    if layout.goal_pos is not None:
        return layout.goal_pos
    from jaxnav.core.goals import main_component

    main, centres = main_component(layout, radius)
    cells = centres[main]
    far = np.linalg.norm(cells - np.asarray(start), axis=-1)
    fits = np.flatnonzero(far >= cfg.goal_min_distance)
    pick = rng.choice(fits) if fits.size else int(np.argmax(far))
    return tuple(float(x) for x in cells[pick])


def _quiet(text: str) -> None:
    """The loop's log: its states are counted per tick instead."""


class Twin:
    """One room in classic MuJoCo and the node's loop in it, one episode at a time."""

    def __init__(self, layout: RoomLayout, policy_path, cfg: TwinConfig, video: bool = False):
        self.layout, self.cfg, self.messages = layout, cfg, Messages()
        args, rest = node_args(["--policy", str(policy_path), *cfg.node_flags])
        if rest:
            raise TwinError(f"node_flags: not flags of the node: {' '.join(rest)}")
        self.get = vars(args)
        loop, rate = make_loop(self.get, _quiet)  # checks the policy file first
        self.policy = loop.controller.policy
        self.model = room_model(layout, cfg)
        self.data = mujoco.MjData(self.model)
        self.dt = float(self.model.opt.timestep)
        self.period = 1.0 / rate
        self.sub = self._every(rate, "the policy's control period")
        self.smoother_every = self._every(cfg.smoother_rate, "smoother_rate")
        self.odom_every = self._every(cfg.odom_rate, "odom_rate")
        self._ids()
        self.renderer = _renderer(self.model, cfg.height, cfg.width)
        self.renderer.enable_depth_rendering()
        self.option = mujoco.MjvOption()
        self.option.geomgroup[:] = 0
        self.option.geomgroup[[FLOOR_GROUP, SOLID_GROUP]] = 1  # the room, not the robot
        self.video = _renderer(self.model, VIDEO_SIZE[1], VIDEO_SIZE[0]) if video else None
        if video:  # shadows cost software OpenGL several times the frame
            self.video.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False

    def close(self) -> None:
        """Frees the renderers' OpenGL contexts."""
        for renderer in (self.renderer, self.video):
            if renderer is not None:
                renderer.close()

    def _every(self, rate: float, name: str) -> int:
        """Physics steps per period of `rate` Hz; it must be a whole number of them."""
        steps = round(1.0 / (rate * self.dt))
        if steps < 1 or abs(steps * self.dt * rate - 1.0) > 1e-6:
            raise TwinError(
                f"{name}: {1 / rate:g} s is not a whole number of the wheeled model's "
                f"{self.dt:g} s physics steps"
            )
        return steps

    def _ids(self) -> None:
        m, name = self.model, mujoco.mj_name2id
        self.camera = name(m, mujoco.mjtObj.mjOBJ_CAMERA, "depth")
        acts = ("wheel_left", "wheel_right")
        self.wheel_acts = [name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in acts]
        wheel = name(m, mujoco.mjtObj.mjOBJ_GEOM, "wheel_left")
        self.wheel_radius = float(m.geom_size[wheel, 0])
        bumper = name(m, mujoco.mjtObj.mjOBJ_GEOM, "bumper")
        radius, half = (float(v) for v in m.geom_size[bumper, :2])  # an upright capsule
        self.radius = radius
        self.solid = solid_for(self.layout, float(m.geom_pos[bumper, 2]) + half + radius)

    def mount(self, draw: Draw) -> tuple[float, float, float]:
        """The episode's camera mount: height m, pitch rad (+ down), yaw rad (+ left): the policy
        file's (the mount it was trained with) off by the drawn error."""
        sensor = self.policy.sensor
        height = sensor.camera_height or TURTLEBOT2I.camera_height
        dz, pitch, yaw = draw.camera
        return height + dz, sensor.camera_pitch + pitch, yaw

    def place(self, draw: Draw) -> None:
        """The robot at rest at the spawn, its camera on the episode's mount."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:3] = draw.spawn
        height, pitch, yaw = self.mount(draw)
        m.cam_pos[self.camera] = (TURTLEBOT2I.camera_forward, 0.0, height)
        m.cam_quat[self.camera] = camera_quat(pitch, yaw)
        m.cam_fovy[self.camera] = math.degrees(
            2 * math.atan(0.5 * self.cfg.height / self.cfg.focal)
        )
        mujoco.mj_forward(m, d)

    def loop(self, draw: Draw):
        """The node's loop for the episode, reading depth with the mount `TwinConfig.mount` says."""
        mode = self.cfg.mount
        calibration = {"calibrate": "use", "check": "check"}.get(mode, "off")
        get = {**self.get, "calibration": calibration}
        if mode == "true":
            height, pitch, _ = self.mount(draw)
            get = {**get, "camera_height": height, "tilt_deg": math.degrees(pitch)}
        return make_loop(get, _quiet)[0]

    def frames(self, phase: float) -> set[int]:
        """The physics steps at which a frame is sent: frame k is due at phase + k / frame_rate s
        (at the nearest step); unless `every_frame`, only those that a tick reads before the
        next frame replaces them."""
        total = self.cfg.steps * self.sub
        k = np.arange(math.ceil(total * self.dt * self.cfg.frame_rate) + 2)
        due = np.round((phase + k / self.cfg.frame_rate) / self.dt).astype(int)
        if not self.cfg.every_frame:
            tick = -(-due[:-1] // self.sub) * self.sub  # the first tick at or after each frame
            due = due[:-1][tick < due[1:]]
        return set(due[due < total].tolist())

    def episode(self, draw: Draw, video: list | None = None) -> dict:
        """Runs one episode: {"collided", "success", "steps", "poses" [steps + 1, 3] (x, y m,
        yaw rad at the start and after each control step), "states" (ticks per loop state)};
        with `video`, a frame per control step is appended to it."""
        loop = self.loop(draw)
        self.place(draw)
        cfg = self.cfg
        drive = self.drive(draw)
        frames, states = self.frames(draw.phase), Counter()
        loop.on_camera_info(self.messages.camera_info(cfg.focal, cfg.width, cfg.height, CLOCK0))
        if loop.goal is not None:
            loop.goal.on_goal_msg(self.messages.goal(draw.goal, CLOCK0))
        poses, hit, success = [self.data.qpos[:3].copy()], False, False
        for n in range(cfg.steps):
            hit = self.control_step(n, loop, drive, frames, states)
            poses.append(self.data.qpos[:3].copy())
            if draw.goal is not None and not hit:
                success = math.dist(draw.goal, poses[-1][:2]) <= self.policy.success_radius
            if video is not None:
                video.append(self.video_frame(np.array(poses)[:, :2]))
            if hit or success:
                break
        poses = np.array(poses)
        return dict(collided=hit, success=success, steps=len(poses) - 1, poses=poses, states=states)

    def reading(self, draw: Draw, pose) -> np.ndarray:
        """[D] the sectors the node's loop reads from one frame rendered with the robot at rest
        at `pose` (x, y, yaw) on the episode's mount: for comparing with the simulator's sensor.
        The loop's reader itself: a goal policy's loop acts only with a goal and odometry, and
        stacks frames."""
        loop = self.loop(draw)
        self.place(draw)
        self.data.qpos[:3] = pose
        mujoco.mj_forward(self.model, self.data)
        loop.on_camera_info(
            self.messages.camera_info(self.cfg.focal, self.cfg.width, self.cfg.height, CLOCK0)
        )
        return np.asarray(loop.reader(self.frame(CLOCK0), loop.controller, loop.camera), np.float32)

    def drive(self, draw: Draw) -> Drive:
        """The episode's command path: its latency, the smoother at its rate and limits (waiting
        3 of the node's periods, at most SMOOTHER_SILENCE, for input), the driver's timeout."""
        cfg, period = self.cfg, self.smoother_every * self.dt
        silence = min(3 * self.period, SMOOTHER_SILENCE)
        accel = (cfg.accel_limit, cfg.angular_accel_limit)
        latency, timeout = draw.latency * self.period, cfg.command_timeout
        return Drive(latency, accel, period, silence, timeout, cfg.smoother_coupled)

    def control_step(self, n: int, loop, drive: Drive, frames: set, states: Counter) -> bool:
        """Control step n, its physics steps one by one: a frame where one is due, odometry
        (goal policies), the node's tick at its start, the smoother's cycles, the wheels.
        Returns whether the robot touched anything."""
        m, d, xy = self.model, self.data, np.empty((self.sub, 2))
        for s in range(self.sub):
            k = n * self.sub + s
            now = CLOCK0 + k * self.dt
            if k in frames:
                loop.on_observation(self.frame(now), now)
            if loop.goal is not None and k % self.odom_every == 0:
                loop.on_odometry(self.odometry(now), now)
            if s == 0:
                drive.command(now, loop.tick(now))
                states[loop.state] += 1
            if k % self.smoother_every == 0:
                drive.cycle(now)
            self.set_wheels(drive.wheels(now))
            mujoco.mj_step(m, d)
            xy[s] = d.qpos[:2]
        return not bool(np.all(is_free(self.solid, xy, self.radius)))

    def frame(self, now: float):
        """The depth camera's image now, as the Astra sends it (sensor_msgs/Image, 16UC1)."""
        mujoco.mj_kinematics(self.model, self.data)  # mj_step leaves the poses a step behind
        mujoco.mj_camlight(self.model, self.data)
        self.renderer.update_scene(self.data, self.camera, self.option)
        depth = self.renderer.render()
        seen = (depth >= self.cfg.blind_zone) & (depth <= self.cfg.max_depth)
        return self.messages.image(np.where(seen, np.rint(depth * 1000), 0).astype(np.uint16), now)

    def odometry(self, now: float):
        """nav_msgs/Odometry of the simulated pose and velocity now."""
        x, y, yaw = self.data.qpos[:3]
        vx, vy, w = self.data.qvel[:3]
        forward = vx * math.cos(yaw) + vy * math.sin(yaw)
        return self.messages.odometry((x, y, yaw), (forward, w), now)

    def set_wheels(self, twist) -> None:
        """The wheels' speed targets (rad/s) for (forward m/s, yaw rad/s)."""
        turn = twist[1] * 0.5 * TURTLEBOT2I.wheelbase
        self.data.ctrl[self.wheel_acts] = np.array([twist[0] - turn, twist[0] + turn])
        self.data.ctrl[self.wheel_acts] /= self.wheel_radius

    def video_frame(self, path: np.ndarray) -> np.ndarray:
        """[H, 2W, 3] uint8: the room from above with the path so far, and the robot's view."""
        r, d = self.video, self.data
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)
        walls = max(self.layout.wall_height, self.cfg.wall_height)
        r.update_scene(d, _top_down(self.layout, VIDEO_SIZE[0] / VIDEO_SIZE[1], self.model, walls))
        for a, b in zip(path[:-1], path[1:], strict=True):
            _add_segment(r.scene, (*a, 0.01), (*b, 0.01))
        above = r.render()
        r.update_scene(d, self.camera, self.option)
        return np.concatenate([above, r.render()], axis=1)


def _renderer(model, height: int, width: int) -> mujoco.Renderer:
    """A MuJoCo renderer, or a TwinError where OpenGL cannot render here."""
    try:
        return mujoco.Renderer(model, height, width)
    except Exception as err:  # noqa: BLE001 - whatever the GL stack raises
        backend = os.environ.get("MUJOCO_GL", "default")
        raise TwinError(
            f"MuJoCo's renderer failed with OpenGL backend {backend!r} ({err}); install "
            "libegl1 or libosmesa6"
        ) from None


def _top_down(layout: RoomLayout, aspect: float, model, height: float) -> mujoco.MjvCamera:
    """A free camera looking straight down on the whole room (walls `height` m), +x to the
    right."""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.azimuth, cam.elevation = 90.0, -90.0
    tan = math.tan(math.radians(model.vis.global_.fovy) / 2)
    half = 0.5 * np.asarray(layout.size) + WALL_THICKNESS + 0.3
    cam.distance = height + max(half[1] / tan, half[0] / (tan * aspect))
    return cam


def _add_segment(scene, start, end) -> None:
    """A red line on the floor from `start` to `end` (m) in `scene`, while it has room."""
    if scene.ngeom >= scene.maxgeom:
        return
    geom, kind = scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_CAPSULE
    mujoco.mjv_initGeom(geom, kind, np.zeros(3), np.zeros(3), np.eye(3).ravel(), np.zeros(4))
    mujoco.mjv_connector(geom, kind, 0.02, np.asarray(start, float), np.asarray(end, float))
    geom.rgba[:] = (0.85, 0.2, 0.1, 1.0)
    scene.ngeom += 1


# ------------------------------------------------------------------------------
# Rooms and results


def run_room(policy_path, layout: RoomLayout, index: int, cfg: TwinConfig, video=False) -> dict:
    """`cfg.episodes` episodes in one room: its per-episode arrays ("collided", "steps",
    "distance", "start", "goal", "metrics", "paths" [T + 1, 2], "poses" [T + 1, 3], "draws"),
    "control_period", "states" (ticks per loop state; "episode_states" per episode), "seconds"
    of wall time, and with `video`
    the first episode's "frames"."""
    tick = time.perf_counter()
    twin = Twin(layout, policy_path, cfg, video)
    goals = twin.policy.extra_observations > 0
    runs, frames = [], [] if video else None
    try:
        for e in range(cfg.episodes):
            rng = np.random.default_rng([cfg.seed, index, e])
            draw = draw_episode(layout, cfg, rng, twin.radius, goals)
            runs.append((draw, twin.episode(draw, frames if e == 0 else None)))
    finally:
        twin.close()
    paths = [run["poses"][:, :2] for _, run in runs]
    distance = np.array([np.linalg.norm(np.diff(p, axis=0), axis=-1).sum() for p in paths])
    room = {
        "collided": np.array([run["collided"] for _, run in runs]),
        "steps": np.array([run["steps"] for _, run in runs]),
        "distance": distance,
        "start": np.array([d.spawn[:2] for d, _ in runs]),
        "goal": np.array([d.goal if goals else d.spawn[:2] for d, _ in runs]),
        "metrics": {},
        "paths": paths,
        "poses": [run["poses"] for _, run in runs],
        "draws": [draw for draw, _ in runs],
        "control_period": twin.period,
        "states": sum((run["states"] for _, run in runs), Counter()),
        "episode_states": [run["states"] for _, run in runs],
        "frames": frames,
    }
    if goals:
        success = np.array([run["success"] for _, run in runs], np.float64)
        room["metrics"] = {"success": success, "path_length": distance}
    room["seconds"] = time.perf_counter() - tick
    return room


def _score_room(room: dict, layout: RoomLayout, radius: float, success_radius) -> None:
    """Adds the room's "coverage" and (goal policies) the goal task's declared metrics per
    episode (`GoalEnv.eval_metrics`: success, SPL, time to goal), as evaluate measures them."""
    from jaxnav.core.families import coverage
    from jaxnav.evaluation import declared_values
    from jaxnav.tasks.goal import GoalConfig, GoalEnv

    room["coverage"] = coverage(layout, room["paths"])
    if room["metrics"]:
        task = GoalConfig(success_radius=success_radius)
        room.update(layout=layout, robot_radius=radius, task=task)
        room["declared"] = declared_values(GoalEnv.eval_metrics, room)


def run_twin(
    policy_path, layouts=None, *, suite=None, cfg: TwinConfig = TwinConfig(), video=False, log=None
) -> dict:
    """Runs the twin in each layout (or each room of `suite`): evaluate's results ("layouts",
    "overall", "policy", "physics", "steps", "seed"; with a suite "suite" and "families"), and
    "twin": the settings, "loop_states" (ticks per loop state) and "control_steps_per_s".
    "_rooms" holds each room's `run_room` record (per-episode arrays; with `video`, frames)."""
    from jaxnav.evaluation import load_suite, unique_names

    _ensure_gl()
    if (layouts is None) == (suite is None):
        raise ValueError("layouts, suite: give exactly one of them")
    groups = load_suite(suite) if suite is not None else {}
    layouts = [r for rooms in groups.values() for r in rooms] if suite else list(layouts)
    policy = NumpyPolicy.from_npz(policy_path)
    if policy.success_radius is not None:
        for layout in layouts:
            check_goal_distance(layout, policy.success_radius)
    names, rooms = unique_names(layouts), []
    for i, (name, layout) in enumerate(zip(names, layouts, strict=True)):
        room = run_room(policy_path, layout, i, cfg, video)
        _score_room(room, layout, TURTLEBOT2I.radius, policy.success_radius)
        rooms.append(room)
        if log is not None:
            steps, seconds = room["steps"].sum(), room["seconds"]
            log(f"{name}: {cfg.episodes} episodes, {steps} control steps in {seconds:.0f} s")
    return _results(policy_path, cfg, names, rooms, suite, groups)


def _results(policy_path, cfg: TwinConfig, names, rooms, suite, groups) -> dict:
    """The results of `run_twin` from each room's `run_room` record."""
    from jaxnav.evaluation import pool
    from jaxnav.tasks.goal import GoalEnv

    steps = sum(int(r["steps"].sum()) for r in rooms)
    results = {
        "layouts": {name: pool([room]) for name, room in zip(names, rooms, strict=True)},
        "overall": pool(rooms),
        "policy": str(policy_path),
        "physics": "wheeled",
        "steps": cfg.steps,
        "seed": cfg.seed,
        "twin": dataclasses.asdict(cfg),
        "loop_states": dict(sum((r["states"] for r in rooms), Counter()).most_common()),
        "control_steps_per_s": steps / max(sum(r["seconds"] for r in rooms), 1e-9),
        "_rooms": dict(zip(names, rooms, strict=True)),
        "_eval_metrics": GoalEnv.eval_metrics if rooms[0]["metrics"] else (),
    }
    if suite is not None:
        ends = np.cumsum([0] + [len(v) for v in groups.values()])
        spans = zip(groups, ends[:-1], ends[1:], strict=True)
        results["suite"] = suite
        results["families"] = {family: pool(rooms[a:b]) for family, a, b in spans}
    return results


def _ensure_gl() -> None:
    """Picks an OpenGL backend for MuJoCo's renderer where MUJOCO_GL does not name one."""
    if os.environ.get("MUJOCO_GL"):
        return
    from jaxnav.viz.render import GL_HINT, gl_backend

    if gl_backend() is None:
        raise TwinError(f"no OpenGL backend for MuJoCo's renderer ({GL_HINT})")


def write_videos(results: dict, folder: Path) -> list[Path]:
    """One GIF per room of the first episode's frames (`run_twin(..., video=True)`): the room
    from above with the path so far, and the robot's camera."""
    from jaxnav.evaluation import file_stems, printable
    from jaxnav.viz.render import _write_gif

    rooms = results["_rooms"]
    out = []
    for (name, room), stem in zip(rooms.items(), file_stems(list(rooms)), strict=True):
        outcome = "collision" if room["collided"][0] else "no collision"
        title = f"{printable(name)}: twin, episode 1 ({outcome})"
        fps = round(1 / room["control_period"])
        out.append(_write_gif(room["frames"], folder / f"{stem}.gif", fps, title, 1 / fps))
    return out


if __name__ == "__main__":  # `python -m jaxnav.twin`: the command line
    import sys

    from jaxnav.cli.twin import main

    sys.exit(main())
