"""The robot side on its own: numpy only, importable and runnable where jax cannot be imported."""

import json
import math
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

import jaxnav
from jaxnav.robot_side import Controller, NumpyPolicy
from jaxnav.robot_side import policy as policy_module
from jaxnav.robot_side.observation import (
    Intrinsics,
    Sensor,
    action_to_twist,
    depth_image_to_sectors,
    reduce_sectors,
    sector_nearest,
)

ROOT = Path(jaxnav.__file__).parent.parent
COMMANDS = np.array([[0.4, 0.0], [0.0, 1.0], [0.0, -1.0]], np.float32)  # forward, left, right

# Prepended to code run in a subprocess: any import of jax & co. fails, as on a robot without them.
BLOCK_JAX = """
import sys

class BlockJax:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in ("jax", "jaxlib", "flax", "optax", "mujoco"):
            raise ImportError(f"{name} is blocked: the robot has no jax")

sys.meta_path.insert(0, BlockJax())
try:
    import jax
except ImportError:
    pass
else:
    raise SystemExit("the block failed: jax imported")
"""


def run_without_jax(code: str, cwd: Path, pythonpath: Path | None = None):
    """Runs `code` in a fresh interpreter in `cwd` where jax, flax and mujoco cannot be imported."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run(
        [sys.executable, "-c", BLOCK_JAX + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=120,
    )


ASTRA_VFOV = math.radians(49.5)


def floor_image(wall=5.0, box=None, camera_height=0.295, height=480, width=640):
    """A 640 x 480 depth image (Astra: 49.5 deg vertically, camera level) as the Astra reports it
    (0 outside 0.6-8 m): the floor, a wall across the view at depth `wall`, and with box =
    (depth, top) a box face across the view at that depth, from the floor to `top` m."""
    focal = 0.5 * height / math.tan(0.5 * ASTRA_VFOV)
    up = ((0.5 * (height - 1) - np.arange(height)) / focal)[:, None]  # [H, 1] per metre of depth
    depth = np.full((height, width), wall)
    with np.errstate(divide="ignore"):
        depth = np.where(up < 0, np.minimum(depth, camera_height / -up), depth)
    if box is not None:
        d, top = box
        face = (camera_height + d * up >= 0) & (camera_height + d * up <= top)
        depth = np.where(face, np.minimum(depth, d), depth)
    return np.where((depth >= 0.6) & (depth <= 8.0), depth, 0.0).astype(np.float32)


# The common Orbbec Astra calibration (OpenNI's default) of its 640 x 480 depth image.
ASTRA_K = Intrinsics(fx=570.3, fy=570.3, cx=319.5, cy=239.5, width=640, height=480)


def astra_frame(camera=ASTRA_K, wall=5.0, posts=(), box=None, camera_height=0.295):
    """A depth image as the Astra reports it (0 outside 0.6-8 m) from a level camera of calibration
    `camera`: the floor, a wall across the view at depth `wall`, tall posts (depth, offset to the
    left, width; m) and with box = (depth, top) a box face across the view from the floor up."""
    across = (camera.cx - np.arange(camera.width)) / camera.fx  # [W] left per metre of depth
    up = ((camera.cy - np.arange(camera.height)) / camera.fy)[:, None]  # [H, 1] up per metre
    depth = np.full((camera.height, camera.width), float(wall))
    with np.errstate(divide="ignore"):
        depth = np.where(up < 0, np.minimum(depth, camera_height / -up), depth)
    for d, left, width in posts:
        face = (np.abs(across * d - left) <= width / 2) & (camera_height + d * up >= 0)
        depth = np.where(face, np.minimum(depth, d), depth)
    if box is not None:
        d, top = box
        face = (camera_height + d * up >= 0) & (camera_height + d * up <= top)
        depth = np.where(face, np.minimum(depth, d), depth)
    return np.where((depth >= 0.6) & (depth <= 8.0), depth, 0.0).astype(np.float32)


def write_policy_npz(path: Path, **changes) -> Path:
    """A small policy file in the export format, written by hand (one hidden layer of 16)."""
    rng = np.random.default_rng(0)
    arrays = dict(
        W0=rng.normal(size=(8, 16)).astype(np.float32),
        b0=rng.normal(size=16).astype(np.float32),
        W1=rng.normal(size=(16, 3)).astype(np.float32),
        b1=np.zeros(3, np.float32),
        obs_mean=np.full(8, 3.0, np.float32),
        obs_var=np.full(8, 4.0, np.float32),
        obs_std=np.full(8, 2.0, np.float32),
        clip=np.float32(10.0),
        leaky_slope=np.float32(0.01),
        action_names=np.array(["forward", "left", "right"]),
        commands=COMMANDS,
        fov=np.float32(np.deg2rad(60.0)),
        range_min=np.float32(0.6),
        range_max=np.float32(8.0),
        num_sectors=np.int32(8),
        format_version=np.int32(2),
    )
    arrays.update(changes)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def test_robot_side_runs_without_jax(tmp_path):
    """Every robot_side module imports with jax blocked; a forward pass and an image -> twist run."""
    write_policy_npz(tmp_path / "policy.npz")
    obs = np.random.default_rng(1).uniform(0.6, 8.0, (50, 8)).astype(np.float32)
    np.save(tmp_path / "obs.npy", obs)
    code = """
        import json
        import numpy as np
        import jaxnav.robot_side.bag
        import jaxnav.robot_side.calibrate
        import jaxnav.robot_side.observation
        import jaxnav.robot_side.policy
        import jaxnav.robot_side.ros_node
        from jaxnav.robot_side import Controller, NumpyPolicy

        policy = NumpyPolicy.from_npz("policy.npz")
        image = np.full((4, 64), 3.0, np.float32)
        image[:, :8] = 0.9  # close on the left
        twist = Controller(policy, speed_calibration=2.0).image_to_twist(image)
        actions = policy(np.load("obs.npy")).tolist()
        heavy = sorted(m for m in sys.modules if m.partition(".")[0] in ("jax", "flax", "rclpy"))
        print(json.dumps({"twist": list(twist), "actions": actions, "heavy": heavy}))
    """
    proc = run_without_jax(code, cwd=tmp_path, pythonpath=ROOT)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    policy = NumpyPolicy.from_npz(tmp_path / "policy.npz")
    image = np.full((4, 64), 3.0, np.float32)
    image[:, :8] = 0.9
    want = Controller(policy, speed_calibration=2.0).image_to_twist(image)
    assert got["twist"] == pytest.approx(list(want))
    assert got["actions"] == policy(obs).tolist() and len(set(got["actions"])) > 1
    assert got["heavy"] == []


def test_replay_imports_without_jax():
    """`python -m jaxnav.replay` runs where jax cannot be imported (numpy, matplotlib, rosbags)."""
    code = """
        import jaxnav.cli.replay
        import jaxnav.replay
        heavy = sorted(m for m in sys.modules if m.partition(".")[0] in ("jax", "flax", "rclpy"))
        print(heavy)
    """
    proc = run_without_jax(code, cwd=ROOT, pythonpath=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[]"


def test_forward_pass_by_hand(tmp_path):
    policy = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "policy.npz"))
    obs = np.random.default_rng(2).uniform(0.0, 50.0, (20, 8)).astype(np.float32)
    x = np.clip((obs - 3.0) / 2.0, -10.0, 10.0)
    (w0, b0), (w1, b1) = policy.layers
    h = x @ w0 + b0
    want = np.where(h > 0, h, 0.01 * h) @ w1 + b1
    np.testing.assert_allclose(policy.logits(obs), want, rtol=1e-5, atol=1e-5)
    assert policy.action_names == ("forward", "left", "right")
    assert policy.sensor.num_sectors == 8 and policy.commands.shape == (3, 2)
    assert isinstance(policy(obs[0]), int)


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(format_version=np.int32(1)), "policy file format 1; this reader knows 2, 3"),
        (dict(commands=None), "no 'commands'"),
        (dict(commands=COMMANDS[:2]), "3 actor outputs"),
        (dict(num_sectors=np.int32(6)), "do not chain from the observation size 6"),
    ],
)
def test_policy_file_errors_name_the_file(tmp_path, changes, message):
    path = write_policy_npz(tmp_path / "policy.npz", **changes)
    with pytest.raises(ValueError, match=message) as err:
        NumpyPolicy.from_npz(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_sensor_rows_and_mount_come_from_the_policy_file(tmp_path):
    old = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "old.npz")).sensor
    assert old.elevations == (0.0,) and old.camera_height is None and old.camera_pitch == 0.0
    rows = dict(elevations=np.array([-0.38, 0.0, 0.17]), camera_height=np.float64(0.3))
    mount = dict(camera_pitch=np.float64(0.05), floor_margin=np.float64(0.03))
    path = write_policy_npz(tmp_path / "new.npz", **rows, **mount)
    new = NumpyPolicy.from_npz(path).sensor
    assert new.elevations == (-0.38, 0.0, 0.17) and new.camera_height == 0.3
    assert new.camera_pitch == 0.05 and new.floor_margin == 0.03 and new.floor_margin_slope == 0.01


def test_unreadable_policy_file(tmp_path):
    path = tmp_path / "policy.npz"
    path.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="policy.npz: unreadable policy file"):
        NumpyPolicy.from_npz(path)


def bounded(fn, *args, fifo=None, seconds=20.0):
    """fn(*args), run in a thread that must finish within `seconds`: a read that blocks (on `fifo`)
    fails the test instead of hanging it. Returns fn's result or raises its exception."""
    out = {}

    def target():
        try:
            out["result"] = fn(*args)
        except BaseException as err:  # noqa: BLE001 - handed to the caller
            out["error"] = err

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        if fifo is not None:  # let the blocked reader go: a writer that opens and closes
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail(f"{fn.__name__} blocked for over {seconds:g} s")
    if "error" in out:
        raise out["error"]
    return out["result"]


