"""The `goal` task: reachable goal draws, SPL's shortest paths, reward terms, success, continuous
actions within the limits, goals in layouts, and no recompilation when goals change."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, start_in, traced_once

import jaxnav
from jaxnav.core import families, flood_kernel, goals
from jaxnav.core.geometry import signed_distance
from jaxnav.core.goals import GRID_CELL, grid_steps, shortest_paths
from jaxnav.core.motion import still
from jaxnav.core.randomize import TRAINING, RandomizeConfig, family_weights, make_bank
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.io.layouts import Box, LayoutError, RoomLayout, parse_layouts
from jaxnav.ppo.distributions import Gaussian
from jaxnav.robot_side.policy import FrameStack
from jaxnav.tasks.avoid import AvoidConfig
from jaxnav.tasks.base import BACK_SHARE, velocity_actions
from jaxnav.tasks.goal import spl_values
from jaxnav.wrappers import EPISODE, AutoReset, EpisodeStats

R = TURTLEBOT2I.radius

# A 6 x 4 m room whose east end is a closed-off pocket (a wall from wall to wall at x = 1.5):
# spawns drawn there must move, and no goal may be drawn there.
POCKET = RoomLayout(
    name="pocket",
    size=(6.0, 4.0),
    obstacles=(Box(pos=(1.5, 0.0), size=(0.2, 4.0)), Box(pos=(-1.0, 0.8), size=(0.6, 0.6))),
)
OPEN = RoomLayout(name="open", size=(5.0, 5.0), robot_pos=(-1.5, -1.5))
CORRIDOR = RoomLayout(
    name="corridor", size=(8.0, 2.0), robot_pos=(-3.0, 0.0), robot_yaw=0.0, goal_pos=(2.0, 0.0)
)


@pytest.fixture(scope="module")
def mixed():
    """Layouts with and without spawns, a pocket, and sampled rooms, with random spawns; reset and
    step compile once for every room and goal (`chex.assert_max_traces`)."""
    randomize = dataclasses.replace(TRAINING, random_spawn_prob=0.5)
    env = jaxnav.make_env("goal", layouts=[POCKET, OPEN, CORRIDOR], randomize=randomize)

    return env, *traced_once(env)


def test_goal_draws_are_free_far_and_reachable(mixed):
    env, reset, _ = mixed
    states = [reset(jax.random.PRNGKey(seed)) for seed in range(120)]
    state = jax.tree_util.tree_map(lambda *x: np.stack(x), *states)
    params = state.info["params"]
    goals, starts = np.asarray(state.info["goal"]), np.asarray(state.data.qpos[:, :2])
    ids = np.asarray(params.layout_id)
    assert (ids == -1).any() and all((ids == k).any() for k in range(3))
    layouts = [POCKET, OPEN, CORRIDOR]
    for e in range(len(ids)):
        room = jax.tree_util.tree_map(lambda x, e=e: x[e], params)
        layout = layouts[ids[e]] if ids[e] >= 0 else families.to_layout(room, "sampled")
        # The goal and the start leave the robot's disc free, in the room the episode sees.
        for point in (goals[e], starts[e]):
            assert float(families.lay.clearance(layout, point)) > R
        length = shortest_paths(layout, starts[e][None], goals[e][None])[0]
        assert np.isfinite(length), (ids[e], starts[e], goals[e])
        if ids[e] == 0:
            assert goals[e][0] < 1.5 and starts[e][0] < 1.5  # never in the pocket
        if ids[e] == 2:
            np.testing.assert_allclose(goals[e], CORRIDOR.goal_pos)
    far = np.linalg.norm(goals - starts, axis=-1) >= env.task.goal_min_distance
    assert far[ids != 2].mean() > 0.95  # drawn goals (a few small rooms may not allow it)


def test_shortest_path_by_hand():
    """Straight and diagonal paths are exact; around a wall, within the grid's error of the hand
    value; SPL from them."""
    room = RoomLayout(name="empty", size=(3.0, 3.0))
    straight = shortest_paths(room, [[-0.95, 0.05]], [[1.05, 0.05]])
    np.testing.assert_allclose(straight, [2.0], atol=1e-9)
    diagonal = shortest_paths(room, [[-0.95, -0.95]], [[0.05, 0.05]])
    np.testing.assert_allclose(diagonal, [np.sqrt(2.0)], atol=1e-9)
    # A wall across a 4 x 4 m room from the south wall to y = 1, 0.2 m thick: the robot
    # (inflated wall: |x| <= 0.1 + R, y <= 1 + R) goes round its end.
    wall = RoomLayout(
        name="wall", size=(4.0, 4.0), obstacles=(Box(pos=(0.0, -0.5), size=(0.2, 3.0)),)
    )
    start, goal = np.array([-1.05, -1.05]), np.array([1.05, -1.05])
    corner = np.array([0.1 + R, 1.0 + R])
    hand = 2 * np.linalg.norm(corner * [-1, 1] - start) + 2 * corner[0]
    got = shortest_paths(wall, [start], [goal])[0]
    # 8-connected steps add up to 8 %; the grid rounds the inflated wall out by up to a cell.
    assert hand <= got <= 1.08 * hand + 4 * 0.1
    # SPL: success x l / max(driven, l), l the shortest path less the success radius.
    reach = got - 0.3
    track = {
        "start": np.array([start] * 4),
        "goal": np.array([goal] * 4),
        "distance": np.array([reach, 2 * reach, reach, got]),
        "metrics": {"success": np.array([1.0, 1.0, 0.0, 1.0])},
    }
    np.testing.assert_allclose(spl_values(wall, track, R, 0.3), [1.0, 0.5, 0.0, reach / got])
    closed = RoomLayout(
        name="closed", size=(4.0, 4.0), obstacles=(Box(pos=(0, 0), size=(0.4, 4.0)),)
    )
    assert np.isinf(shortest_paths(closed, [start], [goal])[0])


# Facing east in the middle of a 3 x 3 m room, the goal behind it.
WALL = RoomLayout(
    name="wall", size=(3.0, 3.0), robot_pos=(0.0, 0.0), goal_pos=(-1.0, 0.0), robot_yaw=0.0
)


@pytest.fixture(scope="module")
def exact_env():
    env = jaxnav.make_env(
        "goal", layouts=[CORRIDOR, WALL], randomize=EXACT, max_steps=100, progress="straight"
    )
    return env, jax.jit(env.reset), jax.jit(env.step)


def test_reward_terms_and_success_ends_the_episode(exact_env):
    env, reset, step = exact_env
    t = env.task
    state = start_in(env, reset, 0)
    frame = env.observation_size // (1 + t.history)  # 13: 8 sectors, goal [3], command [2]
    np.testing.assert_allclose(state.obs[8:frame], [5.0, 0.0, 1.0, 0.0, 0.0], atol=1e-5)
    stack = FrameStack(t.history)  # the robot side's stacking, fed the simulator's frames
    np.testing.assert_array_equal(stack(state.obs[:frame]), state.obs)
    steps = 0
    while not bool(state.done):
        nxt = step(state, jnp.int32(0))  # forward, straight at the goal
        before = np.linalg.norm(np.asarray(state.info["goal"] - state.data.qpos[:2]))
        after = np.linalg.norm(np.asarray(nxt.info["goal"] - nxt.data.qpos[:2]))
        success = after <= t.success_radius
        want = t.progress_reward * (before - after) + t.time_reward + success * t.success_reward
        np.testing.assert_allclose(nxt.reward, want, rtol=1e-4, atol=1e-5)
        assert float(nxt.metrics["success"]) == float(success)
        np.testing.assert_allclose(nxt.obs[11:frame], [1.0, 0.0])  # the last command, scaled
        np.testing.assert_array_equal(stack(nxt.obs[:frame]), nxt.obs)  # newest frame first
        state, steps = nxt, steps + 1
    assert float(state.metrics["success"]) == 1.0 and not bool(state.truncated)
    assert 94 <= steps <= 100  # 4.7 m at 0.5 m/s = 9.4 s
    assert float(state.metrics["collision"]) == 0.0


def test_collision_penalty_and_time_limit(exact_env):
    env, reset, step = exact_env
    state = start_in(env, reset, 1)
    while not bool(state.done):
        state = step(state, jnp.int32(0))  # away from the goal, into the east wall
    assert float(state.metrics["collision"]) == 1.0 and float(state.metrics["success"]) == 0.0
    assert float(state.reward) < env.task.collision_reward + 0.1
    state = start_in(env, reset, 1)
    for _ in range(100):
        assert not bool(state.done)
        state = step(state, jnp.int32(1))  # turning in place until the time limit
    assert bool(state.done) and bool(state.truncated)


@pytest.mark.slow
def test_continuous_actions_respect_the_limits():
    """Commands out of range or NaN are clipped to the action bounds. Slow: the continuous
    goal env compiles a program of its own."""
    env = jaxnav.make_env("goal", layouts=[OPEN], randomize=EXACT, actions="continuous")
    spec = env.action_spec
    assert (spec.low, spec.high) == ((0.0, -1.5), (0.5, 1.5))
    step = jax.jit(env.step)
    state = jax.jit(env.reset)(jax.random.PRNGKey(1))
    for action in ([9.0, 9.0], [-3.0, -9.0], [np.nan, 0.7], [0.3, -0.4]):
        state = step(state, jnp.array(action, jnp.float32))
        command = np.asarray(state.info["command"])
        assert spec.low[0] <= command[0] <= spec.high[0] and abs(command[1]) <= spec.high[1]
        speed = np.hypot(*np.asarray(state.data.qvel[:2]))
        assert speed <= spec.high[0] + 1e-3 and abs(float(state.data.qvel[2])) <= 1.5 + 1e-3
    np.testing.assert_allclose(command, [0.3, -0.4])
    # avoid has the option too; its reward interpolates Table I between forward and turning.
    avoid = jaxnav.make_env("avoid", layouts=[OPEN], randomize=EXACT, actions="continuous")
    s = jax.jit(avoid.reset)(jax.random.PRNGKey(1))
    step = jax.jit(jax.vmap(avoid.step, in_axes=(None, 0)))
    rewards = step(s, jnp.array([[0.0, 0.0], [0.25, 0.0], [0.5, 0.0]])).reward
    np.testing.assert_allclose(rewards[1], 0.5 * (rewards[0] + rewards[2]), rtol=1e-5)


@pytest.mark.slow
def test_stop_action_holds_still_and_clearance_costs_near_walls():
    """`discrete_stop` adds a fourth action, stop (0, 0), that leaves the robot where it stands;
    `clearance` costs clearance_reward x (1 - gap / clearance) a step, the gap measured here from
    the wall's position. Slow: the env compiles a program of its own."""
    near_wall = RoomLayout(
        name="near", size=(4.0, 4.0), robot_pos=(1.7, 0.0), robot_yaw=np.pi, goal_pos=(-1.5, 0.0)
    )
    env = jaxnav.make_env(
        "goal",
        layouts=[near_wall],
        randomize=EXACT,
        actions="discrete_stop",
        clearance=0.3,
        progress="straight",  # progress measured here too: the straight line to the goal
    )
    spec, t = env.action_spec, env.task
    assert spec.names == ("forward", "left", "right", "stop")
    np.testing.assert_array_equal(spec.table()[3], [0.0, 0.0])
    step = jax.jit(env.step)
    state = start = jax.jit(env.reset)(jax.random.PRNGKey(0))
    to_go = lambda s: float(np.hypot(*(np.asarray(s.data.qpos[:2]) - (-1.5, 0.0))))  # noqa: E731
    for action, steps in ((3, 5), (0, 15)):  # stop by the wall, then drive away from it
        for _ in range(steps):
            before, state = to_go(state), step(state, jnp.int32(action))
            gap = 2.0 - float(state.data.qpos[0]) - env.scene.bumper_radius  # east wall, x = 2
            cost = t.clearance_reward * max(0.0, 1 - gap / t.clearance)
            expected = t.time_reward + t.progress_reward * (before - to_go(state)) + cost
            np.testing.assert_allclose(float(state.reward), expected, atol=1e-4)
        if action == 3:
            assert 0.0 < gap < 0.3 and cost < -0.02
            moved = np.asarray(state.data.qpos[:3] - start.data.qpos[:3])
            np.testing.assert_allclose(moved, 0.0, atol=1e-4)
    assert gap > 0.3  # out of the clearance: no cost beyond the paper's terms
    with pytest.raises(ValueError, match="GoalConfig.clearance: must be >= 0 m"):
        jaxnav.make_env("goal", clearance=-0.1)
    with pytest.raises(ValueError, match="GoalConfig.clearance_reward: must be <= 0 .a cost."):
        jaxnav.make_env("goal", clearance_reward=0.05)


