"""The env contract: a second task needs no change elsewhere, given rooms are simulated exactly,
collision detection agrees with MuJoCo's own, and the wrappers keep episode statistics."""

import csv
import dataclasses
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from stand_still import StandStillConfig, StandStillEnv

import jaxnav
from jaxnav.core import geometry
from jaxnav.core.episode import sample
from jaxnav.core.geometry import ray_cast, signed_distance
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.core.scene import OBSTACLE_GROUP, SCENES_DIR, SceneConfig
from jaxnav.export import export
from jaxnav.policy import forward_policy
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.tasks import registry
from jaxnav.wrappers import EPISODE


@pytest.fixture
def stand_still():
    registry.register("stand_still", StandStillEnv, StandStillConfig)
    yield "stand_still"
    registry.TASKS.pop("stand_still")


@pytest.mark.slow
def test_a_second_task_trains_logs_evaluates_and_exports(stand_still, tmp_path):
    """A task defined outside the package goes through train, evaluate and export. Slow: a
    training run, an evaluation and an export, each compiled for this task alone."""
    tiny = dict(num_envs=16, rollout_length=16, minibatch_size=128, num_epochs=4)
    # 16 updates of 16 steps: the 50-step episodes end in at least 4 of them.
    ckpt = jaxnav.train(
        out=tmp_path / "run", env=stand_still, total_steps=16 * 16 * 16, updates_per_chunk=4,
        learning_rate=3e-3, progress=False, **tiny,
    )  # fmt: skip
    with open(tmp_path / "run" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert "drift" in rows[0] and "collision" in rows[0]
    drift = [float(r["drift"]) for r in rows if r["drift"] not in ("", "nan")]
    assert len(drift) >= 4 and drift[-1] < drift[0]  # it learns to move less
    policy = jaxnav.load_policy(tmp_path / "run")
    assert policy.env == stand_still
    rooms = jaxnav.load_layout(SCENES_DIR / "inference_room.json")
    trained = jaxnav.evaluate(policy, rooms, episodes=8, steps=30)
    spec = StandStillConfig().action_spec
    creeping = jaxnav.evaluate(
        dataclasses.replace(forward_policy(spec), env=stand_still), rooms, episodes=8, steps=30
    )
    assert trained["overall"]["drift"] < creeping["overall"]["drift"]
    file = export(ckpt, "numpy", tmp_path / "policy.npz")
    exported = NumpyPolicy.from_npz(file)
    assert exported.action_names == spec.names
    np.testing.assert_allclose(exported.commands, spec.table())


def test_unknown_task_names_the_valid_ones():
    with pytest.raises(ValueError, match="valid names: avoid"):
        jaxnav.train(env="nope", progress=False)


def test_given_layouts_are_simulated_exactly():
    rooms = jaxnav.load_layout(SCENES_DIR / "train_room.json")
    rooms += jaxnav.load_layout(SCENES_DIR / "inference_room.json")
    env = jaxnav.make_env("avoid", layouts=rooms)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 200))
    ids = np.asarray(states.info["params"].layout_id)
    assert set(ids.tolist()) == {0, 1}  # both rooms, never a sampled one
    spawns = np.array([[*r.robot_pos, r.robot_yaw] for r in rooms], np.float32)
    np.testing.assert_allclose(np.asarray(states.data.qpos), spawns[ids], atol=1e-6)


def test_default_env_is_the_training_mixture():
    env = jaxnav.make_env("avoid")
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 200))
    params = states.info["params"]
    assert 0.65 < np.mean(np.asarray(params.layout_id) == -1) < 0.85  # 3 in 4 sampled rooms
    assert np.asarray(params.latency).max() > 0  # the sim-to-real ranges are on
    assert np.asarray(params.accel).min() > 0


