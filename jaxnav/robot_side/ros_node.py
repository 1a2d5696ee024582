"""ROS 2 node: depth image (or LaserScan) -> exported policy -> geometry_msgs/Twist at a fixed rate.

On the robot, in the folder `python -m jaxnav.export RUN --bundle DIR` wrote (numpy and rclpy only):

    python3 -m jaxnav_robot.ros_node --policy policy.npz --ros-args -r cmd_vel:=commands/velocity
    python3 -m jaxnav_robot.ros_node --policy policy.npz --scan --topic /scan \\
        --ros-args -r cmd_vel:=commands/velocity

(`python -m jaxnav.robot_side.ros_node` works too where jaxnav is installed.) The flags set the
defaults of ROS 2 parameters of the same names (policy, topic, scan, cmd_vel, stamped,
camera_info_topic, enable_topic, goal_topic, odom_topic, goal_status_topic, goal_frame_tf,
goal_tf_max_age, header_stamps, goal_point, rate_hz, max_age, speed_calibration,
blind_fraction, readings_per_stray, max_unknown, blind_hold, vfov_deg, band_deg, tilt_deg,
camera_height, calibration, calibration_frames, pitch_tolerance_deg, height_tolerance,
roll_tolerance_deg), which `--ros-args -p` overrides.

What it does (the logic is `ControlLoop` below, which has no ROS in it and is tested alone;
`python -m jaxnav.replay` drives the same loop from a recorded bag):

- A timer at `rate_hz` (default: 1 / the control period the policy file stores, else 10 Hz) sends
  the policy's command for the NEWEST sensor message; messages in between are dropped, not queued.
- It sends zero velocity when that message is older than `max_age` (default 0.25 s), aged from its
  header.stamp where that is set (else from its arrival; `--no-header-stamps`: always from its
  arrival), before the first message, when a stamp is ahead of this computer's clock, when a frame
  is almost all unknown (over `max_unknown`, default 90 %: a covered lens or sunlight; but for
  `blind_hold` s after a frame that measured a surface just beyond range_min it reads everything
  near, as trained, so the robot turns away from a wall that filled the blind zone), when a
  message cannot be converted or the policy fails (logged; it carries on), and while `false` was
  last published on `enable_topic` (std_msgs/Bool, default `~/enable`) until `true` comes.
- Policies trained with several rows (a floor rule) first estimate the camera's mount from the
  floor in their first `calibration_frames` depth frames (`calibrate.StartupCalibration`),
  sending zero velocity meanwhile; with `calibration` check (default) a pitch or height off
  tilt_deg/camera_height by more than `pitch_tolerance_deg`/`height_tolerance`, or a roll beyond
  `roll_tolerance_deg`, keeps it at zero velocity for good, said in one log line; with use it
  reads depth at the estimated mount; off skips it. Its state goes to `/diagnostics`
  (diagnostic_msgs: OK driving, WARN waiting, ERROR a fault) at each change and every second.
- The std_srvs/Trigger service `~/calibrate` runs that calibration again on the running node
  (`ControlLoop.recalibrate`; e.g. after the camera stand was adjusted): zero velocity at once
  and until the next `calibration_frames` frames with floor give the mount, which is then
  checked or used as at start-up. The response says whether the robot may drive, and why, once
  that is decided, or after CALIBRATION_WAIT (10) s that it is not yet (the calibration goes on).
- A policy file that fails its checks (`policy.NumpyPolicy.from_npz`: unreadable, not a regular
  file, NaN weights, absurd commands, wrong sizes) ends the node with one `error: ...` line and
  exit status 2 before any command is sent; so does a bad parameter.
- Ctrl-C (SIGINT) or SIGTERM sends zero velocity, then shuts down. rclpy's own SIGINT handler
  (Humble and later) would shut the ROS context down before any code of ours ran, so rclpy is
  started without it and this node installs its own handlers. Python runs them between callbacks,
  so within one timer period.

Output: `cmd_vel` by default, geometry_msgs/Twist, or with `--stamped` TwistStamped (frame
`base_link`: what Nav2 and newer distributions use). The Kobuki driver (kobuki_ros) takes Twist
on `commands/velocity`: remap (`--ros-args -r cmd_vel:=commands/velocity`), or feed a velocity
mux. The driver stops the base by itself when no command has come for `cmd_vel_timeout_sec`
(0.6 s by default), a second line behind this node's watchdog. Run `kobuki_safety_controller`
beside it (enable it by publishing on its `enable` topic): on a bumper, cliff or wheel-drop event
it commands backing off (0.1 m/s) or a stop on its own `cmd_vel`, which a mux must rank above this
node. The camera's blind zone (nearer than ~0.6 m) reads near (see `observation.reduce_sectors`),
but the bumper is the last resort.

Goal policies (exported from the `goal` task) also need the goal and the robot's pose: a
geometry_msgs/PoseStamped on `goal_topic` (default `goal_pose`, what RViz's "2D Goal Pose" tool
publishes; with `goal_point`, a PointStamped, e.g. RViz's "Publish Point" on /clicked_point) and
nav_msgs/Odometry on `odom_topic` (default `odom`, the Kobuki driver's). A goal in another frame
than the odometry's (e.g. `map`, where a localisation node publishes map -> odom) is placed in
the odometry's frame at every tick with tf2's newest transform (x, y and yaw of
`lookup_transform(odom, map)`, not waited for: `tf2_transforms`), so the robot drives to the map
point while map and odom drift apart; where there is no such transform (none published yet, the
newest over `goal_tf_max_age` s old, tf2_ros not installed, or `goal_frame_tf` false) the goal
is refused with zero velocity, the reason in the goal status and the diagnostics. The node sends
zero velocity before the first goal, when the odometry is older than `max_age`, after an odometry
jump (a step farther or a turn wider than the robot can make, `odometry_jump`) until the odometry
has been consistent for `ODOM_RESUME` messages, and once the robot is within the policy's success
radius of the goal, until a new goal comes (the goal stays reached if the robot drifts out again).
Each tick it publishes the goal's status on `goal_status_topic` (std_msgs/String, default
`goal_status`): "no goal", "driving", "reached", "odometry jump" or "stopped: <why>". A goal
policy with a memory (`robot_side.memory`) remembers each depth frame at the odometry pose of the
frame's time, interpolated between the poses of the last POSE_TRACK odometry messages.

Depth images may be 32FC1 (metres) or 16UC1 (millimetres). Their column angles and ray rows come
from the camera's calibration, the K of sensor_msgs/CameraInfo on `camera_info_topic` (default:
`camera_info` beside the image topic); until one comes (or with K all zero), from `vfov_deg` where
set, else from the policy file's field of view taken to span the image's width. For a policy
trained with one row of rays (a horizontal fan) only image rows within +-band_deg of the horizon
are read; for one trained with several rows (`--sensor.rows 5`) the pixels along its rays are read
and those that see the floor are left out, by the simulator's own rule (`observation.floor_mask`),
which needs the camera's pitch and height (tilt_deg, camera_height; default: the policy file's).
rclpy, tf2_ros and the message packages are imported on `main`'s path only: everything else
here is numpy, and reads messages by their fields (`MessageReader`), so rclpy's messages and
those the `rosbags` library deserialises both work.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import dataclasses
import math
import signal
import sys
from collections.abc import Callable

import numpy as np

from .calibrate import (
    HEIGHT_TOLERANCE,
    MODES,
    PITCH_TOLERANCE_DEG,
    ROLL_TOLERANCE_DEG,
    StartupCalibration,
    Tolerance,
)
from .memory import Memory
from .observation import (
    BLIND_FRACTION,
    MAX_UNKNOWN,
    READINGS_PER_STRAY,
    BlindFrame,
    Controller,
    Intrinsics,
    Sensor,
    Twist,
)
from .policy import FrameStack, NumpyPolicy, goal_observation

STOP = Twist(0.0, 0.0)
DEFAULT_RATE_HZ = 10.0  # the paper's ~10 Hz, where the policy file does not give its control period
# s; a 30 Hz camera has missed ~7 frames by then; the Kobuki driver's own timeout is 0.6 s
DEFAULT_MAX_AGE = 0.25
ASTRA_VFOV_DEG = 49.5  # Orbbec Astra vertical field of view (the simulator has no vertical extent)
# s a header stamp may lead its own arrival: one clock, or clocks kept within milliseconds by
# NTP; a stamp further ahead would keep a stalled sensor's last message fresh that much longer.
MAX_AHEAD = 0.05
# odometry poses kept to place a depth frame at the pose it was taken from (a goal policy's
# memory): 2.5 s of the Kobuki's 50 Hz odometry, more than a frame may age (`max_age`)
POSE_TRACK = 128
OTHER_CLOCK = " (by header.stamp: another clock? header_stamps:=false ages by arrival)"
CMD_FRAME = "base_link"  # the frame of TwistStamped commands (Nav2's robot_base_frame)
# Loop states of a fault (`ControlLoop.diagnosis`: ERROR), as opposed to waiting (WARN).
FAULTS = ("camera mount refused", "sensor blind", "error:", "no sensor message for",
          "sensor messages over", "sensor stamps over")  # fmt: skip
DIAGNOSTICS_PERIOD = 1.0  # s between diagnostic_msgs reports, besides one at each change of state
# s at least between the frames given to the start-up calibration (every third of a 30 Hz camera):
# one costs 10-40 ms, and a camera facing no floor would take most of a core while the robot waits.
CALIBRATION_PERIOD = 0.08
# s a `~/calibrate` request waits for the new estimate before it is answered "not decided" (the
# calibration goes on): 5 frames with floor take 0.4 s at the least.
CALIBRATION_WAIT = 10.0
CALIBRATE_SERVICE = "~/calibrate"  # std_srvs/Trigger: re-calibrate the camera mount
BLIND_ZONE = "blind zone: read near"  # the loop's state while it holds a blind frame as near
BLIND_HOLD = 3.0
"""Default longest time (s) a frame almost all unknown (`BlindFrame`) is read as everything at
range_min after the robot's last readable frame measured a surface within NEAR_MARGIN of
range_min: a surface that came into the camera's blind zone across the whole view, which the
simulator reads as near, so the policy turns away from it. Later, or when the last readable frame
measured nothing that near (a covered lens, sunlight), such a frame stops the robot.

