"""Task registry: `make_env(name, layouts=..., **overrides)`."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from jaxnav.core.randomize import RandomizeConfig, make_bank
from jaxnav.core.scene import SCENES_DIR, SceneConfig
from jaxnav.core.sensors import SensorConfig
from jaxnav.io.layouts import RoomLayout, load_layout
from jaxnav.tasks.avoid import AvoidConfig, AvoidEnv, EnvState

ENVS = {"avoid": (AvoidEnv, AvoidConfig)}
DEFAULT_LAYOUTS = SCENES_DIR / "train_room.json"

__all__ = ["ENVS", "AvoidConfig", "AvoidEnv", "EnvState", "make_env", "default_layouts"]


def default_layouts() -> list[RoomLayout]:
    """The default training rooms: the paper's training room (Fig. 4)."""
    return load_layout(DEFAULT_LAYOUTS)


def make_env(
    name: str = "avoid",
    layouts: Sequence[RoomLayout] | None = None,
    *,
    task: AvoidConfig | None = None,
    randomize: RandomizeConfig | None = None,
    sensor: SensorConfig | None = None,
    scene: SceneConfig | None = None,
    **overrides,
):
    """Builds a task. `layouts=None` uses the default rooms; `[]` trains on sampled rooms only.

    `overrides` are fields of the task config (e.g. `near_threshold=0.8`). Slot counts grow to fit
    the largest layout and the sampler's maximum obstacle counts.
    """
    if name not in ENVS:
        raise ValueError(f"unknown environment '{name}'; valid names: {', '.join(sorted(ENVS))}")
    env_cls, task_cls = ENVS[name]
    fields = [f.name for f in dataclasses.fields(task_cls)]
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        raise ValueError(
            f"make_env: unknown {task_cls.__name__} fields {unknown}; valid: {', '.join(fields)}"
        )
    task = dataclasses.replace(task or task_cls(), **overrides)
    randomize = randomize or RandomizeConfig()
    layouts = default_layouts() if layouts is None else list(layouts)
    if not layouts:
        randomize = dataclasses.replace(randomize, sampled_room_prob=1.0)
    scene = scene or SceneConfig()
    nb = max([scene.num_boxes, randomize.num_boxes[1]] + [len(lay.boxes) for lay in layouts])
    nc = max(
        [scene.num_cylinders, randomize.num_cylinders[1]] + [len(lay.cylinders) for lay in layouts]
    )
    scene = dataclasses.replace(scene, num_boxes=nb, num_cylinders=nc)
    bank = make_bank(layouts, nb, nc)
    return env_cls(
        bank, task=task, randomize=randomize, sensor=sensor or SensorConfig(), scene=scene
    )
