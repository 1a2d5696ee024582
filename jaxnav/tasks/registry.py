"""Task registry: `make_env(name, layouts=..., **overrides)` and `register` for new tasks.

A task is an env class (the contract of `jaxnav.core.types`, usually a `NavTask`), its frozen config
class (with `max_steps`, `action_spec` and `check_robot`) and its default rooms. Adding a task is a new
file and one `register` line.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

from jaxnav.core.episode import walker_config
from jaxnav.core.families import grid_size
from jaxnav.core.goals import make_goal_cells
from jaxnav.core.randomize import (
    TRAINING,
    RandomizeConfig,
    family_weights,
    layout_grid_size,
    make_bank,
)
from jaxnav.core.robot import TURTLEBOT2I, RobotSpec
from jaxnav.core.scene import SCENES_DIR, SceneConfig
from jaxnav.core.sensors import SensorConfig
from jaxnav.io.layouts import RoomLayout, load_layout
from jaxnav.tasks import presets
from jaxnav.tasks.avoid import AvoidConfig, AvoidEnv
from jaxnav.tasks.goal import GoalConfig, GoalEnv


class TaskEntry(NamedTuple):
    env_cls: type
    config_cls: type
    default_layouts: tuple[str, ...]  # file names in jaxnav's scenes: the task's training rooms
    defaults: dict  # {group: {field: value}}: run-config fields ("ppo", "randomize"...), any preset
    preset_defaults: dict  # {preset: {group: {field: value}}}: over `defaults` with that preset


TASKS: dict[str, TaskEntry] = {}


def register(
    name: str,
    env_cls: type,
    config_cls: type,
    default_layouts=("train_room.json",),
    defaults: dict | None = None,
    preset_defaults: dict | None = None,
):
    """Makes task `name` available to `make_env`, the CLIs and saved runs. `defaults` are fields
    of a run's config groups ({"ppo": {...}, "randomize": {...}}, any group of
    `jaxnav.runconfig.GROUPS`: over the preset's PPO settings, `randomize.TRAINING` and the
    other groups' defaults) with every preset, `preset_defaults[preset]` over them with that
    preset, all under the user's own settings (`task_defaults`)."""
    TASKS[name] = TaskEntry(
        env_cls,
        config_cls,
        tuple(default_layouts),
        {group: dict(fields) for group, fields in (defaults or {}).items()},
        {p: {g: dict(f) for g, f in gs.items()} for p, gs in (preset_defaults or {}).items()},
    )


register("avoid", AvoidEnv, AvoidConfig, **presets.AVOID)
register("goal", GoalEnv, GoalConfig, **presets.GOAL)


def task_entry(name: str) -> TaskEntry:
    """The registered task `name`; an unknown name lists the valid ones."""
    if name not in TASKS:
        raise ValueError(f"unknown environment '{name}'; valid names: {', '.join(sorted(TASKS))}")
    return TASKS[name]


def task_defaults(name: str, preset: str | None = None) -> dict[str, dict]:
    """{group: {field: value}}: task `name`'s defaults, with those of `preset` over them."""
    entry, merged = task_entry(name), {}
    for groups in (entry.defaults, entry.preset_defaults.get(preset, {})):
        for group, fields in groups.items():
            merged[group] = {**merged.get(group, {}), **fields}
    return merged


def training_randomize(name: str = "avoid") -> RandomizeConfig:
    """Task `name`'s training distribution: `randomize.TRAINING` with the task's own settings of
    every preset over it (a preset's own settings are `build_config`'s)."""
    return dataclasses.replace(TRAINING, **task_defaults(name).get("randomize", {}))


def critic_size(task, privileged: bool) -> int:
    """C, the inputs only a privileged critic sees: the task config's `critic_observations` (the
    goal task's) with `privileged` (`PPOConfig.privileged_critic`), else 0. A task without them
    and `privileged` is an error naming the flag."""
    size = getattr(task, "critic_observations", 0)
    if privileged and not size:
        raise ValueError(
            "--privileged-critic: this task has no inputs for the critic alone (the goal task "
            "has); leave it off"
        )
    return size if privileged else 0


