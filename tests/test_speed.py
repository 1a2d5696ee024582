"""The speed levers against the full MJX path: each shortcut must leave episodes as they were."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import XLA_CPU_CODE
from mujoco import mjx
from toy_envs import Countdown, Ledger

import jaxnav
from jaxnav.core.randomize import TRAINING
from jaxnav.core.scene import SceneConfig
from jaxnav.wrappers import RESET_KEY, AutoReset, EpisodeStats

ROBOTS, STEPS = 32, 60


def forward_biased(key, shape):
    """Actions that drive forward 4 times in 5, so most robots reach an obstacle: [shape] int32."""
    u = jax.random.uniform(key, shape)
    return jnp.where(u < 0.8, 0, jnp.where(u < 0.9, 1, 2)).astype(jnp.int32)


def rollout(env):
    """Jitted (state [R], actions [T, R]) -> per step (qpos, qvel, obs, reward, done), bare env,
    compiled to XLA's own CPU code (the bit-identical episodes are a claim about it)."""

    @functools.partial(jax.jit, compiler_options=XLA_CPU_CODE)
    def run(state, actions):
        def body(s, a):
            n = jax.vmap(env.step)(s, a)
            return n, (n.data.qpos, n.data.qvel, n.obs, n.reward, n.done)

        return jax.lax.scan(body, state, actions)[1]

    return run


@pytest.fixture(scope="module")
def full_and_fast():
    """Trajectories of the training distribution (sim-to-real ranges on, rooms sampled and from
    layouts) with MJX's contact pass (the full path) and without (the default), from the same
    episodes (one reset compiled: the fast env places the robots in its own physics state)."""
    full = jaxnav.make_env("avoid", randomize=TRAINING, scene=SceneConfig(fast_contacts=True))
    fast = jaxnav.make_env("avoid", randomize=TRAINING)
    start = jax.jit(jax.vmap(full.reset))(jax.random.split(jax.random.PRNGKey(7), ROBOTS))
    placed = start.replace(data=jax.jit(jax.vmap(fast.place))(start.info["params"]))
    actions = forward_biased(jax.random.PRNGKey(8), (STEPS, ROBOTS))
    runs = rollout(full)(start, actions), rollout(fast)(placed, actions)
    return [[np.asarray(x) for x in r] for r in runs]


def test_fast_physics_skips_mjx_contacts():
    """By default the fast physics has no MJX contacts or constraint rows; the full path and the
    wheeled physics keep them."""
    no_contact = mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    build = jaxnav.core.scene.build_mj_model
    assert build(SceneConfig()).opt.disableflags & no_contact == no_contact
    for cfg in (SceneConfig(fast_contacts=True), SceneConfig(physics="wheeled")):
        assert not build(cfg).opt.disableflags & no_contact


def test_fast_physics_steps_the_robot_alone():
    """Without MJX contacts the physics steps the robot's bodies, joints and motors alone (no
    geoms, sites or camera), with the room model's masses and inertias: MuJoCo steps both models
    the same, bit for bit (the bit-identical episodes below check it under MJX)."""
    cfg = SceneConfig()
    room, alone = jaxnav.core.scene.build_mj_model(cfg), jaxnav.core.scene.build_robot_model(cfg)
    assert (alone.ngeom, alone.nsite, alone.ncam) == (0, 0, 0) and room.ngeom > 20
    bodies = slice(alone.nbody)  # the room model's bodies are the robot's
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat"):
        np.testing.assert_array_equal(getattr(alone, field), getattr(room, field)[bodies], field)
    for field in ("dof_armature", "dof_damping", "actuator_gear"):
        np.testing.assert_array_equal(getattr(alone, field), getattr(room, field), field)
    assert (alone.opt.timestep, alone.opt.disableflags) == (
        room.opt.timestep,
        room.opt.disableflags,
    )
    runs = []
    for m in (room, alone):
        d = mujoco.MjData(m)
        d.qpos[:3] = 0.5, -1.0, 0.3
        poses = []
        for t in range(30):
            d.ctrl[:] = 2.0 * np.sin(t), 1.5 * np.cos(t), 0.05 * np.sin(3 * t)
            mujoco.mj_step(m, d)
            poses.append(np.concatenate([d.qpos, d.qvel]))
        runs.append(np.array(poses))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.abs(runs[0][-1, :3] - [0.5, -1.0, 0.3]).max() > 0.1  # it moved
    # ... and that is what the env steps, unless MJX's contacts are on (the room model then).
    assert jaxnav.make_env("avoid").scene.physics_model(None).ngeom == 0
    contacts = jaxnav.make_env("avoid", scene=SceneConfig(fast_contacts=True)).scene
    assert contacts.data_model.ngeom == room.ngeom


