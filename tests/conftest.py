"""Shared fixtures: environments and a tiny training run are made once per session and reused."""

import atexit
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile


def _session_compilation_cache() -> None:
    """One persistent XLA compilation cache for the session, removed at its end; the subprocesses
    (CLI runs, notebook kernels, the workers of `-n`) inherit it through the environment, so the
    tiny runs of several tests that compile the same programs compile them once. It caches compiled code only: every
    test still traces and runs its program. Set before jax is imported, which reads the variable
    then (the same name on jax 0.10 and 0.11); a cache folder given by the caller is kept."""
    if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
        folder = tempfile.mkdtemp(prefix="jaxnav-xla-cache-")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    # Every program, however quickly it compiled: at -O0 most of the suite's programs compile in
    # under JAX's default second, and many are compiled again by other tests, workers and
    # subprocesses.
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")


def _loop_emitters() -> bool:
    """Whether this jaxlib's XLA still has its older CPU loop emitters (jaxlib 0.11 has not)."""
    import importlib.metadata

    major, minor = (int(part) for part in importlib.metadata.version("jaxlib").split(".")[:2])
    return (major, minor) < (0, 11)


# Quicker XLA compiles for the whole session, its subprocesses included: the suite's time is
# mostly compiling small programs (every env a test builds compiles its own), and these flags
# trade run time for compile time (the suite's times with them: docs/development.md).
# Where XLA has them, its older CPU loop emitters (`FUSION_EMITTERS` off) compile quicker code that
# runs slower (docs/development.md). Set before jax is imported; a caller's own XLA_FLAGS (even
# empty) are kept as they are.
FUSION_EMITTERS = "xla_cpu_use_fusion_emitters"
LOOP_EMITTERS = _loop_emitters()
FAST_XLA = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true" + (
    f" --{FUSION_EMITTERS}=false" if LOOP_EMITTERS else ""
)
# A test whose claim is about the bits XLA's own CPU code computes (two programs bit for bit alike,
# a bound found on these trajectories) compiles its programs with these options.
XLA_CPU_CODE = {FUSION_EMITTERS: True} if LOOP_EMITTERS else {}


_session_compilation_cache()
os.environ.setdefault("XLA_FLAGS", FAST_XLA)


