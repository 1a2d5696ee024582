"""PPO training: learning on a tiny budget, the CLI end to end, checkpoints and config errors."""

import csv
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from conftest import TINY_FLAGS, run_cli

import jaxnav
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.io import checkpoint
from jaxnav.ppo.config import PPOConfig, preset
from jaxnav.ppo.train import make_train

TINY = dict(num_envs=64, rollout_length=32, minibatch_size=512, num_epochs=4, updates_per_chunk=5)


@pytest.mark.slow
def test_tiny_training_improves_reward(optimised):
    """40 tiny updates raise the reward. Slow: a training run long enough to learn."""
    # Without the velocity smoother and latency a random policy collides often, so 40 tiny updates
    # show learning plainly (the sim-to-real default is learnt by the quick start, README Results).
    mixture = RandomizeConfig(sampled_room_prob=0.5, random_spawn_prob=0.5)
    env = jaxnav.make_env("avoid", max_steps=200, randomize=mixture)
    cfg = preset("cpu", **TINY, total_steps=64 * 32 * 40)
    _, metrics = make_train(cfg, env).train(jax.random.PRNGKey(0))
    reward = np.asarray(metrics["episode_reward"])
    collisions = np.asarray(metrics["collision"])
    assert np.isfinite(np.asarray(metrics["total"])).all()
    first, last = np.nanmean(reward[:8]), np.nanmean(reward[-8:])
    assert last > first + 50, (first, last)
    assert np.nanmean(collisions[-8:]) < 0.5 * np.nanmean(collisions[:8])


def test_config_refuses_impossible_combinations():
    with pytest.raises(
        ValueError, match="--minibatch-size 300 must divide --num-envs x --rollout-length"
    ):
        PPOConfig(num_envs=8, rollout_length=100, minibatch_size=300)
    with pytest.raises(ValueError, match="--preset: unknown preset 'fast'; valid: paper, cpu, gpu"):
        preset("fast")
    paper = preset("paper")
    assert (paper.num_updates, paper.rollout_length, paper.num_envs, paper.learning_rate) == (
        1500,
        100,
        1,
        1e-3,
    )
    assert (paper.num_epochs, paper.gamma, paper.gae_lambda, paper.clip_eps) == (
        10,
        0.99,
        0.95,
        0.2,
    )
    assert paper.critic_output == "tanh" and paper.hidden == (64, 64)


