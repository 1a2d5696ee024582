"""The camera's mount from the floor it sees: pitch, roll and height from depth frames (numpy only).

    python -m jaxnav_robot.calibrate frames.npy --out config/mount.yaml    # in a bundle
    python -m jaxnav_robot.calibrate rec/ --policy policy.npz              # a rosbag2 recording
    python -m jaxnav_robot.calibrate --live /camera/depth/image_raw        # ROS 2 sourced

(`python -m jaxnav.robot_side.calibrate` where jaxnav is installed.) The floor rule of a policy
trained with rows below the horizon (`observation.floor_mask`) needs the camera's pitch and height:
2 deg of pitch error puts the floor 3.5 cm high 1 m out, beyond the rule's margin, and the policy
sees phantom obstacles. With the robot on open floor, each frame's lower image rows are
back-projected through the camera's calibration (`Intrinsics.back_project`), a plane is fitted
(RANSAC among planes near the expected mount, then least squares on the points within `cut` of it,
then within cut / 2) and the camera's pose above that plane is the mount. A frame in which the plane holds
less than `min_floor_share` of the lower rows' pixels is rejected (a wall, a person, a box in
front); the frames' estimates are combined by their median.

The command line reads frames from a .npy ([H, W] or [N, H, W] depth, m), a .npz (one such array,
or one per frame), a rosbag2 folder (its depth image topic, and the CameraInfo beside it, read with
the `rosbags` library as `python -m jaxnav.replay` reads bags) or, with ROS 2 sourced, live
(`--live TOPIC`). It prints the mount and, with `--out`, writes it as a parameters file of the
node (`tilt_deg`, `camera_height`), which a bundle's launch file passes after config/jaxnav.yaml
when `config/mount.yaml` exists. The node does the same at start-up (`StartupCalibration`): from
its first frames it checks the mount it was given, or uses the estimate (`calibration` parameter).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

from .observation import Intrinsics

ASTRA_FOCAL = 570.3  # px at 640 px wide: the Astra's common calibration (OpenNI's default)
PITCH_TOLERANCE_DEG = 0.5
"""deg of pitch error the node's start-up check lets pass. Measured on 640x480 frames of open floor
and a wall at 5 m (a 5-row policy's floor rule at the configured mount, the camera pitched down
by more than that): 1.0 deg still reads 4.98 m, 1.1 deg 2.2 m, 2 deg 0.93 m (the floor rule's
margin grows by 0.01 m per m, `observation.FLOOR_MARGIN_SLOPE`, 0.57 deg); half the largest
harmless error, for the estimate's own error and for obstacles told from the floor."""
HEIGHT_TOLERANCE = 0.01
"""m of camera height error the check lets pass: half the floor rule's 2 cm margin at the camera
(measured as above: 2 cm too high or too low reads 5 m, 3 cm too low 0.63 m)."""
ROLL_TOLERANCE_DEG = 1.0
"""deg of roll the check lets pass, also when the estimate is used (the floor rule has no roll,
the policy trained without): measured as above, 2 deg reads 5 m, 3 deg a side sector 1.98 m."""


class CalibrationError(ValueError):
    """Frames from which no mount can be estimated; one line saying why."""


@dataclasses.dataclass(frozen=True)
class CalibrationConfig:
    """How the floor plane is found."""

    step: int = 4
    """Every step-th row and column of the lower image rows is used (640x480: ~9,600 pixels)."""
    cut: float = 0.02
    """m: a point this close to the plane is floor (the floor rule's own margin at the camera)."""
    min_floor_share: float = 0.3
    """A frame whose floor holds less than this share of its lower rows' pixels is rejected."""
    max_tilt_deg: float = 10.0
    """deg: the plane's normal must lie within this of the expected mount's up (a floor, not a
    wall or a ramp)."""
    height_range: tuple[float, float] = (0.05, 2.0)
    """m: the camera's height above the plane must lie in this range."""
    hypotheses: int = 200
    """Planes tried (RANSAC), each through three random pixels."""
    seed: int = 0
    """Seed of the RANSAC draws (the same frames give the same estimate)."""

    def __post_init__(self):
        if self.step < 1 or self.hypotheses < 1:
            raise ValueError(f"step, hypotheses: must be >= 1, got {self.step}, {self.hypotheses}")
        if not 0 < self.cut < math.inf:
            raise ValueError(f"cut: must be > 0 m, got {self.cut}")
        if not 0 <= self.min_floor_share <= 1:
            raise ValueError(f"min_floor_share: must be in [0, 1], got {self.min_floor_share}")
        if not 0 < self.max_tilt_deg < 90:
            raise ValueError(f"max_tilt_deg: must be in (0, 90), got {self.max_tilt_deg}")