def refused(path, message: str) -> str:
    """The error of loading `path`: a ValueError of one line that starts with the file's name and
    holds `message`."""
    with pytest.raises(ValueError) as err:
        NumpyPolicy.from_npz(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ") and "\n" not in text and message in text, text
    return text


def nan_at(name: str, index, shape) -> dict:
    """The changes to write_policy_npz's file that put NaN into entry `name` of `shape`."""
    rng = np.random.default_rng(0)
    value = rng.normal(size=shape).astype(np.float32)
    value[index] = np.nan
    return {name: value}


@pytest.mark.parametrize(
    "changes, message",
    [
        (nan_at("W1", (3, 1), (16, 3)), "W1: 1 of 48 values are NaN or infinite"),
        (dict(b0=np.full(16, np.inf, np.float32)), "b0: 16 of 16 values are NaN or infinite"),
        (dict(W0=np.full((8, 16), 1e300)), "W0: 128 of 128 values are NaN or infinite"),
        (dict(clip=np.float32(np.nan)), "clip: must be > 0 (inf: not clipped), got nan"),
        (dict(leaky_slope=np.float32(np.nan)), "leaky_slope: must be in [0, 1), got nan"),
        (dict(fov=np.float32(np.nan)), "Sensor.fov: must be in (0, 2 pi) rad, got nan"),
        (dict(range_max=np.float32(np.inf)), "need 0 <= range_min < range_max < inf"),
        (dict(camera_pitch=np.float64(np.nan)), "Sensor.camera_pitch: must be in (-pi/2, pi/2)"),
        (dict(control_period=np.float64(np.nan)), "control_period: must be finite and > 0"),
    ],
)
def test_non_finite_numbers_are_refused_at_load(tmp_path, changes, message):
    """A NaN weight used to load, and its NaN scores picked the first action: forward, always."""
    refused(write_policy_npz(tmp_path / "policy.npz", **changes), message)


def continuous_npz(path, low=(0.0, -1.5), high=(0.5, 1.5)) -> Path:
    """A continuous policy (format 3) with the given command bounds."""
    rng, bounds = np.random.default_rng(1), np.array([low, high], np.float32)
    return write_policy_npz(
        path, W1=rng.normal(size=(16, 2)).astype(np.float32), b1=np.zeros(2, np.float32),
        action_names=np.array(["lowest", "highest"]), commands=bounds,
        action_low=bounds[0], action_high=bounds[1], format_version=np.int32(3),
    )  # fmt: skip


LIMITS = "a policy file may command at most"


def table(forward=0.4, left=1.0) -> np.ndarray:
    """The action table forward, left, right with these speeds."""
    return np.array([[forward, 0.0], [0.0, left], [0.0, -1.0]], np.float32)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: write_policy_npz(p, commands=table(forward=1e9)), f"commands[0]: forward speed 1e+09 m/s; {LIMITS} 2 m/s either way"),
        (lambda p: write_policy_npz(p, commands=table(left=np.nan)), f"commands[1]: yaw rate nan rad/s; {LIMITS} 6.283 rad/s either way"),
        (lambda p: write_policy_npz(p, commands=table(left=10.0)), f"commands[1]: yaw rate 10 rad/s; {LIMITS} 6.283 rad/s either way"),
        (lambda p: continuous_npz(p, low=(0.0, -1e9)), f"commands[0]: yaw rate -1e+09 rad/s; {LIMITS} 6.283 rad/s"),
        (lambda p: continuous_npz(p, high=(np.nan, 1.5)), f"commands[1]: forward speed nan m/s; {LIMITS} 2 m/s"),
        (lambda p: continuous_npz(p, low=(0.5, -1.5), high=(0.0, 1.5)), "action_low [0.5, -1.5] must be below action_high [0.0, 1.5] in both dimensions"),
    ],
    ids=["forward-1e9", "yaw-nan", "yaw-10", "bound-1e9", "bound-nan", "bounds-crossed"],
)  # fmt: skip
def test_absurd_commands_are_refused_at_load(tmp_path, make, message):
    """Commands and continuous bounds must be finite and within MAX_FORWARD, MAX_YAW_RATE."""
    refused(make(tmp_path / "policy.npz"), message)


