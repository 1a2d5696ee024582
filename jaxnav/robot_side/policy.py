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
camera_height (m; absent: no pixel is floor), camera_pitch (rad, down +), floor_margin (m) and
floor_margin_slope (m/m).

Format 3 (FORMAT_VERSION; written only for policies a format-2 reader would misuse) may add:
action_low, action_high float32 [2] (continuous actions: the actor's A = 2 outputs are means in
half-ranges, the command is centre + half * mean clipped to the bounds; action_names are then the
two dimensions and commands is [2, 2] of the bounds), and goal inputs: extra_observations (5: the
observation is the sectors, then `goal_features` [3], then the last command / command_scale [2]),
command_scale float32 [2], success_radius (m) and history (int: that many earlier observations
follow the newest, newest first; `FrameStack`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .observation import Sensor

FORMAT_VERSION = 3
READS = (2, 3)  # the formats this reader knows
_REQUIRED = ("W0", "b0", "obs_mean", "obs_std", "clip", "leaky_slope", "action_names", "commands")
_REQUIRED += ("fov", "range_min", "range_max", "num_sectors")


def _optional_sensor_fields(arrays: dict) -> dict:
    """The `Sensor` fields an .npz may hold (see the module docstring); absent ones keep their
    defaults."""
    out = {}
    if "elevations" in arrays:
        out["elevations"] = tuple(float(e) for e in np.atleast_1d(arrays["elevations"]))
    for name in ("camera_height", "camera_pitch", "floor_margin", "floor_margin_slope"):
        if name in arrays:
            out[name] = float(arrays[name])
    return out


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
    """Earlier observations the goal task stacks after the newest (`FrameStack`); 0 = none."""

    @property
    def continuous(self) -> bool:
        """The policy outputs commands (not an index into `commands`)."""
        return self.action_low is not None

    @property
    def observation_size(self) -> int:
        """D: sectors plus the task's extra entries, times the stacked frames."""
        return (self.sensor.num_sectors + self.extra_observations) * (1 + self.history)

    @classmethod
    def from_arrays(cls, arrays: dict, source: str = "policy") -> NumpyPolicy:
        """The policy held by the arrays of an exported .npz; errors name `source`."""
        version = int(arrays["format_version"]) if "format_version" in arrays else None
        if version not in READS:
            raise ValueError(
                f"{source}: policy file format {version}; this reader knows "
                f"{', '.join(map(str, READS))} (export it again with python -m jaxnav.export)"
            )
        missing = [k for k in _REQUIRED if k not in arrays]
        if missing:
            raise ValueError(f"{source}: no '{missing[0]}' in the policy file")
        n = sum(1 for k in arrays if k.startswith("W"))
        policy = cls(
            layers=tuple((arrays[f"W{i}"], arrays[f"b{i}"]) for i in range(n)),
            obs_mean=arrays["obs_mean"],
            obs_std=arrays["obs_std"],
            clip=np.float32(arrays["clip"]),
            leaky_slope=np.float32(arrays["leaky_slope"]),
            sensor=Sensor(
                fov=float(arrays["fov"]),
                num_sectors=int(arrays["num_sectors"]),
                range_min=float(arrays["range_min"]),
                range_max=float(arrays["range_max"]),
                **_optional_sensor_fields(arrays),
            ),
            action_names=tuple(str(a) for a in arrays["action_names"]),
            commands=np.asarray(arrays["commands"], np.float32),
            control_period=float(arrays["control_period"]) if "control_period" in arrays else None,
            action_low=_optional(arrays, "action_low"),
            action_high=_optional(arrays, "action_high"),
            extra_observations=int(arrays.get("extra_observations", 0)),
            command_scale=_optional(arrays, "command_scale"),
            success_radius=float(arrays["success_radius"]) if "success_radius" in arrays else None,
            history=int(arrays.get("history", 0)),
        )
        policy.check(source)
        return policy

    @classmethod
    def from_npz(cls, path) -> NumpyPolicy:
        """Loads a file written by `python -m jaxnav.export` (numpy format)."""
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError) as err:
            raise ValueError(f"{path}: unreadable policy file ({err})") from None
        return cls.from_arrays(arrays, source=str(Path(path)))

    def check(self, source: str) -> None:
        """Raises ValueError naming `source` if the sizes do not chain up."""
        widths = [self.observation_size] + [w.shape[1] for w, _ in self.layers]
        shapes = [(w.shape, b.shape) for w, b in self.layers]
        want = [((i, o), (o,)) for i, o in zip(widths[:-1], widths[1:], strict=True)]
        if shapes != want:
            raise ValueError(
                f"{source}: layer shapes {shapes} do not chain from the observation size "
                f"{self.observation_size}"
            )
        if self.control_period is not None and not self.control_period > 0:
            raise ValueError(f"{source}: control_period must be > 0 s, got {self.control_period}")
        a = widths[-1]
        if self.extra_observations and (self.command_scale is None or self.success_radius is None):
            raise ValueError(f"{source}: goal inputs without command_scale and success_radius")
        if self.continuous and (a != 2 or self.action_high is None):
            raise ValueError(f"{source}: continuous actions need 2 outputs and both bounds")
        if len(self.action_names) != a or self.commands.shape != (a, 2):
            raise ValueError(
                f"{source}: {a} actor outputs, but {len(self.action_names)} action_names "
                f"and commands of shape {self.commands.shape} (want [{a}, 2])"
            )

    def logits(self, obs) -> np.ndarray:
        """The actor's output: obs [..., D] -> [..., A] float32 (action scores, or a continuous
        policy's means in half-ranges)."""
        # Same arithmetic and order as jaxnav.ppo.networks.normalize, so results match in float32.
        x = (np.asarray(obs, np.float32) - self.obs_mean) / self.obs_std
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
    earlier ones (the simulator's `GoalEnv` does the same at an episode's start)."""

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


def _optional(arrays: dict, key: str):
    return np.asarray(arrays[key], np.float32) if key in arrays else None


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
