"""The deployment files of a robot bundle (`jaxnav.bundle`), which cannot run here: the launch file
is run against stand-ins for ROS 2's `launch`, `launch_ros` and `ament_index_python` modules, the
parameter files are read back and checked against the parameters the node declares and
cmd_vel_mux's format, and the Dockerfile and the README are read."""

import dataclasses
import importlib.util
import math
import re
import sys
import types
from pathlib import Path

import pytest
import yaml
from test_export import one_run, runs  # noqa: F401  (the checkpoint: made once, no training)

from jaxnav import bundle, export
from jaxnav.core.randomize import FIDELITY, TRAINING, RandomizeConfig
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.robot_side import ros_node

DOCS = Path(__file__).resolve().parents[1] / "docs" / "deployment.md"
# The ROS packages of the default launch; kobuki_node only with driver:=true.
ROS_PACKAGES = {
    "kobuki_velocity_smoother",
    "cmd_vel_mux",
    "kobuki_safety_controller",
    "kobuki_node",
}
SMOOTHER_PARAMETERS = {  # kobuki_velocity_smoother's README: name -> type
    "speed_lim_v": float,
    "speed_lim_w": float,
    "accel_lim_v": float,
    "accel_lim_w": float,
    "decel_factor": float,
    "frequency": float,
    "feedback": int,
    "quiet": bool,
}
MUX_FIELDS = {"topic": str, "timeout": float, "priority": int, "short_desc": str}


@pytest.fixture(scope="module")
def deployed(one_run, tmp_path_factory):  # noqa: F811
    """A bundle folder written by `export.bundle`."""
    return export.bundle(one_run[0], tmp_path_factory.mktemp("bundle") / "robot")


def read_yaml(folder: Path, name: str) -> dict:
    return yaml.safe_load((folder / name).read_text())


# Stand-ins for the ROS 2 launch API: each records how it was made.
class Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def stub_modules(installed) -> dict[str, types.ModuleType]:
    """The modules the launch file imports, as stand-ins; `installed`: the ROS packages found."""
    modules = {
        name: types.ModuleType(name)
        for name in (
            "launch",
            "launch.actions",
            "launch_ros",
            "launch_ros.actions",
            "ament_index_python",
            "ament_index_python.packages",
        )
    }
    modules["launch"].LaunchDescription = type("LaunchDescription", (Recorded,), {})
    for name in ("DeclareLaunchArgument", "ExecuteProcess", "LogInfo", "OpaqueFunction"):
        setattr(modules["launch.actions"], name, type(name, (Recorded,), {}))
    modules["launch_ros.actions"].Node = type("Node", (Recorded,), {})

    class PackageNotFoundError(KeyError):
        pass

    def get_package_share_directory(package):
        if package not in installed:
            raise PackageNotFoundError(package)
        return f"/opt/ros/share/{package}"

    packages = modules["ament_index_python.packages"]
    packages.PackageNotFoundError = PackageNotFoundError
    packages.get_package_share_directory = get_package_share_directory
    modules["launch"].actions = modules["launch.actions"]
    modules["launch_ros"].actions = modules["launch_ros.actions"]
    modules["ament_index_python"].packages = packages
    return modules