def test_continuous_bounds_are_checked_apart_from_commands(tmp_path):
    """The bounds a continuous policy clips to are checked too, not only the `commands` copy."""
    path = continuous_npz(tmp_path / "policy.npz")
    arrays = dict(np.load(path))
    arrays["action_high"] = np.array([1e9, 1.5], np.float32)
    with pytest.raises(ValueError, match=f"p: action_high: forward speed 1e\\+09 m/s; {LIMITS}"):
        NumpyPolicy.from_arrays(arrays, "p")
    arrays["action_high"] = np.array([0.5, 1.5, 0.0], np.float32)
    with pytest.raises(ValueError, match=r"p: action_high: shape \[3\], want \[2\]"):
        NumpyPolicy.from_arrays(arrays, "p")


class NanPolicy:
    """A continuous stand-in policy whose command is not finite."""

    continuous, commands = True, COMMANDS

    def __init__(self, sensor):
        self.sensor = sensor

    def __call__(self, obs):
        return np.array([np.nan, 0.0], np.float32)


def test_twists_are_never_non_finite(tmp_path):
    """A non-finite command, observation or speed calibration is a ValueError, never a Twist."""
    policy = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "policy.npz"))
    obs = np.full(8, 3.0, np.float32)
    with pytest.raises(ValueError, match=r"command \(nan, 0.0\) is not finite"):
        Controller(NanPolicy(policy.sensor)).act(obs)
    obs[5] = np.nan  # e.g. a NaN odometry pose in the goal task's entries
    with pytest.raises(ValueError, match=r"observation entries \[5\] are NaN or infinite"):
        Controller(policy).act(obs)  # its NaN scores would pick the first action: forward
    with pytest.raises(ValueError, match="speed_calibration: must be finite and > 0, got inf"):
        Controller(policy, speed_calibration=math.inf)
    with pytest.raises(ValueError, match="is not finite"):
        action_to_twist(1, table(left=np.inf))


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(obs_mean=np.full(7, 3.0, np.float32)), "obs_mean: 7 values, the observation has 8"),
        (dict(obs_std=np.full(9, 2.0, np.float32)), "obs_std: 9 values, the observation has 8"),
        (dict(obs_std=np.full((8, 1), 2.0)), "obs_std: shape [8, 1], the observation has 8"),
        (dict(obs_var=np.ones(7, np.float32)), "obs_var: 7 values, the observation has 8"),
        (dict(obs_std=np.arange(8.0) - 2), "obs_std: must be > 0, got -2 at entry 0"),
        (dict(obs_mean=np.array(["a"] * 8)), "obs_mean: numbers expected, got <U1"),
        (dict(num_sectors=np.float64(8.5)), "num_sectors: must be a whole number, got 8.5"),
        (dict(action_names=np.array("forward")), "action_names: a list expected, got shape []"),
        (dict(b2=np.zeros(3, np.float32)), "b2: a bias without its layer's weights"),
        (dict(W2=np.zeros((3, 3), np.float32)), "no 'b2' in the policy file"),
    ],
)
def test_shapes_are_checked_at_load(tmp_path, changes, message):
    """A short obs_mean used to load and fail only at the first observation."""
    refused(write_policy_npz(tmp_path / "policy.npz", **changes), message)