@dataclasses.dataclass(frozen=True)
class Mount:
    """A camera mount estimated from the floor."""

    pitch: float
    """rad, positive = looking down (as `Sensor.camera_pitch`, the node's tilt_deg in radians)."""
    roll: float
    """rad about the optical axis, positive = the image's left side up."""
    height: float
    """m: the optical centre above the floor."""
    residual: float
    """m: RMS distance of the floor points from the plane (the fit's noise; median over frames)."""
    floor_share: float
    """Share of the lower image rows' pixels on the floor (mean over the frames used)."""
    frames: int
    """Frames the estimate combines."""
    rejected: int = 0
    """Frames rejected (too little floor)."""

    def describe(self) -> str:
        """One line: the mount and how well the floor fitted."""
        return (
            f"pitch {math.degrees(self.pitch):.2f} deg (down +), roll "
            f"{math.degrees(self.roll):.2f} deg, height {self.height:.3f} m; floor "
            f"{100 * self.floor_share:.0f} % of the lower image, {1000 * self.residual:.1f} mm RMS, "
            f"{self.frames} frames ({self.rejected} rejected)"
        )


def lower_pixels(depth, camera: Intrinsics, step: int) -> tuple[np.ndarray, int]:
    """(points [N, 3] m in the camera's frame (forward, left, up) of the known pixels of every
    step-th row and column below the principal point of depth [H, W], how many pixels were
    looked at, unknown ones included)."""
    depth = np.asarray(depth, np.float64)
    camera.fits(*depth.shape)
    rows = np.arange(math.ceil(camera.cy), depth.shape[0], step)
    cols = np.arange(0, depth.shape[1], step)
    grid = depth[rows[:, None], cols[None, :]]  # [R, C]
    with np.errstate(invalid="ignore"):
        r, c = np.nonzero(np.isfinite(grid) & (grid > 0))
    return camera.back_project(grid[r, c], rows[r], cols[c]), grid.size


def plane_mount(normal, offset) -> tuple[float, float, float]:
    """(pitch, roll, height) of a camera above the plane normal . p + offset = 0 (normal [3] unit,
    pointing up, in the camera's frame): the world's up seen from a camera pitched down by p and
    rolled by r is (-sin p, sin r cos p, cos r cos p)."""
    pitch = math.asin(float(np.clip(-normal[0], -1.0, 1.0)))
    return pitch, math.atan2(float(normal[1]), float(normal[2])), float(offset)


def up_of(pitch: float, roll: float = 0.0) -> np.ndarray:
    """[3] the world's up in the frame of a camera pitched `pitch` and rolled `roll` (rad)."""
    return np.array(
        [-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)]
    )


def _hypotheses(points, rng, cfg: CalibrationConfig, up) -> tuple[np.ndarray, np.ndarray]:
    """(normals [K, 3], offsets [K]) of planes through three random points each, kept where the
    normal lies within max_tilt_deg of `up` and the camera at a height in height_range."""
    a, b, c = points[rng.integers(0, len(points), (3, cfg.hypotheses))]  # each [K, 3]
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = normal / length * np.sign(normal @ up)[:, None]  # pointing up
    offset = -(normal * a).sum(-1)  # the camera (origin) is `offset` above the plane
    low, high = cfg.height_range
    fits = (normal @ up >= math.cos(math.radians(cfg.max_tilt_deg))) & (offset >= low)
    fits &= offset <= high
    return normal[fits], offset[fits]