def grid_cells(layouts: Sequence[RoomLayout], randomize: RandomizeConfig) -> int:
    """G, the occupancy-grid side of a batch's rooms (`jaxnav.core.grid`): the largest of the
    layouts' grids and of the grid families in `randomize.families`; 0: no room has one."""
    sampled = grid_size(family_weights(randomize.families)) if randomize.families else 0
    return max(layout_grid_size(layouts), sampled)


def check_grid_physics(grid: int, scene: SceneConfig) -> None:
    """Grid cells are not MJX geoms: only the fast physics without MJX contacts, which collides
    analytically, simulates them."""
    if grid and (scene.fast_contacts or scene.physics != "fast"):
        flag = "--scene.fast-contacts" if scene.fast_contacts else "--physics wheeled"
        raise ValueError(
            f"{flag}: rooms with grid obstacles (dense_field, layout grids) run only on the fast "
            "physics without MJX contacts; leave it off or drop the grid rooms"
        )


def default_layouts(name: str = "avoid") -> list[RoomLayout]:
    """The task's default training rooms (for `avoid`: the paper's training room, Fig. 4)."""
    return [lay for f in task_entry(name).default_layouts for lay in load_layout(SCENES_DIR / f)]


def make_env(
    name: str = "avoid",
    layouts: Sequence[RoomLayout] | None = None,
    *,
    task=None,
    randomize: RandomizeConfig | None = None,
    sensor: SensorConfig | None = None,
    scene: SceneConfig | None = None,
    robot: RobotSpec = TURTLEBOT2I,
    **overrides,
):
    """Builds task `name` for one robot (vmap its `reset`/`step` for a batch; wrap it with
    `jaxnav.wrappers.AutoReset(EpisodeStats(env))` for training).

    `layouts` given: exactly those rooms, each from its own spawn (random free spawns where a
    room has none), unless `randomize` says otherwise. `layouts=None`: the task's default rooms
    with its training distribution (`training_randomize(name)`: sampled rooms and spawns mixed
    in; a preset's own settings are the CLI's).
    `layouts=[]`: sampled rooms only. `overrides` are fields of the task config
    (e.g. `near_threshold=0.8`). Slot counts grow to fit the largest layout and the sampler, and
    by `randomize.moving_count[1]` cylinder slots for the moving obstacles it adds and as many
    as its walkers take.
    """
    entry = task_entry(name)
    fields = [f.name for f in dataclasses.fields(entry.config_cls)]
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        raise ValueError(
            f"make_env: unknown {entry.config_cls.__name__} fields {unknown}; "
            f"valid: {', '.join(fields)}"
        )
    task = dataclasses.replace(task or entry.config_cls(), **overrides)
    if randomize is None:
        randomize = training_randomize(name) if layouts is None else RandomizeConfig()
    layouts = default_layouts(name) if layouts is None else list(layouts)
    if not layouts:
        randomize = dataclasses.replace(randomize, sampled_room_prob=1.0)
    scene = scene or SceneConfig()
    nb = max([scene.num_boxes, randomize.num_boxes[1]] + [len(lay.boxes) for lay in layouts])
    nc = max(
        [scene.num_cylinders, randomize.num_cylinders[1]] + [len(lay.cylinders) for lay in layouts]
    )
    nc += randomize.moving_count[1]  # the last slots: `motion.add_movers`
    nc += walker_config(randomize).slots  # the slots before them: `crowd.add_walkers`
    scene = dataclasses.replace(scene, num_boxes=nb, num_cylinders=nc)
    grid = grid_cells(layouts, randomize)
    check_grid_physics(grid, scene)
    bank = make_bank(layouts, nb, nc, grid)
    if getattr(entry.env_cls, "uses_goals", False):  # goal tasks: goals and free cells per layout
        bank = bank.replace(goals=make_goal_cells(layouts, robot.radius))
    return entry.env_cls(
        bank,
        task=task,
        randomize=randomize,
        sensor=sensor or SensorConfig(),
        scene=scene,
        robot=robot,
    )
