"""The camera mount from the floor (`robot_side.calibrate`): the estimate on synthetic 640x480
frames, the node's start-up check, the command line (also from a bundle, without jax)."""

import math
import shutil
import types

import numpy as np
import pytest
import yaml
from test_robot_side import ASTRA_K, ROOT, run_without_jax, write_policy_npz
from test_ros_node import FakeRos, camera_info

from jaxnav.robot_side import calibrate, ros_node
from jaxnav.robot_side.calibrate import (
    CalibrationError,
    StartupCalibration,
    estimate_mount,
    frame_mount,
)
from jaxnav.robot_side.observation import Sensor, depth_image_to_sectors
from jaxnav.robot_side.policy import NumpyPolicy

HEIGHT = 0.295  # m: the 2i's camera
ROWS = tuple(np.linspace(-0.38, 0.17, 5))  # a 5-row policy's ray elevations
FIVE_ROWS = Sensor(math.radians(60.0), 8, 0.6, 8.0, elevations=ROWS, camera_height=HEIGHT)
WALL = (5.0, 5.1, -20.0, 20.0, 3.0)  # a wall across the view 5 m ahead
BOXES = ((1.0, 1.6, -0.4, 0.2, 0.3), (0.8, 1.2, 0.3, 0.7, 0.6))  # box footprints ahead, tops


def tilted_frame(pitch=0.0, roll=0.0, height=HEIGHT, boxes=(WALL,), noise=None, camera=ASTRA_K):
    """[H, W] float32 depth (m) as the Astra reports it (millimetres, 0 outside 0.6-8 m) from a
    camera `height` m above the floor, pitched `pitch` down and rolled `roll` (rad, left side up):
    the floor and boxes (x0, x1, y0, y1, top; m, x ahead, y left, from the floor up). `noise`: a
    Generator adding the structured-light error, sd 0.0016 d^2 m."""
    rows, cols = np.mgrid[: camera.height, : camera.width]
    ray = camera.back_project(np.ones(rows.size), rows.ravel(), cols.ravel())  # [N, 3] per m
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    down = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])  # about the left axis
    rolled = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])  # about the forward one
    world = ray @ (down @ rolled).T  # [N, 3] forward, left, up per metre of depth
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(world[:, 2] < 0, -height / world[:, 2], np.inf)
        for x0, x1, y0, y1, top in boxes:  # the slab test, the camera at the origin
            a = (np.array([x0, y0, -height]) / world).T
            b = (np.array([x1, y1, top - height]) / world).T
            near = np.nanmax(np.minimum(a, b), 0)
            far = np.nanmin(np.maximum(a, b), 0)
            depth = np.where((near <= far) & (near > 0), np.minimum(depth, near), depth)
    depth = depth.reshape(camera.height, camera.width)
    if noise is not None:
        depth = depth + noise.normal(size=depth.shape) * 0.0016 * np.minimum(depth, 9.0) ** 2
    depth = np.round(depth * 1000) / 1000  # 16UC1 millimetres
    return np.where((depth >= 0.6) & (depth <= 8.0), depth, 0.0).astype(np.float32)


