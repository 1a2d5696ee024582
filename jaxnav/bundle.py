"""The deployment files of a robot bundle (`python -m jaxnav.export RUN --bundle DIR`).

Beside `policy.npz` and `jaxnav_robot/`, a bundle holds what starts the policy on the robot in one
command, filled from the exported policy and the run's configuration:

    launch/jaxnav.launch.py          ROS 2 launch file: the policy node (from the folder, no colcon
                                     build), kobuki_velocity_smoother, cmd_vel_mux and
                                     kobuki_safety_controller
    config/jaxnav.yaml               the policy node's parameters (every flag of ros_node)
    config/velocity_smoother.yaml    the speed and acceleration limits the policy trained with
    config/cmd_vel_mux.yaml          the safety controller, then teleop, then the policy
    Dockerfile                       ROS 2 Humble (default) or Jazzy and those packages
    README.txt                       the deployment in five commands

How the topics connect (relative names: a ROS namespace pushes them all down):

    depth image -> jaxnav_policy -> policy/cmd_vel -> kobuki_velocity_smoother
      -> cmd_vel_mux/input/policy  -+
    kobuki_safety_controller        |
      -> cmd_vel_mux/input/safety  -+-> cmd_vel_mux -> commands/velocity (the Kobuki driver)
    teleop                          |
      -> cmd_vel_mux/input/teleop  -+

The smoother sits between the policy and the mux: the policy meets the acceleration limits it was
trained with, and the safety controller's back-off and a person's teleop reach the base without
waiting for a ramp (from 0.5 m/s forward to backing off takes 2 s at 0.3 m/s^2). The smoother
reads the mux's output as feedback (`feedback: 2`), so that it ramps from what the base was last
told when the policy gets the robot back.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from jaxnav.core.randomize import FIDELITY
from jaxnav.robot_side import ros_node

ROBOT_PACKAGE = "jaxnav_robot"  # the name of jaxnav/robot_side in a bundle
NODE_NAME = "jaxnav_policy"  # the ROS node's name (ros_node)
LAUNCH_FILE = "launch/jaxnav.launch.py"
NODE_CONFIG = "config/jaxnav.yaml"
SMOOTHER_CONFIG = "config/velocity_smoother.yaml"
MUX_CONFIG = "config/cmd_vel_mux.yaml"
FOLDERS = ("launch", "config")  # what `write_deployment` adds to a bundle: these folders,
FILES = ("Dockerfile",)  # these files, and README.txt
# Written on the robot into a bundle (`python3 -m jaxnav_robot.calibrate --out config/mount.yaml`):
# a new bundle in its place keeps them.
KEPT = ("config/mount.yaml",)
DRIVER_TOPIC = "commands/velocity"  # kobuki_ros's velocity input (geometry_msgs/Twist)
POLICY_TOPIC = "policy/cmd_vel"  # the policy's output, the smoother's input
# cmd_vel_mux inputs: (name, topic, timeout s, priority, description), highest priority first.
# The timeouts: the safety controller publishes at 10 Hz while a bumper, cliff or wheel drop is
# active; a teleop key held (or pressed again within a second) keeps control; the smoother sends
# at SMOOTHER_HZ while the policy runs.
SMOOTHER_HZ = 20.0
MUX_INPUTS = (
    ("safety_controller", "cmd_vel_mux/input/safety", 0.2, 30, "kobuki_safety_controller"),
    ("teleop", "cmd_vel_mux/input/teleop", 1.0, 20, "a person with a keyboard or joystick"),
    ("jaxnav_policy", "cmd_vel_mux/input/policy", 4 / SMOOTHER_HZ, 10, "the jaxnav policy"),
)


@dataclasses.dataclass(frozen=True)
class Deployment:
    """What the deployment files are filled from: the exported policy and its run's config."""

    source: str
    """The checkpoint the policy was exported from."""
    folder: str
    """The bundle folder's name (in the README's copy command)."""
    control_period: float
    """s each command was held in training; the node sends 1 / this commands per second."""
    actions: tuple[tuple[str, float, float], ...]
    """(name, forward m/s, yaw rad/s) per row of the policy file's `commands`."""
    sensor: str
    """The trained sensor in words."""
    top_speed: tuple[float, float]
    """The robot's top speeds in training (m/s, rad/s): the smoother's speed limits."""
    accel_limit: tuple[float, float]
    """Acceleration limits (m/s^2, rad/s^2): the middle of the ranges training sampled."""
    accel_note: str
    """Where `accel_limit` comes from."""
    camera_height: float
    """m: the camera height the policy was trained with (its floor rule)."""
    camera_pitch: float
    """rad, down +: the camera pitch the policy was trained with."""
    blind_fraction: float
    """The sensor's blind fraction in training (a sector with this share unknown reads near)."""
    readings_per_stray: int
    """The sensor's rule in training: a sector reads its (1 + n // this)-th nearest reading."""
    coupled_smoother: bool = False
    """Whether training limited the speeds as kobuki_velocity_smoother does (both changes shrunk
    by one factor, `randomize.coupled_smoother`); False: each on its own, which the robot's
    smoother does not (`smoother_note`)."""

    @classmethod
    def from_policy(cls, arrays: dict, config, source, folder: str = "robot") -> Deployment:
        """From `export.actor_arrays`' arrays and the run's config (a `RunConfig`)."""
        sensor = config.sensor
        names = [str(n) for n in arrays["action_names"]]
        commands = np.asarray(arrays["commands"], np.float64)
        actions = tuple((n, float(v), float(w)) for n, (v, w) in zip(names, commands, strict=True))
        accel, note = trained_accel(config.randomize)
        return cls(
            source=str(source),
            folder=folder,
            control_period=float(arrays["control_period"]),
            actions=actions,
            sensor=f"{math.degrees(sensor.fov):g} deg field of view in {sensor.num_sectors} "
            f"sectors, {sensor.range_min:g}-{sensor.range_max:g} m",
            top_speed=(float(config.robot.max_linear_speed), float(config.robot.max_angular_speed)),
            accel_limit=accel,
            accel_note=note,
            camera_height=float(arrays["camera_height"]),
            camera_pitch=float(arrays["camera_pitch"]),
            blind_fraction=float(sensor.blind_fraction),
            readings_per_stray=int(sensor.readings_per_stray),
            coupled_smoother=bool(config.randomize.coupled_smoother),
        )


