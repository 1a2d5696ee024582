"""The robot side on its own: numpy only, importable and runnable where jax cannot be imported."""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import jaxnav
from jaxnav.robot_side import Controller, NumpyPolicy

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