@pytest.mark.slow
def test_cli_writes_csv_png_checkpoints(tiny_run):
    """The CLI writes its metrics, curve and checkpoints. Slow: a training process (the tiny run)."""
    out, proc = tiny_run
    assert f"Results in {out}" in proc.stdout
    with open(out / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["update"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    assert {"episode_reward", "collision", "entropy", "steps_per_second"} <= set(rows[0])
    assert (out / "reward_curve.png").stat().st_size > 1000
    ckpts = checkpoint.list_checkpoints(out)
    assert [c.name for c in ckpts] == ["update_000002", "update_000004", "update_000006"]
    config = json.loads((out / "config.json").read_text())
    assert config["task"]["near_threshold"] == 0.8 and config["seed"] == 3


@pytest.mark.slow
def test_load_policy_acts(tiny_run):
    """A run folder loads as a policy that acts. Slow: it needs the tiny CLI run."""
    out, _ = tiny_run
    policy = jaxnav.load_policy(out)
    assert policy.env_kwargs["task"].near_threshold == 0.8
    obs = jax.random.uniform(jax.random.PRNGKey(0), (5, 8), minval=0.6, maxval=8.0)
    action = jax.jit(policy.act)(obs, jax.random.PRNGKey(1))
    assert action.shape == (5,) and set(np.asarray(action).tolist()) <= {0, 1, 2}


@pytest.mark.slow
def test_cli_refuses_existing_run_and_bad_flags(tiny_run, tmp_path):
    """Exit status 2 and one line for an existing run and a bad flag. Slow: two CLI processes,
    each importing jax, after the tiny run."""
    out, _ = tiny_run
    proc = run_cli("--out", str(out), "--num-envs", "16", "--minibatch-size", "128")
    assert proc.returncode == 2 and "already holds a training run" in proc.stderr
    proc = run_cli("--out", str(tmp_path / "x"), "--num-envs", "0")
    assert proc.returncode == 2 and proc.stderr.startswith("error: --num-envs")
    assert "Traceback" not in proc.stderr
    proc = run_cli("--out", str(tmp_path / "y"), "--layouts", str(tmp_path / "missing.json"))
    assert proc.returncode == 2 and "missing.json" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_evaluate_cli_on_checkpoint(tiny_run, tmp_path):
    """Slow: an evaluation process starts Python, loads the checkpoint and compiles the env and
    the trained policy's rollout (the fast tier evaluates in-process with built-in policies)."""
    out, _ = tiny_run
    report = tmp_path / "eval.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxnav.evaluate",
            "--checkpoint",
            str(out),
            "--episodes",
            "3",
            "--steps",
            "20",
            "--json",
            str(report),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(report.read_text())
    metrics = result["layouts"]["inference-room"]
    assert {"episodes", "collision_free_rate", "mean_speed", "mean_distance", "mean_steps"} <= set(
        metrics
    )  # today's keys stay; new ones are added
    assert {"coverage", "time_to_collision"} <= set(metrics)
    assert metrics["episodes"] == 3 and 0 <= metrics["collision_free_rate"] <= 1
    assert (tmp_path / "inference-room.png").exists()


def test_python_api_names():
    assert callable(jaxnav.train) and callable(jaxnav.evaluate)
    from jaxnav.policy import forward_policy

    layout = jaxnav.load_layout(jaxnav.core.scene.SCENES_DIR / "inference_room.json")
    result = jaxnav.evaluate(forward_policy(), layout, episodes=2, steps=5)
    assert result["overall"]["episodes"] == 2


def test_default_run_folder_never_collides(tmp_path):
    from jaxnav.cli.train import _new_run_dir

    assert _new_run_dir(tmp_path, "avoid-cpu") == tmp_path / "avoid-cpu"
    (tmp_path / "avoid-cpu").mkdir()
    (tmp_path / "avoid-cpu-2").mkdir()
    assert _new_run_dir(tmp_path, "avoid-cpu") == tmp_path / "avoid-cpu-3"


@pytest.mark.parametrize("env", ["avoid", "goal"])
def test_minibatch_follows_num_envs_unless_given(env):
    """A small run never fails on a minibatch size the user did not set: the preset's number of
    minibatches is kept; one the user set is theirs, and its error lists sizes that work."""
    from jaxnav.training import build_config

    base = build_config("cpu", env=env).ppo
    small = build_config("cpu", env=env, overrides={"ppo": {"num_envs": 32}}).ppo
    assert small.batch_size % small.minibatch_size == 0
    assert small.num_minibatches == base.num_minibatches
    odd = build_config("cpu", env=env, overrides={"ppo": {"num_envs": 3, "rollout_length": 7}})
    assert odd.ppo.batch_size % odd.ppo.minibatch_size == 0
    with pytest.raises(ValueError, match="values that do: 64, 128, 256, 512"):
        build_config("cpu", overrides={"ppo": {"num_envs": 32, "minibatch_size": 300}})


def _help(capsys, *argv) -> str:
    from jaxnav.cli.train import parse_args

    with pytest.raises(SystemExit) as done:
        parse_args(list(argv))
    assert done.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_help_shows_the_defaults_a_run_uses_grouped(capsys):
    main = _help(capsys, "--help")
    assert (
        "Robots simulated in parallel" not in main
        and "flag groups" in main
        and "randomize what is drawn" in main
    )
    goal = _help(capsys, "--env", "goal", "--help", "ppo")
    assert "Robots simulated in parallel. (default: 512)" in goal
    assert "sees the observation only. (default: True)" in goal and "--randomize." not in goal
    assert "instead of one of the layouts" in _help(capsys, "--help", "randomize")
    assert "(default: 0.75)" in _help(capsys, "--help", "randomize")
    assert "--robot.radius" in _help(capsys, "--help", "all")


def test_a_long_compile_says_it_goes_on(capsys):
    from jaxnav.process import Waiting, interruptible

    waiting = Waiting("compiling...")  # captured output is not a terminal: whole lines
    for seconds in (1, 29, 31, 45, 61, 130):
        waiting(seconds)
    waiting.end()
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        "compiling...",
        "compiling... still running after 31 s",
        "compiling... still running after 61 s",
        "compiling... still running after 130 s",
    ]
    seen = []
    assert interruptible(lambda: time.sleep(0.35) or 7, waiting=seen.append) == 7 and seen


def test_xla_log_lines_are_kept_out_of_a_command_unless_asked(monkeypatch):
    from jaxnav.process import quiet_xla_logs

    monkeypatch.delenv("TF_CPP_MIN_LOG_LEVEL", raising=False)
    monkeypatch.setenv("JAXNAV_XLA_LOGS", "1")
    quiet_xla_logs()
    assert "TF_CPP_MIN_LOG_LEVEL" not in os.environ
    monkeypatch.delenv("JAXNAV_XLA_LOGS")
    quiet_xla_logs()
    assert os.environ["TF_CPP_MIN_LOG_LEVEL"] == "3"
    monkeypatch.setenv("TF_CPP_MIN_LOG_LEVEL", "0")  # the user's own choice stays
    quiet_xla_logs()
    assert os.environ["TF_CPP_MIN_LOG_LEVEL"] == "0"


def test_commands_keep_compiled_programs_in_the_user_cache(tmp_path, monkeypatch):
    import jax

    from jaxnav import programs
    from jaxnav.process import compile_cache

    before = jax.config.jax_compilation_cache_dir
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    try:
        assert compile_cache() == tmp_path / "jaxnav" / "xla"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "jaxnav" / "xla")
        assert programs.folder() == tmp_path / "jaxnav" / "xla" / "programs"
        assert compile_cache(enabled=False) is None and not jax.config.jax_compilation_cache_dir
        assert programs.folder() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def stored_init(trainer, config, key):
    """The trainer's init from the program store (`programs.program`), or None."""
    from jaxnav import programs

    run = programs.run_of(config, None)
    return programs.program(trainer, run, "init", (jax.ShapeDtypeStruct(key.shape, key.dtype),))