def _refine(points, normal, offset, cut: float):
    """(normal [3], offset, inliers [N] bool): least squares on the points within `cut` of the
    plane, then on those within cut / 2 of that one (the foot of a box or a wall, within `cut`
    of the floor, pulls the plane less)."""
    for within in (cut, 0.5 * cut):
        inliers = np.abs(points @ normal + offset) <= within
        centre = points[inliers].mean(0)
        normal = np.linalg.svd(points[inliers] - centre, full_matrices=False)[2][-1]
        normal = normal if normal[2] > 0 else -normal
        offset = -float(normal @ centre)
    return normal, offset, np.abs(points @ normal + offset) <= cut


def frame_mount(depth, camera: Intrinsics, pitch=0.0, roll=0.0, cfg=CalibrationConfig()) -> Mount:
    """The mount seen from one depth frame [H, W] (m; 0, NaN: unknown) of calibration `camera`,
    the plane searched within cfg.max_tilt_deg of a camera pitched `pitch` and rolled `roll`
    (rad); a CalibrationError where the floor holds too little of the lower rows."""
    points, looked = lower_pixels(depth, camera, cfg.step)
    need = cfg.min_floor_share * looked
    if len(points) < max(need, 3):
        raise CalibrationError(
            f"{len(points)} of {looked} lower-image pixels read, need {need:.0f} on the floor"
        )
    rng = np.random.default_rng(cfg.seed)
    normals, offsets = _hypotheses(points, rng, cfg, up_of(pitch, roll))
    if len(normals) == 0:
        raise CalibrationError(f"no floor plane within {cfg.max_tilt_deg:g} deg of the expected")
    votes = (np.abs(points @ normals.T + offsets) <= cfg.cut).sum(0)  # [K]
    best = int(np.argmax(votes))
    normal, offset, inliers = _refine(points, normals[best], offsets[best], cfg.cut)
    share = inliers.sum() / looked
    if share < cfg.min_floor_share:
        raise CalibrationError(
            f"floor in {100 * share:.0f} % of the lower image, need "
            f"{100 * cfg.min_floor_share:.0f} % (face open floor)"
        )
    residual = float(np.sqrt(np.mean((points[inliers] @ normal + offset) ** 2)))
    return Mount(*plane_mount(normal, offset), residual, float(share), 1)


def estimate_mount(frames, camera: Intrinsics, pitch=0.0, roll=0.0, cfg=CalibrationConfig()):
    """The `Mount` of depth frames [N, H, W] (or one [H, W]): each frame's (`frame_mount`),
    combined by the median; a CalibrationError naming the first frame's problem where none has
    enough floor."""
    frames = np.asarray(frames)
    frames = frames[None] if frames.ndim == 2 else frames
    if frames.ndim != 3 or len(frames) == 0:
        raise CalibrationError(f"frames: need [N, H, W] or [H, W] depth, got shape {frames.shape}")
    mounts, problems = [], []
    for i, depth in enumerate(frames):
        try:
            mounts.append(frame_mount(depth, camera, pitch, roll, cfg))
        except CalibrationError as err:
            problems.append(f"frame {i}: {err}")
    if not mounts:
        more = f" (and {len(problems) - 1} more frames)" if len(problems) > 1 else ""
        raise CalibrationError(f"no floor found: {problems[0]}{more}")
    return combine(mounts, len(problems))