@pytest.fixture
def launch(deployed, monkeypatch):
    """launch(installed=ROS_PACKAGES, **arguments) -> the actions the bundle's launch file starts
    for those launch arguments, with those ROS packages installed."""

    def run(installed=ROS_PACKAGES, **arguments):
        for name, module in stub_modules(set(installed)).items():
            monkeypatch.setitem(sys.modules, name, module)
        path = deployed / bundle.LAUNCH_FILE
        spec = importlib.util.spec_from_file_location("jaxnav_bundle_launch", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        description = module.generate_launch_description()
        entities = description.args[0]
        declared = {
            e.args[0]: e.kwargs["default_value"]
            for e in entities
            if type(e).__name__ == "DeclareLaunchArgument"
        }
        unknown = set(arguments) - set(declared)
        assert not unknown, f"not launch arguments: {unknown}"
        (opaque,) = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
        context = types.SimpleNamespace(launch_configurations={**declared, **arguments})
        return opaque.kwargs["function"](context)

    return run


def by_kind(actions) -> dict:
    """{"jaxnav": the policy process, package: its Node, "log": [messages]}."""
    out = {"log": []}
    for action in actions:
        kind = type(action).__name__
        if kind == "ExecuteProcess":
            out["jaxnav"] = action
        elif kind == "Node":
            out[action.kwargs["package"]] = action
        else:
            assert kind == "LogInfo", kind
            out["log"].append(action.kwargs["msg"])
    return out


def node_overrides(process) -> dict:
    """The `-p NAME:=VALUE` parameters of the policy process, VALUE read as ROS reads it (YAML)."""
    cmd = process.kwargs["cmd"]
    pairs = [cmd[i + 1] for i, word in enumerate(cmd) if word == "-p"]
    return {k: yaml.safe_load(v) for k, v in (p.split(":=", 1) for p in pairs)}


def remapped(node) -> dict:
    return dict(node.kwargs["remappings"])


def test_bundle_holds_the_deployment_files(deployed):
    assert sorted(p.name for p in deployed.iterdir()) == sorted(export.BUNDLE)
    for name in (bundle.LAUNCH_FILE, bundle.NODE_CONFIG, bundle.SMOOTHER_CONFIG, bundle.MUX_CONFIG):
        assert (deployed / name).is_file(), name
    compile((deployed / bundle.LAUNCH_FILE).read_text(), bundle.LAUNCH_FILE, "exec")


def test_launch_reads_the_calibrated_mount(deployed, launch):
    """config/mount.yaml, as `python3 -m jaxnav_robot.calibrate --out` writes it, is passed after
    config/jaxnav.yaml (so its tilt_deg and camera_height win) where it exists."""
    mount = deployed / "config" / "mount.yaml"
    mount.write_text("/**/jaxnav_policy:\n  ros__parameters:\n    tilt_deg: 2.0\n")
    try:
        cmd = by_kind(launch())["jaxnav"].kwargs["cmd"]
    finally:
        mount.unlink()
    files = [cmd[i + 1] for i, word in enumerate(cmd) if word == "--params-file"]
    assert files == [str(deployed / bundle.NODE_CONFIG), str(mount)]
    cmd = by_kind(launch())["jaxnav"].kwargs["cmd"]
    assert cmd.count("--params-file") == 1


def test_launch_connects_policy_smoother_mux_and_safety_controller(deployed, launch):
    started = by_kind(launch())
    assert set(started) == {"jaxnav", "kobuki_velocity_smoother", "cmd_vel_mux",
                            "kobuki_safety_controller", "log"}  # fmt: skip
    policy, smoother = started["jaxnav"], started["kobuki_velocity_smoother"]
    mux, safety = started["cmd_vel_mux"], started["kobuki_safety_controller"]
    # The node runs from the bundle folder (its jaxnav_robot package), no colcon build.
    cmd = policy.kwargs["cmd"]
    assert cmd[:4] == ["python3", "-m", "jaxnav_robot.ros_node", "--ros-args"]
    assert Path(policy.kwargs["cwd"]) == deployed and (deployed / "jaxnav_robot").is_dir()
    assert cmd[4:6] == ["--params-file", str(deployed / bundle.NODE_CONFIG)]  # before the -p
    assert node_overrides(policy) == {"cmd_vel": bundle.POLICY_TOPIC, "stamped": False}
    # policy -> smoother -> the mux's policy input; the mux -> the driver; safety -> its input.
    inputs = read_yaml(deployed, bundle.MUX_CONFIG)["cmd_vel_mux"]["ros__parameters"]
    inputs = inputs["subscribers"]
    assert remapped(smoother)["~/input"] == node_overrides(policy)["cmd_vel"]
    assert remapped(smoother)["~/smoothed"] == inputs["jaxnav_policy"]["topic"]
    assert remapped(smoother)["~/feedback/cmd_vel"] == "commands/velocity"
    assert remapped(mux)["cmd_vel"] == "commands/velocity"
    assert remapped(safety)["cmd_vel"] == inputs["safety_controller"]["topic"]
    # The nodes get the parameters of the bundle's files.
    smoothing = read_yaml(deployed, bundle.SMOOTHER_CONFIG)
    assert smoother.kwargs["parameters"] == [
        smoothing["kobuki_velocity_smoother"]["ros__parameters"]
    ]
    assert mux.kwargs["parameters"][0]["subscribers"] == inputs
    executables = {n.kwargs["package"]: n.kwargs["executable"] for n in (smoother, mux, safety)}
    assert executables == {
        "kobuki_velocity_smoother": "velocity_smoother",
        "cmd_vel_mux": "cmd_vel_mux_node",
        "kobuki_safety_controller": "kobuki_safety_controller_node",
    }


def test_launch_arguments(deployed, launch, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a relative policy path is where ros2 launch was started
    started = by_kind(
        launch(
            policy="other.npz",
            depth_topic="/camera/depth/image_rect_raw",
            camera_info_topic="/camera/depth/camera_info",
        )
    )
    got = node_overrides(started["jaxnav"])
    assert got["policy"] == str(tmp_path / "other.npz")
    assert got["topic"] == "/camera/depth/image_rect_raw"
    assert got["camera_info_topic"] == "/camera/depth/camera_info"
    # use_mux:=false: policy -> smoother -> the driver, alone.
    started = by_kind(launch(use_mux="false"))
    assert set(started) == {"jaxnav", "kobuki_velocity_smoother", "log"}
    assert remapped(started["kobuki_velocity_smoother"])["~/smoothed"] == "commands/velocity"
    assert any("no teleop" in msg for msg in started["log"])
    # stamped:=true: the node alone, TwistStamped on cmd_vel; not with the mux (it takes Twist).
    started = by_kind(launch(use_mux="false", stamped="true"))
    assert set(started) == {"jaxnav", "log"}
    assert node_overrides(started["jaxnav"]) == {"cmd_vel": "cmd_vel", "stamped": True}
    with pytest.raises(RuntimeError, match="stamped:=true needs use_mux:=false"):
        launch(stamped="true")
    with pytest.raises(ValueError, match="use_mux:=yes: must be true or false"):
        launch(use_mux="yes")
    # driver:=true: the Kobuki driver too, on the given port.
    started = by_kind(launch(driver="true", device_port="/dev/ttyUSB0"))
    assert started["kobuki_node"].kwargs["executable"] == "kobuki_ros_node"
    assert started["kobuki_node"].kwargs["parameters"][-1] == {"device_port": "/dev/ttyUSB0"}


def test_launch_names_a_missing_package(launch):
    with pytest.raises(RuntimeError, match="cmd_vel_mux is not installed: apt install ros-.*"):
        launch(installed=ROS_PACKAGES - {"cmd_vel_mux"})
    with pytest.raises(RuntimeError, match="kobuki_velocity_smoother is not installed"):
        launch(installed=ROS_PACKAGES - {"kobuki_velocity_smoother"}, use_mux="false")
    with pytest.raises(RuntimeError, match="kobuki_node is not installed"):
        launch(installed=ROS_PACKAGES - {"kobuki_node"}, driver="true")
    # Not released for every distribution: the rest starts, and the log says what is missing.
    started = by_kind(launch(installed=ROS_PACKAGES - {"kobuki_safety_controller"}))
    assert "kobuki_safety_controller" not in started and "cmd_vel_mux" in started
    assert any("kobuki_safety_controller is not installed" in m for m in started["log"])


class ParameterNode:
    """Declares parameters as rclpy does with overrides (a params file): the override's value,
    which must have the type of the declared default (rclpy refuses another)."""

    def __init__(self, overrides: dict):
        self.overrides, self.declared = overrides, {}

    def declare_parameter(self, name, default):
        self.declared[name] = default
        value = self.overrides.get(name, default)
        assert type(value) is type(default), f"{name}: {value!r} for a {type(default).__name__}"
        return types.SimpleNamespace(value=value)


def test_node_parameters_are_those_the_node_declares(deployed, launch):
    (key,) = read_yaml(deployed, bundle.NODE_CONFIG)
    assert key == "/**/jaxnav_policy"  # the node's name in any namespace
    params = read_yaml(deployed, bundle.NODE_CONFIG)[key]["ros__parameters"]
    params["policy"] = str(deployed / params["policy"])  # the node runs in the bundle folder
    node = ParameterNode(params)
    get = ros_node._declare_parameters(node, ros_node.parse_args([])[0])
    assert set(params) <= set(node.declared)
    assert set(node.declared) - set(params) == {"vfov_deg"}  # NaN: CameraInfo's, where published
    # The values the policy needs: its control rate and the camera mount it was trained with.
    assert params["rate_hz"] == 10.0
    assert params["camera_height"] == 0.295 and params["tilt_deg"] == 0.0
    assert params["blind_fraction"] == 0.5 and params["readings_per_stray"] == 50
    loop, rate = ros_node.make_loop(get, print)
    assert rate == 10.0 and loop.controller.policy.action_names == ("forward", "left", "right")
    # The launch file's -p overrides have the types the node declares too.
    for name, value in node_overrides(by_kind(launch(policy="p.npz"))["jaxnav"]).items():
        assert type(value) is type(node.declared[name]), name


def test_velocity_smoother_has_the_trained_limits(deployed):
    (key,) = read_yaml(deployed, bundle.SMOOTHER_CONFIG)
    assert key == "kobuki_velocity_smoother"  # the node's name
    params = read_yaml(deployed, bundle.SMOOTHER_CONFIG)[key]["ros__parameters"]
    assert {k: type(v) for k, v in params.items()} == SMOOTHER_PARAMETERS
    # The run trained with the TRAINING ranges (FIDELITY's): their middles.
    assert TRAINING.accel_limit == (0.25, 0.35) and TRAINING.angular_accel_limit == (3.0, 4.0)
    assert params["accel_lim_v"] == pytest.approx(0.3) and params["accel_lim_w"] == 3.5
    assert params["decel_factor"] == 1.0  # the simulator limits slowing down alike
    assert params["speed_lim_v"] == TURTLEBOT2I.max_linear_speed
    assert params["speed_lim_w"] >= TURTLEBOT2I.max_angular_speed
    assert params["feedback"] == 2  # the mux's output: ramps from what the base was last told
    readme = (deployed / "README.txt").read_text()
    assert "One command every 0.1 s (10 Hz)" in readme
    assert "0.3 m/s^2" in readme and "3.5 rad/s^2" in readme


def test_a_policy_trained_per_axis_is_told_of_the_kobukis_smoother(deployed, one_run):  # noqa: F811
    """The Kobuki's smoother shrinks both speed changes by one factor; a goal policy trained with
    the simulator's per-axis rule lost 11 points of success under it. A bundle of such a policy
    says so (README.txt, the smoother's YAML, the export command), and one trained with the
    robot's rule does not."""
    readme = (deployed / "README.txt").read_text()
    assert "Note: the policy trained with each speed's change limited on its own" in readme
    assert "--randomize.coupled-smoother true" in readme
    smoother = (deployed / bundle.SMOOTHER_CONFIG).read_text()
    assert "python -m jaxnav.evaluate --coupled-smoother" in smoother
    saved = export.read_policy(export.resolve(one_run[0]))
    dep = bundle.Deployment.from_policy(export.actor_arrays(saved), saved.config, "run")
    assert dep.coupled_smoother is False
    coupled = dataclasses.replace(dep, coupled_smoother=True)
    assert "Note:" not in bundle.readme(coupled)
    assert "trained with this smoother's rule" in bundle.smoother_yaml(coupled)
    assert bundle.smoother_note(True) is None


def test_accel_limits_where_training_had_none():
    bare = RandomizeConfig()  # no smoother in training: the Kobuki's nominal values
    accel, note = bundle.trained_accel(bare)
    assert accel == pytest.approx((0.3, 3.5))
    assert accel == pytest.approx(tuple(0.5 * sum(FIDELITY[k]) for k in FIDELITY if "accel" in k))
    assert "no accel_limit or angular_accel_limit" in note
    accel, note = bundle.trained_accel(RandomizeConfig(accel_limit=(0.5, 0.7)))
    assert accel == pytest.approx((0.6, 3.5)) and "no angular_accel_limit" in note


def test_cmd_vel_mux_ranks_safety_then_teleop_then_policy(deployed):
    (key,) = read_yaml(deployed, bundle.MUX_CONFIG)
    assert key == "cmd_vel_mux"  # the node's name
    inputs = read_yaml(deployed, bundle.MUX_CONFIG)[key]["ros__parameters"]["subscribers"]
    for name, fields in inputs.items():  # all four, of their types; the mux refuses less
        assert {k: type(v) for k, v in fields.items()} == MUX_FIELDS, name
        assert fields["topic"] and fields["short_desc"] and fields["timeout"] > 0, name
        assert 0 <= fields["priority"] <= 2**32 - 1, name
    priorities = [fields["priority"] for fields in inputs.values()]
    assert len(set(priorities)) == len(priorities)  # unique, as the mux requires
    rank = sorted(inputs, key=lambda name: -inputs[name]["priority"])
    assert rank == ["safety_controller", "teleop", "jaxnav_policy"]
    # The smoother sends at its frequency while the policy runs: the input outlasts two sends.
    frequency = read_yaml(deployed, bundle.SMOOTHER_CONFIG)["kobuki_velocity_smoother"]
    frequency = frequency["ros__parameters"]["frequency"]
    assert inputs["jaxnav_policy"]["timeout"] >= 2 / frequency


def test_dockerfile_builds_humble_or_jazzy_with_the_bundle(deployed, launch):
    text = (deployed / "Dockerfile").read_text()
    lines = [line for line in text.splitlines() if not line.startswith("#")]
    assert lines[0] == "ARG ROS_DISTRO=humble"  # before FROM: it picks the base image
    assert lines[1].startswith("FROM ros:${ROS_DISTRO}-")
    assert "--build-arg ROS_DISTRO=jazzy" in text
    assert "python3-numpy" in text
    packaged = set(re.findall(r"ros-\$\{ROS_DISTRO\}-([a-z0-9-]+)", text))
    packaged |= set(bundle.OPTIONAL_PACKAGES)
    for package in ROS_PACKAGES | {"depthimage_to_laserscan", "teleop_twist_keyboard"}:
        assert package.replace("_", "-") in packaged, package
    started = by_kind(launch(driver="true"))  # every package the launch file starts is installed
    assert {k for k in started if k not in ("jaxnav", "log")} <= ROS_PACKAGES
    (copy,) = [line for line in lines if line.startswith("COPY ")]
    home = copy.split()[-1]
    assert copy.split()[1] == "." and f"WORKDIR {home}" in lines
    (cmd,) = [line for line in lines if line.startswith("CMD ")]
    launched = Path(cmd.split('"')[-2])
    assert cmd.startswith('CMD ["ros2", "launch"') and launched.parent.parent == Path(home)
    assert (deployed / launched.relative_to(home)).is_file()
    assert "STOPSIGNAL SIGINT" in lines  # docker stop = Ctrl-C: the node sends zero first


def five_commands(text: str) -> list[str]:
    """The command after each of the README's `# 1.` ... `# 5.` lines."""
    lines = [line.strip() for line in text.splitlines()]
    return [lines[i + 1] for i, line in enumerate(lines) if re.match(r"# [1-5]\. ", line)]


def test_readme_deploys_in_five_commands(deployed):
    readme = (deployed / "README.txt").read_text()
    commands = five_commands(readme)
    assert len(commands) == 5
    assert commands[0].startswith("scp -r robot ")  # the bundle folder's name
    assert "docker build -t jaxnav ." in commands[1]
    assert commands[2].startswith("docker run ") and commands[2].endswith(" jaxnav")
    inputs = read_yaml(deployed, bundle.MUX_CONFIG)["cmd_vel_mux"]["ros__parameters"]
    teleop = inputs["subscribers"]["teleop"]["topic"]
    assert commands[3].endswith(f"teleop_twist_keyboard --ros-args -r cmd_vel:={teleop}")
    assert commands[4] == "docker stop jaxnav"
    assert f"ros2 launch {bundle.LAUNCH_FILE}" in readme  # without Docker
    # The documentation shows the same five commands.
    assert five_commands(DOCS.read_text()) == commands


def test_yaml_numbers_keep_their_type():
    assert [bundle._yaml(v) for v in (1.0, 10.0, 0.295, math.pi, 3, True, "a b")] == [
        "1.0",
        "10.0",
        "0.295",
        "3.141593",
        "3",
        "true",
        '"a b"',
    ]
    with pytest.raises(ValueError):
        bundle._yaml(math.nan)


def test_a_file_where_a_bundle_has_a_folder_is_not_replaced(tmp_path):
    folder = tmp_path / "robot"
    folder.mkdir()
    (folder / "config").write_text("")  # not a previous bundle's config/
    with pytest.raises(export.ExportError, match="its config is not a folder"):
        export.check_bundle(folder)
    (folder / "config").unlink()
    (folder / "config").mkdir()
    export.check_bundle(folder)  # a previous bundle's: replaced
