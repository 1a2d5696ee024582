"""The env contract: the state every task's `reset`/`step` returns and what a task declares.

An env is any object with `reset(key) -> EnvState`, `step(state, action) -> EnvState` (pure, for one
robot; `jax.vmap` them for a batch), `observation_size`, `action_spec`, `metric_names` and
`control_period`. PPO, the run log, evaluation, export and checkpoints read only this contract.
Auto-reset and episode statistics are wrappers (`jaxnav.wrappers`), not fields of every task.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import numpy as np
from flax import struct
from mujoco import mjx


@dataclasses.dataclass(frozen=True)
class DiscreteActions:
    """A fixed table of velocity commands; the policy picks one index per control step."""

    names: tuple[str, ...]
    """Name of each action, in index order (shown in logs and stored with exported policies)."""
    commands: tuple[tuple[float, float], ...]
    """Per action: (forward speed m/s, yaw rate rad/s, positive = left) sent to the base."""

    def __post_init__(self):
        if not self.names or len(self.names) != len(self.commands):
            raise ValueError(
                f"DiscreteActions: need one command per name, got {len(self.names)} names and "
                f"{len(self.commands)} commands"
            )

    @property
    def n(self) -> int:
        """Number of actions."""
        return len(self.names)

    def table(self) -> np.ndarray:
        """[n, 2] float32 commands (forward m/s, yaw rad/s)."""
        return np.asarray(self.commands, np.float32).reshape(self.n, 2)


@dataclasses.dataclass(frozen=True)
class ContinuousActions:
    """The policy outputs the command itself, within per-dimension bounds."""

    low: tuple[float, ...]
    """Lower bound per action dimension (e.g. forward m/s, yaw rad/s)."""
    high: tuple[float, ...]
    """Upper bound per action dimension."""

    @property
    def size(self) -> int:
        """Action dimensions."""
        return len(self.low)


ActionSpec = DiscreteActions | ContinuousActions


@struct.dataclass
class Body:
    """The robot's physics state from one control step to the next: what MuJoCo's next step
    reads (its integration state and the solver's warm start). Everything else in `mjx.Data`
    (body poses, inertias, forces) each step derives from these before reading it, so an env
    carries, auto-resets and stores these five arrays rather than mjx.Data's forty-odd."""

    time: jax.Array  # [] s
    qpos: jax.Array  # [nq] the free base's x, y, yaw first (and a wheeled model's wheel angles)
    qvel: jax.Array  # [nv]
    act: jax.Array  # [na] actuator activations (none for the models here)
    qacc_warmstart: jax.Array  # [nv] the constraint solver's starting accelerations

    @classmethod
    def of(cls, data: mjx.Data) -> Body:
        """The carried part of `data`: its fields of this class's names."""
        return cls(**{f.name: getattr(data, f.name) for f in dataclasses.fields(cls)})

    def into(self, data: mjx.Data) -> mjx.Data:
        """`data` (e.g. `mjx.make_data`'s) with this state in place: what a step starts from."""
        return data.replace(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)})


@struct.dataclass
class EnvState:
    """One robot's state (a batch adds a leading axis to every array)."""

    data: Body  # physics state
    obs: jax.Array  # [observation_size] float32
    reward: jax.Array  # [] float32, of the last step
    done: jax.Array  # [] bool: the last step ended the episode (collision, success or time)
    truncated: jax.Array  # [] bool: it ended by the time limit only (bootstrap the value there)
    metrics: dict[str, jax.Array]  # [] float32 per name in `env.metric_names`, of the last step
    info: dict[str, Any]  # the task's own traced state (episode parameters, step counter, key)


@struct.dataclass
class Banked:
    """One robot's `bank[index]`, read where it lies. An auto-reset running a rollout keeps each
    of a task's `banked_info` arrays (constant from an episode's reset to its end) in one bank a
    block of robots, the block's own and its new episodes', and carries only each robot's row of
    it, so that no step moves the arrays (`jaxnav.wrappers.AutoReset.bank`). A task reads such an
    array only through `window`, which takes it banked or as it is."""

    bank: jax.Array  # [M, ...] the robot's block's arrays and its new episodes'
    index: jax.Array  # [] int32: this robot's row of `bank`

    @property
    def shape(self) -> tuple[int, ...]:
        """The shape of one robot's array."""
        return self.bank.shape[1:]


def window(array, start, size) -> jax.Array:
    """`jax.lax.dynamic_slice(array, start, size)` of an array or of a `Banked` one (read from
    its bank: one slice of the bank, not the robot's whole row first)."""
    if isinstance(array, Banked):
        return jax.lax.dynamic_slice(array.bank, (array.index, *start), (1, *size))[0]
    return jax.lax.dynamic_slice(array, tuple(start), tuple(size))


class Env(Protocol):
    """What PPO, evaluation and export need from a task."""

    observation_size: int
    action_spec: ActionSpec
    metric_names: tuple[str, ...]  # per-step values summed over an episode; "collision" is one
    control_period: float  # s per step
    # C: inputs only a privileged critic sees, state.info["critic"] [C] (0: none; PPO reads 0 for an
    # env without the attribute). The actor, and so an exported policy, never sees them.
    critic_size: int
    # Keys of `state.info` whose arrays stay the same from an episode's reset to its end and that
    # the task reads only through `window` (optional: none). A training auto-reset may hand them
    # to `step` as `Banked` and leaves them in place: `step` returns them as it got them.
    banked_info: tuple[str, ...]

    def reset(self, key: jax.Array) -> EnvState: ...

    def step(self, state: EnvState, action: jax.Array) -> EnvState: ...