@pytest.mark.slow
def test_sparse_mass_matrix_on_a_gpu_steps_as_the_dense_one():
    """On a GPU the fast physics factors its mass matrix sparsely (no batched Cholesky call), on
    the CPU densely, as MJX chooses; under MJX a robot driven for 200 steps ends in the same
    place either way, to float32 rounding. The wheeled model keeps its MJCF's own choice. Slow:
    about 7 s on 2 cores, two MJX models compiled and driven."""
    cfg, sparse_bit = SceneConfig(), mujoco.mjtJacobian.mjJAC_SPARSE
    on_gpu = jax.default_backend() == "gpu"
    for build in (jaxnav.core.scene.build_robot_model, jaxnav.core.scene.build_mj_model):
        assert (build(cfg).opt.jacobian == sparse_bit) == on_gpu
    wheeled = jaxnav.core.scene.build_mj_model(SceneConfig(physics="wheeled"))
    assert wheeled.opt.jacobian != sparse_bit
    sparse, dense = (jaxnav.core.scene.build_robot_model(cfg) for _ in range(2))
    sparse.opt.jacobian, dense.opt.jacobian = sparse_bit, mujoco.mjtJacobian.mjJAC_DENSE
    ctrl = jnp.stack([2.0 * jnp.sin(jnp.arange(200.0)), 1.5 * jnp.cos(jnp.arange(200.0))], -1)
    ctrl = jnp.concatenate([ctrl, 0.05 * jnp.sin(3 * jnp.arange(200.0))[:, None]], -1)  # [T, 3]

    @jax.jit
    def drive(model):
        step = lambda d, u: (mjx.step(model, d.replace(ctrl=u)), None)  # noqa: E731
        d = mjx.make_data(model).replace(qpos=jnp.array([0.5, -1.0, 0.3]))
        d, _ = jax.lax.scan(step, d, ctrl)
        return jnp.concatenate([d.qpos, d.qvel])

    ends = [np.asarray(drive(mjx.put_model(m))) for m in (sparse, dense)]
    assert np.abs(ends[0][:3] - [0.5, -1.0, 0.3]).max() > 0.1  # it moved
    np.testing.assert_allclose(ends[0], ends[1], atol=1e-5)


def test_robot_alone_from_a_robots_own_mjcf(tmp_path):
    """A robot's MJCF with sensors on its sites still builds its robot-alone model (the sensors
    go with the sites); one whose motors act through a site cannot, and says so in one line
    naming the file and the flag that steps the whole model; a malformed one is named too."""
    import dataclasses

    from jaxnav.core.robot import TURTLEBOT2I
    from jaxnav.core.scene import Scene, robot_mjcf

    xml = robot_mjcf(TURTLEBOT2I).read_text()
    sensed = tmp_path / "sensed.xml"
    sensor = '<sensor><framepos objtype="site" objname="camera"/></sensor></mujoco>'
    sensed.write_text(xml.replace("</mujoco>", sensor))
    scene = Scene(SceneConfig(), dataclasses.replace(TURTLEBOT2I, mjcf=str(sensed)))
    assert scene.data_model.ngeom == 0 and scene.data_model.nsensor == 0
    pushed = tmp_path / "pushed.xml"
    site_motor = '<motor name="push" site="camera" gear="1 0 0 0 0 0"/></actuator>'
    pushed.write_text(xml.replace("</actuator>", site_motor))
    with pytest.raises(ValueError, match=r"RobotSpec.mjcf: .*pushed.xml: .*--scene.fast-contacts"):
        Scene(SceneConfig(), dataclasses.replace(TURTLEBOT2I, mjcf=str(pushed)))
    broken = tmp_path / "broken.xml"  # and a file MuJoCo cannot read at all
    broken.write_text(xml.replace('<geom name="shell"', '<geom name="shell" colour="red"'))
    with pytest.raises(ValueError, match=r"^RobotSpec.mjcf: .*broken.xml: XML Error: [^\n]*$"):
        Scene(SceneConfig(), dataclasses.replace(TURTLEBOT2I, mjcf=str(broken)))


