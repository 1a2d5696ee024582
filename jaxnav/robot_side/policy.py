"""The trained actor's greedy forward pass in plain numpy: all a robot needs besides the weights.

numpy only (no jax or flax). `python -m jaxnav.export RUN --bundle DIR` writes this package (as
`DIR/jaxnav_robot/`) and the policy file into one folder for the robot:

    from jaxnav_robot.policy import NumpyPolicy      # on the robot, in DIR
    policy = NumpyPolicy.from_npz("policy.npz")
    action = policy(obs)  # obs: the sector minima in metres, right to left -> index into action_names

The .npz (format 2) holds: W0, b0, ..., Wk, bk (float32 actor layers; LeakyReLU between them),
obs_mean, obs_var (the training normaliser's, float32 [D]), obs_std = sqrt(obs_var + 1e-8) (what is
applied; with obs_mean zeros/ones when training did not normalise), clip (inf when it did not),
leaky_slope, action_names [A] str, commands float32 [A, 2] (forward m/s, yaw rad/s per action), the
sensor's fov (rad), range_min and range_max (m) and num_sectors (= D), and format_version.
Optional (older files lack them; readers that do not know them ignore them): control_period (s per
action in training; the ROS node's timer runs at its inverse); the sensor's ray rows and floor rule,
`Sensor`'s fields of the same names: elevations [R] (rad; absent: one horizontal row),
camera_height (m; absent: no pixel is floor), camera_pitch (rad, down +), floor_margin (m),
floor_margin_slope (m/m) and far_reads_max (0/1; absent: 0).

Format 3 (FORMAT_VERSION; written only for policies a format-2 reader would misuse) may add:
action_low, action_high float32 [2] (continuous actions: the actor's A = 2 outputs are means in
half-ranges, the command is centre + half * mean clipped to the bounds; action_names are then the
two dimensions and commands is [2, 2] of the bounds); history (int: that many earlier
observations follow the newest, newest first; `FrameStack`; either task); and goal inputs:
extra_observations (5: the observation is the sectors, then `goal_features` [3], then the last
command / command_scale [2]), command_scale float32 [2] and success_radius (m).

Format 4 (MEMORY_FORMAT; written only for policies with a memory) adds memory_bins, memory_steps,
memory_reach (m) and memory_forward (m): the observation ends with the memory's `memory_bins`
entries (`jaxnav_robot.memory`, `MemorySpec`'s fields of the same names; memory_forward is its
camera_forward).

Loading checks the whole file before anything runs, and any problem is a ValueError of one line
naming the file and the entry: only a regular file of at most MAX_FILE_BYTES is read (a FIFO or a
device is refused at once, never waited on); a damaged archive says so; format_version and the
counts (num_sectors, extra_observations, history, memory_bins, memory_steps) must be whole
numbers, the memory's at most 360 bins and 600 steps, and only with goal inputs; every number must
be finite (clip may be inf); every per-observation array must have one value per observation
entry (obs_std > 0); and every command (commands, action_low, action_high) must lie within
+-MAX_FORWARD m/s and +-MAX_YAW_RATE rad/s.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import re
import stat
from pathlib import Path

import numpy as np

from .memory import MemorySpec
from .observation import Sensor

FORMAT_VERSION = 3
MEMORY_FORMAT = 4  # the format of policies with a memory, which a format-3 reader would misread
READS = (2, 3, 4)  # the formats this reader knows
_REQUIRED = ("W0", "b0", "obs_mean", "obs_std", "clip", "leaky_slope", "action_names", "commands")
_REQUIRED += ("fov", "range_min", "range_max", "num_sectors")
MAX_FILE_BYTES = 64 * 2**20  # two 64-unit layers take ~20 kB: far more than any real policy
# The largest command a policy file may hold, either way. About three and two times a Kobuki's top
# speeds (0.7 m/s, pi rad/s): room for faster robots, while a damaged number (1e9, 3e38) is refused.
MAX_FORWARD = 2.0  # m/s
MAX_YAW_RATE = 2 * math.pi  # rad/s
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # an archive's first bytes (the second: empty)


def _kind(mode: int) -> str:
    kinds = {stat.S_ISDIR: "a directory", stat.S_ISFIFO: "a FIFO (named pipe)"}
    kinds |= {stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device"}
    kinds |= {stat.S_ISSOCK: "a socket"}
    return next((name for test, name in kinds.items() if test(mode)), "not a regular file")


def read_regular_file(path, limit: int = MAX_FILE_BYTES) -> bytes:
    """The content of regular file `path` (at most `limit` bytes), or a ValueError naming it.

    The robot side's `jaxnav.io.files.read_bytes`, which it cannot import: opened without blocking
    and checked with fstat before reading, so a FIFO or a device is refused at once.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except (OSError, ValueError) as err:  # ValueError: a NUL in the path
        raise ValueError(f"{path}: cannot read ({getattr(err, 'strerror', None) or err})") from None
    mode = os.fstat(fd).st_mode  # of what was opened, whatever the path names by now
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise ValueError(f"{path}: is {_kind(mode)}, expected a regular file")
    with os.fdopen(fd, "rb") as fh:
        try:
            data = fh.read(limit + 1)
        except OSError as err:
            raise ValueError(f"{path}: cannot read ({err.strerror})") from None
    if len(data) > limit:
        raise ValueError(f"{path}: larger than {limit // 2**20} MB: not a policy file")
    return data


