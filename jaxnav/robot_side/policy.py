"""The trained actor's greedy forward pass in plain numpy: all a robot needs besides the weights.

This module imports numpy only (no jax, flax or jaxnav), so it runs on the TurtleBot's own computer.
Export the weights on the training machine, then copy this single file and the .npz to the robot:

    python -m jaxnav.export runs/avoid-cpu --format numpy --out policy.npz
    scp jaxnav/numpy_policy.py policy.npz turtlebot:~/nav/

    from numpy_policy import NumpyPolicy          # on the robot
    policy = NumpyPolicy.from_npz("policy.npz")
    action = policy(obs)  # obs: the 8 sector minima in metres, right to left -> 0 fwd, 1 left, 2 right

(`import jaxnav.robot_side.policy` works too, but the `jaxnav` package itself imports jax.)

The .npz (FORMAT_VERSION 1) holds: W0, b0, ..., Wk, bk (float32 actor layers; LeakyReLU between them),
obs_mean, obs_var (the training normaliser's, float32 [8]), obs_std = sqrt(obs_var + 1e-8) (what is
applied; with obs_mean zeros/ones when training did not normalise), clip (inf when it did not),
leaky_slope, action_names, forward_speed, turn_rate, fov, range_min, range_max, num_sectors,
format_version.
"""

import numpy as np

FORMAT_VERSION = 1


class NumpyPolicy:
    """Greedy (argmax) actor: obs [8] or [N, 8] metres -> action int or [N] ints."""

    def __init__(self, arrays: dict):
        version = int(arrays["format_version"])
        if version != FORMAT_VERSION:
            raise ValueError(f"policy file format {version}; this reader knows {FORMAT_VERSION}")
        n = sum(1 for k in arrays if k.startswith("W"))
        self.layers = [(arrays[f"W{i}"], arrays[f"b{i}"]) for i in range(n)]
        self.mean, self.std = arrays["obs_mean"], arrays["obs_std"]
        self.clip, self.slope = np.float32(arrays["clip"]), np.float32(arrays["leaky_slope"])
        self.action_names = tuple(str(a) for a in arrays["action_names"])
        self.forward_speed, self.turn_rate = (
            float(arrays["forward_speed"]),
            float(arrays["turn_rate"]),
        )
        self.fov, self.num_sectors = float(arrays["fov"]), int(arrays["num_sectors"])
        self.range_min, self.range_max = float(arrays["range_min"]), float(arrays["range_max"])

    @classmethod
    def from_npz(cls, path) -> "NumpyPolicy":
        """Loads a file written by `python -m jaxnav.export --format numpy`."""
        with np.load(path, allow_pickle=False) as data:
            return cls({k: data[k] for k in data.files})

    def logits(self, obs) -> np.ndarray:
        """Unnormalised action scores: obs [..., 8] -> [..., 3] float32."""
        # Same arithmetic and order as jaxnav.ppo.networks.normalize, so results match in float32.
        x = (np.asarray(obs, np.float32) - self.mean) / self.std
        x = np.minimum(np.maximum(x, -self.clip), self.clip)  # np.clip is twice as slow on [8]
        for w, b in self.layers[:-1]:
            x = x @ w + b
            x = np.maximum(x, self.slope * x)  # LeakyReLU for 0 <= slope < 1
        w, b = self.layers[-1]
        return x @ w + b

    def __call__(self, obs):
        """Greedy action: an int for one observation [8], an int array [N] for a batch [N, 8]."""
        action = self.logits(obs).argmax(axis=-1)
        return int(action) if action.ndim == 0 else action