def test_robot_alone_keeps_every_bodys_inertia():
    """A robot of several bodies (the wheeled model: base, two wheels) keeps each body's mass
    and inertia, in the compiled order, when its geoms go."""
    cfg = SceneConfig(physics="wheeled")
    room, alone = jaxnav.core.scene.build_mj_model(cfg), jaxnav.core.scene.build_robot_model(cfg)
    assert alone.nbody == 4 and alone.ngeom == 0
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_parentid"):
        np.testing.assert_array_equal(getattr(alone, field), getattr(room, field)[:4], field)


@pytest.mark.slow  # two env steps and a reset to compile: about 80 s on a 2-core CPU
def test_episodes_without_mjx_contacts_are_bit_identical(full_and_fast):
    """Every step of every episode up to its end, the colliding step included, is the same bit
    for bit: pose, velocity, observation, reward and termination. Slow: the full MJX path
    (contacts, the constraint solver) compiles beside the fast one."""
    full, fast = full_and_fast
    done = full[-1]  # [T, R]
    live = np.cumsum(done, 0) - done == 0  # [T, R]: the step starts in the first episode
    assert done.any(0).sum() >= ROBOTS // 3  # many robots reach an obstacle
    assert (full[3][done & live] == -100).mean() > 0.9  # ... and collide there
    for name, a, b in zip(("qpos", "qvel", "obs", "reward", "done"), full, fast, strict=True):
        np.testing.assert_array_equal(a[live], b[live], err_msg=name)
    # After the collision the full path's contacts push back, the fast path goes on: the two
    # really are different physics.
    after = ~live & done.any(0)
    assert not np.array_equal(full[0][after], fast[0][after])