def trained_accel(randomize) -> tuple[tuple[float, float], str]:
    """((m/s^2, rad/s^2), where from): the middle of the run's `accel_limit` and
    `angular_accel_limit` ranges; where training had no limit (a range of zeros), the middle of
    `randomize.FIDELITY`'s (the Kobuki's nominal 0.3 m/s^2, 3.5 rad/s^2)."""
    limits, fallback = [], []
    for name in ("accel_limit", "angular_accel_limit"):
        low, high = getattr(randomize, name)
        if high > 0:
            limits.append(0.5 * (low + high))
        else:
            limits.append(0.5 * sum(FIDELITY[name]))
            fallback.append(name)
    if not fallback:
        note = "the middle of the ranges the policy trained with (randomize.accel_limit, "
        note += "randomize.angular_accel_limit)"
    else:
        note = f"training had no {' or '.join(fallback)}: the Kobuki's nominal values "
        note += "(the middle of randomize.FIDELITY's ranges)"
    return (float(limits[0]), float(limits[1])), note


def node_parameters(dep: Deployment) -> dict:
    """The policy node's parameters for this policy: the node's flag defaults (`ros_node.parse_args`)
    with the policy's rate, camera mount and sector rule; parameters whose default is unset
    (None or NaN, e.g. vfov_deg: from CameraInfo) are left out."""
    flags = vars(ros_node.parse_args([])[0])
    values = {k: v for k, v in flags.items() if v is not None and not _nan(v)}
    values.update(
        policy="policy.npz",
        cmd_vel=POLICY_TOPIC,
        rate_hz=1.0 / dep.control_period,
        tilt_deg=math.degrees(dep.camera_pitch),
        camera_height=dep.camera_height,
        blind_fraction=dep.blind_fraction,
        readings_per_stray=dep.readings_per_stray,
    )
    return {k: values[k] for k in (*flags, "rate_hz") if k in values}