def test_fourth_actions_stop_and_back():
    """`discrete_stop` and `discrete_back` add one command to the paper's three: stop (0, 0), or
    back at BACK_SHARE of the forward speed; `avoid`, whose Table I pays neither, refuses both."""
    paper = [[0.5, 0.0], [0.0, 1.5], [0.0, -1.5]]
    stop, back = (velocity_actions(a, 0.5, 1.5) for a in ("discrete_stop", "discrete_back"))
    assert stop.names == ("forward", "left", "right", "stop")
    assert back.names == ("forward", "left", "right", "back")
    np.testing.assert_array_equal(stop.table(), [*paper, [0.0, 0.0]])
    np.testing.assert_array_equal(back.table(), [*paper, [-BACK_SHARE * 0.5, 0.0]])
    for actions in ("discrete_stop", "discrete_back"):
        with pytest.raises(ValueError, match=f"AvoidConfig.actions: '{actions}' is for the goal"):
            AvoidConfig(actions=actions)


@pytest.mark.slow
def test_back_action_backs_away_along_the_heading():
    """The `back` action drives the robot backwards along its heading, without turning, and the
    reward counts the metres it backs away from the goal. Slow: the env compiles its own program."""
    room = RoomLayout(
        name="back", size=(4.0, 4.0), robot_pos=(0.0, 0.0), robot_yaw=np.pi, goal_pos=(-1.5, 0.0)
    )
    env = jaxnav.make_env(
        "goal", layouts=[room], randomize=EXACT, actions="discrete_back", progress="straight"
    )
    t, step = env.task, jax.jit(env.step)
    state = start = jax.jit(env.reset)(jax.random.PRNGKey(0))
    to_go = lambda s: float(np.hypot(*(np.asarray(s.data.qpos[:2]) - (-1.5, 0.0))))  # noqa: E731
    for _ in range(10):
        before, state = to_go(state), step(state, jnp.int32(3))
        expected = t.time_reward + t.progress_reward * (before - to_go(state))
        np.testing.assert_allclose(float(state.reward), expected, atol=1e-4)
    moved = np.asarray(state.data.qpos[:3] - start.data.qpos[:3])
    back = 10 * env.control_period * BACK_SHARE * t.forward_speed  # +x, as it faces -x
    np.testing.assert_allclose(moved, [back, 0.0, 0.0], atol=1e-3)  # no drift, no turn
    assert not bool(state.done)