def _mujoco_touching(env, fields, qpos) -> bool:
    """MuJoCo's own collision (CPU, not MJX) of the bumper at `qpos` in the room whose geom fields
    (`scene.geom_fields`, as numpy) are `fields`."""
    m = env.scene.mj_model
    m.geom_pos[:], m.geom_quat[:], m.geom_size[:] = (
        fields["geom_pos"], fields["geom_quat"], fields["geom_size"],
    )  # fmt: skip
    # The compiled model knows the parked slots: unrotated (so MuJoCo reuses the world frame)
    # and small (its collision bounds). Make it recompute frames and bounds for this room.
    m.geom_sameframe[:] = 0
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_MIDPHASE
    box, cap, size = m.geom_type == 6, m.geom_type == 3, m.geom_size  # mjGEOM_BOX, _CAPSULE
    m.geom_rbound[box] = np.linalg.norm(size[box], axis=1)
    m.geom_aabb[box, 3:] = size[box]
    m.geom_rbound[cap] = size[cap, 0] + size[cap, 1]
    m.geom_aabb[cap, 3:] = np.stack([size[cap, 0], size[cap, 0], size[cap].sum(1)], 1)
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    return bool((d.contact.dist[: d.ncon] < 0).any())


def test_analytic_collision_agrees_with_mujoco():
    # MuJoCo's contacts, which the fast physics skips by default (SceneConfig.fast_contacts).
    env = jaxnav.make_env("avoid", layouts=[], scene=SceneConfig(fast_contacts=True))
    cfg = RandomizeConfig(sampled_room_prob=1.0, num_boxes=(6, 8), num_cylinders=(3, 4))
    keys = jax.random.split(jax.random.PRNGKey(1), 12)
    rooms = jax.jit(jax.vmap(lambda k: sample(k, cfg, env.bank, env.robot.radius)))(keys)
    # Low obstacles too, some under the bumper's centre height, so the test is 3-D.
    heights = jax.random.uniform(jax.random.PRNGKey(2), (12, 12), minval=0.05, maxval=0.6)
    rooms = rooms.replace(box_height=heights[:, :8], cyl_height=heights[:, 8:])
    rng = np.random.default_rng(0)

    @jax.jit
    def ours(room, qpos):  # (touching, the bumper's gap) by the env's analytic test
        gap = signed_distance(room, qpos[:2], env.scene.bumper_z)
        return env.touching(room, SimpleNamespace(qpos=qpos)), gap

    fields = jax.device_get(jax.jit(jax.vmap(env.scene.geom_fields))(rooms))
    agree = checked = 0
    for i in range(12):
        room = jax.tree_util.tree_map(lambda x, i=i: x[i], rooms)
        half = np.asarray(room.room_half)
        for _ in range(40):
            qpos = np.array([*rng.uniform(-half, half), rng.uniform(-np.pi, np.pi)], np.float32)
            touching, gap = ours(room, jnp.asarray(qpos))
            if abs(float(gap) - env.scene.bumper_radius) < 1e-3:
                continue  # within float32 round-off of touching: either answer is right
            room_fields = {k: v[i] for k, v in fields.items()}
            agree += bool(touching) == _mujoco_touching(env, room_fields, qpos)
            checked += 1
    assert checked > 400 and agree == checked