def test_in_place_auto_reset_is_the_select():
    """`AutoReset(in_place=True)` gives every leaf of the state of the select, bit for bit, in
    steps that end fewer episodes than the pool holds (the rows written) and more (the select)."""
    n, pool = 64, 6
    envs = [AutoReset(EpisodeStats(Countdown()), pool, in_place=flag) for flag in (False, True)]

    @jax.jit
    def run(keys):
        out = []
        for env in envs:
            state = env.reset(keys)
            states = jax.lax.scan(
                lambda s, a, env=env: (env.step(s, a),) * 2, state, jnp.ones((30, n))
            )[1]
            out.append(states)
        return out

    select, in_place = run(jax.random.split(jax.random.PRNGKey(0), n))
    ended = np.asarray(select.done).sum(1)  # [T]
    assert (ended > pool).any() and ((ended > 0) & (ended <= pool)).any()
    for a, b in zip(
        jax.tree_util.tree_leaves(select), jax.tree_util.tree_leaves(in_place), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def run_steps(env, keys, steps=30):
    """States [steps, N] of `env` (an AutoReset) after each of `steps` steps, drawing per step."""
    state = env.reset(keys)
    actions = jnp.ones((steps, keys.shape[0]))
    return jax.lax.scan(lambda s, a: (env.step(s, a),) * 2, state, actions)[1]


def run_ahead(env, keys, windows=3, steps=10):
    """(states [windows x steps, N], the new episodes each step was given [windows x steps, G,
    P/G]) of `env` (an AutoReset) drawing every window's new episodes at its start."""
    ones = jnp.ones(keys.shape[0])

    def window(state, _):
        state, fresh = env.draw(state, steps)
        state, states = jax.lax.scan(lambda s, f: (env.step(s, ones, f),) * 2, state, fresh)
        return state, (states, fresh)

    _, out = jax.lax.scan(window, env.reset(keys), None, windows)
    return jax.tree_util.tree_map(lambda x: x.reshape(windows * steps, *x.shape[2:]), out)


@pytest.mark.parametrize("in_place", [False, True])
def test_drawn_ahead_episodes_start_where_envs_finish(in_place):
    """With the new episodes drawn ahead, the k-th env of a block to finish in step t starts
    draw k mod P of step t's draws (data, observation and info as drawn); every step's draws are
    new ones (no draw is used in two steps)."""
    n, pool, groups = 64, 6, 2
    env = AutoReset(EpisodeStats(Countdown()), pool, in_place, groups=groups)
    states, fresh = jax.jit(run_ahead, static_argnums=0)(
        env, jax.random.split(jax.random.PRNGKey(2), n)
    )
    done = np.asarray(states.done).reshape(30, groups, n // groups)  # [T, G, N/G]
    obs = np.asarray(states.obs).reshape(30, groups, n // groups, 2)
    left = np.asarray(states.info["left"]).reshape(30, groups, n // groups)
    drawn_obs, drawn_left = np.asarray(fresh.obs), np.asarray(fresh.info["left"])  # [T, G, P/G]
    assert (done.sum(2) > pool // groups).any()  # steps that reuse draws within the step
    for t, g in np.ndindex(30, groups):
        slot = (np.cumsum(done[t, g]) - 1)[done[t, g]] % (pool // groups)
        np.testing.assert_array_equal(obs[t, g][done[t, g]], drawn_obs[t, g][slot])
        np.testing.assert_array_equal(left[t, g][done[t, g]], drawn_left[t, g][slot])
    assert len(np.unique(drawn_obs.reshape(-1, 2), axis=0)) == drawn_obs.size // 2


@pytest.mark.parametrize("groups", [1, 2])
def test_each_drawn_episode_is_the_reset_of_its_own_key(groups):
    """`draw(state, steps)`'s episode [t, g, p] is the env's reset of block g's p-th pool key
    folded with t: one vmap over a block's keys puts every episode where its key is."""
    n, pool, steps = 64, 6, 4
    env = AutoReset(EpisodeStats(Countdown()), pool, groups=groups)
    state = env.reset(jax.random.split(jax.random.PRNGKey(3), n))
    after, fresh = env.draw(state, steps)
    reset = EpisodeStats(Countdown()).reset
    pairs = jax.vmap(jax.random.split)(state.info[RESET_KEY])  # [N, 2, 2]
    np.testing.assert_array_equal(after.info[RESET_KEY], pairs[:, 0])
    first = env._pool_keys(pairs[:, 1])  # [G, P/G, 2]
    for t, g, p in np.ndindex(steps, groups, pool // groups):
        want = reset(jax.random.fold_in(first[g, p], t))
        for a, b in zip(*(jax.tree_util.tree_leaves(x) for x in (fresh, want)), strict=True):
            np.testing.assert_array_equal(np.asarray(a)[t, g, p], np.asarray(b))
    assert jax.tree_util.tree_leaves(fresh)[0].shape[:3] == (steps, groups, pool // groups)


@pytest.mark.parametrize("task", ["avoid", "goal"])
@pytest.mark.slow
def test_drawn_episodes_observed_apart_are_the_resets(task, mixed_env, monkeypatch):
    """A task's reset in two parts (`begin`, then `first_observation`, as AutoReset's draws make
    them: the observations in OBSERVED_APART batches after the rooms) is its reset: every drawn
    episode is its key's, its rooms, poses, goals and keys bit for bit, its first observation
    (and the goal task's memory of it) within float rounding. The goal task with its memory, as
    the presets have it. Slow: the draws and steps compile twice, about 9 s for `avoid` on 2
    cores, and the goal task's env's reset and draws more."""
    env = mixed_env
    if task == "goal":
        env = jaxnav.make_env("goal", randomize=TRAINING, memory_bins=16, max_steps=20)
    n, pool, steps = 16, 4, 3  # 12 episodes drawn: two batches of 6
    auto, stats = AutoReset(EpisodeStats(env), pool), EpisodeStats(env)
    state = jax.jit(auto.reset)(jax.random.split(jax.random.PRNGKey(4), n))
    apart = []  # the draws' traces of first_observation: its batch is a vmap inside a loop
    observe = env.first_observation
    monkeypatch.setattr(env, "first_observation", lambda *a: apart.append(1) or observe(*a))
    after, fresh = jax.jit(auto.draw, static_argnums=1)(state, steps)
    monkeypatch.undo()
    assert apart
    pairs = jax.vmap(jax.random.split)(state.info[RESET_KEY])  # [N, 2, 2]
    first = auto._pool_keys(pairs[:, 1])[0]  # [P, 2]
    keys = jax.vmap(lambda t: jax.vmap(lambda k: jax.random.fold_in(k, t))(first))(
        jnp.arange(steps)
    )
    want = jax.jit(jax.vmap(stats.reset))(keys.reshape(-1, 2))  # [T * P]
    got = jax.tree_util.tree_map(lambda x: x.reshape(steps * pool, *x.shape[3:]), fresh)
    leaves = [jax.tree_util.tree_flatten_with_path(x)[0] for x in (got, want)]
    for (path, a), (_, b) in zip(*leaves, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-5, err_msg=str(path))
        else:
            np.testing.assert_array_equal(a, b, err_msg=str(path))
    assert np.abs(np.asarray(got.obs)).max() > 0.1  # observed, not left as zeros


@pytest.mark.parametrize("in_place", [False, True])
@pytest.mark.parametrize("ahead", [False, True])
def test_grouped_auto_reset_is_each_block_on_its_own(in_place, ahead):
    """`AutoReset(groups=2)` over 64 envs with a pool of 6 is, bit for bit, two auto-resets of
    pool 3 each over its own 32 envs, drawing per step or ahead: a block draws from its own envs'
    keys only (what lets every device reset its own robots)."""
    n, pool = 64, 6
    grouped = AutoReset(EpisodeStats(Countdown()), pool, in_place, groups=2)
    alone = AutoReset(EpisodeStats(Countdown()), pool // 2, in_place)
    run = (lambda env, keys: run_ahead(env, keys)[0]) if ahead else run_steps

    keys = jax.random.split(jax.random.PRNGKey(1), n)
    both = jax.jit(run, static_argnums=0)(grouped, keys)
    halves = [jax.jit(run, static_argnums=0)(alone, k) for k in (keys[: n // 2], keys[n // 2 :])]
    ended = np.asarray(both.done).reshape(30, 2, n // 2).sum(2)  # [T, block]
    assert (ended > pool // 2).any() and ((ended > 0) & (ended <= pool // 2)).any()
    for a, *parts in zip(*(jax.tree_util.tree_leaves(t) for t in (both, *halves)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.concatenate(parts, axis=1))


def run_banked(env, keys, banked: bool, windows=3, steps=10):
    """(states [windows x steps, N] with every banked array as the env's own, the state after
    the last window) of `env` (an AutoReset of a Ledger) drawing every window's new episodes at
    its start, its steps given the banks or selecting the arrays along."""
    ones = jnp.ones(keys.shape[0])

    def window_of_steps(state, _):
        state, fresh = env.draw(state, steps)
        banks = {}
        if banked:
            state, fresh, banks = env.bank(state, fresh)
            assert state.info["table"].dtype == jnp.int32  # rows of the bank are what steps carry
        step = lambda s, f: (env.step(s, ones, f, banks),) * 2  # noqa: E731
        state, states = jax.lax.scan(step, state, fresh)
        if banked:
            states = jax.vmap(lambda s: env.unbank(s, banks))(states)
        return env.unbank(state, banks), states

    last, states = jax.lax.scan(window_of_steps, env.reset(keys), None, windows)
    return jax.tree_util.tree_map(lambda x: x.reshape(windows * steps, *x.shape[2:]), states), last


@pytest.mark.parametrize(
    ("in_place", "groups"),
    [
        (False, 1),
        pytest.param(True, 1, marks=pytest.mark.slow),
        pytest.param(False, 2, marks=pytest.mark.slow),
    ],
)
def test_banked_arrays_step_as_selected_ones(in_place, groups):
    """Steps given `AutoReset.bank`'s banks, which move only each env's row of them, give every
    state of the steps that select the arrays along with the rest, bit for bit: the arrays each
    step reads (its reward), and after `unbank` the arrays themselves, in steps that end more
    episodes than the pool holds and fewer; with two blocks, each reading a bank of its own. Slow
    but for the first: 5-7 s each on 2 cores, both windows compiled."""
    n, pool = 64, 20  # 8-37 episodes end in a step
    env = AutoReset(EpisodeStats(Ledger()), pool, in_place, groups=groups)
    keys = jax.random.split(jax.random.PRNGKey(5), n)
    run = jax.jit(run_banked, static_argnums=(0, 2))
    (selected, last), (banked, banked_last) = run(env, keys, False), run(env, keys, True)
    ended = np.asarray(selected.done).sum(1)  # [T]
    assert (ended > pool).any() and ((ended > 0) & (ended <= pool)).any()
    for a, b in zip(*(jax.tree_util.tree_leaves(x) for x in (selected, banked)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(*(jax.tree_util.tree_leaves(x) for x in (last, banked_last)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    state = env.reset(keys)
    bank = env.bank(state, env.draw(state, 2)[1])[2]["table"]
    assert bank.shape == (groups, n // groups + 2 * pool // groups, 8)


@pytest.mark.parametrize(
    "scene",
    [{}, {"physics": "wheeled"}],
    ids=["fast", "wheeled"],
)
@pytest.mark.slow
def test_the_carried_body_steps_as_the_whole_mjx_data(scene):
    """An env carries `Body` (MuJoCo's integration state and the solver's warm start) from one
    control step to the next, not the whole mjx.Data, and its reset places the robot without
    MuJoCo's kinematics (`NavTask.place`): driven for 30 steps among obstacles, the robot's poses
    and velocities are bit for bit those of mjx.Data carried whole from a posed start (every
    derived field from the step before; the wheeled model's contacts and solver included); on a
    GPU, which fuses the two programs' sums in orders of their own, within 1e-4 relative. Slow:
    two MJX programs compile, 12 s on 2 cores for the fast model, 25 s for the wheeled one, whose
    contacts and solver compile twice. Both programs scan its 20 physics steps a control step
    (unrolled, they took 128 s)."""
    from jaxnav.core.types import Body

    env = jaxnav.make_env("avoid", scene=SceneConfig(**scene))
    params = jax.jit(env.reset)(jax.random.PRNGKey(4)).info["params"]
    control = env._wheel_speeds if env.scene.wheeled else env._base_forces
    model = env.scene.physics_model(params)
    t = jnp.arange(30.0)
    commands = jnp.stack([0.3 + 0.2 * jnp.sin(t), 1.2 * jnp.cos(0.7 * t)], -1)  # [T, 2]

    def whole(d, command):
        def substep(d, _):
            return mjx.step(model, d.replace(ctrl=control(params, d, command))), None

        d = jax.lax.scan(substep, d, None, env.scene.substeps)[0]  # the wheeled model's 20
        return d, jnp.concatenate([d.qpos, d.qvel])

    def carried(body, command):
        body, _ = env.drive(params, body, command)
        return body, jnp.concatenate([body.qpos, body.qvel])

    start = env.place(params)
    assert isinstance(start, Body)
    jit = functools.partial(jax.jit, compiler_options=XLA_CPU_CODE)
    with jax.default_matmul_precision("highest"):  # float32 on a GPU too, as `drive` runs
        got = jit(lambda: jax.lax.scan(carried, start, commands)[1])()
        posed = lambda: mjx.kinematics(model, start.into(env._data0))  # noqa: E731  derived poses
        want = jit(lambda: jax.lax.scan(whole, posed(), commands)[1])()
    assert np.abs(np.asarray(got[-1, :2] - got[0, :2])).max() > 0.3  # it drove
    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    else:  # a GPU fuses the two programs' sums in orders of their own
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-4, atol=1e-5)