def test_gaussian_policy_log_prob_and_entropy():
    from scipy.stats import norm

    dist = Gaussian(low=(0.0, -1.5), high=(0.5, 1.5))
    out = jnp.array([0.2, -0.4, -0.5, 0.1])  # means (half-ranges), log-stds
    mean = np.array([0.25 + 0.25 * 0.2, -0.4 * 1.5])
    std = np.array([0.25 * np.exp(-0.5), 1.5 * np.exp(0.1)])
    a = np.array([0.4, 0.3])
    np.testing.assert_allclose(dist.log_prob(out, a), norm.logpdf(a, mean, std).sum(), rtol=1e-5)
    np.testing.assert_allclose(dist.entropy(out), norm.entropy(mean, std).sum(), rtol=1e-5)
    np.testing.assert_allclose(dist.mode(jnp.array([9.0, -9.0, 0.0, 0.0])), [0.5, -1.5])


def test_goals_change_without_recompiling(mixed):
    _, reset, step = mixed  # test_goal_draws_are_free_far_and_reachable ran 120 resets through it
    seen = set()
    for seed in range(10):
        state = step(reset(jax.random.PRNGKey(seed)), jnp.int32(seed % 3))
        seen.add(tuple(np.round(np.asarray(state.info["goal"]), 2)))
    assert len(seen) >= 8  # fixed and drawn goals, layouts and sampled rooms: one compile