def test_analytic_rays_agree_with_mjx_ray():
    """The sensor's analytic rays (geometry.ray_cast) against MJX's own mjx.ray on the scene's
    geoms, over random rooms with low obstacles and overhangs and rays in every direction."""
    env = jaxnav.make_env("avoid", layouts=[])
    cfg = RandomizeConfig(
        sampled_room_prob=1.0, num_boxes=(6, 8), num_cylinders=(3, 4), low_prob=0.3,
        overhang_prob=0.3,
    )  # fmt: skip
    keys = jax.random.split(jax.random.PRNGKey(5), 20)
    rooms = jax.jit(jax.vmap(lambda k: sample(k, cfg, env.bank, env.robot.radius)))(keys)
    groups = tuple(int(g == OBSTACLE_GROUP) for g in range(6))

    @jax.jit
    def both(room, origin, dirs):
        m = env.scene.model_for(room)
        d = mjx.kinematics(m, mjx.make_data(m).replace(qpos=room.spawn))
        cast = lambda v: mjx.ray(m, d, origin, v, geomgroup=groups)  # noqa: E731
        dist, geom = jax.vmap(cast)(dirs)
        ours, slot = ray_cast(room, origin, dirs)
        return dist, jnp.asarray(env.scene.slot_of_geom)[jnp.maximum(geom, 0)], ours, slot

    rng = np.random.default_rng(0)
    hits = 0
    for i in range(20):
        room = jax.tree_util.tree_map(lambda x, i=i: x[i], rooms)
        origin = jnp.append(room.spawn[:2], rng.uniform(0.1, 0.5))
        dirs = rng.normal(size=(256, 3)) * [1, 1, 0.3]
        dirs = jnp.asarray(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), jnp.float32)
        dist, slot_mjx, ours, slot = (np.asarray(x) for x in both(room, origin, dirs))
        # MJX parks an inactive slot's geom far below the floor, where a steep ray can reach it
        # (the sensor's rays end at the floor): such rays are left out.
        active = np.concatenate([np.asarray(room.box_active), np.asarray(room.cyl_active)])
        kept = (dist < 0) | (slot_mjx < 0) | active[np.maximum(slot_mjx, 0)]
        seen = (dist >= 0) & kept
        np.testing.assert_array_equal(np.isfinite(ours)[kept], seen[kept])
        np.testing.assert_allclose(ours[seen], dist[seen], atol=1e-4)
        np.testing.assert_array_equal(slot[seen], slot_mjx[seen])
        hits += int((slot[seen] >= 0).sum())
    assert hits > 500  # most rays above are not walls: the obstacles are really tested


@pytest.mark.parametrize("backend", ["cpu", "gpu"])
def test_a_rays_least_hit_is_argmins_on_either_backend(backend, monkeypatch):
    """`geometry.least`, in the form each backend traces (the value read back at the index on
    the CPU, a reduction of its own on a GPU): the least value and its first index, as
    `x.min(-1)` and `jnp.argmin`, misses (inf) and ties included."""
    monkeypatch.setattr(geometry.jax, "default_backend", lambda: backend)
    rng = np.random.default_rng(3)
    x = rng.choice([0.5, 1.0, 2.5, np.inf], size=(512, 13)).astype(np.float32)
    x[:64] = np.inf  # rays that meet nothing
    value, index = geometry.least(jnp.asarray(x))  # eager: each call takes its branch anew
    np.testing.assert_array_equal(value, x.min(-1))
    np.testing.assert_array_equal(index, np.argmin(x, -1))


def test_wrappers_publish_finished_episode_sums(wrapped_mixed):
    wrapped, reset, step = wrapped_mixed  # 20-step episodes; batch 16, as the fixture's other test
    assert wrapped.task.max_steps == 20
    state = reset(jax.random.split(jax.random.PRNGKey(0), 16))
    ids = set(np.asarray(state.info["params"].layout_id).tolist())
    assert {-1, 0, 1} <= ids, ids  # sampled rooms and both layouts in one batch
    assert state.obs.shape == (16, 8) and state.obs.dtype == jnp.float32
    lo, hi = wrapped.sensor.range_min, wrapped.sensor.range_max
    returns = np.zeros(16)
    for _ in range(20):
        state = step(state, jnp.full(16, 1, jnp.int32))  # turning in place never collides
        returns += np.asarray(state.reward)
        obs = np.asarray(state.obs)
        assert np.isfinite(obs).all() and np.isfinite(returns).all()
        assert ((obs >= lo - 1e-6) & (obs <= hi)).all()
    assert state.reward.shape == (16,) and state.done.shape == (16,)
    assert np.asarray(state.done).all() and np.asarray(state.truncated).all()
    np.testing.assert_allclose(np.asarray(state.info[EPISODE]["return"]), returns, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(state.info[EPISODE]["length"]), 20)
    assert (np.asarray(state.info["steps"]) == 0).all()  # a new episode has started