NODE_NOTES = {
    "policy": "relative to the bundle folder (launch argument policy:=)",
    "topic": "sensor_msgs/Image depth, 32FC1 m or 16UC1 mm (launch argument depth_topic:=)",
    "scan": "true: `topic` is a sensor_msgs/LaserScan (e.g. from depthimage_to_laserscan)",
    "cmd_vel": "output; set by the launch file (cmd_vel with stamped:=true)",
    "stamped": "geometry_msgs/TwistStamped, not Twist; set by the launch file (stamped:=)",
    "camera_info_topic": "sensor_msgs/CameraInfo; empty: camera_info beside `topic`",
    "enable_topic": "std_msgs/Bool: false = zero velocity until true",
    "goal_status_topic": "goal policies: std_msgs/String status",
    "header_stamps": "age sensor messages by header.stamp (false: by arrival)",
    "goal_topic": "goal policies: geometry_msgs/PoseStamped goal (odom, or a frame tf2 links)",
    "goal_frame_tf": "goal policies: a goal in another frame (map) is placed in odom with tf2",
    "goal_tf_max_age": "goal policies: s; that transform older than this refuses the goal",
    "goal_point": "true: goal_topic carries geometry_msgs/PointStamped (RViz's Publish Point)",
    "odom_topic": "goal policies: nav_msgs/Odometry (the Kobuki driver's)",
    "rate_hz": "commands per second: 1 / the control period the policy was trained with",
    "max_age": "s; sensor data older than this: zero velocity",
    "speed_calibration": "multiplies both speeds; measure the robot's and set it",
    "blind_fraction": "a sector with this share of unknown readings reads near (as trained)",
    "readings_per_stray": "a sector reads its (1 + known // this)-th nearest (as trained)",
    "max_unknown": "a frame with more unknown readings than this share: zero velocity",
    "blind_hold": "s such a frame reads near after one that measured a surface that near",
    "band_deg": "one-row policies: image rows within +-this of the horizon are read",
    "tilt_deg": "camera pitch, deg, down +: as trained; config/mount.yaml's where calibrated",
    "camera_height": "camera height above the floor, m: as trained; config/mount.yaml's too",
    "calibration": "check: refuse to drive where the first frames' mount is off tilt_deg, "
    "camera_height; use: drive with that mount; off",
    "calibration_frames": "frames with floor the calibration estimates from (also ~/calibrate)",
    "pitch_tolerance_deg": "calibration check: largest pitch error let pass, deg",
    "height_tolerance": "calibration check: largest camera height error let pass, m",
    "roll_tolerance_deg": "calibration check and use: largest roll let pass, deg",
}


def node_yaml(dep: Deployment) -> str:
    """config/jaxnav.yaml: the policy node's parameters."""
    lines = [
        f"# Parameters of the {NODE_NAME} node (python3 -m {ROBOT_PACKAGE}.ros_node) for policy.npz,",
        f"# exported from {dep.source}.",
        "# Each is also a flag of the node; --ros-args -p NAME:=VALUE overrides (floats need the",
        "# decimal point). Not set here: vfov_deg, the depth image's vertical field of view, which",
        "# CameraInfo gives (set it, e.g. 49.5 for an Astra, where no CameraInfo is published).",
        f"/**/{NODE_NAME}:",
        "  ros__parameters:",
    ]
    for name, value in node_parameters(dep).items():
        note = NODE_NOTES.get(name)
        lines.append(f"    {name}: {_yaml(value)}" + (f"  # {note}" if note else ""))
    return "\n".join(lines) + "\n"


def smoother_parameters(dep: Deployment) -> dict:
    """kobuki_velocity_smoother's parameters (its README's names and types)."""
    return {
        "speed_lim_v": dep.top_speed[0],
        "speed_lim_w": dep.top_speed[1],
        "accel_lim_v": dep.accel_limit[0],
        "accel_lim_w": dep.accel_limit[1],
        "decel_factor": 1.0,
        "frequency": SMOOTHER_HZ,
        "feedback": 2,
        "quiet": True,
    }


SMOOTHER_NOTES = {
    "speed_lim_v": "m/s: the robot's top speed in training",
    "speed_lim_w": "rad/s: the robot's top yaw rate in training",
    "accel_lim_v": "m/s^2",
    "accel_lim_w": "rad/s^2",
    "decel_factor": "training limits slowing down as speeding up",
    "frequency": "Hz: commands out (the policy sends one per control period)",
    "feedback": "2: ramp from the command the mux last sent (~/feedback/cmd_vel)",
    "quiet": "no warning each time the mux hands the robot to another input",
}