@pytest.mark.parametrize(
    "version, message",
    [
        (np.float64(2.7), "format_version: must be a whole number, got 2.7"),
        (np.array([2, 3]), "format_version: one number expected, got shape [2]"),
        (np.array("2"), "format_version: numbers expected, got <U1"),
        (np.float64(np.nan), "format_version: must be a whole number, got nan"),
    ],
)
def test_format_version_is_one_whole_number(tmp_path, version, message):
    """2.7 used to be read as 2, and an array gave a TypeError."""
    refused(write_policy_npz(tmp_path / "policy.npz", format_version=version), message)
    ok = NumpyPolicy.from_npz(write_policy_npz(tmp_path / "ok.npz", format_version=np.float64(2)))
    assert ok.sensor.num_sectors == 8


# A policy file with each problem that loading must refuse: kind -> (write_policy_npz's changes,
# what the error says after the file's name).
BAD_CONTENT = {
    "nan-weights": (nan_at("W1", (3, 1), (16, 3)), "W1: 1 of 48 values are NaN or infinite"),
    "absurd-command": (
        dict(commands=np.array([[1e9, 0], [0, 1], [0, -1]], np.float32)),
        "commands[0]: forward speed 1e+09 m/s; a policy file may command at most 2 m/s either way",
    ),
    "short-obs_mean": (
        dict(obs_mean=np.full(7, 3.0, np.float32)),
        "obs_mean: 7 values, the observation has 8",
    ),
    "version-2.7": (
        dict(format_version=np.float64(2.7)),
        "format_version: must be a whole number, got 2.7",
    ),
    "version-array": (
        dict(format_version=np.array([2, 3])),
        "format_version: one number expected, got shape [2]",
    ),
}