def load_arrays(path) -> dict[str, np.ndarray]:
    """The arrays of the .npz file `path`; a ValueError naming it if it cannot be read."""
    data = read_regular_file(path)
    if not data.startswith(_ZIP_MAGIC):
        raise ValueError(f"{path}: unreadable policy file (not an .npz archive)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            unpacked = sum(info.file_size for info in npz.zip.infolist())
            if unpacked > MAX_FILE_BYTES:  # a compressed archive may claim any size
                raise ValueError(f"unpacks to {unpacked} bytes")
            return {k: npz[k] for k in npz.files}
    except Exception as err:  # noqa: BLE001 - damage surfaces as zipfile, zlib, numpy, memory errors
        detail = " ".join(str(err).split()) or type(err).__name__
        raise ValueError(f"{path}: unreadable policy file ({detail})") from None


@dataclasses.dataclass(frozen=True)
class _Entries:
    """The arrays of a policy file read as numbers; errors name the file and the entry."""

    arrays: dict
    source: str

    def numbers(self, name: str) -> np.ndarray:
        """Entry `name`, an array of numbers (of any shape)."""
        value = np.asarray(self.arrays[name])
        if value.dtype.kind not in "iuf":
            raise ValueError(f"{self.source}: {name}: numbers expected, got {value.dtype}")
        return value

    def floats(self, name: str, default=None) -> np.ndarray | None:
        """Entry `name` as float32 (`default` where absent); `check` tests its shape and values."""
        if name not in self.arrays:
            return default
        with np.errstate(over="ignore"):  # a float64 beyond float32 becomes inf: refused later
            return self.numbers(name).astype(np.float32)

    def number(self, name: str, default=None) -> float | None:
        """Entry `name`, a single number (`default` where absent)."""
        if name not in self.arrays:
            return default
        value = self.numbers(name)
        if value.size != 1:
            raise ValueError(
                f"{self.source}: {name}: one number expected, got shape {list(value.shape)}"
            )
        return float(value.reshape(()))

    def whole(self, name: str, default=None) -> int | None:
        """Entry `name`, a single whole number (`default` where absent)."""
        value = self.number(name)
        if value is None:
            return default
        if not (math.isfinite(value) and value == round(value)):
            raise ValueError(f"{self.source}: {name}: must be a whole number, got {value:g}")
        return int(value)

    def layers(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """(W, b) of each dense layer: W0, b0, W1, b1, ... numbered without a gap."""
        numbered = {k for k in self.arrays if re.fullmatch(r"[Wb]\d+", k)}
        n = sum(1 for k in numbered if k.startswith("W"))
        want = {f"{k}{i}" for i in range(n) for k in "Wb"}
        if missing := sorted(want - numbered):
            raise ValueError(f"{self.source}: no '{missing[0]}' in the policy file")
        if extra := sorted(numbered - want):
            raise ValueError(f"{self.source}: {extra[0]}: a bias without its layer's weights")
        return tuple((self.floats(f"W{i}"), self.floats(f"b{i}")) for i in range(n))

    def sensor(self) -> Sensor:
        """The `Sensor` of the file; its optional fields keep their defaults where absent."""
        optional = {}
        if "elevations" in self.arrays:
            elevations = self.numbers("elevations").astype(np.float64)  # as written: exact
            if elevations.ndim > 1:
                shape = list(elevations.shape)
                raise ValueError(f"{self.source}: elevations: a list expected, got shape {shape}")
            optional["elevations"] = tuple(np.atleast_1d(elevations).tolist())
        for name in ("camera_height", "camera_pitch", "floor_margin", "floor_margin_slope"):
            if name in self.arrays:
                optional[name] = self.number(name)
        if "far_reads_max" in self.arrays:
            optional["far_reads_max"] = bool(self.whole("far_reads_max"))
        fields = {k: self.number(k) for k in ("fov", "range_min", "range_max")}
        fields["num_sectors"] = self.whole("num_sectors")
        try:
            return Sensor(**fields, **optional)
        except ValueError as err:  # Sensor's own checks: name the file too
            raise ValueError(f"{self.source}: {err}") from None

    def memory(self) -> MemorySpec | None:
        """The file's `MemorySpec`; None where it has none."""
        if "memory_bins" not in self.arrays:
            return None
        names = ("memory_steps", "memory_reach", "memory_forward")
        if missing := [n for n in names if n not in self.arrays]:
            raise ValueError(f"{self.source}: memory_bins without {', '.join(missing)}")
        bins, steps = self.whole("memory_bins"), self.whole("memory_steps")
        for name, value, top in (("memory_bins", bins, 360), ("memory_steps", steps, 600)):
            if not 0 <= value <= top:  # a damaged count would allocate without bound
                raise ValueError(f"{self.source}: {name}: must be in [0, {top}], got {value}")
        reach, forward = self.number("memory_reach"), self.number("memory_forward")
        try:
            return MemorySpec(bins=bins, steps=steps, reach=reach, camera_forward=forward)
        except ValueError as err:  # MemorySpec's own checks: name the file too
            raise ValueError(f"{self.source}: {err}") from None

    def names(self, name: str) -> tuple[str, ...]:
        """Entry `name`, a list of names."""
        value = np.asarray(self.arrays[name])
        if value.ndim != 1:
            raise ValueError(
                f"{self.source}: {name}: a list expected, got shape {list(value.shape)}"
            )
        return tuple(str(a) for a in value)


def _check_version(get: _Entries) -> None:
    """A format this reader knows, or a ValueError saying which it got."""
    version = get.whole("format_version")
    if version not in READS:
        raise ValueError(
            f"{get.source}: policy file format {version}; this reader knows "
            f"{', '.join(map(str, READS))} (export it again with python -m jaxnav.export)"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class NumpyPolicy:
    """Greedy (argmax) actor: obs [D] or [N, D] metres -> action int or [N] ints."""

    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    """(W [in, out], b [out]) float32 per dense layer; LeakyReLU between them."""
    obs_mean: np.ndarray
    """[D] float32 subtracted from the observation."""
    obs_std: np.ndarray
    """[D] float32 the centred observation is divided by."""
    clip: np.float32
    """The normalised observation is clipped to [-clip, clip] (inf: not clipped)."""
    leaky_slope: np.float32
    """LeakyReLU's negative slope, 0 <= slope < 1."""
    sensor: Sensor
    """The sensor of training: what turns depth images and scans into observations."""
    action_names: tuple[str, ...]
    """[A] name of each action."""
    commands: np.ndarray
    """[A, 2] float32 (forward m/s, yaw rad/s, positive = left) each action commands."""
    control_period: float | None = None
    """s each action was held in training; None where the file does not say."""
    action_low: np.ndarray | None = None
    """[2] float32 lower command bounds of a continuous policy; None: a table of `commands`."""
    action_high: np.ndarray | None = None
    """[2] float32 upper command bounds of a continuous policy."""
    extra_observations: int = 0
    """Observation entries after the sectors: 5 for the goal task (`goal_observation`)."""
    command_scale: np.ndarray | None = None
    """[2] the last command is divided by this in the goal task's observation."""
    success_radius: float | None = None
    """m: the goal task's goal counts as reached within this distance."""
    history: int = 0
    """Earlier observations the policy stacks after the newest (`FrameStack`); 0 = none."""
    memory: MemorySpec | None = None
    """What the observation's last `memory.bins` entries remember (`jaxnav_robot.memory`);
    None: no memory."""

    @property
    def continuous(self) -> bool:
        """The policy outputs commands (not an index into `commands`)."""
        return self.action_low is not None

    @property
    def observation_size(self) -> int:
        """D: sectors plus the task's extra entries, times the stacked frames, then the memory."""
        frames = (self.sensor.num_sectors + self.extra_observations) * (1 + self.history)
        return frames + (self.memory.bins if self.memory else 0)

    @classmethod
    def from_arrays(cls, arrays: dict, source: str = "policy") -> NumpyPolicy:
        """The policy held by the arrays of an exported .npz, checked (`check`); errors name
        `source` and the entry."""
        get = _Entries(arrays, source)
        _check_version(get)
        missing = [k for k in _REQUIRED if k not in arrays]
        if missing:
            raise ValueError(f"{source}: no '{missing[0]}' in the policy file")
        policy = cls(
            layers=get.layers(),
            obs_mean=get.floats("obs_mean"),
            obs_std=get.floats("obs_std"),
            clip=np.float32(get.number("clip")),
            leaky_slope=np.float32(get.number("leaky_slope")),
            sensor=get.sensor(),
            action_names=get.names("action_names"),
            commands=get.floats("commands"),
            control_period=get.number("control_period"),
            action_low=get.floats("action_low"),
            action_high=get.floats("action_high"),
            extra_observations=get.whole("extra_observations", 0),
            command_scale=get.floats("command_scale"),
            success_radius=get.number("success_radius"),
            history=get.whole("history", 0),
            memory=get.memory(),
        )
        policy.check(source)
        if "obs_var" in arrays:  # not applied (obs_std is), but a wrong one means a damaged file
            _check_observation_array(policy, source, "obs_var", get.floats("obs_var"), None)
        return policy

    @classmethod
    def from_npz(cls, path) -> NumpyPolicy:
        """Loads a file written by `python -m jaxnav.export` (numpy format), checked (`check`)."""
        return cls.from_arrays(load_arrays(path), source=str(Path(path)))

    def check(self, source: str) -> None:
        """Raises ValueError naming `source` and the field if the policy cannot run safely: sizes
        that do not chain up, numbers that are not finite, commands beyond the limits (see the
        module docstring)."""
        for name in ("extra_observations", "history"):
            if getattr(self, name) < 0:
                raise ValueError(f"{source}: {name}: must be >= 0, got {getattr(self, name)}")
        self._check_layers(source)
        for name, low in (("obs_mean", None), ("obs_std", 0.0)):
            _check_observation_array(self, source, name, getattr(self, name), low, strict=True)
        if not self.clip > 0:
            raise ValueError(f"{source}: clip: must be > 0 (inf: not clipped), got {self.clip}")
        if not 0 <= self.leaky_slope < 1:
            raise ValueError(f"{source}: leaky_slope: must be in [0, 1), got {self.leaky_slope}")
        for name in ("control_period", "success_radius"):
            value = getattr(self, name)
            if value is not None and not 0 < value < math.inf:
                raise ValueError(f"{source}: {name}: must be finite and > 0, got {value}")
        self._check_actions(source)
        if self.extra_observations:
            if self.command_scale is None or self.success_radius is None:
                raise ValueError(f"{source}: goal inputs without command_scale and success_radius")
            _check_pair(source, "command_scale", self.command_scale)
            if not (self.command_scale > 0).all():
                raise ValueError(f"{source}: command_scale: must be > 0, got {self.command_scale}")
        elif self.memory is not None:
            raise ValueError(f"{source}: memory_bins without the goal inputs (extra_observations)")

    def _check_layers(self, source: str) -> None:
        """Every layer finite, and their sizes chain from the observation to the outputs."""
        shapes = [(w.shape, b.shape) for w, b in self.layers]
        widths = [self.observation_size] + [w.shape[-1] if w.ndim else -1 for w, _ in self.layers]
        want = [((i, o), (o,)) for i, o in zip(widths[:-1], widths[1:], strict=True)]
        if shapes != want:
            raise ValueError(
                f"{source}: layer shapes {shapes} do not chain from the observation size "
                f"{self.observation_size}"
            )
        for i, (w, b) in enumerate(self.layers):
            _check_finite(source, f"W{i}", w)
            _check_finite(source, f"b{i}", b)

    def _check_actions(self, source: str) -> None:
        """Names and commands for every actor output, commands within the limits."""
        a = self.layers[-1][0].shape[1]
        if self.continuous and (a != 2 or self.action_high is None):
            raise ValueError(f"{source}: continuous actions need 2 outputs and both bounds")
        if len(self.action_names) != a or self.commands.shape != (a, 2):
            raise ValueError(
                f"{source}: {a} actor outputs, but {len(self.action_names)} action_names "
                f"and commands of shape {self.commands.shape} (want [{a}, 2])"
            )
        for i, command in enumerate(self.commands):
            _check_command(source, f"commands[{i}]", command)
        if self.continuous:
            for name in ("action_low", "action_high"):
                _check_pair(source, name, getattr(self, name))
                _check_command(source, name, getattr(self, name))
            if not (self.action_low < self.action_high).all():
                raise ValueError(
                    f"{source}: action_low {self.action_low.tolist()} must be below action_high "
                    f"{self.action_high.tolist()} in both dimensions"
                )

    def logits(self, obs) -> np.ndarray:
        """The actor's output: obs [..., D] -> [..., A] float32 (action scores, or a continuous
        policy's means in half-ranges)."""
        obs = np.asarray(obs, np.float32)
        if obs.shape[-1:] != (self.observation_size,):
            stack = " (with history: stack the frames, FrameStack)" if self.history else ""
            raise ValueError(
                f"observation of shape {obs.shape}: the policy reads {self.observation_size} "
                f"entries{stack}"
            )
        # Same arithmetic and order as jaxnav.ppo.networks.normalize, so results match in float32.
        x = (obs - self.obs_mean) / self.obs_std
        x = np.minimum(np.maximum(x, -self.clip), self.clip)  # np.clip is twice as slow on [8]
        for w, b in self.layers[:-1]:
            x = x @ w + b
            x = np.maximum(x, self.leaky_slope * x)  # LeakyReLU for 0 <= slope < 1
        w, b = self.layers[-1]
        return x @ w + b

    def __call__(self, obs):
        """Greedy action: an int for one observation [D], an int array [N] for a batch [N, D];
        continuous: the command [2] or [N, 2] (forward m/s, yaw rad/s) within the bounds."""
        out = self.logits(obs)
        if self.continuous:
            centre = 0.5 * (self.action_high + self.action_low)
            half = 0.5 * (self.action_high - self.action_low)
            return np.clip(centre + half * out, self.action_low, self.action_high)
        action = out.argmax(axis=-1)
        return int(action) if action.ndim == 0 else action

    def command(self, obs) -> np.ndarray:
        """[2] float32 (forward m/s, yaw rad/s) the policy sends for one observation [D]."""
        action = self(obs)
        return np.asarray(action if self.continuous else self.commands[action], np.float32)


class FrameStack:
    """The stacked observation of a policy with `history` > 0: the newest frame, then the
    `history` frames before it, newest first; the first frame after `reset` stands in for the
    earlier ones (the simulator's tasks do the same at an episode's start)."""

    def __init__(self, history: int):
        self.history = history
        self._obs: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the earlier frames (a new goal, or the robot was stopped)."""
        self._obs = None

    def __call__(self, frame) -> np.ndarray:
        """[(1 + history) x F] float32 after adding `frame` [F]."""
        frame = np.asarray(frame, np.float32)
        if self._obs is None:
            self._obs = np.tile(frame, 1 + self.history)
        else:
            self._obs = np.concatenate([frame, self._obs[: self._obs.size - frame.size]])
        return self._obs


def _check_finite(source: str, name: str, value: np.ndarray) -> None:
    bad = value.size - np.count_nonzero(np.isfinite(value))
    if bad:
        raise ValueError(f"{source}: {name}: {bad} of {value.size} values are NaN or infinite")


def _check_observation_array(policy, source, name, value, low, strict=False) -> None:
    """`value` holds one finite value per observation entry, each above `low` (or at least `low`
    unless `strict`; None: any)."""
    size = policy.observation_size
    if value.shape != (size,):
        got = f"{value.size} values" if value.ndim == 1 else f"shape {list(value.shape)}"
        raise ValueError(f"{source}: {name}: {got}, the observation has {size}")
    _check_finite(source, name, value)
    if low is not None and not (value > low if strict else value >= low).all():
        i = int(np.argmin(value))
        sign = ">" if strict else ">="
        raise ValueError(f"{source}: {name}: must be {sign} {low:g}, got {value[i]:g} at entry {i}")


def _check_pair(source: str, name: str, value: np.ndarray) -> None:
    """`value` is [2] (forward, yaw) and finite."""
    if value.shape != (2,):
        raise ValueError(f"{source}: {name}: shape {list(value.shape)}, want [2] (forward, yaw)")
    _check_finite(source, name, value)


def _check_command(source: str, name: str, command: np.ndarray) -> None:
    """command (forward m/s, yaw rad/s) is finite and within MAX_FORWARD, MAX_YAW_RATE."""
    for value, what, top, unit in (
        (command[0], "forward speed", MAX_FORWARD, "m/s"),
        (command[1], "yaw rate", MAX_YAW_RATE, "rad/s"),
    ):
        if not abs(value) <= top:  # NaN too
            raise ValueError(
                f"{source}: {name}: {what} {value:g} {unit}; a policy file may command at "
                f"most {top:.4g} {unit} either way"
            )


def goal_features(pose, goal) -> np.ndarray:
    """[3] float32 the goal seen from pose (x, y, yaw): distance m, sin and cos of its bearing
    (rad from the heading, positive = left); the simulator's `jaxnav.tasks.goal.goal_features`."""
    x, y, yaw = (np.float32(v) for v in pose)
    dx, dy = np.float32(goal[0]) - x, np.float32(goal[1]) - y
    bearing = np.arctan2(dy, dx) - yaw
    return np.array([np.hypot(dx, dy), np.sin(bearing), np.cos(bearing)], np.float32)


def goal_observation(sectors, pose, goal, last_command, command_scale) -> np.ndarray:
    """[D] float32 the goal task's observation: the sector minima [S] (m), `goal_features` of
    pose (x, y, yaw) and goal (x, y) in one frame (odometry), and the last command the policy
    sent (forward m/s, yaw rad/s, before any speed calibration) divided by command_scale [2]."""
    scaled = np.asarray(last_command, np.float32) / np.asarray(command_scale, np.float32)
    return np.concatenate([np.asarray(sectors, np.float32), goal_features(pose, goal), scaled])