def test_the_program_store_keeps_reads_back_and_traces_a_damaged_file_again(tmp_path, capsys):
    """`programs.program` exports the trainer's init into the store, reads it back without
    tracing, traces a damaged file again (saying so), and gives none when the store is off; the
    stored program computes what the function does."""
    from jaxnav import programs
    from jaxnav.ppo.train import Trainer
    from jaxnav.training import build_config

    traced = []

    def init(key):
        traced.append(key)
        return {"twice": key * 2, "sum": key.sum()}

    trainer = Trainer(None, jax.jit(init), None, None, {"init": init})
    config, key = build_config("cpu"), jax.random.PRNGKey(3)
    programs.use(tmp_path)
    kept = stored_init(trainer, config, key)
    assert isinstance(kept, programs.Stored) and len(traced) == 1
    got = kept(key)
    np.testing.assert_array_equal(got["twice"], key * 2)
    assert int(got["sum"]) == int(key.sum())
    (path,) = tmp_path.iterdir()
    read = stored_init(trainer, config, key)
    assert len(traced) == 1 and read(key)["twice"].tolist() == (key * 2).tolist()
    path.write_bytes(b"damaged")
    assert isinstance(stored_init(trainer, config, key), programs.Stored)
    assert len(traced) == 2 and f"{path}: not readable" in capsys.readouterr().err
    programs.use(None)
    assert stored_init(trainer, config, key) is None