def combine(mounts: list[Mount], rejected: int = 0) -> Mount:
    """One Mount of several frames' `mounts`: the median of each angle, height and residual."""
    med = {f: float(np.median([getattr(m, f) for m in mounts])) for f in ("pitch", "roll")}
    height = float(np.median([m.height for m in mounts]))
    residual = float(np.median([m.residual for m in mounts]))
    share = float(np.mean([m.floor_share for m in mounts]))
    return Mount(**med, height=height, residual=residual, floor_share=share,
                 frames=len(mounts), rejected=rejected)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """How far the estimated mount may lie from the configured one before the node refuses."""

    pitch: float = math.radians(PITCH_TOLERANCE_DEG)
    """rad (`PITCH_TOLERANCE_DEG`)."""
    height: float = HEIGHT_TOLERANCE
    """m (`HEIGHT_TOLERANCE`)."""
    roll: float = math.radians(ROLL_TOLERANCE_DEG)
    """rad (`ROLL_TOLERANCE_DEG`); checked also when the estimate is used (the floor rule has no
    roll)."""

    def __post_init__(self):
        for name in ("pitch", "height", "roll"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"Tolerance.{name}: must be > 0, got {getattr(self, name)}")


def mount_problem(mount: Mount, pitch: float, height, tol: Tolerance, use: bool = False):
    """What keeps `mount` from the configured pitch (rad) and height (m; None: not checked), or
    None; `use`: only the roll (the estimate replaces the rest)."""
    problems = []
    if not use and abs(mount.pitch - pitch) > tol.pitch:
        problems.append(
            f"pitch {math.degrees(mount.pitch):.2f} deg, configured "
            f"{math.degrees(pitch):.2f} (tolerance {math.degrees(tol.pitch):.2g})"
        )
    if not use and height is not None and abs(mount.height - height) > tol.height:
        problems.append(
            f"height {mount.height:.3f} m, configured {height:.3f} (tolerance {tol.height:.2g})"
        )
    if abs(mount.roll) > tol.roll:
        problems.append(
            f"roll {math.degrees(mount.roll):.2f} deg (tolerance {math.degrees(tol.roll):.2g}; "
            "level the camera)"
        )
    return "; ".join(problems) or None


MODES = ("check", "use", "off")


class StartupCalibration:
    """The node's calibration of the camera mount: its first `frames` depth frames with floor give
    the mount (`add`), then `problem` says why not to drive (None: drive). Modes: "check" (refuse
    where the estimate is off the configured pitch/height by more than `tolerance`), "use" (drive
    with the estimate as the mount; a roll beyond tolerance is still refused), "off" (no
    calibration). `restart` starts over from the next frames (the node's `~/calibrate` service)."""

    def __init__(self, mode="check", frames=5, tolerance=Tolerance(), cfg=CalibrationConfig()):
        if mode not in MODES:
            raise ValueError(f"calibration: must be one of {', '.join(MODES)}, got {mode!r}")
        if frames < 1:
            raise ValueError(f"calibration_frames: must be >= 1, got {frames}")
        self.mode, self.frames, self.tolerance, self.cfg = mode, int(frames), tolerance, cfg
        self.restart()

    def restart(self) -> None:
        """Forgets the estimate and the frames: the next `frames` frames with floor decide anew."""
        self.mounts: list[Mount] = []
        self.rejected, self.last_problem = 0, None  # frames without floor, the latest reason
        self.mount: Mount | None = None  # the estimate, once `frames` frames gave one
        self.problem: str | None = None  # why it refuses to drive, once decided

    @property
    def done(self) -> bool:
        """No more frames needed: mode "off", or the estimate is made."""
        return self.mode == "off" or self.mount is not None

    def add(self, depth, camera: Intrinsics, pitch: float, height) -> None:
        """One depth frame [H, W] (m) of calibration `camera`, the configured pitch (rad) and
        height (m, or None); decides once `frames` frames had floor."""
        if self.done:
            return
        try:
            self.mounts.append(frame_mount(depth, camera, pitch, 0.0, self.cfg))
        except CalibrationError as err:
            self.rejected, self.last_problem = self.rejected + 1, str(err)
            return
        if len(self.mounts) == self.frames:
            self.mount = combine(self.mounts, self.rejected)
            use = self.mode == "use"
            self.problem = mount_problem(self.mount, pitch, height, self.tolerance, use)

    def outcome(self) -> tuple[bool, str] | None:
        """(whether the robot may drive, one line saying why) once decided; None before."""
        if self.mount is None:
            return None
        if self.problem:
            return False, self.refusal()
        how = "used" if self.mode == "use" else "within tolerance"
        return True, f"camera mount {how}: {self.mount.describe()}"

    def waiting(self) -> str:
        """Why it is not decided yet (a loop state)."""
        text = f"calibrating the camera mount: {len(self.mounts)} of {self.frames} frames"
        if self.last_problem:
            text += f" ({self.rejected} without floor, the last: {self.last_problem})"
        return text

    def refusal(self) -> str:
        """The loop state of a refused mount: the problem and what to do."""
        return (
            f"camera mount refused: {self.problem}; measured {self.mount.describe()}; set "
            "tilt_deg and camera_height (python3 -m jaxnav_robot.calibrate writes them), or "
            "calibration:=use"
        )


