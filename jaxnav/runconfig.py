"""A training run's full configuration, its JSON form, and command-line flags generated from it."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import typing
from typing import Any

from jaxnav.core.randomize import TRAINING, RandomizeConfig
from jaxnav.core.robot import TURTLEBOT2I, RobotSpec
from jaxnav.core.scene import SceneConfig
from jaxnav.core.sensors import SensorConfig
from jaxnav.ppo.config import PPOConfig
from jaxnav.tasks.avoid import AvoidConfig
from jaxnav.tasks.registry import critic_size, task_entry

# Config groups of a run: (attribute, class, flag prefix). PPO flags have no prefix; the task's
# class (None here) is the config class of the run's task (`group_class`).
GROUPS = (
    ("ppo", PPOConfig, ""),
    ("task", None, "task."),
    ("randomize", RandomizeConfig, "randomize."),
    ("sensor", SensorConfig, "sensor."),
    ("scene", SceneConfig, "scene."),
    ("robot", RobotSpec, "robot."),
)


# Short forms of a few flags, the names the documentation and the issues use.
ALIASES = {"scene.physics": "--physics"}


def group_class(attr: str, cls, env: str):
    """The config class of group `attr` for task `env`."""
    return task_entry(env).config_cls if attr == "task" else cls


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run; saved as config.json in the run folder."""

    ppo: PPOConfig = PPOConfig()
    """Learner hyper-parameters."""
    task: Any = AvoidConfig()
    """The task's config (its class is the registered config class of `env`)."""
    randomize: RandomizeConfig = TRAINING
    """Per-episode randomisation: the training distribution (sampled rooms and spawns mixed in)."""
    sensor: SensorConfig = SensorConfig()
    """Depth sensor geometry."""
    scene: SceneConfig = SceneConfig()
    """Physics timestep, substeps and obstacle slot counts."""
    robot: RobotSpec = TURTLEBOT2I
    """The robot: MJCF, footprint, speed limits and sensor mount."""
    layouts: tuple[dict, ...] | None = None
    """Training rooms in the layout JSON format; None = the default rooms."""
    seed: int = 0
    """Seed of everything random in the run."""
    preset: str = "cpu"
    """Name of the preset the PPO settings started from."""
    env: str = "avoid"
    """Task name for `make_env`."""

    def __post_init__(self):
        # Limits that need two groups at once, checked before anything is written.
        self.task.check_robot(self.robot)
        self.randomize.check_robot(self.robot.radius)
        critic_size(self.task, self.ppo.privileged_critic)  # the task has critic-only inputs

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> RunConfig:
        """Inverse of `to_dict`; unknown keys or values of the wrong type raise ValueError naming
        them (`config: ppo.num_envs ...`)."""
        if not isinstance(raw, dict):
            raise ValueError(f"config: expected a JSON object, got {type(raw).__name__}")
        kwargs = dict(raw)
        env = kwargs.get("env", "avoid")
        if not isinstance(env, str):
            raise ValueError(f"config: env must be a string, got {env!r}")
        task_entry(env)  # an unknown task lists the valid ones
        for attr, group_cls, _ in GROUPS:
            default = dataclasses.asdict(TRAINING) if attr == "randomize" else {}
            kwargs[attr] = _build(
                group_class(attr, group_cls, env), kwargs.get(attr, default), attr
            )
        unknown = set(kwargs) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"config: unknown keys {sorted(unknown)}")
        layouts = kwargs.get("layouts")
        if layouts is not None:
            if not isinstance(layouts, list | tuple) or not all(
                isinstance(x, dict) for x in layouts
            ):
                raise ValueError("config: layouts must be a list of room objects or null")
            kwargs["layouts"] = tuple(layouts)
        for name, kind in (("seed", int), ("preset", str), ("env", str)):
            if name in kwargs and not _is(kwargs[name], kind):
                raise ValueError(
                    f"config: {name} must be {_KIND_NAMES[kind]}, got {kwargs[name]!r}"
                )
        return cls(**kwargs)

    def env_kwargs(self) -> dict[str, Any]:
        """`make_env` keyword arguments that define the robot and task (not the rooms or their
        randomisation, which evaluation chooses itself)."""
        return dict(task=self.task, sensor=self.sensor, scene=self.scene, robot=self.robot)