def test_layout_goal_is_checked():
    room = {"name": "r", "room": {"size": [4, 4]}, "robot": {"pos": [-1, -1]}}
    assert parse_layouts({**room, "goal": {"pos": [1, 1]}})[0].goal_pos == (1.0, 1.0)
    assert parse_layouts(room)[0].goal_pos is None  # optional; other tasks ignore it
    box = [{"type": "box", "pos": [1, 1], "size": [0.5, 0.5]}]
    cases = [
        ({"goal": {"pos": [1, 1]}, "obstacles": box}, "room 'r' (#0): goal.pos: the robot"),
        ({"goal": {"pos": [1]}}, "goal.pos: must be two numbers"),
        ({"goal": {"position": [1, 1]}}, "goal.position: unknown key"),
        ({"goal": [1, 1]}, "goal: must be an object"),
    ]
    for extra, message in cases:
        with pytest.raises(LayoutError, match=message.replace("(", r"\(").replace(")", r"\)")):
            parse_layouts({**room, **extra}, "rooms.json")
    walled = {**room, "goal": {"pos": [1.5, 0]}}
    walled["obstacles"] = [{"type": "box", "pos": [0.5, 0], "size": [0.2, 4.0]}]
    with pytest.raises(LayoutError, match="room 'r': goal.pos: not reachable from robot.pos"):
        jaxnav.make_env("goal", layouts=parse_layouts(walled))


@pytest.mark.slow
def test_goal_success_rises_above_random(tmp_path, optimised):
    """A short run in an open room: the success rate of its last updates is well above that of
    its first (a near-uniform random policy's). Slow: a training run long enough to learn."""
    import csv

    from jaxnav.io.layouts import save_layouts

    rooms = tmp_path / "open.json"
    save_layouts(rooms, RoomLayout(name="open", size=(4.0, 4.0)))
    jaxnav.train(
        out=tmp_path / "run", env="goal", layouts=[rooms], progress=False,
        num_envs=64, rollout_length=32, minibatch_size=1024, num_epochs=4, learning_rate=3e-3,
        total_steps=64 * 32 * 80, updates_per_chunk=10, checkpoint_every=80,
        task={"max_steps": 100}, randomize={"sampled_room_prob": 0.0},
    )  # fmt: skip
    with open(tmp_path / "run" / "metrics.csv") as fh:
        success = [float(r["success"]) for r in csv.DictReader(fh) if r["success"] != "nan"]
    first, last = np.mean(success[:5]), np.mean(success[-5:])
    assert last > first + 0.3 and last > 0.5, (first, last)