@pytest.mark.parametrize(
    "pitch_deg, roll_deg, height, boxes",
    [
        (0.0, 0.0, HEIGHT, (WALL,)),
        (2.0, 0.0, HEIGHT, (WALL,)),
        (-3.0, 1.0, 0.31, (WALL,)),
        (2.5, -0.5, 0.28, (WALL, *BOXES)),  # boxes on the floor ahead
        (8.0, 0.0, 0.45, (WALL, *BOXES)),  # a stand tilted far down on the top deck
    ],
)
def test_estimate_is_within_a_fifth_of_a_degree_and_a_centimetre(
    pitch_deg, roll_deg, height, boxes
):
    rng = np.random.default_rng(0)
    pitch, roll = math.radians(pitch_deg), math.radians(roll_deg)
    frames = [tilted_frame(pitch, roll, height, boxes, noise=rng) for _ in range(3)]
    mount = estimate_mount(frames, ASTRA_K, pitch=math.radians(pitch_deg // 4 * 4))
    assert (
        math.degrees(abs(mount.pitch - pitch)) < 0.2 and math.degrees(abs(mount.roll - roll)) < 0.2
    )
    assert abs(mount.height - height) < 0.01
    assert mount.frames == 3 and mount.rejected == 0 and mount.residual < 0.005
    assert 0.3 < mount.floor_share <= 1.0


def test_frames_with_too_little_floor_are_rejected():
    """A box filling the view's lower half leaves no floor: the frame is rejected, with one line;
    others with floor still give the estimate."""
    blocked = tilted_frame(math.radians(2.0), boxes=((0.7, 1.0, -2.0, 2.0, 1.0),))
    with pytest.raises(CalibrationError, match=r"^(floor in \d+ %|\d+ of \d+ lower-image)"):
        frame_mount(blocked, ASTRA_K)
    with pytest.raises(
        CalibrationError, match=r"^no floor found: frame 0: .* \(and 1 more frames\)$"
    ):
        estimate_mount([blocked, blocked], ASTRA_K)
    mount = estimate_mount([blocked, tilted_frame(math.radians(2.0))], ASTRA_K)
    assert mount.frames == 1 and mount.rejected == 1
    assert math.degrees(mount.pitch) == pytest.approx(2.0, abs=0.1)
    with pytest.raises(CalibrationError, match="need \\[N, H, W\\]"):
        estimate_mount(np.zeros(5), ASTRA_K)


def obs(depth, pitch=0.0, height=HEIGHT) -> np.ndarray:
    """The 5-row observation the node reads from an Astra frame, its floor rule at the mount
    (pitch rad, height m) it is given."""
    sensor = Sensor(**{**vars(FIVE_ROWS), "camera_pitch": pitch, "camera_height": height})
    return depth_image_to_sectors(depth, sensor, camera=ASTRA_K)


def test_calibrated_mount_removes_the_phantom():
    """Open floor and a wall at 5 m, the camera pitched 2 deg down from the configured mount: the
    floor rule at the configured mount sees a phantom obstacle under 1 m; at the estimated mount
    every sector reads the wall. The tolerances: 1 deg of pitch or 2 cm of height error still
    reads the wall (so PITCH_TOLERANCE_DEG and HEIGHT_TOLERANCE pass only harmless errors), 1.1
    deg does not."""
    frame = tilted_frame(math.radians(2.0))
    assert obs(frame).min() == pytest.approx(0.93, abs=0.01)  # the phantom
    mount = estimate_mount([frame], ASTRA_K)
    # camera depth of the wall: 5 m along the floor, less along the tilted optical axis
    np.testing.assert_allclose(obs(frame, mount.pitch, mount.height), 5.0, rtol=0.01)
    assert obs(tilted_frame(math.radians(1.0))).min() > 4.9
    assert obs(tilted_frame(math.radians(1.1))).min() < 2.5
    assert obs(tilted_frame(0.0, 0.0, HEIGHT - 0.02)).min() == pytest.approx(5.0)
    assert 2 * calibrate.PITCH_TOLERANCE_DEG <= 1.0 and 2 * calibrate.HEIGHT_TOLERANCE <= 0.02


def image_msg(depth):
    """A 16UC1 sensor_msgs/Image-like message (millimetres), as the Astra driver sends."""
    mm = np.round(np.asarray(depth) * 1000).astype(np.uint16)
    h, w = mm.shape
    return types.SimpleNamespace(
        encoding="16UC1", height=h, width=w, data=mm.tobytes(), step=2 * w, is_bigendian=0
    )


@pytest.fixture(scope="module")
def five_row_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("calibrate") / "policy.npz"
    rows = dict(elevations=np.array(ROWS, np.float32), camera_height=np.float32(HEIGHT))
    return write_policy_npz(path, camera_pitch=np.float32(0.0), **rows)


def node_loop(npz, logs, **params):
    """The node's ControlLoop (`make_loop`) with its flag defaults and `params`."""
    args = ros_node.parse_args(["--policy", str(npz)])[0]
    return ros_node.make_loop({**vars(args), **params}, logs.append)[0]


def run(loop, frame, seconds=1.0, rate=30.0, start=0.0):
    """Sends `frame` at `rate` Hz for `seconds` from `start` s with the camera's CameraInfo,
    ticking at 10 Hz; the states of the ticks."""
    loop.on_camera_info(camera_info(ASTRA_K))
    states = []
    for k in range(round(seconds * rate)):
        now = start + k / rate
        loop.on_observation(image_msg(frame), now)
        if k % 3 == 0:
            loop.tick(now)
            states.append(loop.state)
    return states


def test_node_refuses_a_tilted_camera_and_drives_once_calibrated(five_row_npz, tmp_path, capsys):
    """The node at start-up: a camera 2 deg down from the configured mount is refused (zero
    velocity, one log line saying why and what to do); the mount that `calibrate` writes, or
    calibration:=use, lets it drive, reading the wall at 5 m where it read a phantom."""
    frame = tilted_frame(math.radians(2.0))
    logs = []
    loop = node_loop(five_row_npz, logs)
    states = run(loop, frame)
    assert states[0].startswith("calibrating the camera mount: 1 of 5 frames")
    assert states[-1].startswith("camera mount refused: pitch 2.0") and loop.obs is None
    assert loop.tick(1.0) == ros_node.STOP
    refusals = [line for line in logs if line.startswith("camera mount refused")]
    assert len(refusals) == 1 and "calibration:=use" in refusals[0]
    assert "tilt_deg" in refusals[0] and "jaxnav_robot.calibrate" in refusals[0]
    # The command line's mount, as the launch file passes it (after config/jaxnav.yaml).
    np.save(tmp_path / "frames.npy", np.stack([frame, frame]))
    out = tmp_path / "mount.yaml"
    assert calibrate.main([str(tmp_path / "frames.npy"), "--out", str(out)]) == 0
    params = yaml.safe_load(out.read_text())["/**/jaxnav_policy"]["ros__parameters"]
    assert params["tilt_deg"] == pytest.approx(2.0, abs=0.1)
    assert "pitch 2.0" in capsys.readouterr().out
    loop = node_loop(five_row_npz, logs, **params)
    assert run(loop, frame)[-1] == "policy"
    np.testing.assert_allclose(loop.obs, 5.0, rtol=0.01)
    # Or the estimate used as it is.
    loop = node_loop(five_row_npz, logs, calibration="use")
    assert run(loop, frame)[-1] == "policy"
    np.testing.assert_allclose(loop.obs, 5.0, rtol=0.01)
    # Without the start-up calibration the phantom is back.
    loop = node_loop(five_row_npz, logs, calibration="off")
    assert run(loop, frame)[-1] == "policy" and loop.obs.min() < 1.0


def test_node_waits_for_floor_and_checks_roll(five_row_npz):
    """Frames without floor keep the robot stopped (calibrating, the reason given); a camera
    rolled beyond the tolerance is refused even with calibration:=use (the floor rule has no
    roll)."""
    wall = tilted_frame(boxes=((0.7, 1.0, -2.0, 2.0, 1.0),))
    loop = node_loop(five_row_npz, [])
    states = run(loop, wall)
    assert states[-1].startswith("calibrating the camera mount: 0 of 5 frames (10 without floor")
    loop = node_loop(five_row_npz, [], calibration="use")
    assert run(loop, tilted_frame(roll=math.radians(2.0)))[-1].startswith(
        "camera mount refused: roll 2.0"
    )


def test_only_floor_rule_policies_calibrate(five_row_npz, tmp_path):
    """One-row policies (a band around the horizon, no floor rule) and scans start at once."""
    one_row = write_policy_npz(tmp_path / "one_row.npz")
    assert node_loop(one_row, []).calibration is None
    assert node_loop(five_row_npz, [], scan=True).calibration is None
    assert isinstance(node_loop(five_row_npz, []).calibration, StartupCalibration)
    with pytest.raises(ValueError, match="calibration: must be one of check, use, off"):
        StartupCalibration("sometimes")


def test_command_line_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "frames.txt").write_text("x")
    np.save(tmp_path / "wall.npy", tilted_frame(boxes=((0.7, 1.0, -2.0, 2.0, 1.0),)))
    np.save(tmp_path / "flat.npy", np.zeros(7))
    for argv, message in [
        ([], "give FRAMES (a .npy, .npz or rosbag2) or --live TOPIC, one"),
        ([str(tmp_path / "frames.txt")], "frames.txt: give a .npy, a .npz or a rosbag2 folder"),
        ([str(tmp_path / "flat.npy")], "flat.npy: need depth frames [H, W] or [N, H, W]"),
        ([str(tmp_path / "wall.npy")], "no floor found: frame 0: "),
        ([str(tmp_path / "missing")], "missing: give a .npy, a .npz or a rosbag2 folder"),
    ]:
        assert calibrate.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {message}") or message in err, err
        assert err.count("\n") == 1


def test_calibrate_from_a_bag(tmp_path):
    """A rosbag2 of 16UC1 depth and its CameraInfo (written with rosbags, as the replay reads)."""
    test_replay = pytest.importorskip("test_replay")  # needs rosbags
    ts = test_replay.TS
    frame = tilted_frame(math.radians(-1.5), height=0.3)
    mm = np.round(frame * 1000).astype(np.uint16)
    images = [(k * 33_000_000, test_replay.image(test_replay.T0 + k * 33_000_000, mm, "16UC1"))
              for k in range(3)]  # fmt: skip
    info = ts.types["sensor_msgs/msg/CameraInfo"](
        header=test_replay.header(test_replay.T0), height=480, width=640,
        distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([ASTRA_K.fx, 0, ASTRA_K.cx, 0, ASTRA_K.fy, ASTRA_K.cy, 0, 0, 1], float),
        r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=ts.types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )  # fmt: skip
    bag = test_replay.write_bag(
        tmp_path / "rec",
        {"/camera/depth/image_raw": images, "/camera/depth/camera_info": [(0, info)]},
    )
    frames, camera = calibrate.load_frames(bag)
    assert frames.shape == (3, 480, 640) and camera == ASTRA_K
    mount = estimate_mount(frames, camera)
    assert math.degrees(mount.pitch) == pytest.approx(-1.5, abs=0.1)
    assert mount.height == pytest.approx(0.3, abs=0.005)


def test_bundle_runs_calibrate_without_jax(tmp_path):
    """`python -m jaxnav_robot.calibrate` in a bundle's folder (the package copied as the export
    copies it), with jax blocked."""
    shutil.copytree(
        ROOT / "jaxnav" / "robot_side", tmp_path / "jaxnav_robot",
        ignore=shutil.ignore_patterns("__pycache__"),
    )  # fmt: skip
    np.save(tmp_path / "frames.npy", tilted_frame(math.radians(1.0)))
    code = """
    import runpy, sys
    sys.argv = ["calibrate", "frames.npy", "--out", "mount.yaml"]
    try:
        runpy.run_module("jaxnav_robot.calibrate", run_name="__main__")
    except SystemExit as done:
        assert done.code == 0, done.code
    """
    result = run_without_jax(code, tmp_path, pythonpath=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "pitch 1.0" in result.stdout
    assert "tilt_deg: 1.0" in (tmp_path / "mount.yaml").read_text()


def test_policy_comparison(five_row_npz, tmp_path, capsys):
    np.save(tmp_path / "frames.npy", tilted_frame(math.radians(2.0)))
    assert calibrate.main([str(tmp_path / "frames.npy"), "--policy", str(five_row_npz)]) == 0
    out = capsys.readouterr().out
    assert "trained with pitch 0.00 deg, height 0.295 m: off (pitch 2.0" in out
    assert NumpyPolicy.from_npz(five_row_npz).sensor.camera_height == pytest.approx(HEIGHT)


def test_node_reports_the_refusal_on_diagnostics(monkeypatch, five_row_npz):
    """Through the node (rclpy stand-ins): zero velocity, and a diagnostic_msgs ERROR saying why
    with the estimate, after the WARNs of calibrating."""
    ros = FakeRos().install(monkeypatch)
    node = ros_node._make_node(ros_node.parse_args(["--policy", str(five_row_npz)])[0])
    on_image = next(cb for kind, _, cb in node.subscriptions_ if kind == "Image")
    on_info = next(cb for kind, _, cb in node.subscriptions_ if kind == "CameraInfo")
    on_info(camera_info(ASTRA_K))
    on_timer = node.timers_[0][1]
    frame = image_msg(tilted_frame(math.radians(2.0)))
    for k in range(24):
        ros.time = 5.0 + k / 30
        on_image(frame)
        if k % 3 == 0:
            on_timer()
    assert set(ros.published()) == {(0.0, 0.0)}
    reports = [m.status[0] for m in ros.messages("DiagnosticArray")]
    assert [r.level for r in reports[:2]] == [b"\x01", b"\x01"]  # waiting: calibrating
    last = reports[-1]
    assert last.level == b"\x02" and last.message.startswith("camera mount refused: pitch 2.0")
    values = {kv.key: kv.value for kv in last.values}
    assert values["tilt_deg"] == "0.00" and values["calibration"].startswith("check: pitch 2.0")


def test_recalibration_stops_collects_and_decides(five_row_npz):
    """The mount was checked at start-up only: a stand knocked 2 deg down later was driven with
    (a phantom obstacle), and a fixed stand needed a restart. `recalibrate` (the node's
    ~/calibrate) stops the robot at once, takes the next 5 frames with floor and decides as at
    start-up: refused (check), driving again once the stand is level, or with the new estimate
    (use); `calibration_answer` gives the outcome, or after 10 s that there is none yet."""
    level, knocked = tilted_frame(), tilted_frame(math.radians(2.0))
    logs = []
    loop = node_loop(five_row_npz, logs)
    assert run(loop, level, 0.7)[-1] == "policy"
    assert run(loop, knocked, 0.2, start=1.0)[-1] == "policy" and loop.obs.min() < 1.0
    assert loop.recalibrate() is None and loop.tick(1.2) == ros_node.STOP
    assert loop.state == "calibrating the camera mount: 0 of 5 frames"
    assert logs[-2:] == ["re-calibrating the camera mount from the next 5 frames",
                         "calibrating the camera mount: 0 of 5 frames: sending zero velocity"]  # fmt: skip
    assert loop.calibration_answer(1.2, 1.2) is None
    states = run(loop, knocked, 0.3, start=1.3)
    assert loop.recalibrate() is None  # under way: the frames so far count
    assert len(loop.calibration.mounts) == 3 and loop.calibration_answer(1.2, 1.6) is None
    states += run(loop, knocked, 0.4, start=1.6)
    assert states[0] == "calibrating the camera mount: 1 of 5 frames" and loop.obs is None
    assert states[-1].startswith("camera mount refused: pitch 2.0")
    drives, why = loop.calibration_answer(1.2, 2.0)
    assert not drives and why == loop.state
    assert loop.recalibrate() is None  # the stand levelled again
    assert run(loop, level, 0.7, start=3.0)[-1] == "policy"
    assert loop.calibration_answer(1.2, 3.7) == (True, f"camera mount within tolerance: "
                                                 f"{loop.calibration.mount.describe()}")  # fmt: skip
    use = node_loop(five_row_npz, [], calibration="use")
    assert run(use, level, 0.7)[-1] == "policy" and use.recalibrate() is None
    assert run(use, knocked, 0.7, start=1.0)[-1] == "policy"
    np.testing.assert_allclose(use.obs, 5.0, rtol=0.01)  # read at the new mount: no phantom
    drives, why = use.calibration_answer(1.0, 1.7)
    assert drives and why.startswith("camera mount used: pitch 2.0")
    wall = tilted_frame(boxes=((0.7, 1.0, -2.0, 2.0, 1.0),))
    assert use.recalibrate() is None and run(use, wall, 0.3, start=2.0)[-1].startswith(
        "calibrating the camera mount: 0 of 5 frames (3 without floor"
    )
    assert use.calibration_answer(2.0, 11.9) is None
    drives, why = use.calibration_answer(2.0, 12.0)
    assert not drives and why.startswith("undecided after 10 s, stopped: calibrating the camera")


def test_recalibration_where_there_is_none(five_row_npz, tmp_path):
    """A scan or a one-row policy reads no floor, and calibration:=off was asked for: the
    request is answered at once, the robot left as it is."""
    for loop, why in [
        (node_loop(five_row_npz, [], scan=True), "no camera mount to calibrate: scans and one-row"),
        (node_loop(write_policy_npz(tmp_path / "one.npz"), []), "no camera mount to calibrate"),
        (node_loop(five_row_npz, [], calibration="off"), "calibration is off (calibration:=check"),
    ]:
        drives, message = loop.recalibrate()
        assert not drives and message.startswith(why)


def answer(coroutine):
    """The response of a service coroutine once it has one (None while it waits)."""
    try:
        coroutine.send(None)
    except StopIteration as done:
        return done.value
    return None


def test_node_calibrate_service(monkeypatch, five_row_npz):
    """std_srvs/Trigger on ~/calibrate: the node sends zero velocity at once, calibrates from the
    frames that come while the call waits (a coroutine: the executor runs the image callbacks
    meanwhile), and answers with the outcome; a scan node answers at once."""
    ros = FakeRos().install(monkeypatch)
    node = ros_node._make_node(ros_node.parse_args(["--policy", str(five_row_npz)])[0])
    kind, on_calibrate = node.services_["~/calibrate"]
    assert kind == "Trigger"
    on_image = next(cb for kind, _, cb in node.subscriptions_ if kind == "Image")
    next(cb for kind, _, cb in node.subscriptions_ if kind == "CameraInfo")(camera_info(ASTRA_K))
    on_timer = node.timers_[0][1]

    def frames(frame, start, count):
        for k in range(count):
            ros.time = start + k / 30
            on_image(image_msg(frame))
            if k % 3 == 0:
                on_timer()

    frames(tilted_frame(), 5.0, 21)
    assert ros.published()[-1] != (0.0, 0.0)
    driven = len(ros.published())
    call = on_calibrate(None, FakeRos.TriggerResponse())
    assert answer(call) is None and ros.published()[-1] == (0.0, 0.0)  # stopped at once
    knocked = tilted_frame(math.radians(2.0))
    frames(knocked, 6.0, 12)
    assert answer(call) is None and node.loop.state.startswith("calibrating the camera mount: 4")
    frames(knocked, 6.4, 1)  # the fifth: decided, answered at the tick after it
    response = answer(call)
    assert not response.success and response.message.startswith("camera mount refused: pitch 2.0")
    assert ros.published()[driven:] == [(0.0, 0.0)] * 6  # the call's, then 5 ticks
    assert ros.messages("DiagnosticArray")[-1].status[0].level == b"\x02"
    scan = ros_node._make_node(ros_node.parse_args(["--policy", str(five_row_npz), "--scan"])[0])
    response = answer(scan.services_["~/calibrate"][1](None, FakeRos.TriggerResponse()))
    assert not response.success and response.message.startswith("no camera mount to calibrate")