_KIND_NAMES = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _is(value, kind) -> bool:
    """Whether a JSON value fits a field of type `kind` (JSON has no int/float split for floats)."""
    if kind is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def _build(cls, values: dict, where: str):
    """A config group from its JSON object; every value is type-checked against the field."""
    if not isinstance(values, dict):
        raise ValueError(f"config: '{where}' must be an object, got {type(values).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"config: unknown keys in '{where}': {sorted(unknown)}")
    fixed = {}
    for k, v in values.items():
        hint = hints[k]
        if typing.get_origin(hint) is tuple:
            args = typing.get_args(hint)
            kind = args[0]
            ok = isinstance(v, list | tuple) and all(_is(x, kind) for x in v)
            if ok and args[-1] is not Ellipsis:
                ok = len(v) == len(args)
            if not ok:
                count = "" if args[-1] is Ellipsis else f"{len(args)} "
                raise ValueError(
                    f"config: {where}.{k} must be a list of {count}"
                    f"{_KIND_NAMES[kind].split(' ', 1)[1]}s, got {v!r}"
                )
            v = tuple(v)
        elif hint in _KIND_NAMES and not _is(v, hint):
            raise ValueError(f"config: {where}.{k} must be {_KIND_NAMES[hint]}, got {v!r}")
        fixed[k] = float(v) if hint is float else v
    return cls(**fixed)


# What each group's flags set, under its heading in --help.
GROUP_HELP = {
    "ppo": "the learner: batch, optimiser, PPO losses, network, chunks and checkpoints",
    "task": "the task: reward, episode length, actions and its own settings",
    "randomize": "what is drawn per episode: rooms, spawns, the robot, the sensor, movers",
    "sensor": "the depth camera (or lidar): rays, sectors, range",
    "scene": "the physics: timestep, substeps, obstacle slots, the fast or wheeled model",
    "robot": "the robot: footprint, speed limits, sensor mount",
}


def add_flags(parser: argparse.ArgumentParser, env: str = "avoid", defaults=None) -> None:
    """One flag per config field: `--num-envs` for PPO, `--task.near-threshold` etc. for the rest
    (the task's flags are those of `env`'s config class), in one argument group per config group.

    Defaults are None so that only flags the user gave override the preset; the help shows the
    values of `defaults` (the RunConfig the run would use; else the classes' own). `ALIASES`
    adds a second name to some (`--physics` for `--scene.physics`).
    """
    for attr, cls, prefix in GROUPS:
        cls = group_class(attr, cls, env)
        title = f"{attr} settings" if prefix else "PPO settings"
        group = parser.add_argument_group(title, GROUP_HELP[attr])
        add_field_flags(group, attr, cls, prefix, shown=getattr(defaults, attr, None))


def add_field_flags(group, attr: str, cls, prefix: str, names=None, shown=None) -> None:
    """The flags of the fields `names` (default: all) of config class `cls` in group `attr`, as
    `add_flags` makes them (dest `attr.field`, default None; `overrides_from_args` reads them).
    The help gives each field's value in `shown` (a `cls`), else the class default."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if names is not None and f.name not in names:
            continue
        flag = "--" + prefix + f.name.replace("_", "-")
        kind, nargs = _flag_type(hints[f.name])
        value = getattr(shown, f.name) if shown is not None else f.default
        help_text = (_field_docs(cls).get(f.name, "") + f" (default: {value})").replace("%", "%%")
        dest = f"{attr}.{f.name}"
        group.add_argument(
            *([flag, ALIASES[dest]] if dest in ALIASES else [flag]),
            dest=dest,
            type=kind,
            nargs=nargs,
            default=None,
            help=help_text,
            metavar=f.name.upper(),
        )


def _flag_type(hint):
    if hint is bool:
        return _parse_bool, None
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        return args[0], ("+" if args[-1] is Ellipsis else len(args))
    return hint, None


def _parse_bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got '{text}'")


@functools.cache
def _field_docs(cls) -> dict[str, str]:
    """{field: the docstring written under it} of a dataclass, its source parsed once a class."""
    import ast
    import inspect
    import textwrap

    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs = {}
    for node, nxt in zip(body, body[1:], strict=False):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant):
                docs.setdefault(node.target.id, " ".join(str(nxt.value.value).split()))
    return docs


def overrides_from_args(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """{group: {field: value}} of the flags the user gave."""
    out: dict[str, dict[str, Any]] = {attr: {} for attr, _, _ in GROUPS}
    for dest, value in vars(args).items():
        if "." in dest and value is not None:
            attr, name = dest.split(".", 1)
            out[attr][name] = tuple(value) if isinstance(value, list) else value
    return out