def test_the_program_store_keeps_within_its_size_removing_the_least_used_first(
    tmp_path, monkeypatch
):
    """Past `MAX_BYTES` the programs used longest ago are removed, never the one just kept; a
    program read back counts as used."""
    import os

    from jaxnav import programs
    from jaxnav.ppo.train import Trainer
    from jaxnav.training import build_config

    def init(key):
        return key * 2

    trainer = Trainer(None, jax.jit(init), None, None, {"init": init})
    key = jax.random.PRNGKey(0)
    configs = [
        build_config("cpu", seed=0, overrides={"ppo": {"total_steps": n * 8192}}) for n in (1, 2, 3)
    ]
    programs.use(tmp_path)
    paths = []
    for age, config in enumerate(configs[:2]):  # two programs, the first used longest ago
        stored_init(trainer, config, key)
        (new,) = set(tmp_path.iterdir()) - set(paths)
        os.utime(new, (1000.0 + age, 1000.0 + age))
        paths.append(new)
    size = paths[0].stat().st_size
    monkeypatch.setattr(programs, "MAX_BYTES", 2 * size + size // 2)  # room for two
    stored_init(trainer, configs[0], key)  # read back: now the newest
    assert paths[0].stat().st_mtime > 1001.0
    stored_init(trainer, configs[2], key)  # a third: the least used goes
    assert paths[0].exists() and not paths[1].exists() and len(list(tmp_path.iterdir())) == 2
    monkeypatch.setattr(programs, "MAX_BYTES", 1)  # below one program: the one just kept stays
    stored_init(trainer, configs[1], key)
    assert len(list(tmp_path.iterdir())) == 1
    programs.use(None)


def test_the_program_store_keys_on_what_the_trace_depends_on(tmp_path):
    """The key of a run's stored programs is the same for equal configs and for configs that
    differ in their seed only (init's argument), and changes with the config (the step budget
    is part of the chunk), the MuJoCo model the env built (what an MJCF or a file it includes
    holds) and a JAX option, so a stored program is never one traced for something else."""
    import dataclasses

    import mujoco

    from jaxnav.programs import run_key
    from jaxnav.training import build_config

    config = build_config("cpu")
    assert run_key(config) == run_key(build_config("cpu")) == run_key(build_config("cpu", 7))
    budget = dataclasses.replace(config.ppo, total_steps=2 * config.ppo.total_steps)
    assert run_key(dataclasses.replace(config, ppo=budget)) != run_key(config)
    mjcf = tmp_path / "robot.xml"
    mjcf.write_text("<mujoco><worldbody><geom size='0.1'/></worldbody></mujoco>")
    built = run_key(config, mujoco.MjModel.from_xml_path(str(mjcf)))
    assert built == run_key(config, mujoco.MjModel.from_xml_path(str(mjcf))) != run_key(config)
    mjcf.write_text("<mujoco><worldbody><geom size='0.2'/></worldbody></mujoco>")
    assert run_key(config, mujoco.MjModel.from_xml_path(str(mjcf))) != built
    plain, promotion = run_key(config), jax.config.jax_numpy_rank_promotion
    jax.config.update("jax_numpy_rank_promotion", "warn" if promotion != "warn" else "raise")
    try:
        assert run_key(config) != plain
    finally:
        jax.config.update("jax_numpy_rank_promotion", promotion)


@pytest.mark.slow
def test_a_repeated_run_compiles_nothing_anew(tmp_path):
    """Two processes (the cache is what outlives a process): the second run of the same shapes
    adds nothing to the cache. Slow: two training processes, one compiling, one reading the
    cache (the process boundary is what is tested)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    cache = tmp_path / "cache" / "jaxnav" / "xla"

    def train(out, *flags):
        cmd = [sys.executable, "-m", "jaxnav.train", "--out", str(tmp_path / out), *TINY_FLAGS]
        proc = subprocess.run([*cmd, *flags], capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        return sorted(p.name for p in cache.iterdir()) if cache.exists() else []

    first = train("a")
    assert first and train("b") == first


@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_no_compile_cache_turns_the_cache_off_before_anything_compiles(
    command, tmp_path, monkeypatch, capsys
):
    """`--no-compile-cache` reaches the cache before the first compile: a command that stops at
    a missing layout file (before any program is built) has left JAX without a cache folder,
    and the user's cache folder is not made."""
    import importlib

    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    main = importlib.import_module(f"jaxnav.cli.{command}").main
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "elsewhere"))
    try:
        missing = ["--layouts", str(tmp_path / "none.json"), "--no-compile-cache"]
        extra = ["--out", str(tmp_path / "run")] if command == "train" else ["--policy", "forward"]
        assert main([*missing, *extra]) == 2
        assert not jax.config.jax_compilation_cache_dir
        assert not (tmp_path / "cache").exists()
        assert "none.json" in capsys.readouterr().err
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_train_layouts_of_several_files_are_named_by_file(tmp_path):
    from jaxnav.io.layouts import LayoutError
    from jaxnav.training import build_config

    room = {"room": {"size": [4.0, 4.0]}, "robot": {"pos": [0.0, 0.0], "yaw": 0.0}}
    (tmp_path / "a.json").write_text(json.dumps([room, {**room, "name": "office"}]))
    (tmp_path / "b.json").write_text(json.dumps([room, {**room, "name": "office"}]))
    files = [str(tmp_path / "a.json"), str(tmp_path / "b.json")]
    with pytest.raises(LayoutError, match=r"b\.json.*duplicate room name.*a\.json"):
        build_config(layout_files=files)
    config = build_config(layout_files=files[:1])
    assert [r["name"] for r in config.layouts] == ["a-0", "office"]
    with pytest.raises(LayoutError, match="given twice"):
        build_config(layout_files=files[:1] * 2)
    near = {**room, "goal": {"pos": [0.1, 0.0]}}
    (tmp_path / "near.json").write_text(json.dumps(near))
    with pytest.raises(LayoutError, match="success radius"):
        build_config(layout_files=[str(tmp_path / "near.json")], env="goal")