def _bfs(free: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    """4-connected breadth-first steps from `seed` over `free` (inf where unreached)."""
    steps = np.full(free.shape, np.inf)
    steps[seed], frontier = 0, [seed]
    while frontier:
        nxt = []
        for r, c in frontier:
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                i, j = r + dr, c + dc
                inside = 0 <= i < free.shape[0] and 0 <= j < free.shape[1]
                if inside and free[i, j] and steps[i, j] == np.inf:
                    steps[i, j] = steps[r, c] + 1
                    nxt.append((i, j))
        frontier = nxt
    return steps


def _grids(rng, shape: tuple[int, int, int], cell: tuple[int, int]):
    """([B, H, W] random free masks with `cell` free, [B, H, W] seed masks at `cell`, [B, H, W]
    breadth-first steps from it)."""
    free = rng.random(shape) > 0.3
    free[:, cell[0], cell[1]] = True
    seed = np.zeros_like(free)
    seed[:, cell[0], cell[1]] = True
    return free, seed, np.stack([_bfs(f, cell) for f in free])


def test_traced_flood_matches_breadth_first_search():
    rng = np.random.default_rng(0)
    free, seed, want = _grids(rng, (6, 30, 30), (5, 5))
    got = np.asarray(jax.vmap(lambda f, s: grid_steps(f, s, sweeps=40))(free, seed))
    np.testing.assert_array_equal(got, want)
    # Nested vmaps, a seed shared by the batch, and the three floods (the CPU's loop over rows,
    # one GPU's kernel, through Pallas' interpreter here, the other platforms' associative scans)
    # called directly on a batch, all alike.
    nested = jax.vmap(jax.vmap(lambda f, s: grid_steps(f, s, sweeps=40), (0, None)), (0, None))
    got = nested(free.reshape(2, 3, 30, 30), seed[0])
    np.testing.assert_array_equal(np.asarray(got).reshape(want.shape), want)
    for flood in (goals._flood_rows, goals._flood_scans, _kernel_flood):
        np.testing.assert_array_equal(
            np.asarray(jax.jit(flood, static_argnums=2)(free, seed, 40)), want
        )
    # Fewer rounds never claim a path that is not there, nor a shorter one.
    few = np.asarray(grid_steps(jnp.asarray(free[0]), jnp.asarray(seed[0]), sweeps=2))
    assert (few >= want[0]).all() and np.isinf(few).sum() > np.isinf(want[0]).sum()
    # Grids longer than wide (a long hall's), through both floods.
    wide, start, want = _grids(rng, (3, 12, 40), (2, 30))
    got = np.asarray(jax.vmap(lambda f, s: grid_steps(f, s, sweeps=40))(wide, start))
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(np.asarray(goals._flood_scans(wide, start, 40)), want)
    np.testing.assert_array_equal(np.asarray(_kernel_flood(wide[None], start[None], 40))[0], want)


def _kernel_flood(free, seed, sweeps):
    """The GPU's flood kernel (`flood_kernel.flood`), run by Pallas' interpreter on the CPU."""
    return flood_kernel.flood(jnp.asarray(free), jnp.asarray(seed), sweeps, interpret=True)


def _nine_cells(field, xy, half):
    """The geodesic's least value at `xy` [2], in numpy: over the 3 x 3 cells around xy's cell,
    clipped to the grid, of steps x GRID_CELL + the line to the cell's centre (inf if none)."""
    rows, cols = field.shape
    grid_half = 0.5 * np.array([cols, rows]) * GRID_CELL
    p = xy[::-1] if (rows != cols and half[1] > half[0]) else xy  # the grid's frame
    col, row = np.round((p + grid_half) / GRID_CELL - 0.5).astype(int)
    best = np.inf
    for r in np.clip(row + np.arange(-1, 2), 0, rows - 1):
        for c in np.clip(col + np.arange(-1, 2), 0, cols - 1):
            centre = (np.array([c, r]) + 0.5) * GRID_CELL - grid_half
            best = min(best, field[r, c] * GRID_CELL + np.hypot(*(centre - p)))
    return best


def test_probes_read_the_geodesic_from_one_window():
    """`geodesics` reads every probe's nine cells from one slice of the field around the robot:
    the values of reading each probe's own cells, to float32 rounding, at the grid's edges and
    beyond them, on square grids and on a hall's grid lying either way round; from the float32
    field and from the int16 steps an episode keeps (`pack_field`) alike."""
    from jaxnav.tasks.goal import LOOK, LOOK_DIRECTIONS

    rng = np.random.default_rng(0)
    for shape, half in (((20, 20), (2.0, 2.0)), ((12, 40), (4.0, 1.2)), ((12, 40), (1.2, 4.0))):
        field = rng.integers(0, 40, (64, *shape)).astype(np.float32)
        field[rng.random(field.shape) < 0.3] = np.inf
        reach = max(half) + 0.5  # some robots beyond the grid
        xy = rng.uniform(-reach, reach, (64, 2)).astype(np.float32)
        xy[:16] = np.round(xy[:16] / 0.1) * 0.1  # on cell boundaries
        angles = rng.uniform(-np.pi, np.pi, (64, 1)) + np.arange(LOOK_DIRECTIONS) * np.pi / 4
        probes = (xy[:, None] + LOOK * np.stack([np.cos(angles), np.sin(angles)], -1)).astype(
            np.float32
        )  # [64, 8, 2]
        read = jax.vmap(goals.geodesics, (0, 0, 0, None, None))
        want = [[_nine_cells(f, p, half) for p in ps] for f, ps in zip(field, probes, strict=True)]
        packed = goals.pack_field(jnp.asarray(field))
        assert packed.dtype == jnp.int16 and packed.nbytes == field.nbytes // 2
        for grid in (field, packed):
            got = read(grid, xy, probes, LOOK, jnp.asarray(half))
            np.testing.assert_allclose(
                np.asarray(got), np.array(want, np.float32), rtol=1e-6, atol=1e-6
            )
        assert np.isinf(want).any() and np.isfinite(want).any()


@pytest.mark.slow
def test_family_goals_are_reachable_and_often_behind_walls():
    """Corridors, L/T/U rooms and joined rooms keep their walls; the goal is drawn reachable.
    Slow: a goal env over three sampled families compiles its own reset."""
    randomize = dataclasses.replace(TRAINING, families="corridor,ltu,joined", sampled_room_prob=1.0)
    env = jaxnav.make_env("goal", randomize=randomize)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 24))
    params, goals = state.info["params"], np.asarray(state.info["goal"])
    detours, geodesics = (
        [],
        np.asarray(
            jax.vmap(jaxnav.core.goals.geodesic)(
                state.info["field"], state.info["goal"], params.spawn[:, :2]
            )
        ),
    )
    rooms = jax.device_get(params)  # numpy: the loop below indexes it per env
    for e in range(len(goals)):
        room = jax.tree_util.tree_map(lambda x, e=e: x[e], rooms)
        layout = families.to_layout(room, "family")
        start = np.asarray(room.spawn[:2])
        assert float(families.lay.clearance(layout, goals[e])) > R
        length = shortest_paths(layout, start[None], goals[e][None])[0]
        assert np.isfinite(length)
        straight = np.linalg.norm(goals[e] - start)
        assert straight >= env.task.goal_min_distance - 1e-5
        # The reward's geodesic: 4-connected grid steps, at most sqrt(2) x the 8-connected path
        # (plus a cell either end), never shorter than the straight line.
        assert straight - 1e-4 <= geodesics[e] <= np.sqrt(2) * length + 2 * GRID_CELL
        detours.append(length / straight)
    assert max(detours) > 1.5  # some goals lie behind a wall


# A 6 x 4 m room split by a partition open 1 m at its north end, the goal east behind it.
DETOUR = RoomLayout(
    name="detour",
    size=(6.0, 4.0),
    obstacles=(Box(pos=(0.0, -0.5), size=(0.2, 3.0)),),  # open 1 m at the north end
    robot_pos=(-1.53, -1.07),  # off the 0.2 m grid's lines, which probes could round across
    robot_yaw=np.pi / 2,  # north, along the wall
    goal_pos=(1.5, -1.0),  # east, behind the wall
)
AT_WALL = dataclasses.replace(DETOUR, name="at_wall", robot_pos=(-0.35, -1.07), robot_yaw=0.0)
ON_GRID = dataclasses.replace(DETOUR, name="on_grid", robot_pos=(-1.5, -1.0))