def damaged(kind: str, tmp_path: Path) -> tuple[Path, str]:
    """(a damaged, unreadable or refused policy file of `kind` (DAMAGE or BAD_CONTENT), what its
    error says after its name)."""
    good = write_policy_npz(tmp_path / "good.npz").read_bytes()
    path = tmp_path / f"{kind}.npz"
    if kind in BAD_CONTENT:
        changes, message = BAD_CONTENT[kind]
        return write_policy_npz(path, **changes), message
    if kind == "truncated":
        path.write_bytes(good[: len(good) // 2])
        return path, "unreadable policy file (File is not a zip file)"
    if kind == "bit-flipped":
        flipped = bytearray(good)
        flipped[good.find(b"\x93NUMPY", good.find(b"obs_mean.npy")) + 140] ^= 4  # its data
        path.write_bytes(bytes(flipped))
        return path, "unreadable policy file (Bad CRC-32 for file 'obs_mean.npy')"
    if kind == "npy":
        with open(path, "wb") as fh:  # a handle: np.save would add .npy to the name
            np.save(fh, np.zeros(3))
        return path, "unreadable policy file (not an .npz archive)"
    if kind == "directory":
        path.mkdir()
        return path, "is a directory, expected a regular file"
    if kind == "fifo":
        os.mkfifo(path)
        return path, "is a FIFO (named pipe), expected a regular file"
    if kind == "device":
        return Path("/dev/zero"), "is a character device, expected a regular file"
    return path, "no such file"


DAMAGE = ("truncated", "bit-flipped", "npy", "directory", "fifo", "device", "missing")


@pytest.mark.parametrize("kind", DAMAGE)
def test_damaged_or_special_files_are_one_line(tmp_path, kind):
    """Truncated and bit-flipped archives used to raise zipfile.BadZipFile; a FIFO blocked."""
    path, message = damaged(kind, tmp_path)
    with pytest.raises(ValueError) as err:
        bounded(NumpyPolicy.from_npz, path, fifo=path if kind == "fifo" else None)
    assert str(err.value) == f"{path}: {message}"


def test_every_single_bit_flip_loads_or_is_one_line(tmp_path):
    """A bit flipped anywhere: the policy loads (a flip the archive does not guard, e.g. in a
    timestamp) or loading fails with one line naming the file; nothing else."""
    good = write_policy_npz(tmp_path / "good.npz").read_bytes()
    path, failed = tmp_path / "flipped.npz", 0
    for i in range(0, len(good), 5):
        flipped = bytearray(good)
        flipped[i] ^= 1 << (i % 8)
        path.write_bytes(bytes(flipped))
        try:
            NumpyPolicy.from_npz(path)
        except ValueError as err:
            assert str(err).startswith(f"{path}: ") and "\n" not in str(err), err
            failed += 1
    assert failed > len(good) // 10


def test_only_bounded_regular_files_are_read(tmp_path):
    path = tmp_path / "big.npz"
    path.write_bytes(bytes(100))
    with pytest.raises(ValueError, match="big.npz: larger than 0 MB: not a policy file"):
        policy_module.read_regular_file(path, limit=50)
    assert policy_module.read_regular_file(path, limit=100) == bytes(100)


ONE_ROW = Sensor(math.radians(60.0), 8, 0.6, 8.0)  # a default policy's
FIVE_ROWS = Sensor(  # a 5-row policy's (SensorConfig(rows=5)), the 2i's camera at 0.295 m
    ONE_ROW.fov, 8, 0.6, 8.0, elevations=tuple(np.linspace(-0.38, 0.17, 5)), camera_height=0.295
)


def astra_obs(depth, sensor, **rules) -> np.ndarray:
    """The observation the ROS node reads from an Astra image (calibration ASTRA_K): a 5-row
    sensor's ray pixels, floor left out, or a one-row sensor's +-2 deg band around the horizon."""
    if len(sensor.elevations) > 1:
        return depth_image_to_sectors(depth, sensor, camera=ASTRA_K, **rules)
    rows, angles = ASTRA_K.horizon_rows(2.0), ASTRA_K.column_angles()
    return depth_image_to_sectors(depth, sensor, rows, angles, **rules)


def test_sector_nearest_rule():
    """Each sector reads its k-th nearest known reading, k = 1 + known // readings_per_stray."""
    nan, inf = np.nan, np.inf
    readings = np.full((4, 120), nan)
    readings[0, :100] = np.linspace(1.0, 5.0, 100)  # 100 known: k = 3
    readings[1, :3] = [4.0, inf, 2.0]  # 3 known: k = 1, the minimum
    readings[2, :110] = inf  # no return within range, 110 times: k = 3
    got = sector_nearest(readings, readings_per_stray=50)
    np.testing.assert_allclose(got[:3], [readings[0, 2], 2.0, inf])
    assert np.isnan(got[3])  # nothing known: the blind rule decides
    np.testing.assert_allclose(sector_nearest(readings, 0)[:3], [1.0, 2.0, inf])  # the minimum
    # reduce_sectors: sector 0 holds a stray at 0.9 m among 59 readings at 3 m (k = 2).
    depth = np.r_[0.9, np.full(59, 3.0), np.full(10, 2.0)]
    sector = np.r_[np.zeros(60, int), np.ones(10, int)]
    np.testing.assert_allclose(reduce_sectors(depth, sector, ONE_ROW)[:2], [3.0, 2.0])
    plain = reduce_sectors(depth, sector, ONE_ROW, readings_per_stray=0)
    np.testing.assert_allclose(plain[:2], [0.9, 2.0])
    with pytest.raises(ValueError, match="readings_per_stray: must be 0 .* or a whole number >= 2"):
        Controller(None, readings_per_stray=1)


def with_strays(depth, share, rng):
    """`depth` with `share` of its pixels replaced by strays at random depths within 0.6-8 m."""
    stray = rng.random(depth.shape) < share
    return np.where(stray, rng.uniform(0.6, 8.0, depth.shape), depth).astype(np.float32)


@pytest.mark.parametrize("sensor", [FIVE_ROWS, ONE_ROW], ids=["five-rows", "one-row"])
def test_stray_pixels_make_no_phantom(sensor):
    """Stray pixels used to become phantom obstacles: the sector took the minimum of ~150 (5 rows)
    or ~3000 (the band) pixels. Measured on 640 x 480 frames (ASTRA_K, a wall at 5 m, strays at
    random depths in 0.6-8 m, 200 frames; a phantom: a sector below 4.5 m), 5 rows / band:

        readings_per_stray    0.1 % strays      0.3 % strays      1 % strays     2 cm leg seen to
        0 (the minimum)       55 % / 100 %      95 % / 100 %      100 % / 100 %  7.5 m / 7.5 m
        100                   3.5 % / 0         29 % / 0          95 % / 0       3.5 m / 7.5 m
        50 (default)          0 / 0 (of 1000)   0.3 % / 0         16 % / 0       2.5 m / 3.5 m
        25                    0 / 0             0 / 0             0.5 % / 0      2 m / 1.5 m

    (leg: seen in all 21 placements across the two middle sectors, a 2 cm post before a wall at
    7.95 m; beyond, in some: with 50, 3 m in 14 of 21 on the 5 rows, 5 m in 20 of 21 on the
    band). A 2 cm leg at d m covers 0.02 * 570.3 / d columns: 11.4 at 1 m, of which 4 of the 5 ray
    rows (the lowest meets the floor first) make 45 pixels, k = 4 needed; in the band 456, k = 61.
    The simulator's rays, 2.5 deg apart, miss such a leg beyond ~0.5 m anyway. 50 is the default:
    no phantom at 0.1 %, the leg seen from 2.5 m on.
    """
    rng = np.random.default_rng(0)
    scene = astra_frame()
    np.testing.assert_allclose(astra_obs(scene, sensor), 5.0, rtol=1e-6)
    frames = [with_strays(scene, 0.001, rng) for _ in range(40)]
    plain = np.array([astra_obs(f, sensor, readings_per_stray=0) for f in frames])
    robust = np.array([astra_obs(f, sensor) for f in frames])
    assert (plain < 4.5).any(1).mean() > 0.3 and robust.min() == pytest.approx(5.0)
    assert 11 <= 0.02 * ASTRA_K.fx / 1.0 < 12  # columns of a 2 cm leg at 1 m
    for left in np.linspace(-0.07, 0.07, 8):  # across the two middle sectors, their border at 0
        leg = astra_frame(wall=7.95, posts=[(1.0, left, 0.02)])
        assert astra_obs(leg, sensor).min() == pytest.approx(1.0, abs=0.01)