class _Asked:
    """A meta path finder that notes every top-level module the import system asks it for."""

    def __init__(self):
        self.names = []

    def find_spec(self, name, path=None, target=None):
        self.names.append(name)
        return None  # let the other finders answer


def test_tensorboard_writer_is_made_without_importing_torch(tmp_path, monkeypatch):
    """tensorboardX imports torch wherever it is installed (seconds on a GPU host); the run's
    writer imports it without: the import system is never asked for torch, and afterwards torch
    imports as before. Without the guard the same import asks for it."""
    from jaxnav.io import runlog

    def fresh_import(guarded: bool) -> list[str]:
        for name in [m for m in sys.modules if m.split(".")[0] == "tensorboardX"]:
            monkeypatch.delitem(sys.modules, name)
        asked = _Asked()
        monkeypatch.setattr(sys, "meta_path", [asked, *sys.meta_path])
        if guarded:
            writer = runlog._tensorboard(tmp_path / "tb")
            writer.add_scalar("train/x", 1.0, 0)
            writer.close()
        else:
            import tensorboardX  # noqa: F401
        monkeypatch.setattr(sys, "meta_path", [f for f in sys.meta_path if f is not asked])
        return asked.names

    if "torch" in sys.modules:
        pytest.skip("torch is loaded in this process: the writer leaves it as it is")
    assert "torch" not in fresh_import(guarded=True)
    assert "torch" not in sys.modules  # nothing left behind: `import torch` works as before
    assert list((tmp_path / "tb").iterdir())  # the event file
    assert "torch" in fresh_import(guarded=False)