# ------------------------------------------------------------------------------
# Command line


def astra_camera(height: int, width: int) -> Intrinsics:
    """The Astra's common calibration (ASTRA_FOCAL at 640 px, scaled), principal point centred."""
    focal = ASTRA_FOCAL * width / 640
    return Intrinsics(focal, focal, 0.5 * (width - 1), 0.5 * (height - 1), width, height)


def load_frames(path: Path) -> tuple[np.ndarray, Intrinsics | None]:
    """(frames [N, H, W] m, the camera's calibration where the source has one) of a .npy, .npz or
    rosbag2 folder; a CalibrationError naming the file otherwise."""
    if path.is_dir():
        return bag_frames(path)
    if path.suffix not in (".npy", ".npz"):
        raise CalibrationError(f"{path}: give a .npy, a .npz or a rosbag2 folder")
    try:
        loaded = np.load(path, allow_pickle=False)
        arrays = [loaded] if path.suffix == ".npy" else [loaded[k] for k in loaded.files]
    except (OSError, ValueError) as err:
        raise CalibrationError(f"{path}: unreadable ({err})") from None
    frames = [a[None] if a.ndim == 2 else a for a in arrays]
    if not frames or any(f.ndim != 3 or f.shape[1:] != frames[0].shape[1:] for f in frames):
        raise CalibrationError(f"{path}: need depth frames [H, W] or [N, H, W] of one size (m)")
    return np.concatenate(frames).astype(np.float32), None


def bag_frames(bag: Path, most: int = 30) -> tuple[np.ndarray, Intrinsics | None]:
    """The first `most` frames of a rosbag2's one depth image topic, and its CameraInfo."""
    from .bag import CAMERA_INFO, IMAGE, decoded, listing, open_bag
    from .ros_node import camera_info_intrinsics, image_msg_to_array

    reader, typestore = open_bag(bag)
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        images = [t for t, kind in topics.items() if kind == IMAGE and "depth" in t]
        if len(images) != 1:
            raise CalibrationError(f"{bag}: no single depth image topic; topics: {listing(topics)}")
        wanted = [c for c in reader.connections if c.topic == images[0] or c.msgtype == CAMERA_INFO]
        frames, camera = [], None
        for _, topic, msg in decoded(bag, reader, wanted, typestore):
            if topic != images[0]:
                camera = camera or camera_info_intrinsics(msg)
                continue
            frames.append(image_msg_to_array(msg.encoding, msg.height, msg.width, msg.data,
                                             msg.step, bool(msg.is_bigendian)))  # fmt: skip
            if len(frames) == most:
                break
    finally:
        reader.close()
    if not frames:
        raise CalibrationError(f"{bag}: no messages on {images[0]}")
    return np.stack(frames), camera


