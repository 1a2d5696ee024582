"""The trained actor's greedy forward pass in plain numpy: all a robot needs besides the weights.

numpy only (no jax or flax). `python -m jaxnav.export RUN --bundle DIR` writes this package (as
`DIR/jaxnav_robot/`) and the policy file into one folder for the robot:

    from jaxnav_robot.policy import NumpyPolicy      # on the robot, in DIR
    policy = NumpyPolicy.from_npz("policy.npz")
    action = policy(obs)  # obs: the sector minima in metres, right to left -> index into action_names

The .npz (FORMAT_VERSION 2) holds: W0, b0, ..., Wk, bk (float32 actor layers; LeakyReLU between them),
obs_mean, obs_var (the training normaliser's, float32 [D]), obs_std = sqrt(obs_var + 1e-8) (what is
applied; with obs_mean zeros/ones when training did not normalise), clip (inf when it did not),
leaky_slope, action_names [A] str, commands float32 [A, 2] (forward m/s, yaw rad/s per action), the
sensor's fov (rad), range_min and range_max (m) and num_sectors (= D), and format_version.
Optional (older files lack them; readers that do not know them ignore them): control_period (s per
action in training; the ROS node's timer runs at its inverse); the sensor's ray rows and floor rule,
`Sensor`'s fields of the same names: elevations [R] (rad; absent: one horizontal row),
camera_height (m; absent: no pixel is floor), camera_pitch (rad, down +), floor_margin (m) and
floor_margin_slope (m/m).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .observation import Sensor

FORMAT_VERSION = 2
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

    @classmethod
    def from_arrays(cls, arrays: dict, source: str = "policy") -> NumpyPolicy:
        """The policy held by the arrays of an exported .npz; errors name `source`."""
        version = int(arrays["format_version"]) if "format_version" in arrays else None
        if version != FORMAT_VERSION:
            raise ValueError(
                f"{source}: policy file format {version}; this reader knows {FORMAT_VERSION} "
                "(export it again with python -m jaxnav.export)"
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
        widths = [self.sensor.num_sectors] + [w.shape[1] for w, _ in self.layers]
        shapes = [(w.shape, b.shape) for w, b in self.layers]
        want = [((i, o), (o,)) for i, o in zip(widths[:-1], widths[1:], strict=True)]
        if shapes != want:
            raise ValueError(f"{source}: layer shapes {shapes} do not chain from num_sectors")
        if self.control_period is not None and not self.control_period > 0:
            raise ValueError(f"{source}: control_period must be > 0 s, got {self.control_period}")
        a = widths[-1]
        if len(self.action_names) != a or self.commands.shape != (a, 2):
            raise ValueError(
                f"{source}: {a} actor outputs, but {len(self.action_names)} action_names "
                f"and commands of shape {self.commands.shape} (want [{a}, 2])"
            )

    def logits(self, obs) -> np.ndarray:
        """Unnormalised action scores: obs [..., D] -> [..., A] float32."""
        # Same arithmetic and order as jaxnav.ppo.networks.normalize, so results match in float32.
        x = (np.asarray(obs, np.float32) - self.obs_mean) / self.obs_std
        x = np.minimum(np.maximum(x, -self.clip), self.clip)  # np.clip is twice as slow on [8]
        for w, b in self.layers[:-1]:
            x = x @ w + b
            x = np.maximum(x, self.leaky_slope * x)  # LeakyReLU for 0 <= slope < 1
        w, b = self.layers[-1]
        return x @ w + b

    def __call__(self, obs):
        """Greedy action: an int for one observation [D], an int array [N] for a batch [N, D]."""
        action = self.logits(obs).argmax(axis=-1)
        return int(action) if action.ndim == 0 else action
