"""brax interop: `jaxnav.make_brax_env` under brax's own training wrappers and trainer.

Slow, all of it: brax's wrappers and trainer compile programs of their own (brax is optional).
"""

import functools
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training

import jaxnav
from jaxnav.brax_env import to_command
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.core.sensors import SensorConfig
from jaxnav.io.layouts import Box, RoomLayout

pytestmark = pytest.mark.slow

# No robot pose: every episode draws its spawn (and speed gain), which shows a fresh draw.
ROOM = RoomLayout(name="brax", size=(4.0, 4.0), obstacles=(Box(pos=(1.0, 0.5), size=(0.4, 0.4)),))
RANDOM_SPAWN = RandomizeConfig(random_spawn_prob=1.0, speed_gain=(0.8, 1.2))
ROBOTS, STEPS, EPISODE = 3, 12, 5  # brax's time limit: an episode ends every 5 steps
TASK_STEPS = 3  # the task's own time limit, shorter: brax's must be the one that counts


def small_env(**task):
    """A one-room avoid task with a one-row camera (compiles fastest), as a brax env."""
    kwargs = dict(layouts=[ROOM], randomize=RANDOM_SPAWN, sensor=SensorConfig(rows=1))
    return jaxnav.make_brax_env("avoid", **kwargs, **task)


@pytest.fixture(scope="module")
def env():
    return small_env(max_steps=TASK_STEPS)


@pytest.fixture(scope="module")
def actions():
    """[STEPS, ROBOTS, 2] brax actions, some beyond [-1, 1]; forward at most 0.1 of the range,
    so no robot reaches an obstacle and only the time limit ends episodes."""
    rng = np.random.default_rng(0)
    forward = rng.uniform(-1.5, -0.8, (STEPS, ROBOTS))
    turn = rng.uniform(-2.0, 2.0, (STEPS, ROBOTS))
    return np.stack([forward, turn], -1).astype(np.float32)


@pytest.fixture(scope="module")
def rollout(env, actions):
    """(first state, states [STEPS] of ROBOTS robots) under brax's training wrappers, and its
    evaluation wrapper on top (which adds a metric of its own)."""
    wrapped = training.EvalWrapper(training.wrap(env, episode_length=EPISODE))

    @jax.jit
    def run(key):
        first = wrapped.reset(jax.random.split(key, ROBOTS))
        step = lambda s, a: (wrapped.step(s, a),) * 2  # noqa: E731
        return first, jax.lax.scan(step, first, jnp.asarray(actions))[1]

    return jax.device_get(run(jax.random.PRNGKey(0)))


def test_sizes_and_shapes(env, rollout):
    first, states = rollout
    assert (env.observation_size, env.action_size, env.backend) == (8, 2, "mjx")
    assert env.episode_length == TASK_STEPS
    assert first.obs.shape == (ROBOTS, 8) and states.obs.shape == (STEPS, ROBOTS, 8)
    for x in (states.reward, states.done, states.metrics["collision"]):
        assert x.shape == (STEPS, ROBOTS) and x.dtype == np.float32
    assert np.isfinite(states.obs).all() and np.isfinite(states.reward).all()
    np.testing.assert_array_equal(states.metrics["reward"], states.reward)  # the wrapper's
    # The observation is the physics state's own: both belong to the same episode.
    np.testing.assert_array_equal(states.obs, states.pipeline_state.obs)


def test_actions_map_linearly_onto_the_bounds(env, actions, rollout):
    spec = env.env.action_spec  # forward [0, 0.5] m/s, yaw [-1.5, 1.5] rad/s
    low, high = np.array(spec.low), np.array(spec.high)
    corners = np.array([[-1, -1], [1, 1], [0, 0], [3, -3]], np.float32)
    expected = [low, high, (low + high) / 2, [high[0], low[1]]]
    np.testing.assert_allclose(to_command(spec, corners), expected, rtol=1e-6)
    # Through brax's wrappers: the command queued for the motors, wherever no new episode began.
    _, states = rollout
    queued = states.pipeline_state.info["actuator"].queue[:, :, 0]  # [STEPS, ROBOTS, 2]
    mapped = low + (np.clip(actions, -1, 1) + 1) / 2 * (high - low)
    kept = states.done == 0  # where an episode ended, the state is the next one's: nothing queued
    assert kept.sum() >= STEPS * ROBOTS - 2 * ROBOTS
    np.testing.assert_allclose(queued[kept], mapped[kept], rtol=1e-5, atol=1e-6)


def test_every_episode_after_an_auto_reset_is_a_new_draw(rollout):
    first, states = rollout
    # brax's time limit ends the episodes (not the task's shorter one), as truncations.
    ends = np.zeros((STEPS, ROBOTS), np.float32)
    ends[EPISODE - 1 :: EPISODE] = 1
    np.testing.assert_array_equal(states.done, ends)
    np.testing.assert_array_equal(states.info["truncation"], ends)
    # Spawn and speed gain per step [STEPS + 1, ROBOTS, 4]: constant within an episode, new after.
    params = [first.pipeline_state.info["params"], states.pipeline_state.info["params"]]
    draws = np.concatenate(
        [
            np.concatenate(
                [p.spawn.reshape(-1, ROBOTS, 3), p.speed_gain.reshape(-1, ROBOTS, 1)], -1
            )
            for p in params
        ]
    )
    episode = np.r_[0, np.arange(STEPS) + 1] // EPISODE  # state t+1 follows step t
    for e in range(episode.max() + 1):
        block = draws[episode == e]
        np.testing.assert_array_equal(block, np.broadcast_to(block[0], block.shape))
    starts = draws[np.searchsorted(episode, np.arange(episode.max() + 1))]  # [episodes, ROBOTS, 4]
    for a in range(len(starts)):
        for b in range(a):
            assert (np.abs(starts[a] - starts[b]).max(-1) > 1e-3).all(), (a, b)
    assert (np.abs(starts[0, 0] - starts[0, 1:]).max(-1) > 1e-3).all()  # and per robot


def test_needs_continuous_actions():
    with pytest.raises(ValueError, match="continuous actions"):
        jaxnav.make_brax_env("avoid", layouts=[ROOM], actions="discrete")


def test_importing_jaxnav_does_not_import_brax():
    code = "import sys, jaxnav; jaxnav.make_env; print('brax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.slow
def test_brax_ppo_trains_on_it():
    """brax's own PPO trains on a jaxnav env. Slow: brax's trainer compiles its own programs."""
    from brax.training.agents.ppo import networks, train

    env = small_env(max_steps=50)
    tiny = functools.partial(
        networks.make_ppo_networks, policy_hidden_layer_sizes=(16,), value_hidden_layer_sizes=(16,)
    )
    make_policy, params, metrics = train.train(
        environment=env,
        num_timesteps=2048,
        episode_length=env.episode_length,
        num_envs=8,
        unroll_length=8,
        batch_size=8,
        num_minibatches=2,
        num_updates_per_batch=1,
        num_evals=2,
        run_evals=False,
        network_factory=tiny,
    )
    assert metrics["training/sps"] > 0
    for name in ("policy_loss", "v_loss", "entropy_loss", "total_loss"):
        assert np.isfinite(metrics[f"training/{name}"]), name
    assert all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(params))
    action, _ = make_policy(params, deterministic=True)(jnp.ones((4, 8)), jax.random.PRNGKey(0))
    assert action.shape == (4, 2) and (np.abs(action) <= 1).all()