def pytest_xdist_auto_num_workers(config) -> int:
    """Workers for `-n auto` (pyproject's addopts): one per core this process may use, at most 4.
    A test file runs whole on one worker (`--dist loadfile`), so its module fixtures are made
    once; each worker compiles the session fixtures it uses, XLA's part of it shared through the
    session's compilation cache, so a fifth worker would mostly add memory."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(cores or 1, 4))


import chex  # noqa: E402
import jax  # noqa: E402
import pytest  # noqa: E402

import jaxnav  # noqa: E402
from jaxnav.core.randomize import TRAINING, RandomizeConfig  # noqa: E402
from jaxnav.core.scene import SCENES_DIR  # noqa: E402
from jaxnav.core.sensors import SensorConfig  # noqa: E402
from jaxnav.io.layouts import Box, Cylinder, RoomLayout  # noqa: E402
from jaxnav.viz import render  # noqa: E402
from jaxnav.wrappers import AutoReset, EpisodeStats  # noqa: E402


@pytest.fixture
def optimised(monkeypatch):
    """jaxnav's programs compiled at jaxnav's own LLVM level (`jaxnav.core.xla`) rather than the
    session's -O0, for a test that trains long enough for its run time to outweigh the longer
    compile (on 2 cores the goal task's learning test takes a third of the time): the session's
    XLA_FLAGS without their level, so that `compiler_options` sets jaxnav's on each program it
    compiles from now on (the backend keeps the flags it started with), with XLA's own CPU fusion
    emitters, which the session turns off (FAST_XLA), back on for them."""
    from jaxnav import evaluation, programs
    from jaxnav.core import xla
    from jaxnav.ppo import train

    flags = os.environ.get("XLA_FLAGS", "").split()
    monkeypatch.setenv("XLA_FLAGS", " ".join(f for f in flags if xla.OPTION not in f))

    def options(backend=None, program=None):  # jaxnav's, and on the CPU XLA's own code
        own = xla.compiler_options(backend, program)
        return {**own, **XLA_CPU_CODE} if (backend or jax.default_backend()) == "cpu" else own

    for module in (train, programs, evaluation):
        monkeypatch.setattr(module, "compiler_options", options)


@pytest.fixture(autouse=True)
def _program_store_off():
    """Every test starts with the program store off (`jaxnav.programs`): a command run in this
    process turns it on, and a later test's monkeypatches would not reach programs it stored."""
    from jaxnav import programs

    programs.use(None)
    yield
    programs.use(None)


# Deterministic physics and sensing: no randomisation of gain, traction or noise.
EXACT = RandomizeConfig(
    sampled_room_prob=0.0,
    random_spawn_prob=0.0,
    friction=(1.0, 1.0),
    speed_gain=(1.0, 1.0),
    sensor_noise=(0.0, 0.0),
    sensor_dropout=(0.0, 0.0),
    sensor_noise_quadratic=(0.0, 0.0),
    dark_prob=0.0,
    camera_height_error=0.0,
    camera_pitch_error=0.0,
    camera_yaw_error=0.0,
    latency_steps=(0, 0),
    wheel_asymmetry=(0.0, 0.0),
    accel_limit=(0.0, 0.0),  # no velocity smoother: commanded speeds within one step
    angular_accel_limit=(0.0, 0.0),
)
# The Kobuki's nominal command pipeline: smoother limits 0.3 m/s^2 and 3.5 rad/s^2, no latency.
KOBUKI = dataclasses.replace(EXACT, accel_limit=(0.3, 0.3), angular_accel_limit=(3.5, 3.5))


def corridor(obstacle, size=(8.0, 3.0)) -> RoomLayout:
    """A room with the robot at the origin facing +x and one obstacle ahead of it."""
    return RoomLayout(
        name="probe", size=size, robot_pos=(0.0, 0.0), robot_yaw=0.0, obstacles=(obstacle,)
    )


def probe_layouts() -> list[RoomLayout]:
    """The probe rooms: a box and a cylinder ahead in a corridor, and an empty 3 m room."""
    return [
        corridor(Box(pos=(2.0, 0.0), size=(0.4, 0.8))),  # face at x = 1.8
        corridor(Cylinder(pos=(1.5, 0.0), radius=0.2)),  # surface at x = 1.3
        RoomLayout(name="wall", size=(3.0, 3.0), robot_pos=(0.0, 0.0), robot_yaw=0.0),
    ]


@pytest.fixture(scope="session")
def probe_env():
    """An env whose layout bank holds the probe rooms used by the sensor and collision tests."""
    env = jaxnav.make_env("avoid", layouts=probe_layouts(), randomize=EXACT)
    return env, jax.jit(env.reset), jax.jit(env.step)


# A room 20 m long (rays straight ahead read beyond range_max) whose obstacles on the left and
# right differ, so a mirrored sector order would show.
LOPSIDED = RoomLayout(
    name="lopsided",
    size=(20.0, 4.0),
    robot_pos=(0.0, 0.0),
    robot_yaw=0.0,
    obstacles=(
        Box(pos=(2.0, 0.7), size=(0.4, 0.6)),
        Box(pos=(3.0, -0.9), size=(0.5, 0.5), yaw=0.5),
        Cylinder(pos=(1.2, -0.35), radius=0.1),
    ),
)
LOW_BOX_HEIGHTS = (0.05, 0.12, 0.25)


def low_box(height) -> Box:
    """A box `height` m tall whose face is 0.85 m ahead of the robot's centre in `corridor`."""
    return Box(pos=(1.0, 0.0), size=(0.3, 1.2), height=height)


# The rooms of `one_row_env`'s bank, in order: LOPSIDED, then a corridor per low box height.
ONE_ROW_ROOMS = [LOPSIDED, *(corridor(low_box(h)) for h in LOW_BOX_HEIGHTS)]


@pytest.fixture(scope="session")
def one_row_env():
    """`avoid` with one row of rays (a horizontal fan: what a LaserScan reads) in ONE_ROW_ROOMS,
    exact physics and sensing: (env, jitted reset, jitted step)."""
    env = jaxnav.make_env(
        "avoid", layouts=ONE_ROW_ROOMS, randomize=EXACT, sensor=SensorConfig(rows=1)
    )
    return env, jax.jit(env.reset), jax.jit(env.step)


@pytest.fixture(scope="session")
def mixed_env():
    """`avoid` in the training and inference rooms and sampled rooms, 20-step episodes."""
    layouts = jaxnav.load_layout(SCENES_DIR / "train_room.json") + jaxnav.load_layout(
        SCENES_DIR / "inference_room.json"
    )
    return jaxnav.make_env("avoid", layouts=layouts, randomize=TRAINING, max_steps=20)


@pytest.fixture(scope="session")
def wrapped_mixed(mixed_env):
    """`mixed_env` under AutoReset(EpisodeStats(...)): (env, jitted reset, jitted step), compiled
    once for the tests that step a batch of it (keep their batch at 16 to share the program)."""
    env = AutoReset(EpisodeStats(mixed_env))
    return env, jax.jit(env.reset), jax.jit(env.step)


@pytest.fixture(scope="session")
def needs_gl():
    """Skips, saying what to install, where MuJoCo's renderer has no OpenGL backend."""
    tried = os.environ.get("MUJOCO_GL") or "/".join(render.GL_BACKENDS)
    if render.gl_backend() is None:
        pytest.skip(
            f"no OpenGL backend for MuJoCo's renderer (tried MUJOCO_GL={tried}; "
            "install libegl1 and libgl1-mesa-dri, or libosmesa6)"
        )


def traced_once(env):
    """(jitted reset, jitted step) of `env`, each failing if traced more than once."""

    @jax.jit
    @chex.assert_max_traces(n=1)
    def reset(key):
        return env.reset(key)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(state, action):
        return env.step(state, action)

    return reset, step


def start_in(env, reset, layout_id):
    """Resets until the bank's layout `layout_id` is drawn (layouts are drawn uniformly)."""
    for seed in range(200):
        state = reset(jax.random.PRNGKey(seed))
        if int(state.info["params"].layout_id) == layout_id:
            return state
    raise AssertionError(f"layout {layout_id} never drawn")


def cpu_env(devices: int) -> dict:
    """The environment of a subprocess of `devices` CPU devices that compiles with FAST_XLA (both
    sides of a comparison get the same flags)."""
    return dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        XLA_FLAGS=f"--xla_force_host_platform_device_count={devices} {FAST_XLA}",
    )


def benchmark_script(name: str):
    """The module of `benchmarks/NAME.py`, loaded as when it runs (its folder's `report` importable);
    the test is skipped in a checkout without benchmarks/."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parent.parent / "benchmarks" / f"{name}.py"
    if not script.exists():
        pytest.skip("benchmarks/ is not in this checkout")
    spec = importlib.util.spec_from_file_location(name, script)
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(script.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(script.parent))
    return module


def run_cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "jaxnav.train", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


# 6 updates in chunks of 2, a checkpoint after each chunk.
TINY_FLAGS = [
    *("--num-envs", "16", "--rollout-length", "16", "--minibatch-size", "128"),
    *("--num-epochs", "2", "--total-steps", str(16 * 16 * 6), "--updates-per-chunk", "2"),
    *("--checkpoint-every", "2", "--task.near-threshold", "0.8", "--seed", "3", "--no-progress"),
]


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A tiny training run made once through the CLI: (run folder, completed process)."""
    out = tmp_path_factory.mktemp("run") / "tiny"
    proc = run_cli("--out", str(out), *TINY_FLAGS)
    assert proc.returncode == 0, proc.stderr
    return out, proc