SMOOTHER_RULE_GAP = (
    "the gpu preset's goal policy trained so reached 81.7 % success under this smoother's rule "
    "in simulation against 91.9 % trained with it (docs/results.md)"
)


def smoother_note(coupled_smoother: bool) -> str | None:
    """A warning where the policy trained with the simulator's per-axis smoother rule
    (`coupled_smoother` false), which the robot's kobuki_velocity_smoother does not follow; None
    where it trained with the robot's rule."""
    if coupled_smoother:
        return None
    return (
        "the policy trained with each speed's change limited on its own; kobuki_velocity_smoother "
        f"slows the quicker change to keep the turning radius: {SMOOTHER_RULE_GAP}. Check it "
        "with python -m jaxnav.evaluate --coupled-smoother, or retrain with "
        "--randomize.coupled-smoother true"
    )


def smoother_yaml(dep: Deployment) -> str:
    """config/velocity_smoother.yaml."""
    if dep.coupled_smoother:
        rule = ["# The policy trained with this smoother's rule (--randomize.coupled-smoother)."]
    else:
        rule = [
            "# The simulator clamped each speed's change per control period on its own; this",
            "# smoother ramps at the same rates but slows the quicker change to keep the turning",
            "# radius (python -m jaxnav.evaluate --coupled-smoother measures what that costs).",
        ]
    lines = [
        "# kobuki_velocity_smoother between the jaxnav policy and the cmd_vel mux: the limits the",
        f"# policy was trained with (exported from {dep.source}).",
        "# Acceleration limits: " + dep.accel_note.replace(" (", "\n# (", 1) + ".",
        *rule,
        "kobuki_velocity_smoother:",
        "  ros__parameters:",
    ]
    for name, value in smoother_parameters(dep).items():
        lines.append(f"    {name}: {_yaml(value)}  # {SMOOTHER_NOTES[name]}")
    return "\n".join(lines) + "\n"


def mux_yaml() -> str:
    """config/cmd_vel_mux.yaml: its subscribers, each a topic, a timeout (s, a double), a unique
    priority (higher wins) and a short description (cmd_vel_mux's format)."""
    lines = [
        "# cmd_vel_mux: the highest priority input that has sent within its timeout drives the",
        f"# robot; its output goes to {DRIVER_TOPIC} (the Kobuki driver). The safety controller",
        "# (bumper, cliff, wheel drop) ranks above a person, who ranks above the policy.",
        "cmd_vel_mux:",
        "  ros__parameters:",
        "    subscribers:",
    ]
    for name, topic, timeout, priority, desc in MUX_INPUTS:
        lines += [
            f"      {name}:",
            f"        topic: {_yaml(topic)}",
            f"        timeout: {_yaml(float(timeout))}",
            f"        priority: {priority}",
            f"        short_desc: {_yaml(desc)}",
        ]
    return "\n".join(lines) + "\n"


def _nan(value) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _yaml(value) -> str:
    """A YAML scalar of the type a ROS parameter needs: floats always with a decimal point."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a finite number: {value}")
        return np.format_float_positional(value, precision=6, unique=True, trim="0")
    return json.dumps(str(value))  # a double-quoted YAML string


LAUNCH = '''"""Starts the jaxnav policy on the TurtleBot 2i (written by `python -m jaxnav.export --bundle`).

In the bundle folder, with ROS 2 (Humble or Jazzy) sourced, the Kobuki driver and the camera
driver running:

    ros2 launch launch/jaxnav.launch.py
    ros2 launch launch/jaxnav.launch.py depth_topic:=/camera/depth/image_rect_raw
    ros2 launch launch/jaxnav.launch.py --show-args

Starts the policy node (python3 -m jaxnav_robot.ros_node, from this folder: no colcon build), and
with use_mux:=true (default):

    depth image -> jaxnav_policy -> policy/cmd_vel -> kobuki_velocity_smoother
      -> cmd_vel_mux/input/policy -> cmd_vel_mux -> commands/velocity (the Kobuki driver)
    kobuki_safety_controller -> cmd_vel_mux/input/safety (ranked first)
    teleop -> cmd_vel_mux/input/teleop (ranked above the policy)