A lens covered near an obstacle turns the robot on "everything near" that long before it stops.

Why 3 s: in the twin (`benchmarks/blind_hold.py`, the gpu preset's goal policy, 6 suite rooms x
12 episodes) the node stopped facing a wall in 5 of 72 episodes without the hold and in 1 with
it; no episode spent more than 1.0 s on the hold, so 1.5 s and 3 s gave the same episodes.
"""
# s a map -> odom transform may be older than the node's clock before a goal placed with it is
# refused (`transform_age`): AMCL republishes it with every scan (stamped 1 s ahead), slam_toolbox
# 50 times a second; odometry drifts ~1-2 % of the distance, so 5 s at 0.5 m/s move a goal a few
# cm, while a localisation that died is noticed.
GOAL_TF_MAX_AGE = 5.0
NEAR_MARGIN = 0.25  # m beyond range_min a readable frame's sector must read to arm BLIND_HOLD
# Odometry steps the robot can make (`odometry_jump`): the Kobuki's top speeds, twice over, for the
# time between two messages (at most ODOM_GAP) plus ODOM_JITTER of stamp or delivery jitter.
TOP_SPEED, TOP_YAW_RATE = 0.7, math.pi  # m/s, rad/s
ODOM_MARGIN = 2.0
ODOM_JITTER = 0.05  # s
ODOM_GAP = 1.0  # s; after a longer silence the robot has been stopped (stale odometry)
ODOM_RESUME = 5  # consistent messages after a jump before the goal is driven to again

# sensor_msgs/Image encodings of depth: (numpy dtype, metres per unit)
DEPTH_ENCODINGS = {
    "32FC1": (np.float32, 1.0),
    "16UC1": (np.uint16, 0.001),
    "mono16": (np.uint16, 0.001),
}


def image_msg_to_array(
    encoding: str, height: int, width: int, data, step: int, is_bigendian: bool = False
) -> np.ndarray:
    """[height, width] float32 depth in metres from sensor_msgs/Image fields.

    `step` is the row length in bytes, which may exceed width * pixel size (padding). 16-bit depth is
    in millimetres; its 0 (no data) stays 0, which the observation counts as unknown.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"image encoding '{encoding}' is not depth; use {sorted(DEPTH_ENCODINGS)}")
    dtype, scale = DEPTH_ENCODINGS[encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if is_bigendian else "<")
    row_bytes = width * dtype.itemsize
    buf = np.frombuffer(bytes(data), np.uint8)
    if step < row_bytes or buf.size < height * step:
        raise ValueError(
            f"image data of {buf.size} bytes, step {step}: too short for {height}x{width} {encoding}"
        )
    rows = buf[: height * step].reshape(height, step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    return pixels.astype(np.float32) * np.float32(scale)


def scan_msg_to_arrays(ranges, angle_min: float, angle_increment: float):
    """(ranges [N] float32 m, angles [N] float64 rad) from sensor_msgs/LaserScan fields."""
    ranges = np.asarray(ranges, np.float32)
    return ranges, angle_min + angle_increment * np.arange(ranges.size)


def header_time(msg) -> float | None:
    """msg.header.stamp in seconds; None where the message has no stamp or it is zero (unset)."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    seconds = stamp.sec + 1e-9 * stamp.nanosec
    return seconds if seconds > 0 else None


def camera_info_intrinsics(msg) -> Intrinsics:
    """The `Intrinsics` of a sensor_msgs/CameraInfo: K (row-major 3x3, fx 0 cx / 0 fy cy / 0 0 1)
    for images of its width x height. A ValueError where K is all zero (an uncalibrated camera) or
    holds no positive, finite focal lengths."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, np.float64).ravel()
    if k.size != 9:
        raise ValueError(f"K has {k.size} values, not 9")
    if not k.any():
        raise ValueError("K is all zero (an uncalibrated camera)")
    fx, cx, fy, cy = (float(v) for v in k[[0, 2, 4, 5]])
    if not (np.isfinite(k).all() and fx > 0 and fy > 0 and msg.width > 0 and msg.height > 0):
        raise ValueError(f"K {k.tolist()} for {msg.width}x{msg.height} images is not a pinhole's")
    return Intrinsics(fx, fy, cx, cy, int(msg.width), int(msg.height))


@dataclasses.dataclass(frozen=True)
class MessageReader:
    """A sensor_msgs/Image (depth) or sensor_msgs/LaserScan message -> the policy's observation."""

    scan: bool = False
    """The messages are LaserScans; otherwise depth images (32FC1 metres or 16UC1 millimetres)."""
    vfov_deg: float = math.nan
    """Without a camera calibration: the depth image's vertical field of view, deg (square pixels,
    principal point at the centre); NaN: the policy's horizontal field of view spans the image."""
    band_deg: float = 2.0
    """One-row policies: only image rows within +-band_deg of the horizon are read
    (`Intrinsics.horizon_rows`); 0: all rows. Policies trained with several rows read the pixels
    of their rays, floor left out (`observation.ray_pixels`, `floor_mask`)."""
    tilt_deg: float = math.nan
    """Camera pitch, deg, positive = looking down; NaN: the policy file's (0 for older files)."""
    camera_height: float = math.nan
    """Camera height above the floor, m (the floor rule of several-row policies); NaN: the policy
    file's."""

    def __post_init__(self):
        if not (math.isnan(self.vfov_deg) or 0 < self.vfov_deg < 180):
            raise ValueError(f"vfov_deg: must be in (0, 180), got {self.vfov_deg}")
        if not self.band_deg >= 0:
            raise ValueError(f"band_deg: must be >= 0, got {self.band_deg}")
        if not (math.isnan(self.camera_height) or self.camera_height > 0):
            raise ValueError(f"camera_height: must be > 0 m, got {self.camera_height}")

    def mount(self, sensor: Sensor) -> Sensor:
        """`sensor` with this reader's camera pitch and height where they are set."""
        changes = {}
        if not math.isnan(self.tilt_deg):
            changes["camera_pitch"] = math.radians(self.tilt_deg)
        if not math.isnan(self.camera_height):
            changes["camera_height"] = self.camera_height
        return dataclasses.replace(sensor, **changes)

    def camera(self, given: Intrinsics | None, height: int, width: int, sensor) -> Intrinsics:
        """The calibration to read a height x width image with: `given` (camera_info's; a
        ValueError if it is for another size), else from vfov_deg, else the policy's fov."""
        if given is not None:
            given.fits(height, width)
            return given
        if not math.isnan(self.vfov_deg):
            return Intrinsics.from_vfov(width, height, math.radians(self.vfov_deg))
        return Intrinsics.from_hfov(width, height, sensor.fov)

    def __call__(self, msg, controller: Controller, camera: Intrinsics | None = None):
        """[num_sectors] float32 observation of `msg` for `controller`'s policy and settings;
        `camera`: the depth camera's calibration (CameraInfo), where known."""
        if self.scan:
            ranges, angles = scan_msg_to_arrays(msg.ranges, msg.angle_min, msg.angle_increment)
            return controller.scan_obs(ranges, angles)
        depth = image_msg_to_array(
            msg.encoding, msg.height, msg.width, msg.data, msg.step, bool(msg.is_bigendian)
        )
        sensor = self.mount(controller.policy.sensor)
        camera = self.camera(camera, *depth.shape, sensor)
        if len(sensor.elevations) > 1:
            return controller.image_obs(depth, camera=camera, sensor=sensor)
        rows = None
        if self.band_deg > 0:
            rows = camera.horizon_rows(self.band_deg, sensor.camera_pitch)
        return controller.image_obs(depth, rows, camera.column_angles(), sensor=sensor)


def control_rate(policy, rate_hz: float | None = None) -> float:
    """Ticks per second: `rate_hz` if given, else 1 / the policy's control period, else 10."""
    if rate_hz is None:
        period = getattr(policy, "control_period", None)
        rate_hz = DEFAULT_RATE_HZ if period is None else 1.0 / period
    if not rate_hz > 0:
        raise ValueError(f"rate_hz: must be > 0, got {rate_hz}")
    return float(rate_hz)


def _stderr(text: str) -> None:
    print(text, file=sys.stderr)


def yaw_of(q) -> float:
    """Yaw (rad) of a geometry_msgs/Quaternion."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def odometry_jump(before, after, dt: float) -> str | None:
    """What is wrong with odometry pose `after` (x, y, yaw) dt s after `before`: a step or turn
    beyond what the robot can make (ODOM_MARGIN times its top speeds, over min(dt, ODOM_GAP) +
    ODOM_JITTER s), or a pose that is not finite; None where it can follow."""
    span = min(max(dt, 0.0), ODOM_GAP) + ODOM_JITTER
    moved = math.dist(before[:2], after[:2])
    turned = abs(math.remainder(after[2] - before[2], math.tau))
    if moved <= ODOM_MARGIN * TOP_SPEED * span and turned <= ODOM_MARGIN * TOP_YAW_RATE * span:
        return None  # NaN fails both tests: a jump
    return f"{moved:.2f} m and {math.degrees(turned):.0f} deg in {dt:.3g} s"


def transform_points(transform, points) -> np.ndarray:
    """[..., 2] `points` (x, y; m) of frame A in frame B, where `transform` (x, y, yaw; m, rad)
    is A's origin and heading in B: the rotation by yaw, then the translation (the 2-D part of a
    tf2 lookup_transform(B, A))."""
    x, y, yaw = (float(v) for v in transform)
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s], [s, c]])  # [2, 2]
    return np.asarray(points, np.float64) @ rotation.T + np.array([x, y])


def planar_transform(msg) -> tuple[float, float, float]:
    """(x, y, yaw) of a geometry_msgs/Transform: its translation's x, y and its rotation's yaw
    (z, roll and pitch are left out: the robot drives on the floor)."""
    t = msg.translation
    return float(t.x), float(t.y), yaw_of(msg.rotation)


def no_transforms(why: str) -> Callable[[str, str], tuple[float, float, float]]:
    """A `GoalInput.transforms` that has none, saying `why`."""

    def lookup(target: str, source: str):
        raise LookupError(why)

    return lookup


class GoalInput:
    """The goal task's inputs on the robot: the newest goal and odometry pose.

    A goal in another frame than the odometry's (e.g. `map`) is placed in the odometry's frame
    at every `problem` call (each control tick) with the newest transform of
    `transforms(target, source) -> (x, y, yaw)` (the node's: tf2's, `tf2_transforms`), so the
    robot drives to the goal's point in its own frame while that frame drifts against the
    odometry's; where `transforms` is None or raises, the goal is refused, with the reason.
    """

    def __init__(self, transforms: Callable[[str, str], tuple[float, float, float]] | None = None):
        self.transforms = transforms
        self.goal: tuple[float, float] | None = None  # as given, in goal_frame
        self.goal_frame: str | None = None
        self.target: tuple[float, float] | None = None  # the goal in the odometry's frame
        self.pose: tuple[float, float, float] | None = None  # x, y, yaw
        self.pose_frame: str | None = None
        self.pose_stamp = -math.inf  # when the pose was measured
        self.pose_received = -math.inf  # when it arrived (its stamp may not lead this)
        self.reached = False  # latched at the goal until a new goal comes
        self.jump: str | None = None  # the odometry jump waited out, until ODOM_RESUME steady
        self.jumps = 0  # odometry jumps seen (a goal policy's memory forgets at each)
        self._steady = 0  # consistent odometry messages since the jump
        self._track: collections.deque = collections.deque(maxlen=POSE_TRACK)  # (stamp, pose)

    def on_goal(self, x: float, y: float, frame: str | None = None) -> None:
        """A new goal position (m) in `frame`: to be driven to, even where it equals the last."""
        self.goal, self.goal_frame, self.reached = (float(x), float(y)), frame, False

    def on_pose(self, x: float, y: float, yaw: float, stamp: float, frame=None, received=None):
        """The robot's pose (m, rad) in `frame`, measured at `stamp` (s) and received at
        `received` (default: stamp). Taken as it is: `on_odom_msg` checks for jumps."""
        self.pose, self.pose_frame, self.pose_stamp = (float(x), float(y), float(yaw)), frame, stamp
        self.pose_received = stamp if received is None else received
        if self._track and stamp <= self._track[-1][0]:
            if stamp < self._track[-1][0]:  # out of order, or a clock set back
                self._track.clear()
            else:  # the same stamp again: the newer pose stands for it
                self._track.pop()
        self._track.append((stamp, self.pose))

    def pose_at(self, stamp: float) -> tuple[float, float, float] | None:
        """The odometry pose at `stamp` (s): interpolated between the two kept poses measured
        around it (the last POSE_TRACK, since the last jump); the oldest kept before them, the
        newest after."""
        track = self._track
        if not track or stamp >= track[-1][0]:
            return self.pose
        i = bisect.bisect_right(track, stamp, key=lambda kept: kept[0])
        if i == 0:
            return track[0][1]
        (t0, a), (t1, b) = track[i - 1], track[i]
        w = (stamp - t0) / (t1 - t0)
        turn = math.remainder(b[2] - a[2], math.tau)  # the shorter way round, as odometry_jump
        return (a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), a[2] + w * turn)

    def on_goal_msg(self, msg) -> None:
        """A geometry_msgs/PoseStamped goal (its position; the orientation is not used) or
        PointStamped (RViz's "Publish Point", `--goal-point`)."""
        p = msg.point if hasattr(msg, "point") else msg.pose.position
        self.on_goal(p.x, p.y, msg.header.frame_id)

    def on_odom_msg(self, msg, stamp: float, received: float | None = None) -> None:
        """A nav_msgs/Odometry message measured at `stamp` (s; received then, unless `received`):
        the robot's pose, checked against the previous one (`odometry_jump`)."""
        pose = msg.pose.pose
        x, y, yaw = pose.position.x, pose.position.y, yaw_of(pose.orientation)
        self._follow((x, y, yaw), stamp)
        self.on_pose(x, y, yaw, stamp, msg.header.frame_id, received)

    def _follow(self, pose, stamp: float) -> None:
        """A jump from the previous pose starts a wait; ODOM_RESUME consistent messages end it."""
        if self.pose is None:
            return
        jump = odometry_jump(self.pose, pose, stamp - self.pose_stamp)
        if jump is not None:
            self.jump, self._steady, self.jumps = jump, 0, self.jumps + 1
            self._track.clear()  # no pose is interpolated across the jump
        elif self.jump is not None:
            self._steady += 1
            if self._steady >= ODOM_RESUME:
                self.jump = None

    def problem(self, now: float, max_age: float, success_radius: float) -> str | None:
        """Why the robot must not drive now (None: it may); latches "goal reached"."""
        if self.goal is None:
            return "no goal yet"
        if self.pose is None:
            return "no odometry yet"
        if self.pose_stamp - self.pose_received > MAX_AHEAD:
            return f"odometry stamps over {MAX_AHEAD:g} s ahead of this clock{OTHER_CLOCK}"
        if now - self.pose_stamp > max_age:
            return f"no odometry for over {max_age:g} s"
        unplaced = self._place()
        if unplaced:
            return unplaced
        if self.jump is not None:
            return f"odometry jump of {self.jump}: waiting for {ODOM_RESUME} consistent messages"
        self.reached = self.reached or math.dist(self.target, self.pose[:2]) <= success_radius
        return "goal reached" if self.reached else None

    def _place(self) -> str | None:
        """Sets `target`, the goal in the odometry's frame (through `transforms` where the goal
        is in another); why it cannot be placed (`target` None), or None. An empty frame is the
        odometry's."""
        self.target = self.goal
        if not (self.goal_frame and self.pose_frame) or self.goal_frame == self.pose_frame:
            return None
        self.target = None
        frames = f"goal in frame '{self.goal_frame}', odometry in '{self.pose_frame}'"
        if self.transforms is None:
            return frames
        try:
            target = transform_points(self.transforms(self.pose_frame, self.goal_frame), self.goal)
            if not np.isfinite(target).all():
                raise ValueError(f"not finite: the goal at {target.tolist()}")
        except Exception as err:  # noqa: BLE001 - tf2 raises several kinds; each refuses
            return f"{frames}: no transform ({' '.join(str(err).split()) or type(err).__name__})"
        self.target = (float(target[0]), float(target[1]))
        return None


class ControlLoop:
    """Keeps the newest sensor message; each `tick` sends the policy's command for it, or STOP.

    STOP (zero velocity) is sent when the loop is shut down or paused (`set_enabled`), before the
    first message, when the newest message is more than `max_age` s old at the tick (the camera
    or its driver stalled), when it cannot be read, is almost all unknown (`BlindFrame`, unless
    `blind_hold` reads it near: `_sectors`) or the policy fails on it (the error is logged and the
    loop carries on with the next message), and for goal policies whenever `GoalInput.problem` says
    so, and while the camera mount is being calibrated (at start-up, and again after `recalibrate`)
    or was refused. A message is read and acted on once, at the first tick that uses it; later
    ticks repeat its command while it is fresh. Each change of state is logged once. Times are
    seconds on any one clock (the node's, or a bag's receipt times). A message's age counts from
    its arrival, or with `header_stamps` from its header.stamp where that is set (not zero); a
    stamp more than MAX_AHEAD s ahead of its arrival is refused. `reader(msg, controller,
    camera)` turns a message into the observation (`camera`: the calibration from
    `on_camera_info`, or None).

    After each tick, `obs` is the observation acted on (None when it sent STOP) and `state` says why:
    "policy", BLIND_ZONE (the policy acting on a blind frame read near) or the reason for stopping.
    """

    def __init__(
        self,
        controller: Controller,
        reader: Callable[..., np.ndarray],
        max_age: float = DEFAULT_MAX_AGE,
        log: Callable[[str], None] = _stderr,
        goal: GoalInput | None = None,
        header_stamps: bool = False,
        calibration: StartupCalibration | None = None,
        blind_hold: float = BLIND_HOLD,
    ):
        if not max_age > 0:
            raise ValueError(f"max_age: must be > 0 s, got {max_age}")
        if not blind_hold >= 0:
            raise ValueError(f"blind_hold: must be >= 0 s, got {blind_hold}")
        self.controller, self.reader, self.max_age, self.log = controller, reader, max_age, log
        self.goal = goal  # the goal task's inputs; None for policies without them
        self.header_stamps = header_stamps
        self.calibration = calibration  # the start-up mount check of depth images; None: none
        self.blind_hold = blind_hold  # s a blind frame reads near after a near one (BLIND_HOLD)
        self._near_at = -math.inf  # when the last readable frame measuring a near surface was taken
        self._calibrated_at = -math.inf  # when the last frame went to the calibration
        self.camera: Intrinsics | None = None  # the depth camera's calibration, once known
        self.enabled = True
        self._last = np.zeros(2, np.float32)  # the last command sent, in the policy's units
        policy = controller.policy
        self._frames = FrameStack(getattr(policy, "history", 0))
        spec = getattr(policy, "memory", None)  # the goal policy's memory, if it has one
        self._memory = None
        if spec is not None:
            sensor = policy.sensor
            self._memory = Memory(spec, sensor.fov, sensor.range_min, sensor.range_max)
            # the seconds it remembers: a longer stop leaves nothing it may keep
            self._memory_span = spec.steps * (getattr(policy, "control_period", None) or 0.1)
        self._remembered = None  # the stamp of the sensor message the memory took last
        self._jumps = 0  # the odometry jumps the memory has been emptied for
        self._stopped_at: float | None = None  # since when the robot is told to stop
        self._goal_seen = None  # the goal the stacked frames belong to
        self.obs: np.ndarray | None = None
        self.state = "no sensor message yet"
        self._msg, self._stamp, self._received, self._result = None, -math.inf, -math.inf, None
        self._camera_refused = None  # the last camera_info problem logged
        self._down = False

    def taken_at(self, msg, received: float) -> float:
        """When msg was measured (s): its header.stamp with `header_stamps` where set, else
        `received`."""
        stamp = header_time(msg) if self.header_stamps else None
        return received if stamp is None else stamp

    def on_observation(self, msg, stamp: float) -> None:
        """Keeps `msg`, received at `stamp` (s), as the newest reading, replacing the previous one."""
        self._msg, self._received, self._result = msg, stamp, None
        self._stamp = self.taken_at(msg, stamp)
        due = stamp - self._calibrated_at >= CALIBRATION_PERIOD
        if self.calibration is not None and not self.calibration.done and due:
            self._calibrated_at = stamp
            self._calibrate(msg)

    def _calibrate(self, msg) -> None:
        """Gives a depth image to the start-up calibration; once it has decided, logs the
        estimate and, where it is to be used, reads later images with it."""
        try:
            depth = image_msg_to_array(
                msg.encoding, msg.height, msg.width, msg.data, msg.step, bool(msg.is_bigendian)
            )
            sensor = self.reader.mount(self.controller.policy.sensor)
            camera = self.reader.camera(self.camera, *depth.shape, sensor)
            cal = self.calibration
            cal.add(depth, camera, sensor.camera_pitch, sensor.camera_height)
        except Exception:  # noqa: BLE001 - the tick that reads this message reports it
            return
        if not cal.done:
            return
        self.log(f"camera mount: {cal.mount.describe()}")
        if cal.mode == "use" and cal.problem is None:
            pitch, height = math.degrees(cal.mount.pitch), cal.mount.height
            self.reader = dataclasses.replace(self.reader, tilt_deg=pitch, camera_height=height)

    def recalibrate(self) -> tuple[bool, str] | None:
        """Calibrates the camera mount again, as at start-up (the node's `~/calibrate`): zero
        velocity until the next `calibration_frames` frames with floor give the mount, which is
        then checked or used by the `calibration` mode. None: started, or already under way
        (`calibration_answer` gives the outcome); else (False, why it cannot run)."""
        cal = self.calibration
        if cal is None:
            return False, "no camera mount to calibrate: scans and one-row policies read no floor"
        if cal.mode == "off":
            return False, "calibration is off (calibration:=check or calibration:=use)"
        if cal.done:
            cal.restart()
            self.log(f"re-calibrating the camera mount from the next {cal.frames} frames")
        return None

    def calibration_answer(self, asked: float, now: float) -> tuple[bool, str] | None:
        """The answer at `now` (s) to a `recalibrate` request made at `asked`: (whether the robot
        may drive, why) once the calibration has decided, (False, ...) while it is still
        undecided CALIBRATION_WAIT s later; None: not yet."""
        cal = self.calibration
        outcome = cal.outcome()
        if outcome is None and now - asked >= CALIBRATION_WAIT:
            outcome = False, f"undecided after {CALIBRATION_WAIT:g} s, stopped: {cal.waiting()}"
        return outcome

    def on_odometry(self, msg, received: float) -> None:
        """A nav_msgs/Odometry message received at `received` (s), for the goal inputs."""
        self.goal.on_odom_msg(msg, self.taken_at(msg, received), received)

    def on_camera_info(self, msg) -> None:
        """A sensor_msgs/CameraInfo: its K places the depth image's columns and ray rows from now
        on (`camera_info_intrinsics`); one that cannot be used is logged once and ignored."""
        try:
            camera = camera_info_intrinsics(msg)
        except Exception as err:  # noqa: BLE001 - a bad message must not end the node
            if str(err) != self._camera_refused:
                self.log(f"camera_info not used: {err}")
                self._camera_refused = str(err)
            return
        if camera != self.camera:
            self.camera, self._result, self._camera_refused = camera, None, None
            c = camera
            self.log(
                f"camera_info: fx {c.fx:.1f}, fy {c.fy:.1f}, cx {c.cx:.1f}, cy {c.cy:.1f} px "
                f"for {c.width}x{c.height} images"
            )

    def set_enabled(self, enabled: bool) -> None:
        """False: STOP at every tick until True (std_msgs/Bool on the enable topic)."""
        self.enabled = bool(enabled)

    def tick(self, now: float) -> Twist:
        """The command to send at time `now` (s)."""
        if self._memory is not None and self._stopped_at is not None:
            if now - self._stopped_at > self._memory_span:  # older than it may be
                self._memory.reset()
        obs, twist, state = self._decide(now)
        if obs is None:  # the robot is told to stop: the goal task's last command is zero
            self._last = np.zeros(2, np.float32)  # and its next frame starts a fresh stack
            self._frames.reset()
            self._stopped_at = now if self._stopped_at is None else self._stopped_at
        else:
            self._stopped_at = None
        if state != self.state:
            self.log(f"{state}: {'driving' if obs is not None else 'sending zero velocity'}")
        self.obs, self.state = obs, state
        return twist

    def diagnosis(self) -> tuple[int, str, dict[str, str]]:
        """(level, message, values) of the loop after the last tick, for diagnostic_msgs: level 0
        (OK) while the policy drives, 2 (ERROR) while a fault keeps the robot stopped (FAULTS:
        a refused camera mount, a blind, stale or unreadable sensor), else 1 (WARN: waiting for
        data, calibrating, paused, a goal's state); the message is `state`; the values give the
        camera mount the depth is read with and the start-up estimate."""
        level = 0 if self.state == "policy" else 2 if self.state.startswith(FAULTS) else 1
        values = {}
        if not self.reader.scan:
            sensor = self.reader.mount(self.controller.policy.sensor)
            values["tilt_deg"] = f"{math.degrees(sensor.camera_pitch):.2f}"
            values["camera_height"] = f"{sensor.camera_height}"
        cal = self.calibration
        if cal is not None and cal.mount is not None:
            values["calibration"] = f"{cal.mode}: {cal.mount.describe()}"
        return level, self.state, values

    def goal_status(self) -> str:
        """The goal's status after the last tick: "no goal", "driving", "reached", "odometry
        jump", or "stopped: " and the loop's state."""
        goal = self.goal
        if goal is None or goal.goal is None:
            return "no goal"
        if goal.reached:
            return "reached"
        if goal.jump is not None:
            return "odometry jump"
        return "driving" if self.obs is not None else f"stopped: {self.state}"

    def shutdown(self) -> Twist:
        """Stops for good: returns STOP, and every later tick sends STOP too."""
        self._down = True
        return self.tick(math.inf)  # the time does not matter once down

    def _decide(self, now: float):
        if self._down:
            return None, STOP, "shut down"
        if not self.enabled:
            return None, STOP, "paused (false on the enable topic)"
        if self._msg is None:
            return None, STOP, "no sensor message yet"
        stale = self._staleness(now)
        if stale:
            return None, STOP, stale
        mount = self._mount_state()
        if mount:
            return None, STOP, mount
        if self.goal is not None:  # the pose moves between frames: act at every tick
            radius = self.controller.policy.success_radius
            why = self.goal.problem(now, self.max_age, radius)
            return (None, STOP, why) if why else self._act(self._msg, now)
        if self._frames.history:  # stacked frames: one a tick, as the simulator stacks them
            return self._act(self._msg, now)
        if self._result is None:
            self._result = self._act(self._msg, now)
        return self._result

    def _mount_state(self) -> str | None:
        """Why the camera mount keeps the robot stopped (calibrating, or refused); None: it
        does not."""
        cal = self.calibration
        if cal is None or cal.mode == "off":
            return None
        if not cal.done:
            return cal.waiting()
        return cal.refusal() if cal.problem else None

    def _staleness(self, now: float) -> str | None:
        """Why the newest sensor message is too old (or too new) to act on at `now`; None: fresh."""
        if self._stamp - self._received > MAX_AHEAD:
            return f"sensor stamps over {MAX_AHEAD:g} s ahead of this clock{OTHER_CLOCK}"
        if now - self._stamp <= self.max_age:
            return None
        if self._received - self._stamp > self.max_age:
            return f"sensor messages over {self.max_age:g} s old on arrival{OTHER_CLOCK}"
        return f"no sensor message for over {self.max_age:g} s"

    def _act(self, msg, now: float):
        try:
            obs, state = self._sectors(msg, now)
            # The goal policy's inputs; an avoid policy's stacked frames (with no history: obs).
            obs = self._goal_obs(obs) if self.goal is not None else self._frames(obs)
            return obs, self.controller.act(obs), state
        except BlindFrame as err:
            return None, STOP, f"sensor blind: {err}"
        except Exception as err:  # noqa: BLE001 - any failure must stop the robot, not the node
            return None, STOP, f"error: {type(err).__name__}: {err}"

    def _sectors(self, msg, now: float) -> tuple[np.ndarray, str]:
        """(the sectors of `msg`, the loop's state acting on them). A blind frame (`BlindFrame`)
        within `blind_hold` s of a readable frame with a sector measured within NEAR_MARGIN of
        range_min reads range_min in every sector, as the simulator reads a surface nearer than
        range_min across the view (BLIND_HOLD); otherwise it is raised."""
        sensor = self.controller.policy.sensor
        try:
            sectors = np.asarray(self.reader(msg, self.controller, self.camera), np.float32)
        except BlindFrame:
            if now - self._near_at > self.blind_hold:
                raise
            return np.full(sensor.num_sectors, sensor.range_min, np.float32), BLIND_ZONE
        # above range_min: measured, not made near by the blind share (`reduce_sectors`)
        measured = (sectors > sensor.range_min) & (sectors <= sensor.range_min + NEAR_MARGIN)
        self._near_at = self._stamp if measured.any() else -math.inf
        return sectors, "policy"

    def _goal_obs(self, sectors: np.ndarray) -> np.ndarray:
        """The goal policy's stacked observation of `sectors`, the pose, the goal and the last
        command; records the command the policy sends for it."""
        policy = self.controller.policy
        given = (self.goal.goal, self.goal.goal_frame)  # not its drifting place in odom
        if given != self._goal_seen:  # a new goal: a new episode
            self._frames.reset()
            self._goal_seen = given
            if self._memory is not None:
                self._memory.reset()
        if self._memory is not None and self.goal.jumps != self._jumps:  # another odometry
            self._memory.reset()
            self._jumps = self.goal.jumps
        obs = self._frames(
            goal_observation(
                sectors, self.goal.pose, self.goal.target, self._last, policy.command_scale
            )
        )
        if self._memory is not None:  # a message is remembered once, at the pose it was taken at
            new, self._remembered = self._stamp != self._remembered, self._stamp
            taken_at = self.goal.pose_at(self._stamp)  # also for a frame after a reset
            recalled = self._memory(sectors, self.goal.pose, remember=new, taken_at=taken_at)
            obs = np.concatenate([obs, recalled])
        self._last = policy.command(obs)
        return obs


def twist_msg(twist: Twist, msg_cls):
    """A geometry_msgs/Twist (`msg_cls`) holding the command."""
    msg = msg_cls()
    msg.linear.x, msg.angular.z = float(twist.linear), float(twist.angular)
    return msg


def twist_stamped_msg(twist: Twist, msg_cls, stamp, frame_id: str = CMD_FRAME):
    """A geometry_msgs/TwistStamped (`msg_cls`) holding the command, stamped `stamp` (a
    builtin_interfaces/Time) in `frame_id`."""
    msg = msg_cls()
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    msg.twist.linear.x, msg.twist.angular.z = float(twist.linear), float(twist.angular)
    return msg


def add_loop_flags(p: argparse.ArgumentParser) -> None:
    """The flags of `make_loop`'s settings (shared with `python -m jaxnav.replay`)."""
    p.add_argument("--rate-hz", type=float, help="commands per second (default: policy's, or 10)")
    p.add_argument("--max-age", type=float, default=DEFAULT_MAX_AGE, help="s; older data: stop")
    p.add_argument("--speed-calibration", type=float, default=1.0, help="multiplies both speeds")
    p.add_argument(
        "--blind-fraction", type=float, default=BLIND_FRACTION, help="unknown share: near"
    )
    p.add_argument(
        "--readings-per-stray",
        type=int,
        default=READINGS_PER_STRAY,
        help="a sector reads its nearest reading 1 + known // this readings reach (0: minimum)",
    )
    p.add_argument(
        "--max-unknown", type=float, default=MAX_UNKNOWN, help="frame unknown share: stop above"
    )
    p.add_argument(
        "--blind-hold",
        type=float,
        default=BLIND_HOLD,
        help="s a frame over max-unknown reads near after one that measured a surface that near",
    )
    nan, file = math.nan, "nan: the policy file's"
    p.add_argument(
        "--vfov-deg",
        type=float,
        default=nan,
        help=f"without camera_info: the image's vertical fov (Astra: {ASTRA_VFOV_DEG}; "
        "nan: the policy's fov across the image)",
    )
    p.add_argument("--band-deg", type=float, default=2.0, help="rows within +-this of horizon")
    p.add_argument("--tilt-deg", type=float, default=nan, help=f"camera pitch, + down ({file})")
    p.add_argument("--camera-height", type=float, default=nan, help=f"camera, m ({file})")
    add_calibration_flags(p)


def add_calibration_flags(p: argparse.ArgumentParser) -> None:
    """The start-up calibration of the camera mount (`calibrate.StartupCalibration`)."""
    p.add_argument(
        "--calibration",
        choices=MODES,
        default="check",
        help="several-row policies: estimate the camera mount from the first frames; check: "
        "refuse to drive where it is off tilt_deg/camera_height; use: drive with it; off",
    )
    p.add_argument(
        "--calibration-frames", type=int, default=5, help="frames with floor to estimate from"
    )
    p.add_argument(
        "--pitch-tolerance-deg", type=float, default=PITCH_TOLERANCE_DEG, help="check: pitch"
    )
    p.add_argument(
        "--height-tolerance", type=float, default=HEIGHT_TOLERANCE, help="check: height, m"
    )
    p.add_argument(
        "--roll-tolerance-deg", type=float, default=ROLL_TOLERANCE_DEG, help="check, use: roll"
    )


def add_goal_flags(p: argparse.ArgumentParser) -> None:
    """The goal policies' input topics (shared with `python -m jaxnav.replay`)."""
    p.add_argument(
        "--goal-topic", default="goal_pose", help="goal policies: geometry_msgs/PoseStamped goal"
    )
    p.add_argument("--odom-topic", default="odom", help="goal policies: nav_msgs/Odometry")
    p.add_argument(
        "--goal-point",
        action="store_true",
        help="the goal topic carries geometry_msgs/PointStamped (RViz's Publish Point)",
    )


def _add_node_flags(p: argparse.ArgumentParser) -> None:
    """The node's own topics and clock (not the replay's)."""
    p.add_argument("--cmd-vel", default="cmd_vel", help="velocity command output topic")
    p.add_argument(
        "--stamped", action="store_true", help="send geometry_msgs/TwistStamped, not Twist"
    )
    p.add_argument(
        "--camera-info-topic", default="", help="sensor_msgs/CameraInfo (default: beside --topic)"
    )
    p.add_argument(
        "--enable-topic", default="~/enable", help="std_msgs/Bool: false = zero velocity"
    )
    p.add_argument(
        "--goal-status-topic", default="goal_status", help="goal policies: std_msgs/String"
    )
    p.add_argument(
        "--goal-frame-tf",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="goal policies: place a goal in another frame than the odometry's with tf2's "
        "newest transform at each tick (--no-goal-frame-tf, or no tf2_ros: refuse it)",
    )
    p.add_argument(
        "--goal-tf-max-age",
        type=float,
        default=GOAL_TF_MAX_AGE,
        help="s; a goal's transform older than this (localisation stopped): refuse it",
    )
    p.add_argument(
        "--header-stamps",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="age messages by header.stamp where set (--no-header-stamps: by arrival)",
    )


def parse_args(argv=None):
    """Flags (defaults of the node's ROS parameters) and the rest (for rclpy: --ros-args ...)."""
    p = argparse.ArgumentParser(prog="ros_node", description=__doc__.splitlines()[0])
    p.add_argument("--policy", default="policy.npz", help="exported policy (.npz)")
    p.add_argument("--topic", default="/camera/depth/image_raw", help="depth image or scan topic")
    p.add_argument("--scan", action="store_true", help="the topic is a sensor_msgs/LaserScan")
    _add_node_flags(p)
    add_goal_flags(p)
    add_loop_flags(p)
    return p.parse_known_args(argv)


def camera_info_topic(get: dict) -> str:
    """The CameraInfo topic: the parameter, or `camera_info` beside the image topic (the image
    transport convention: /camera/depth/image_raw -> /camera/depth/camera_info)."""
    if get["camera_info_topic"]:
        return get["camera_info_topic"]
    namespace = get["topic"].rpartition("/")[0]
    return f"{namespace}/camera_info" if namespace else "camera_info"


def make_loop(get: dict, log) -> tuple[ControlLoop, float]:
    """(the node's ControlLoop, its rate in Hz) from the values `get` of the node's parameters:
    policy, scan and those of `add_loop_flags` (rate_hz None: the policy's rate); header_stamps
    where given (absent, as in `python -m jaxnav.replay` on a bag's clock: arrival times)."""
    policy = NumpyPolicy.from_npz(get["policy"])
    controller = Controller(
        policy,
        get["speed_calibration"],
        get["blind_fraction"],
        get["readings_per_stray"],
        get["max_unknown"],
    )
    reader = MessageReader(
        get["scan"], get["vfov_deg"], get["band_deg"], get["tilt_deg"], get["camera_height"]
    )
    goal = GoalInput() if policy.extra_observations else None
    stamps = get.get("header_stamps", False)
    calibration = startup_calibration(get, policy)
    loop = ControlLoop(
        controller, reader, get["max_age"], log, goal, stamps, calibration, get["blind_hold"]
    )
    return loop, control_rate(policy, get["rate_hz"])


def startup_calibration(get: dict, policy) -> StartupCalibration | None:
    """The node's start-up calibration (parameters calibration, calibration_frames and the
    tolerances; absent: the flags' defaults), for depth images read by a floor rule (policies
    trained with several rows, whose file gives the camera's height); None otherwise: a scan has
    no floor, and a one-row policy reads a band around the horizon, which 2 deg of pitch error
    moves onto floor 4 m out at the nearest."""
    sensor = policy.sensor
    if get["scan"] or len(sensor.elevations) < 2 or sensor.camera_height is None:
        return None
    defaults = vars(_calibration_defaults())
    get = {**defaults, **{k: v for k, v in get.items() if k in defaults}}
    tolerance = Tolerance(
        math.radians(get["pitch_tolerance_deg"]),
        get["height_tolerance"],
        math.radians(get["roll_tolerance_deg"]),
    )
    return StartupCalibration(get["calibration"], get["calibration_frames"], tolerance)


def _calibration_defaults() -> argparse.Namespace:
    """The calibration flags' defaults."""
    p = argparse.ArgumentParser()
    add_calibration_flags(p)
    return p.parse_args([])


def _declare_parameters(node, args) -> dict:
    """The values of the node's parameters, declared with the flags' values as defaults."""
    flags = {k: v for k, v in vars(args).items() if v is not None}  # rate_hz may be None
    get = {k: node.declare_parameter(k, v).value for k, v in flags.items()}
    if args.rate_hz is None:  # a float parameter; 0 = the policy's rate
        get["rate_hz"] = node.declare_parameter("rate_hz", 0.0).value or None
    return get


def _subscribe(node, get: dict) -> None:
    """The node's inputs: the sensor first, its CameraInfo (depth images), the enable topic, and
    a goal policy's goal and odometry."""
    from rclpy.qos import qos_profile_sensor_data as sensor_qos
    from sensor_msgs.msg import CameraInfo, Image, LaserScan
    from std_msgs.msg import Bool

    msg_type = LaserScan if get["scan"] else Image
    node.create_subscription(msg_type, get["topic"], node.on_message, sensor_qos)
    if not get["scan"]:
        info = camera_info_topic(get)
        node.create_subscription(CameraInfo, info, node.loop.on_camera_info, sensor_qos)
    node.create_subscription(Bool, get["enable_topic"], node.on_enable, 10)
    if node.loop.goal is not None:
        from geometry_msgs.msg import PointStamped, PoseStamped
        from nav_msgs.msg import Odometry

        goal_type = PointStamped if get.get("goal_point") else PoseStamped
        node.create_subscription(goal_type, get["goal_topic"], node.on_goal, 10)
        node.create_subscription(Odometry, get["odom_topic"], node.on_odom, sensor_qos)


def goal_transforms(node, get: dict, log) -> Callable[[str, str], tuple[float, float, float]]:
    """The goal inputs' `transforms`: tf2's (`tf2_transforms`) with goal_frame_tf (absent: true)
    where tf2_ros imports; otherwise one that says why there are none (logged once here)."""
    if not get.get("goal_frame_tf", True):
        return no_transforms("goal_frame_tf is false")
    try:
        return tf2_transforms(node, get.get("goal_tf_max_age", GOAL_TF_MAX_AGE))
    except ImportError as err:
        log(f"goals only in the odometry's frame: tf2_ros does not import ({err})")
        return no_transforms(f"tf2_ros does not import: {err}")


def tf2_transforms(node, max_age: float) -> Callable[[str, str], tuple[float, float, float]]:
    """transforms(target, source) -> (x, y, yaw): the newest transform of `source` in `target`
    (`planar_transform`) in a tf2 Buffer that a TransformListener on `node` fills; tf2's
    exception where it has none, a LookupError where it is more than `max_age` s older than the
    node's clock (`transform_age`: localisation stopped). It does not wait: it is looked up in
    the control timer, and a wait there would hold back rclpy's single-threaded executor, and
    with it the /tf messages."""
    import tf2_ros
    from rclpy.time import Time

    buffer = tf2_ros.Buffer()
    node.tf_listener = tf2_ros.TransformListener(buffer, node)

    def lookup(target: str, source: str) -> tuple[float, float, float]:
        stamped = buffer.lookup_transform(target, source, Time())
        now = node.get_clock().now().nanoseconds * 1e-9
        why = transform_age(stamped, now, max_age)
        if why:
            raise LookupError(why)
        return planar_transform(stamped.transform)

    return lookup


def transform_age(stamped, now: float, max_age: float) -> str | None:
    """Why a geometry_msgs/TransformStamped is too old to place a goal with at `now` (s): its
    stamp more than `max_age` s before now; None: fresh, or stamped zero (a static transform,
    /tf_static's: it holds for good)."""
    stamp = header_time(stamped)
    if stamp is None or now - stamp <= max_age:
        return None
    return f"newest transform {now - stamp:.1f} s old, over goal_tf_max_age {max_age:g} s"


def diagnostic_array(diagnosis, stamp, name: str):
    """A diagnostic_msgs/DiagnosticArray of one status, `ControlLoop.diagnosis`'s (level,
    message, values), stamped `stamp`, named after the node."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    level, message, values = diagnosis
    status = DiagnosticStatus()
    status.level = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[level]
    status.name, status.message, status.hardware_id = f"{name}: control loop", message, ""
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    array = DiagnosticArray()
    array.header.stamp, array.status = stamp, [status]
    return array


def _make_node(args):
    """The rclpy node, its parameters declared with the flags' values as defaults."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist as TwistMsg
    from geometry_msgs.msg import TwistStamped
    from rclpy.node import Node
    from rclpy.task import Future
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    class PolicyNode(Node):
        def __init__(self):
            super().__init__("jaxnav_policy")
            get = _declare_parameters(self, args)
            logger = self.get_logger()
            warn = getattr(logger, "warning", None) or logger.warn
            self.loop, rate = make_loop(get, warn)
            if self.loop.goal is not None:
                self.loop.goal.transforms = goal_transforms(self, get, warn)
            self.stamped = get["stamped"]
            self.pub = self.create_publisher(
                TwistStamped if self.stamped else TwistMsg, get["cmd_vel"], 10
            )
            _subscribe(self, get)
            self.calibrations = []  # (future, when asked) of ~/calibrate requests unanswered
            self.create_service(Trigger, CALIBRATE_SERVICE, self.on_calibrate)
            self.status_pub = None
            if self.loop.goal is not None:
                self.status_pub = self.create_publisher(String, get["goal_status_topic"], 10)
            self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.diag_sent = (None, -math.inf)  # the last report's state and time
            self.timer = self.create_timer(1.0 / rate, self.on_timer)
            logger.info(f"{get['policy']}: {get['topic']} -> {get['cmd_vel']} at {rate:g} Hz")

        def now(self) -> float:
            return self.get_clock().now().nanoseconds * 1e-9

        def on_message(self, msg):
            self.loop.on_observation(msg, self.now())

        def on_enable(self, msg):
            self.loop.set_enabled(msg.data)
            if not msg.data:  # stop now, not at the next tick
                self.on_timer()

        def on_goal(self, msg):
            self.loop.goal.on_goal_msg(msg)

        def on_odom(self, msg):
            self.loop.on_odometry(msg, self.now())

        async def on_calibrate(self, request, response):
            """std_srvs/Trigger: re-calibrates the camera mount (`ControlLoop.recalibrate`);
            answers once it is decided, or CALIBRATION_WAIT s on. A coroutine, so that the
            executor runs the image callbacks that calibrate while it waits."""
            response.success, response.message = await self.recalibration()
            return response

        def recalibration(self):
            """A future of a re-calibration's (success, message), set at once where it cannot
            run, else by the tick that has the answer (`answer_calibrations`)."""
            future, refused = Future(), self.loop.recalibrate()
            if refused:
                future.set_result(refused)
                return future
            self.calibrations.append((future, self.now()))
            self.on_timer()  # stop now, not at the next tick
            return future

        def answer_calibrations(self):
            """Sets the futures of the re-calibration requests whose answer is known."""
            now, waiting = self.now(), []
            for future, asked in self.calibrations:
                answer = self.loop.calibration_answer(asked, now)
                if answer is None:
                    waiting.append((future, asked))
                else:
                    future.set_result(answer)
            self.calibrations = waiting

        def on_timer(self):
            self.send(self.loop.tick(self.now()))
            if self.status_pub is not None:
                status = String()
                status.data = self.loop.goal_status()
                self.status_pub.publish(status)
            self.diagnose()
            self.answer_calibrations()

        def diagnose(self):
            """A diagnostic_msgs report at each change of the loop's state, and every
            DIAGNOSTICS_PERIOD s."""
            now, (state, sent) = self.now(), self.diag_sent
            if state == self.loop.state and now - sent < DIAGNOSTICS_PERIOD:
                return
            self.diag_sent = (self.loop.state, now)
            msg = diagnostic_array(
                self.loop.diagnosis(), self.get_clock().now().to_msg(), self.get_name()
            )
            self.diag_pub.publish(msg)

        def send(self, twist: Twist) -> None:
            if self.stamped:
                stamp = self.get_clock().now().to_msg()
                self.pub.publish(twist_stamped_msg(twist, TwistStamped, stamp))
            else:
                self.pub.publish(twist_msg(twist, TwistMsg))

        def stop(self):
            try:  # best effort: the context may be gone if something else shut it down
                self.send(self.loop.shutdown())
            except Exception as err:  # noqa: BLE001
                print(f"could not send the stop command: {err}", file=sys.stderr)

    return PolicyNode()


def _init_rclpy(rclpy, args: list[str]) -> None:
    """rclpy.init without rclpy's signal handlers where it has the option (Humble and later)."""
    try:
        from rclpy.signals import SignalHandlerOptions
    except ImportError:  # Foxy, Galactic: our handlers, installed after init, replace rclpy's
        rclpy.init(args=args)
        return
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)


def _stop_on_signals(node) -> dict:
    """SIGINT and SIGTERM send zero velocity at once, then leave spin; returns the old handlers."""
    caught = []

    def handler(signum, frame):
        node.stop()  # now, while the ROS context is still up
        if not caught:  # a second signal during the shutdown only repeats the stop
            caught.append(signum)
            raise KeyboardInterrupt

    return {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}


def main(argv=None) -> int:
    args, ros_args = parse_args(argv)
    import rclpy

    _init_rclpy(rclpy, [sys.argv[0], *ros_args])
    try:
        node = _make_node(args)
    except ValueError as err:  # a bad policy file or parameter: before any command is sent
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    previous = _stop_on_signals(node)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.stop()  # the robot must not keep driving on the last command
        node.destroy_node()
        rclpy.try_shutdown()
        for sig, old in previous.items():
            signal.signal(sig, old)
    return 0


if __name__ == "__main__":
    sys.exit(main())