def live_frames(topic: str, count: int, timeout: float = 10.0):
    """(`count` frames of a live depth image topic, the CameraInfo beside it, where one came);
    needs ROS 2 (rclpy) sourced."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data as qos
    from sensor_msgs.msg import CameraInfo, Image

    from .ros_node import camera_info_intrinsics, image_msg_to_array

    rclpy.init()
    node, frames, infos = rclpy.create_node("jaxnav_calibrate"), [], []
    convert = image_msg_to_array
    node.create_subscription(Image, topic, lambda m: frames.append(convert(
        m.encoding, m.height, m.width, m.data, m.step, bool(m.is_bigendian))), qos)  # fmt: skip
    info = f"{topic.rpartition('/')[0]}/camera_info"
    node.create_subscription(CameraInfo, info, infos.append, qos)
    clock = node.get_clock()
    start = clock.now().nanoseconds
    while len(frames) < count and clock.now().nanoseconds - start < timeout * 1e9:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.try_shutdown()
    if not frames:
        raise CalibrationError(f"--live {topic}: no image in {timeout:g} s")
    return np.stack(frames[:count]), camera_info_intrinsics(infos[0]) if infos else None


def mount_yaml(mount: Mount, source: str) -> str:
    """The node's parameters file of `mount` (tilt_deg, camera_height), for --params-file."""
    return (
        f"# Camera mount estimated by python3 -m jaxnav_robot.calibrate from {source}:\n"
        f"# {mount.describe()}\n"
        "/**/jaxnav_policy:\n"
        "  ros__parameters:\n"
        f"    tilt_deg: {math.degrees(mount.pitch):.3f}  # camera pitch, deg, down +\n"
        f"    camera_height: {mount.height:.4f}  # m above the floor\n"
    )


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m jaxnav_robot.calibrate", description=__doc__.splitlines()[0]
    )
    p.add_argument("frames", nargs="?", type=Path, help=".npy/.npz of depth (m) or a rosbag2")
    p.add_argument("--live", metavar="TOPIC", help="read a live depth image topic (ROS 2)")
    p.add_argument("--count", type=int, default=10, help="frames to use (default 10)")
    p.add_argument("--focal", type=float, help=f"px, without CameraInfo (default {ASTRA_FOCAL})")
    p.add_argument("--policy", help="policy.npz: compare with the mount it was trained with")
    p.add_argument("--pitch-deg", type=float, default=0.0, help="expected pitch (search centre)")
    p.add_argument("--out", type=Path, help="write the node's parameters file here (YAML)")
    return p.parse_args(argv)


def _frames(args) -> tuple[np.ndarray, Intrinsics, str]:
    """(frames, calibration, where from) of the flags."""
    if (args.frames is None) == (args.live is None):
        raise CalibrationError("give FRAMES (a .npy, .npz or rosbag2) or --live TOPIC, one")
    if args.live is not None:
        frames, camera = live_frames(args.live, args.count)
        source = args.live
    else:
        frames, camera = load_frames(args.frames)
        frames, source = frames[: args.count], str(args.frames)
    if args.focal is not None or camera is None:
        camera = astra_camera(*frames.shape[1:])
        if args.focal is not None:
            camera = camera._replace(fx=args.focal, fy=args.focal)
    return frames, camera, source


def _compare(mount: Mount, policy_path: str) -> str:
    """How `mount` compares with the one the policy file was trained with."""
    from .policy import NumpyPolicy

    sensor = NumpyPolicy.from_npz(policy_path).sensor
    problem = mount_problem(mount, sensor.camera_pitch, sensor.camera_height, Tolerance())
    trained = f"trained with pitch {math.degrees(sensor.camera_pitch):.2f} deg"
    if sensor.camera_height is not None:
        trained += f", height {sensor.camera_height:.3f} m"
    return f"{policy_path}: {trained}: " + (f"off ({problem})" if problem else "within tolerance")


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        frames, camera, source = _frames(args)
        mount = estimate_mount(frames, camera, math.radians(args.pitch_deg))
        print(mount.describe())
        if args.policy:
            print(_compare(mount, args.policy))
        if args.out is not None:
            args.out.write_text(mount_yaml(mount, source))
            print(f"wrote {args.out}")
    except (OSError, ValueError) as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