The mux's inputs are config/cmd_vel_mux.yaml's; the smoother's limits config/velocity_smoother.yaml's
(those the policy was trained with); the node's parameters config/jaxnav.yaml's, then the camera
mount of config/mount.yaml where `python3 -m jaxnav_robot.calibrate --out config/mount.yaml`
wrote one, which the launch arguments override. use_mux:=false: policy -> smoother -> commands/velocity, no mux, no safety
controller, no teleop. stamped:=true (with use_mux:=false): the node alone, sending
geometry_msgs/TwistStamped on cmd_vel for a stack that takes them (the smoother and the mux take
Twist). driver:=true also starts the Kobuki driver (kobuki_node) on device_port.
"""

import json
import os
from pathlib import Path

import yaml
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, LogInfo, OpaqueFunction
from launch_ros.actions import Node

BUNDLE = Path(__file__).resolve().parent.parent
CONFIG = BUNDLE / "config"
NODE_NAME = "@NODE_NAME@"
POLICY_TOPIC = "@POLICY_TOPIC@"
DRIVER_TOPIC = "@DRIVER_TOPIC@"
FLAGS = ("stamped", "use_mux", "driver")
ARGUMENTS = (
    ("policy", "", "the exported policy file (empty: config/jaxnav.yaml's, policy.npz)"),
    ("depth_topic", "", "sensor_msgs/Image depth topic (empty: config/jaxnav.yaml's)"),
    ("camera_info_topic", "", "sensor_msgs/CameraInfo (empty: config/jaxnav.yaml's)"),
    ("stamped", "false", "send TwistStamped on cmd_vel, the node alone (needs use_mux:=false)"),
    ("use_mux", "true", "cmd_vel_mux: safety controller, then teleop, then the policy"),
    ("driver", "false", "also start the Kobuki driver (kobuki_node)"),
    ("device_port", "/dev/kobuki", "driver:=true: the Kobuki's serial port"),
    ("params_file", str(CONFIG / "jaxnav.yaml"), "the policy node's parameters"),
)


def generate_launch_description():
    declared = [
        DeclareLaunchArgument(
            name,
            default_value=default,
            description=text,
            **({"choices": ["true", "false"]} if name in FLAGS else {}),
        )
        for name, default, text in ARGUMENTS
    ]
    return LaunchDescription([*declared, OpaqueFunction(function=setup)])


def setup(context, *args, **kwargs):
    """The actions for the launch arguments' values."""
    get = context.launch_configurations
    stamped, use_mux, driver = (_flag(get, name) for name in FLAGS)
    actions = [_driver(get["device_port"])] if driver else []
    if stamped:
        if use_mux:
            raise RuntimeError(
                "stamped:=true needs use_mux:=false: cmd_vel_mux and the velocity smoother take "
                "geometry_msgs/Twist"
            )
        note = f"{NODE_NAME} sends TwistStamped on cmd_vel; no smoother, no mux"
        return [*actions, LogInfo(msg=note), _policy(get, "cmd_vel", True)]
    _require("kobuki_velocity_smoother", "")
    if not use_mux:
        note = f"use_mux:=false: {NODE_NAME} -> smoother -> {DRIVER_TOPIC}; no teleop, no safety"
        return [*actions, LogInfo(msg=note), _policy(get), _smoother(DRIVER_TOPIC)]
    _require("cmd_vel_mux", " (or use_mux:=false)")
    mux = _parameters("cmd_vel_mux.yaml", "cmd_vel_mux")
    inputs = mux["subscribers"]
    actions += [_policy(get), _smoother(inputs[NODE_NAME]["topic"]), _mux(mux)]
    if _installed("kobuki_safety_controller"):
        actions.append(_safety(inputs["safety_controller"]["topic"]))
    else:
        msg = "kobuki_safety_controller is not installed: no back-off on bumper or cliff events"
        actions.append(LogInfo(msg=msg))
    return actions