@pytest.fixture(scope="module")
def detour_env():
    """`goal` in the rooms behind a partition (layouts 0, 1, 2: DETOUR, AT_WALL, ON_GRID), 200-step
    episodes: (env, jitted reset, jitted step), compiled once for the two slow tests below (11 s
    on 2 cores for this env alone)."""
    env = jaxnav.make_env(
        "goal", layouts=[DETOUR, AT_WALL, ON_GRID], randomize=EXACT, max_steps=200
    )
    return env, jax.jit(env.reset), jax.jit(env.step)


@pytest.mark.slow
def test_geodesic_progress_pays_for_a_detour(detour_env):
    """Behind a wall, driving around it gains geodesic progress; the straight line would punish
    the first leg. Summed over the path the progress is the geodesic distance covered. Slow: its
    env (`detour_env`) compiles for two tests."""
    env, reset, step = detour_env
    state = start_in(env, reset, 2)
    geodesic = jax.jit(jaxnav.core.goals.geodesic)
    start_geo = float(geodesic(state.info["field"], state.info["goal"], state.data.qpos[:2]))
    assert start_geo > 5.0  # 1.9 m north, 3 m east, 1.9 m south (the straight line is 3 m)
    total = 0.0
    for _ in range(15):  # 0.75 m north, away from the goal in a straight line
        state = step(state, jnp.int32(0))
        total += float(state.reward) - env.task.time_reward
    assert total > 0.6  # the geodesic shrank by about the distance driven
    geo = float(geodesic(state.info["field"], state.info["goal"], state.data.qpos[:2]))
    np.testing.assert_allclose(total, start_geo - geo, atol=1e-4)


@pytest.mark.slow
def test_privileged_critic_sees_the_way_to_go(detour_env):
    """What only the critic sees (`state.info["critic"]`): the distance to go as the progress
    reward measures it, how much closer a 0.3 m step in each of 8 directions would bring the
    robot, and the share of the time limit used. Behind a wall a step along it towards its open
    end brings the robot closer, where the straight line to the goal says it would not; in the
    open the best step is along the straight line. Slow: its env (`detour_env`) compiles for two
    tests."""
    from jaxnav.tasks.goal import CRITIC_FEATURES, LOOK

    env, reset, step = detour_env
    assert env.task.critic_observations == CRITIC_FEATURES == 10
    state = start_in(env, reset, 0)
    geodesic = jax.jit(jaxnav.core.goals.geodesic)
    goal, field = state.info["goal"], state.info["field"]
    for n in range(4):
        xy, yaw = np.asarray(state.data.qpos[:2]), float(state.data.qpos[2])
        critic = np.asarray(state.info["critic"])
        here = float(geodesic(field, goal, xy))
        np.testing.assert_allclose(critic[0] * 5.0, here, rtol=1e-6)
        angles = yaw + np.arange(8) * np.pi / 4
        probes = xy + LOOK * np.stack([np.cos(angles), np.sin(angles)], -1)
        around = np.array([float(geodesic(field, goal, p, here + LOOK)) for p in probes])
        want = np.clip((here - around) / LOOK, -2.0, 2.0)
        np.testing.assert_allclose(critic[1:9], want, atol=1e-5)
        np.testing.assert_allclose(critic[9], n / 200)
        state = step(state, jnp.int32(0))  # north, towards the wall's open end
    ahead, behind = critic[1], critic[5]  # north, south
    assert ahead > 0.5 and behind < -0.5  # round the wall's north end, not back south
    assert critic[1:9].argmax() == 7  # north-east: towards the opening's corner
    assert here > 5.0 > np.linalg.norm(np.asarray(goal) - xy) + 1.5  # the detour, not the line
    wall = start_in(env, reset, 1)  # 0.07 m from the partition, facing it
    critic = np.asarray(wall.info["critic"])
    np.testing.assert_allclose(critic[1], -1.0, atol=1e-5)  # a step into the wall: no closer
    assert np.abs(critic[1:9]).max() <= 2.0 and critic[1:9].argmax() in (1, 2, 3)  # north-ish
    open_env = jaxnav.make_env("goal", layouts=[OPEN], randomize=EXACT, progress="straight")
    state = jax.jit(open_env.reset)(jax.random.PRNGKey(0))
    xy, goal = np.asarray(state.data.qpos[:2]), np.asarray(state.info["goal"])
    critic = np.asarray(state.info["critic"])
    np.testing.assert_allclose(critic[0] * 5.0, np.linalg.norm(goal - xy), rtol=1e-6)
    bearing = np.arctan2(*(goal - xy)[::-1]) - float(state.data.qpos[2])
    best = int(np.round(bearing / (np.pi / 4))) % 8  # the probe nearest the goal's bearing
    assert critic[1 + best] > 0.9 * np.cos(bearing - best * np.pi / 4)


# A 5 x 5 m room whose centre is walled in (a ring of boxes 1.2 m across): a goal 1.5 m away lies
# outside, so a spawn inside must move out. In a 2.6 x 2.6 m room no cell 1.5 m from the centre
# keeps its clearance, so the L-shaped path to a goal is cleared through the ring instead.
RING = RoomLayout(
    name="ring",
    size=(5.0, 5.0),
    obstacles=tuple(
        Box(pos=pos, size=size)
        for pos, size in [((0, 0.6), (1.4, 0.2)), ((0, -0.6), (1.4, 0.2))]
        + [((0.6, 0), (0.2, 1.4)), ((-0.6, 0), (0.2, 1.4))]
    ),
)
SMALL_RING = dataclasses.replace(RING, name="small_ring", size=(2.6, 2.6))


