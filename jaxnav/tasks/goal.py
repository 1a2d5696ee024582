"""`goal`: point-goal navigation. Reach a goal position in a room of obstacles, touching none.

Observation [(1 + history) x (num_sectors + 5) + memory_bins]: a frame is the depth sectors (m, as
`avoid`), the goal in the robot's frame (distance m, sin and cos of its bearing, positive = to the
left) and the last command the policy sent (forward / forward_speed, yaw / turn_rate); the newest
frame comes first, then the `history` (16) before it, newest first. The stacked frames are a short
memory: a policy that remembers where it has just been gets round walls a memoryless one stalls at
(docs/results.md). The last command rather than the measured velocity: with the Kobuki's velocity
smoother and command latency the robot's motion lags the command, and the policy needs to know what
it already asked for; the command is exact on both sides, where a measured velocity would bring
the odometry's noise and its own sim-to-real gap.
With `memory_bins` the observation ends with a memory (`jaxnav.robot_side.memory`, the same code
on the robot): the distance to the nearest point the camera saw in the last `memory_steps` steps in
each of that many directions round the robot, so an obstacle that left the 60 degree view, or came
nearer than the camera's range_min, is still seen (docs/results.md, "BARN").

Actions: the paper's three (default), those and a stop, or continuous (forward m/s, yaw rad/s),
see `GoalConfig`. Reward per step (`GoalConfig`): progress_reward x (metres closer to the goal) +
time_reward, plus success_reward on the step that reaches it or collision_reward on the step that
collides, and (with `clearance`) a cost for passing nearer than that to anything. Closer
is measured along the room's free space by default (`progress="geodesic"`: the traced grid of
`jaxnav.core.goals.goal_field`), so a detour around a wall is not punished; a potential-based
term, it sums to the geodesic distance covered whatever the path. The
episode ends on success (within success_radius of the goal), on a collision or at the time limit.
Metrics (per step, summed per episode): `collision`, `success`, `path_length` (m travelled).
Goals: a layout's own `goal`, else a reachable one drawn every episode (`jaxnav.core.goals`).
The critic may see more than the policy (`PPOConfig.privileged_critic`, the goal task's default):
`state.info["critic"]` holds the distance to go along the free space and how it changes around
the robot, which no sensor on the robot gives; training uses it, the exported policy does not.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnav.core.checks import require_finite
from jaxnav.core.episode import sample
from jaxnav.core.families import LARGE_EXTENTS
from jaxnav.core.goals import (
    GRID_HALF,
    geodesic,
    geodesics,
    pack_field,
    sample_goal,
    shortest_paths,
)
from jaxnav.core.randomize import family_weights
from jaxnav.core.robot import RobotSpec
from jaxnav.core.types import ActionSpec, EnvState
from jaxnav.robot_side.memory import MemorySpec, recall, remember_frame, sector_points
from jaxnav.tasks.base import (
    Actuator,
    EvalMetric,
    NavTask,
    check_velocity_config,
    stack_frames,
    velocity_actions,
)

GOAL_FEATURES = 3  # distance, sin and cos of the bearing
COMMAND_FEATURES = 2  # the last command, scaled by forward_speed and turn_rate
LOOK = 0.3  # m, how far the critic's look-around probes (`GoalEnv._critic_features`)
LOOK_DIRECTIONS = 8  # probes, 45 degrees apart, the first straight ahead
CRITIC_FEATURES = 1 + LOOK_DIRECTIONS + 1  # distance to go, the look-around, time used


@dataclasses.dataclass(frozen=True)
class GoalConfig:
    """The task: actions, goal placement, reward terms, episode length."""

    actions: str = "discrete"
    """'discrete': the paper's forward / left / right; 'discrete_stop': those and stop (0, 0);
    'discrete_back': those and back (-forward_speed / 2, 0); 'continuous': (forward m/s, yaw
    rad/s) in [0, forward_speed] x [-turn_rate, turn_rate]."""
    forward_speed: float = 0.5
    """Forward speed of the `forward` action (the top of the continuous range), m/s (Kobuki 0.7)."""
    turn_rate: float = 1.5
    """Yaw rate of the `left`/`right` actions (the continuous range's bound), rad/s (Kobuki 3.14)."""
    success_radius: float = 0.3
    """The goal is reached when the robot's centre is within this distance of it, m."""
    goal_min_distance: float = 1.5
    """A sampled goal lies at least this far from the spawn (straight line), m, where the room
    allows; else as far as the draw found."""
    path_clearance: float = 0.15
    """Sampled rooms: obstacles are kept this far beyond the robot's radius from a cleared
    L-shaped path spawn -> goal, m, so the goal is reachable (`jaxnav.core.goals`)."""
    progress_reward: float = 1.0
    """Reward per metre the step brought the robot closer to the goal (negative when farther)."""
    progress: str = "geodesic"
    """How `progress_reward` measures closer: 'geodesic', along the free space (around walls and
    obstacles, on a 0.2 m grid); 'straight', the straight line (a detour is punished)."""
    success_reward: float = 10.0
    """Added on the step that reaches the goal; the episode ends."""
    collision_reward: float = -10.0
    """Added on the step that collides; the episode ends."""
    time_reward: float = -0.01
    """Added on every step (a small cost of time)."""
    clearance: float = 0.0
    """m; a step that ends with the robot's collision volume nearer than this to a wall, an
    obstacle or a person adds clearance_reward x (1 - gap / clearance): the full term at contact,
    none at this gap (training only: the gap is the simulator's, no sensor's). 0 = none. A room's
    occupancy grid counts within `grid.REACH` cells of the robot's centre (0.5 m for 0.1 m
    cells), so in grid rooms a clearance beyond about 0.3 m sees the nearer cells only."""
    clearance_reward: float = -0.05
    """The clearance term at contact (see `clearance`); <= 0, a cost."""
    max_steps: int = 500
    """Time limit in control steps (500 = 50 s at 10 Hz); ends the episode without penalty."""
    history: int = 16
    """Earlier observations appended to the current one, newest first (stacked frames: a 1.6 s
    memory); 0 = none. The observation grows to (1 + history) x (sectors + 5)."""
    memory_bins: int = 0
    """Directions round the robot in which the observation ends with the distance to the nearest
    point the camera saw in the last `memory_steps` steps (`jaxnav.robot_side.memory`: what
    left the view, and what came nearer than range_min); 0 = no memory."""
    memory_steps: int = 20
    """Control steps a sector's reading is remembered (20 = 2 s at 10 Hz)."""
    memory_reach: float = 1.5
    """m; a memory bin with no remembered point nearer reads this."""

    def __post_init__(self):
        require_finite(self)
        for name in ("success_radius", "goal_min_distance"):
            if getattr(self, name) <= 0:
                raise ValueError(f"GoalConfig.{name}: must be > 0 m, got {getattr(self, name)}")
        if self.clearance < 0:
            raise ValueError(f"GoalConfig.clearance: must be >= 0 m, got {self.clearance}")
        if self.clearance_reward > 0:
            raise ValueError(
                f"GoalConfig.clearance_reward: must be <= 0 (a cost), got {self.clearance_reward}"
            )
        if self.path_clearance < 0:
            raise ValueError(
                f"GoalConfig.path_clearance: must be >= 0 m, got {self.path_clearance}"
            )
        if self.max_steps < 1:
            raise ValueError(f"GoalConfig.max_steps: must be >= 1, got {self.max_steps}")
        for name in ("history", "memory_bins"):
            if getattr(self, name) < 0:
                raise ValueError(f"GoalConfig.{name}: must be >= 0, got {getattr(self, name)}")
        if self.memory_steps < 1:
            raise ValueError(f"GoalConfig.memory_steps: must be >= 1, got {self.memory_steps}")
        if self.memory_reach <= 0:
            raise ValueError(f"GoalConfig.memory_reach: must be > 0 m, got {self.memory_reach}")
        if self.progress not in ("geodesic", "straight"):
            raise ValueError(
                f"GoalConfig.progress: must be 'geodesic' or 'straight', got {self.progress!r}"
            )

    @property
    def action_spec(self) -> ActionSpec:
        """The paper's three actions (and a stop or a back), or continuous commands within the same
        speeds."""
        return velocity_actions(self.actions, self.forward_speed, self.turn_rate)

    def check_robot(self, robot: RobotSpec) -> None:
        """The actions are known and the commanded speeds within the robot's limits."""
        check_velocity_config(self, robot)

    @property
    def extra_observations(self) -> int:
        """Observation entries after the depth sectors: the goal and the last command (and the
        stacked earlier observations, sectors included: `num_sectors` is the sensor's)."""
        return GOAL_FEATURES + COMMAND_FEATURES

    @property
    def critic_observations(self) -> int:
        """The critic's own inputs (`GoalEnv._critic_features`; with `PPOConfig.privileged_critic`)."""
        return CRITIC_FEATURES


def goal_features(qpos: jax.Array, goal: jax.Array) -> jax.Array:
    """[3] the goal seen from pose qpos [3] (x, y, yaw): distance m, sin and cos of its bearing
    (rad from the heading, positive = left). The same arithmetic as `robot_side.goal_features`."""
    delta = goal - qpos[:2]
    bearing = jnp.arctan2(delta[1], delta[0]) - qpos[2]
    return jnp.stack([jnp.linalg.norm(delta), jnp.sin(bearing), jnp.cos(bearing)])


def spl_values(layout, room: dict, radius: float, success_radius: float) -> np.ndarray:
    """[N] success weighted by path length per episode (Anderson et al., 2018): S l / max(p, l),
    with p the path the robot drove and l the shortest path that reaches the goal: the shortest
    path from the start to the goal on the room's occupancy grid (`goals.shortest_paths`: 0.1 m
    cells, obstacles inflated by the robot radius, 8-connected) less the success radius (stricter
    than taking the path to the goal's centre, which lets every successful path be that much
    shorter than l). `room`: its episodes' "start", "goal" [N, 2], "distance" [N] and "metrics"."""
    shortest = shortest_paths(layout, room["start"], room["goal"], radius)
    return spl_from(shortest - success_radius, room)


def spl_from(reach: np.ndarray, room: dict) -> np.ndarray:
    """[N] S l / max(p, l) for shortest paths l = `reach` [N] (m) and the episodes' successes and
    driven distances p of `room` (0 where l is not finite)."""
    success = reached(room)
    driven = np.asarray(room["distance"], np.float64)
    reach = np.maximum(reach, 0.0)
    ratio = np.where(success, reach / np.maximum(np.maximum(driven, reach), 1e-9), 0.0)
    return np.where(np.isfinite(ratio), ratio, 0.0)


def reached(room: dict) -> np.ndarray:
    """[N] bool: the episodes of an evaluated room (`EvalMetric`) that reached their goal."""
    return np.asarray(room["metrics"]["success"]) > 0


def _spl(room: dict) -> np.ndarray:
    return spl_values(room["layout"], room, room["robot_radius"], room["task"].success_radius)


EVAL_METRICS = (
    EvalMetric(
        "success_rate",
        value=lambda room: reached(room).astype(np.float64),
        column="success %",
        width=9,
        scale=100.0,
        digits=1,
        title="{:.0%} success",
    ),
    EvalMetric("spl", value=_spl, column="SPL", title="SPL {:.2f}"),
    EvalMetric(  # the longest episode's time where none reached its goal
        "time_to_goal",
        value=lambda room: np.asarray(room["steps"], np.float64) * room["control_period"],
        over=reached,
    ),
)
"""Evaluation's goal metrics: the share of episodes that reached the goal, SPL (`spl_values`),
and the mean time (s) of those that reached it."""


class GoalEnv(NavTask):
    """Point-goal navigation. `reset`/`step` are pure; vmap them for a batch. Its `LayoutBank`
    needs goal data (`make_env("goal", ...)` builds it: `uses_goals`)."""

    metric_names = ("collision", "success", "path_length")
    eval_metrics = EVAL_METRICS
    success_metric = "success"
    uses_goals = True  # make_env adds `jaxnav.core.goals.GoalCells` to the bank

    def __init__(self, bank, task: GoalConfig = GoalConfig(), **specs):
        super().__init__(bank, task, **specs)
        if bank.goals is None:
            raise ValueError("GoalEnv: the layout bank has no goal data; build it with make_env")
        task.check_robot(self.robot)
        self.action_spec = task.action_spec
        self._frames = self.observation_size - task.memory_bins  # the stacked frames
        self._memory = None
        if task.memory_bins:
            if self.sensor.model != "camera":
                raise ValueError(
                    "GoalConfig.memory_bins: needs a camera (--sensor.model camera), or no "
                    "memory (--task.memory-bins 0; the cpu and gpu presets have one)"
                )
            self._memory = MemorySpec(
                task.memory_bins, task.memory_steps, task.memory_reach, self.robot.camera_forward
            )
        self._command_scale = jnp.array([task.forward_speed, task.turn_rate])
        self._grid_extent = self._cover(bank)
        # The geodesic's field, read by `geodesics` alone (`jaxnav.core.types.Banked`).
        self.banked_info = ("field",) if task.progress == "geodesic" else ()

    def _cover(self, bank) -> tuple[float, float]:
        """Half extents (long, short) m of the traced goal grid: at least `GRID_HALF`, and every
        room the episodes may use, with its long axis along the grid's (`goals.grid_shape`)."""
        mix = family_weights(self.randomize.families) if self.randomize.families else {}
        large = [LARGE_EXTENTS[name] for name in mix if name in LARGE_EXTENTS]
        halves = np.sort(np.asarray(bank.rooms.room_half, np.float64).reshape(-1, 2), axis=-1)
        sampled = 0.5 * np.sort(np.asarray(self.randomize.room_size_max, np.float64))
        rooms = [(long, short) for short, long in [*halves, sampled]] + large
        return tuple(max(GRID_HALF, *(room[i] for room in rooms)) for i in (0, 1))

    def begin(self, key: jax.Array) -> tuple[EnvState, jax.Array]:
        """A new episode (`NavTask.begin`): fresh room, spawn, goal and parameters drawn from the
        randomisation."""
        key, k_scene, k_goal, k_obs = jax.random.split(key, 4)
        t, radius = self.task, self.robot.radius
        params = sample(k_scene, self.randomize, self.bank, radius)
        clearance = self.randomize.spawn_clearance
        params, goal, field = sample_goal(
            k_goal,
            params,
            self._grid_extent,
            self.bank.goals,
            radius,
            clearance,
            t.goal_min_distance,
            t.path_clearance,
        )
        info = {"goal": goal, "steps": jnp.int32(0), "key": key}
        if t.progress == "geodesic":  # the still room's: movers do not stay where they start
            info["field"] = pack_field(field)  # [rows, cols] int16 steps
        params = self.with_movers(k_scene, params, goal)
        data = self.place(params)
        f0, b0 = jnp.float32(0), jnp.bool_(False)
        info["params"] = params
        here = self._to_go(info, data.qpos[:2])
        info["critic"] = self._critic_features(info, data.qpos[:3], here, jnp.int32(0))
        if self._memory is not None:
            s, m = self.sensor.num_sectors, self._memory.steps
            info["memory"] = (jnp.zeros((m, s, 2)), jnp.zeros((m, s), bool))
        state = EnvState(
            data=data,
            obs=None,
            reward=f0,
            done=b0,
            truncated=b0,
            metrics={
                "collision": f0,
                "success": f0,
                "path_length": f0,
                **self.walker_hit(params, data, b0),
            },
            info={**info, "actuator": Actuator.zero(), "command": jnp.zeros(2)},
        )
        return state, k_obs

    def first_observation(self, state: EnvState, key: jax.Array) -> EnvState:
        """The first frame, standing in for the earlier ones, and the memory holding it."""
        info = state.info
        args = (info["params"], state.data, info["goal"], info["command"], key, info)
        frame, info, recalled = self._observe(*args)
        obs = jnp.concatenate([jnp.tile(frame, 1 + self.task.history), recalled])
        return state.replace(obs=obs, info=info)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Hold `action` for one control period; end on success, collision or time."""
        t, info = self.task, state.info
        params, goal = self.move(info["params"], state.data), info["goal"]
        target = self.command(action)
        command, actuator = self.actuate(params, info["actuator"], target)
        data, hit = self.drive(params, state.data, command)
        before, after = (self._to_go(info, d.qpos[:2]) for d in (state.data, data))
        success = (jnp.linalg.norm(goal - data.qpos[:2]) <= t.success_radius) & ~hit
        steps = info["steps"] + 1
        truncated = (steps >= t.max_steps) & ~hit & ~success
        reward = t.progress_reward * (before - after) + t.time_reward
        reward += jnp.where(success, t.success_reward, 0.0) + jnp.where(
            hit, t.collision_reward, 0.0
        )
        if t.clearance > 0:
            reward += t.clearance_reward * jnp.clip(1 - self.gap(params, data) / t.clearance, 0, 1)
        key, k_obs = jax.random.split(info["key"])
        moved = jnp.linalg.norm(data.qpos[:2] - state.data.qpos[:2])
        f32 = lambda x: x.astype(jnp.float32)  # noqa: E731
        frame, info, recalled = self._observe(params, data, goal, target, k_obs, info)
        return EnvState(
            data=data,
            obs=jnp.concatenate([stack_frames(frame, state.obs, self._frames), recalled]),
            reward=f32(reward),
            done=hit | success | truncated,
            truncated=truncated,
            metrics={
                "collision": f32(hit),
                "success": f32(success),
                "path_length": f32(moved),
                **self.walker_hit(params, data, hit),
            },
            info={
                **info,
                "params": params,
                "steps": steps,
                "key": key,
                "actuator": actuator,
                "command": target,
                "critic": self._critic_features(info, data.qpos[:3], after, steps),
            },
        )

    def _to_go(self, info, xy) -> jax.Array:
        """[] m from `xy` to the goal, as `GoalConfig.progress` measures it (the geodesic falls
        back to the straight line where `xy` is walled in, see `jaxnav.core.goals.geodesic`)."""
        if self.task.progress == "geodesic":
            return geodesic(info["field"], info["goal"], xy, None, info["params"].room_half)
        return jnp.linalg.norm(info["goal"] - xy)

    def _to_go_near(self, info, xy, points, blocked) -> jax.Array:
        """[P] `_to_go` of each of `points` [P, 2], all within LOOK of `xy` [2] (one read of the
        geodesic's grid around it, `jaxnav.core.goals.geodesics`), `blocked` [] where a point is
        walled in rather than the straight line."""
        if self.task.progress == "geodesic":
            best = geodesics(info["field"], xy, points, LOOK, info["params"].room_half)
            return jnp.where(jnp.isfinite(best), best, blocked)
        return jnp.linalg.norm(info["goal"] - points, axis=-1)

    def _critic_features(self, info, qpos, here, steps) -> jax.Array:
        """[CRITIC_FEATURES] what only the critic sees (`state.info["critic"]`, training only): the
        distance to go as `progress` measures it (/ 5 m), how much closer a LOOK step in each of
        LOOK_DIRECTIONS directions from the heading would bring the robot (/ LOOK: about +1 along
        the way to go, -1 away from it; -1 into an obstacle or a wall, clipped to +-2 where the
        grid's steps or a robot pressed against a wall would give more), and the share of the
        time limit used (`steps` of `max_steps`). `here`: the distance to go from qpos, which the
        caller has already measured. With them the value of a pose behind a partition need not be
        inferred from the sectors."""
        angles = qpos[2] + jnp.arange(LOOK_DIRECTIONS) * (2 * jnp.pi / LOOK_DIRECTIONS)
        probes = qpos[:2] + LOOK * jnp.stack([jnp.cos(angles), jnp.sin(angles)], -1)  # [8, 2]
        around = self._to_go_near(info, qpos[:2], probes, blocked=here + LOOK)  # [8]
        closer = jnp.clip((here - around) / LOOK, -2.0, 2.0)  # [LOOK_DIRECTIONS]
        used = jnp.asarray(steps, jnp.float32) / self.task.max_steps
        return jnp.concatenate([here[None] / 5.0, closer, used[None]])

    def _observe(self, params, data, goal, command, key, info):
        """This step's frame [sectors + 5] (sectors, goal features, the last command scaled to
        [-1, 1]), `info` with the memory that holds its readings, and the memory read back
        [memory_bins] (`jaxnav.robot_side.memory`; [0] without one)."""
        sectors = self.sense(params, data, key)
        features = goal_features(data.qpos[:3], goal)
        frame = jnp.concatenate([sectors, features, command / self._command_scale])
        spec = self._memory
        if spec is None:
            return frame, info, jnp.zeros(0)
        sensor, pose = self.sensor, data.qpos[:3]
        new = sector_points(
            sectors, pose, sensor.fov, sensor.range_min, sensor.range_max, spec.camera_forward, jnp
        )
        points, seen = remember_frame(info["memory"], new, jnp)  # [steps, S, 2], [steps, S]
        recalled = recall(points.reshape(-1, 2), seen.reshape(-1), pose, spec.bins, spec.reach, jnp)
        return frame, {**info, "memory": (points, seen)}, recalled.astype(jnp.float32)
