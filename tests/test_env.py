"""The `avoid` environment: shapes, sensing, collisions, Table I rewards, spawns, no recompilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, probe_layouts, start_in, traced_once

import jaxnav
from jaxnav.core.episode import sample
from jaxnav.core.randomize import RandomizeConfig, clearance
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.core.sensors import SensorConfig


def test_api_sizes(mixed_env):
    assert mixed_env.observation_size == 8 and mixed_env.action_spec.n == 3


def test_unknown_env_lists_valid_names():
    with pytest.raises(ValueError, match="valid names: avoid, goal"):
        jaxnav.make_env("fly")


@pytest.mark.slow
def test_batch_of_mixed_layouts_shapes_and_finite(wrapped_mixed):
    """Random actions (collisions and time limits) in a mixed batch. Slow: it compiles the
    wrapped mixed env's reset and step (15 s); the quick tier checks the same shapes and ranges on
    that program in `test_contract.py::test_wrappers_publish_finished_episode_sums`."""
    _, reset, step = wrapped_mixed
    batch = 16
    state = reset(jax.random.split(jax.random.PRNGKey(0), batch))
    ids = set(np.asarray(state.info["params"].layout_id).tolist())
    assert {-1, 0, 1} <= ids, ids  # sampled rooms and both layouts in one batch
    assert state.obs.shape == (batch, 8) and state.obs.dtype == jnp.float32
    key = jax.random.PRNGKey(1)
    for _ in range(25):  # crosses the 20-step time limit: exercises auto-reset
        key, k = jax.random.split(key)
        state = step(state, jax.random.randint(k, (batch,), 0, 3))
        assert (
            np.isfinite(np.asarray(state.obs)).all() and np.isfinite(np.asarray(state.reward)).all()
        )
        lo, hi = SensorConfig().range_min, SensorConfig().range_max
        assert (np.asarray(state.obs) >= lo - 1e-6).all() and (np.asarray(state.obs) <= hi).all()
    assert state.reward.shape == (batch,) and state.done.shape == (batch,)


@pytest.mark.parametrize("layout_id, surface_x", [(0, 1.8), (1, 1.3)])
def test_obstacle_ahead_read_at_its_distance(probe_env, layout_id, surface_x):
    env, reset, _ = probe_env
    state = start_in(env, reset, layout_id)
    expected = surface_x - TURTLEBOT2I.camera_forward
    centre = np.asarray(state.obs)[3:5]  # the two sectors around the optical axis
    np.testing.assert_allclose(centre, expected, atol=0.03)
    # The side sectors look past the obstacle to the walls: farther.
    assert np.asarray(state.obs)[[0, 7]].min() > expected + 0.2


@pytest.mark.parametrize("layout_id, surface_x", [(0, 1.8), (1, 1.3), (2, 1.5)])
def test_driving_forward_into_obstacle_ends_with_minus_100(probe_env, layout_id, surface_x):
    env, reset, step = probe_env
    state = start_in(env, reset, layout_id)
    speed = env.task.forward_speed
    for t in range(100):  # noqa: B007 (t is the step it collided at)
        state = step(state, jnp.int32(0))
        if bool(state.done):
            break
    assert bool(state.metrics["collision"]) and float(state.reward) == -100.0
    # It stops where the bumper meets the surface, within one control period of travel.
    travel = surface_x - TURTLEBOT2I.radius
    assert abs((t + 1) - travel / (speed * 0.1)) <= 2.5, t
    assert float(state.data.qpos[0]) == pytest.approx(travel, abs=0.06)


def test_table_one_rewards(probe_env):
    env, reset, step = probe_env
    cfg = env.task
    state = start_in(env, reset, 2)  # empty 3 m room: 1.5 m to every wall
    for action, far, near in [(0, 0.6, 0.4), (1, 0.4, 0.6), (2, 0.4, 0.6)]:
        closest = float(np.min(state.obs))
        nxt = step(state, jnp.int32(action))
        expected = (near if closest < cfg.near_threshold else far) - 0.2 / closest
        assert float(nxt.reward) == pytest.approx(expected, rel=1e-5)
        assert not bool(nxt.done)
    # Far case for sure: the wall ahead is 1.38 m from the camera > 1.0 m threshold.
    first = step(state, jnp.int32(0))
    assert float(np.min(state.obs)) > cfg.near_threshold
    assert float(first.reward) == pytest.approx(0.6 - 0.2 / float(np.min(state.obs)), rel=1e-5)
    # Drive until near: forward reward becomes 0.4 - 0.2 / min(s).
    while float(np.min(state.obs)) >= cfg.near_threshold:
        state = step(state, jnp.int32(0))
    closest = float(np.min(state.obs))
    assert float(step(state, jnp.int32(0)).reward) == pytest.approx(0.4 - 0.2 / closest, rel=1e-5)
    assert float(step(state, jnp.int32(1)).reward) == pytest.approx(0.6 - 0.2 / closest, rel=1e-5)


@pytest.mark.slow
def test_history_stacks_frames_and_table_one_reads_the_newest(probe_env):
    """With `history`, avoid's observation is the newest frame, then the earlier ones, as the
    robot side's `FrameStack` stacks them; each step is the paper's step (the probe env's, on
    the same state with the newest frame only): the same reward, frame and motion. Slow: the
    env compiles a program of its own."""
    from jaxnav.robot_side.policy import FrameStack

    _, _, paper_step = probe_env
    env = jaxnav.make_env("avoid", layouts=probe_layouts(), randomize=EXACT, history=2)
    assert env.observation_size == 3 * 8
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = start_in(env, reset, 2)  # the empty 3 m room, facing a wall 1.5 m away
    stack = FrameStack(2)
    np.testing.assert_array_equal(stack(state.obs[:8]), state.obs)  # the first frame, tiled
    for action in (0, 0, 1, 0, 2, 0, 0):
        nxt = step(state, jnp.int32(action))
        want = paper_step(state.replace(obs=state.obs[:8]), jnp.int32(action))
        assert float(nxt.reward) == float(want.reward)
        np.testing.assert_array_equal(nxt.obs[:8], want.obs)
        np.testing.assert_array_equal(nxt.data.qpos, want.data.qpos)
        np.testing.assert_array_equal(stack(nxt.obs[:8]), nxt.obs)  # newest frame first
        state = nxt
    assert not np.array_equal(state.obs[:8], state.obs[16:])  # the frames differ as it drove
    with pytest.raises(ValueError, match="AvoidConfig.history: must be >= 0"):
        jaxnav.make_env("avoid", history=-1)


def test_spawn_never_overlaps(mixed_env):
    cfg = RandomizeConfig(sampled_room_prob=0.5, random_spawn_prob=1.0)
    params = jax.jit(jax.vmap(lambda k: sample(k, cfg, mixed_env.bank, TURTLEBOT2I.radius)))(
        jax.random.split(jax.random.PRNGKey(3), 4000)
    )
    gap = jax.jit(jax.vmap(clearance))(params, params.spawn[:, :2]) - TURTLEBOT2I.radius
    assert float(gap.min()) > 0.0
    # Nearly all spawns also keep the configured clearance (crowded layouts may fall back).
    assert float(jnp.mean(gap >= cfg.spawn_clearance - 1e-4)) > 0.99
    assert (np.asarray(params.layout_id) == -1).any() and (np.asarray(params.layout_id) >= 0).any()


def test_layout_change_does_not_recompile(mixed_env):
    reset, step = traced_once(mixed_env)

    rooms = set()
    for seed in range(12):
        state = reset(jax.random.PRNGKey(seed))
        rooms.add(int(state.info["params"].layout_id))
        for _ in range(2):
            state = step(state, jnp.int32(seed % 3))
    assert len(rooms) >= 2  # different rooms went through the same compiled functions


@pytest.mark.slow
def test_batched_model_matches_per_env_model(mixed_env):
    """The batched MJX model puts each env's geoms where that env's own model does. Slow: MJX's
    kinematics compiles for both models."""
    from mujoco import mjx

    scene = mixed_env.scene
    params = jax.jit(jax.vmap(mixed_env.reset))(jax.random.split(jax.random.PRNGKey(5), 4)).info[
        "params"
    ]

    @jax.jit
    def batched(params):  # [4, G, 3] geom positions of the batched model, and its kinematics'
        model, in_axes = scene.batched_model(params)
        data = jax.vmap(lambda p: mjx.make_data(scene.model).replace(qpos=p.spawn))(params)
        return model.geom_pos, jax.vmap(mjx.kinematics, in_axes=(in_axes, 0))(model, data)

    @jax.jit
    def single(p):  # one env's own model, kinematics at its spawn
        return mjx.kinematics(scene.model_for(p), mjx.make_data(scene.model).replace(qpos=p.spawn))

    geom_pos, out = batched(params)
    assert geom_pos.shape == (4, scene.model.ngeom, 3)
    alone = single(jax.tree_util.tree_map(lambda x: x[2], params))
    np.testing.assert_allclose(out.geom_xpos[2], alone.geom_xpos, atol=1e-6)