def _policy(get, cmd_vel=POLICY_TOPIC, stamped=False):
    """The policy node, run from the bundle folder; the launch arguments given override
    params_file's values."""
    overrides = {"cmd_vel": cmd_vel, "stamped": stamped}
    for arg, name in (("policy", "policy"), ("depth_topic", "topic")):
        if get[arg]:
            overrides[name] = get[arg]
    if get["camera_info_topic"]:
        overrides["camera_info_topic"] = get["camera_info_topic"]
    if "policy" in overrides:  # relative to where ros2 launch was started, not to the bundle
        overrides["policy"] = str(Path(overrides["policy"]).expanduser().resolve())
    params_file = str(Path(get["params_file"]).expanduser().resolve())
    cmd = ["python3", "-m", "jaxnav_robot.ros_node", "--ros-args", "--params-file", params_file]
    if (CONFIG / "mount.yaml").is_file():  # python3 -m jaxnav_robot.calibrate's: it wins
        cmd += ["--params-file", str(CONFIG / "mount.yaml")]
    for name, value in overrides.items():  # after the file: these win
        text = ("true" if value else "false") if isinstance(value, bool) else json.dumps(value)
        cmd += ["-p", f"{name}:={text}"]
    return ExecuteProcess(
        cmd=cmd,
        cwd=str(BUNDLE),
        name=NODE_NAME,
        output="screen",
        additional_env={"PYTHONUNBUFFERED": "1"},
    )


def _smoother(output):
    return Node(
        package="kobuki_velocity_smoother",
        executable="velocity_smoother",
        name="kobuki_velocity_smoother",
        parameters=[_parameters("velocity_smoother.yaml", "kobuki_velocity_smoother")],
        remappings=[
            ("~/input", POLICY_TOPIC),
            ("~/smoothed", output),
            ("~/feedback/cmd_vel", DRIVER_TOPIC),
        ],
        output="screen",
    )


def _mux(parameters):
    return Node(
        package="cmd_vel_mux",
        executable="cmd_vel_mux_node",
        name="cmd_vel_mux",
        parameters=[parameters],
        remappings=[("cmd_vel", DRIVER_TOPIC), ("active", "cmd_vel_mux/active")],
        output="screen",
    )


def _safety(output):
    """kobuki_safety_controller: on the driver's events/bumper, events/cliff, events/wheel_drop it
    backs off (or stops) on its cmd_vel; enabled from the start (publish std_msgs/Empty on
    `enable` where an older release starts it disabled)."""
    return Node(
        package="kobuki_safety_controller",
        executable="kobuki_safety_controller_node",
        name="kobuki_safety_controller",
        remappings=[("cmd_vel", output)],
        output="screen",
    )


def _driver(device_port):
    _require("kobuki_node", " (or driver:=false, with the driver started elsewhere)")
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory("kobuki_node"))
    defaults = share / "config" / "kobuki_node_params.yaml"  # the driver's own example values
    parameters = []
    if defaults.is_file():
        values = yaml.safe_load(defaults.read_text())["kobuki_ros_node"]["ros__parameters"]
        parameters.append(values)
    parameters.append({"device_port": device_port})
    return Node(
        package="kobuki_node",
        executable="kobuki_ros_node",
        parameters=parameters,
        output="screen",
    )


def _parameters(file, node):
    """The ros__parameters of `node` in config/`file`."""
    return yaml.safe_load((CONFIG / file).read_text())[node]["ros__parameters"]


def _flag(get, name):
    value = str(get[name]).strip().lower()
    if value not in ("true", "false"):
        raise ValueError(f"{name}:={get[name]}: must be true or false")
    return value == "true"


def _installed(package):
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        get_package_share_directory(package)
    except PackageNotFoundError:
        return False
    return True


def _require(package, alternative):
    if not _installed(package):
        distro = os.environ.get("ROS_DISTRO", "<distro>")
        debian = f"ros-{distro}-{package.replace('_', '-')}"
        raise RuntimeError(f"{package} is not installed: apt install {debian}{alternative}")