@pytest.mark.slow
def test_one_flood_draws_the_goal_and_its_field(monkeypatch):
    """A reset floods the grid once, from the goal: the field reaches the spawn, which moves out
    of a pocket the goal is not in; where no cell is far enough the path is cleared first. The
    goals, rooms and fields are bit for bit those of the signed distance over the whole grid at
    once (`goals.grid_clearance` computes it in blocks of rows), and the field is `goal_field`'s,
    whichever rooms share the batch. Slow: the goal's draw compiled four times (batches of 4, 3
    and 2 x 2, and one robot) for this check."""
    rooms = [OPEN, RING, SMALL_RING, POCKET]
    spawns = [(-1.5, -1.5), (0.0, 0.0), (0.0, 0.0), (-2.0, 1.0)]
    bank = make_bank(rooms, 8, 4)
    cells = goals.make_goal_cells(rooms)
    params = bank.rooms.replace(
        spawn=jnp.array([(*xy, 0.0) for xy in spawns]),
        layout_id=jnp.array([-1, -1, -1, 3]),  # the rings and open as sampled rooms
        # nothing moves, on paths of no points (leaves with no elements, as in rooms with walkers)
        motion=jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (4, *x.shape)), still(12)),
    )

    def draw(key, params):
        extent = (goals.GRID_HALF, goals.GRID_HALF)
        room, goal, field = goals.sample_goal(key, params, extent, cells, R, 0.3, 1.5, 0.15)
        return room, goal, field, goals.goal_field(room, extent, goal, R)

    keys = jax.random.split(jax.random.PRNGKey(0), len(rooms))
    shared = jax.jit(jax.vmap(draw))(keys, params)
    # A batch computes the cleared room's grid only where one of its rooms needs it: the same
    # draws in a batch without the small ring, and one room at a time.
    at = lambda tree, e: jax.tree_util.tree_map(lambda x: x[e], tree)  # noqa: E731
    others = np.array([0, 1, 3])
    chex.assert_trees_all_equal(
        jax.jit(jax.vmap(draw))(keys[others], at(params, others)), at(shared, others)
    )
    for e in range(len(rooms)):
        chex.assert_trees_all_equal(jax.jit(draw)(keys[e], at(params, e)), at(shared, e))
    pairs = lambda tree: jax.tree_util.tree_map(lambda x: x.reshape(2, 2, *x.shape[1:]), tree)  # noqa: E731
    nested = jax.jit(jax.vmap(jax.vmap(draw)))(pairs(keys), pairs(params))  # as AutoReset.draw
    chex.assert_trees_all_equal(nested, pairs(shared))

    def whole(params, extent, radius):  # the whole grid in one computation
        gap = signed_distance(params, goals._grid(extent)) - radius
        return gap, gap >= 0.5 * GRID_CELL

    monkeypatch.setattr(goals, "_free", whole)
    chex.assert_trees_all_equal(shared, jax.jit(jax.vmap(draw))(keys, params))
    room, goal, field, again = (np.asarray(x) if not hasattr(x, "spawn") else x for x in shared)
    np.testing.assert_array_equal(field, again)
    cleared = np.asarray(room.box_active).sum(-1) < np.asarray(params.box_active).sum(-1)
    np.testing.assert_array_equal(cleared, [False, False, True, False])
    spawn = np.asarray(room.spawn[:, :2])
    moved = np.linalg.norm(spawn - np.asarray(spawns), axis=-1) > 0
    np.testing.assert_array_equal(moved, [False, True, False, False])
    assert np.abs(spawn[1]).max() > 0.7  # out of the ring
    for e in range(len(rooms)):  # the flood from the goal reaches the spawn
        assert float(goals.geodesic(field[e], goal[e], spawn[e])) < 20.0
        col, row = np.asarray(goals._grid_cell(field.shape[1:], spawn[e], None))
        assert np.isfinite(field[e, row, col])
    assert np.linalg.norm(goal[:2] - spawn[:2], axis=-1).min() >= 1.5


@pytest.mark.slow
def test_banked_fields_step_as_selected_ones():
    """The goal task's geodesic field banked over a window of drawn-ahead steps
    (`AutoReset.bank`: the steps move each robot's row, not its field) gives the steps that
    select the fields along: every reward, observation and critic input, and after `unbank`
    the fields themselves, bit for bit, in rooms of every family with the presets' memory. Slow:
    the goal task's draws and two windows of its steps compile."""
    env = jaxnav.make_env("goal", randomize=TRAINING, memory_bins=16, max_steps=5)
    assert env.banked_info == ("field",)
    auto = AutoReset(EpisodeStats(env), 4)
    n, steps = 16, 12

    def run(state, fresh, banked: bool):
        banks = {}
        if banked:
            state, fresh, banks = auto.bank(state, fresh)
        actions = jax.random.randint(jax.random.PRNGKey(1), (steps, n), 0, 3)
        step = lambda s, xs: (auto.step(s, xs[0], xs[1], banks),) * 2  # noqa: E731
        state, states = jax.lax.scan(step, state, (actions, fresh))
        return auto.unbank(state, banks), (states.reward, states.obs, states.info["critic"])

    keys = jax.random.split(jax.random.PRNGKey(6), n)
    drawn = jax.jit(lambda keys: auto.draw(auto.reset(keys), steps))(keys)
    run = jax.jit(run, static_argnums=2)
    (selected, seen), (banked, banked_seen) = run(*drawn, False), run(*drawn, True)
    assert np.asarray(selected.info[EPISODE]["length"]).max() > 0  # episodes ended and restarted
    chex.assert_trees_all_equal((selected, seen), (banked, banked_seen))