'''


def launch_file() -> str:
    """launch/jaxnav.launch.py."""
    text = LAUNCH
    for name, value in (
        ("NODE_NAME", NODE_NAME),
        ("POLICY_TOPIC", POLICY_TOPIC),
        ("DRIVER_TOPIC", DRIVER_TOPIC),
    ):
        text = text.replace(f"@{name}@", value)
    return text


DOCKERFILE = """# The jaxnav policy on the TurtleBot 2i's computer: ROS 2 Humble (default) or Jazzy.
# In the bundle folder:
#   docker build -t jaxnav .                                 # ROS 2 Humble
#   docker build -t jaxnav --build-arg ROS_DISTRO=jazzy .    # ROS 2 Jazzy
#   docker run --rm -it --name jaxnav --net=host --ipc=host jaxnav
#   docker run ... jaxnav ros2 launch {launch} use_mux:=false    # launch arguments
# The Kobuki driver and the depth camera's driver run outside (or driver:=true, with
# --device /dev/kobuki). Packages not released for a distribution are skipped; the launch file
# says which one it misses.
ARG ROS_DISTRO=humble
FROM ros:${{ROS_DISTRO}}-ros-base
ARG ROS_DISTRO

RUN apt-get update \\
    && apt-get install -y --no-install-recommends python3-numpy python3-yaml \\
        ros-${{ROS_DISTRO}}-kobuki-velocity-smoother \\
    && for pkg in {optional}; do \\
        apt-get install -y --no-install-recommends "ros-${{ROS_DISTRO}}-$pkg" \\
            || echo "ros-${{ROS_DISTRO}}-$pkg: not released for ${{ROS_DISTRO}}, skipped"; \\
    done \\
    && rm -rf /var/lib/apt/lists/*

WORKDIR {home}
COPY . {home}
# docker stop: SIGINT, as Ctrl-C: the policy node sends zero velocity before it exits.
STOPSIGNAL SIGINT
CMD ["ros2", "launch", "{home}/{launch}"]
"""
DOCKER_HOME = "/jaxnav"
OPTIONAL_PACKAGES = (
    "cmd-vel-mux",
    "kobuki-safety-controller",
    "kobuki-node",
    "teleop-twist-keyboard",
    "depthimage-to-laserscan",
)


def dockerfile() -> str:
    """Dockerfile: the robot computer's image, ROS 2 Humble or Jazzy (build arg ROS_DISTRO)."""
    return DOCKERFILE.format(
        launch=LAUNCH_FILE, home=DOCKER_HOME, optional=" ".join(OPTIONAL_PACKAGES)
    )


README = """jaxnav policy for the TurtleBot 2i, exported from {source}

Trained with: {sensor}.
Actions (forward m/s, yaw rad/s): {actions}.
One command every {period:g} s ({rate:g} Hz), through a velocity smoother of {accel_v:g} m/s^2 and
{accel_w:g} rad/s^2 (config/velocity_smoother.yaml holds the same limits).{smoother_note}

The deployment in five commands (ROS 2 Humble or Jazzy; the Kobuki driver, which listens on
commands/velocity, and the depth camera's driver already running on the robot):

  # 1. copy this folder onto the robot's computer
  scp -r {folder} turtlebot:~/jaxnav && ssh turtlebot

  # 2. build the image (--build-arg ROS_DISTRO=jazzy for Jazzy)
  cd ~/jaxnav && docker build -t jaxnav .

  # 3. launch: policy -> velocity smoother -> cmd_vel mux -> commands/velocity
  docker run --rm -it --name jaxnav --net=host --ipc=host jaxnav

  # 4. take over with the keyboard (a second terminal; the policy drives again 1 s after the last key)
  docker exec -it jaxnav /ros_entrypoint.sh ros2 run teleop_twist_keyboard teleop_twist_keyboard --ros-args -r cmd_vel:={teleop}

  # 5. stop (the policy sends zero; the Kobuki driver stops the base within 0.6 s anyway)
  docker stop jaxnav

Without Docker, steps 2 and 3 are (in this folder):

  source /opt/ros/humble/setup.bash    # humble or jazzy, in this line and the next
  sudo apt install ros-humble-kobuki-velocity-smoother ros-humble-cmd-vel-mux ros-humble-kobuki-safety-controller
  ros2 launch {launch}

Launch arguments (name:=value after the launch command; --show-args lists them): policy,
depth_topic, camera_info_topic (default: config/jaxnav.yaml's), use_mux (true: the mux ranks
kobuki_safety_controller, then teleop, then the policy; false: policy -> smoother ->
commands/velocity alone), stamped (true, with use_mux:=false: TwistStamped on cmd_vel, the node
alone), driver (true: also start the Kobuki driver on device_port; docker run --device /dev/kobuki).
Pause the policy (zero velocity) and resume it:

  ros2 topic pub --once /{node}/enable std_msgs/msg/Bool "{{data: false}}"
  ros2 topic pub --once /{node}/enable std_msgs/msg/Bool "{{data: true}}"

Re-check the camera mount (robot on open floor; zero velocity meanwhile, the answer says whether
it drives again):

  ros2 service call /{node}/calibrate std_srvs/srv/Trigger

The configuration: {node_config} (the policy node: topics, rate, camera mount,
speed_calibration), {smoother_config} (the limits the policy trained with),
{mux_config} (inputs, timeouts, priorities).

The node alone, without the launch file (ROS 2 sourced, in this folder):

  # depth camera -> policy -> Kobuki base (kobuki_ros listens on commands/velocity)
  python3 -m {package}.ros_node --policy policy.npz --ros-args -r cmd_vel:=commands/velocity

  # a LaserScan instead of the depth image
  python3 -m {package}.ros_node --policy policy.npz --scan --topic /scan \\
      --ros-args -r cmd_vel:=commands/velocity

  # the robot moves slower or faster than commanded: scale both speeds
  python3 -m {package}.ros_node --policy policy.npz \\
      --ros-args -r cmd_vel:=commands/velocity -p speed_calibration:=1.2

  # the camera's height (m) and pitch (deg, down +), for the floor rule of policies trained
  # with several rows, measured from the floor (robot on open floor; the launch file reads
  # config/mount.yaml; the node checks the mount at start-up and refuses to drive where it is off)
  python3 -m {package}.calibrate --live /camera/depth/image_raw --out config/mount.yaml
  python3 -m {package}.ros_node --policy policy.npz \\
      --ros-args -r cmd_vel:=commands/velocity -p camera_height:=0.3 -p tilt_deg:=1.0

  # all flags (camera tilt, rows read around the horizon, topics)
  python3 -m {package}.ros_node --help

Without ROS, in Python:

  from {package} import Controller, NumpyPolicy
  from {package}.observation import horizon_rows
  controller = Controller(NumpyPolicy.from_npz("policy.npz"))
  # the pixels of the trained rays, floor left out (Astra: 49.5 deg vertical field of view)
  twist = controller.image_to_twist(depth, vfov=0.864)  # depth [H, W] in metres -> (m/s, rad/s)
  # or, for a one-row policy, the image rows near the horizon
  twist = controller.image_to_twist(depth, horizon_rows(depth.shape[0], vfov=0.864))
"""


def readme(dep: Deployment) -> str:
    """README.txt: the deployment in five commands, then the node alone and without ROS."""
    return README.format(
        source=dep.source,
        sensor=dep.sensor,
        actions=", ".join(f"{n} ({v:g}, {w:g})" for n, v, w in dep.actions),
        period=dep.control_period,
        rate=1.0 / dep.control_period,
        accel_v=dep.accel_limit[0],
        accel_w=dep.accel_limit[1],
        smoother_note=f"\nNote: {note}." if (note := smoother_note(dep.coupled_smoother)) else "",
        folder=dep.folder,
        teleop=dict((name, topic) for name, topic, *_ in MUX_INPUTS)["teleop"],
        launch=LAUNCH_FILE,
        node=NODE_NAME,
        node_config=NODE_CONFIG,
        smoother_config=SMOOTHER_CONFIG,
        mux_config=MUX_CONFIG,
        package=ROBOT_PACKAGE,
    )


def write_deployment(folder: Path, dep: Deployment) -> None:
    """Writes the launch file, the configuration, the Dockerfile and README.txt into `folder`."""
    files = {
        LAUNCH_FILE: launch_file(),
        NODE_CONFIG: node_yaml(dep),
        SMOOTHER_CONFIG: smoother_yaml(dep),
        MUX_CONFIG: mux_yaml(),
        "Dockerfile": dockerfile(),
        "README.txt": readme(dep),
    }
    for name, text in files.items():
        path = Path(folder) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