def test_goal_runs_train_in_the_room_families_the_cpu_preset_weighted_to_the_hard_ones():
    """The goal task's training distribution is `TRAINING` with its sampled rooms drawn from the
    room families and the 'random' rooms alike, on the cpu preset from the families only,
    corridors and clutter most often, and on the gpu preset with long halls too (both with a
    collision margin); in runs and in `make_env` without layouts, under the user's settings;
    `avoid` keeps `TRAINING` as it is."""
    from jaxnav.tasks.presets import GOAL_CPU_FAMILIES, GOAL_GPU_FAMILIES
    from jaxnav.tasks.registry import training_randomize
    from jaxnav.training import build_config

    cpu, gpu = (build_config(p, env="goal").randomize for p in ("cpu", "gpu"))
    assert (cpu.families, gpu.families) == (GOAL_CPU_FAMILIES, GOAL_GPU_FAMILIES)
    assert family_weights(gpu.families)["long_hall"] == pytest.approx(0.1)
    # Both presets train with a 7.5 cm collision margin.
    assert cpu.collision_margin == gpu.collision_margin == (0.075, 0.075)
    cpu, gpu = (dataclasses.replace(r, collision_margin=(0.0, 0.0)) for r in (cpu, gpu))
    for r in (cpu, gpu):
        assert dataclasses.replace(r, families="") == TRAINING  # only the families differ
    w = family_weights(cpu.families)
    assert "random" not in w and abs(sum(w.values()) - 1) < 1e-9
    assert w["corridor"] > w["clutter"] > w["pillars"] > w["joined"] > w["open"] == w["ltu"]
    assert set(w) == set(family_weights("all")) - {"random"}
    for name in ("cpu", "gpu", "paper"):
        assert build_config(name, env="avoid").randomize == TRAINING
    told = build_config(env="goal", overrides={"randomize": {"families": "random"}}).randomize
    assert told.families == "random"
    everywhere = dataclasses.replace(gpu, families="all")
    assert jaxnav.make_env("goal").randomize == training_randomize("goal") == everywhere
    assert jaxnav.make_env("avoid").randomize == TRAINING
    room = RoomLayout(name="r", size=(4.0, 4.0), robot_pos=(0.0, 0.0), robot_yaw=0.0)
    assert jaxnav.make_env("goal", layouts=[room]).randomize == RandomizeConfig()


def test_goal_runs_draw_fewer_new_episodes_ahead_unless_told():
    """The goal task's own PPO defaults (1/64 of the robots draw a new episode per step; each
    rollout's drawn at its start, as every task's) go over every preset, its cpu defaults (512
    robots, 2 epochs) over the cpu preset's and its gpu defaults (256 x 256 networks, a memory)
    over the gpu preset's, all under the user's settings; other tasks keep the preset's."""
    from jaxnav.training import build_config

    for name in ("cpu", "gpu", "paper"):
        goal, avoid = build_config(name, env="goal").ppo, build_config(name, env="avoid").ppo
        assert (goal.reset_share, goal.reset_ahead) == (1 / 64, True)
        assert (avoid.reset_share, avoid.reset_ahead) == (1 / 16, True)
        robots = {"cpu": 512, "gpu": 8192, "paper": 1}[name]
        assert (goal.num_envs, avoid.num_envs) == (robots, 256 if name == "cpu" else robots)
    cpu = build_config("cpu", env="goal", overrides={"ppo": {"num_envs": 128}}).ppo
    # The preset's 4 minibatches of the smaller batch (128 x 32 steps).
    assert (cpu.num_envs, cpu.minibatch_size, cpu.num_epochs) == (128, 1024, 2)
    assert cpu.total_steps == 16_000_000 and build_config("cpu").ppo.num_epochs == 4
    for name in ("cpu", "gpu", "paper"):  # the goal task's critic sees its own inputs too
        assert build_config(name, env="goal").ppo.privileged_critic
        assert not build_config(name, env="avoid").ppo.privileged_critic
    widths = {name: build_config(name, env="goal").ppo.hidden for name in ("cpu", "gpu")}
    assert widths == {"cpu": (64, 64), "gpu": (256, 256)}
    memory = {name: build_config(name, env="goal").task.memory_bins for name in ("cpu", "gpu")}
    assert memory == {"cpu": 16, "gpu": 16}  # both presets' policies have a memory
    span = {name: build_config(name, env="goal").task.memory_steps for name in ("cpu", "gpu")}
    assert span == {"cpu": 20, "gpu": 40}  # of 2 s and 4 s
    assert build_config("gpu", env="avoid").ppo.hidden == (64, 64)
    narrow = build_config("gpu", env="goal", overrides={"ppo": {"hidden": (32,)}})
    assert narrow.ppo.hidden == (32,)
    told = build_config(
        "gpu", env="goal", overrides={"ppo": {"reset_share": 0.25, "reset_ahead": False}}
    )
    assert (told.ppo.reset_share, told.ppo.reset_ahead) == (0.25, False)
