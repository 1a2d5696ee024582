"""Exporting the actor out of JAX: numpy and ONNX parity, the robot bundle, the CLI."""

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_robot_side import run_without_jax

import jaxnav
from jaxnav import export
from jaxnav.cli import export as export_cli
from jaxnav.core.sensors import SensorConfig
from jaxnav.io import checkpoint
from jaxnav.ppo.config import preset
from jaxnav.ppo.networks import RunningStats, normalize
from jaxnav.ppo.train import TrainState, make_network
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.runconfig import RunConfig
from jaxnav.tasks.avoid import AvoidConfig


def make_run(root: Path, ppo, seed: int, task: AvoidConfig = AvoidConfig()):
    """A run folder with one checkpoint of a freshly initialised network, without training.

    The params come from the same `make_network(...).init` as `make_train`'s; the policy head is
    scaled up (its init gain of 0.01 makes all logits nearly equal) and the normaliser holds
    non-trivial statistics, so that the parity checks below mean something. `task`'s stacked
    frames set the observation's size (8 sectors a frame).
    """
    size = 8 * (1 + task.history)
    network = make_network(ppo, task.action_spec)
    params = jax.jit(network.init)(jax.random.PRNGKey(seed), jnp.zeros((1, size)))
    head = params["params"]["actor"]["Dense_2"]
    params["params"]["actor"]["Dense_2"] = {**head, "kernel": head["kernel"] * 200.0}
    keys = jax.random.split(jax.random.PRNGKey(seed + 1), 2)
    stats = RunningStats(
        mean=jax.random.uniform(keys[0], (size,), minval=1.0, maxval=4.0),
        var=jax.random.uniform(keys[1], (size,), minval=0.05, maxval=3.0),
        count=jnp.float32(1e4),
    )
    ts = TrainState(params, (), stats, (), jax.random.PRNGKey(0), jnp.int32(3))
    checkpoint.save(root, ts, RunConfig(ppo=ppo, task=task), {})

    def reference_logits(obs):  # in float32 throughout (a GPU's default rounds to TF32)
        x = normalize(stats, obs) if ppo.normalize_obs else obs
        with jax.default_matmul_precision("highest"):
            return np.asarray(network.apply(params, x)[0])

    return root, reference_logits


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{name: (run folder, reference logits)}: the cpu preset, and the paper's (no normaliser)."""
    ppos = {
        "normalised": preset("cpu"),
        "raw": preset("paper", hidden=(32, 16)),  # other widths and depths export too
    }
    return {
        name: make_run(tmp_path_factory.mktemp(name), ppo, seed=i)
        for i, (name, ppo) in enumerate(ppos.items())
    }


@pytest.fixture(params=["normalised", "raw"])
def run(request, runs):
    return runs[request.param]


@pytest.fixture(scope="module")
def one_run(runs):
    """The run the command-line and robot-file tests use (subprocesses are slow: one run only)."""
    return runs["normalised"]


def random_obs(n=1000, seed=0):
    # Beyond the sensor range on both sides: exercises the normaliser's clipping.
    return np.random.default_rng(seed).uniform(0.0, 10.0, (n, 8)).astype(np.float32)


def assert_same_greedy_actions(logits, actions, reference_logits):
    """Actions equal the reference argmax wherever the top two logits are not a float32 tie."""
    top2 = np.sort(reference_logits, axis=-1)[:, -2:]
    clear = top2[:, 1] - top2[:, 0] > 1e-5
    assert clear.mean() > 0.95
    np.testing.assert_array_equal(np.asarray(actions)[clear], reference_logits.argmax(-1)[clear])
    np.testing.assert_array_equal(np.asarray(actions), logits.argmax(-1))


def test_numpy_export_matches_jax(run, tmp_path):
    folder, reference = run
    out = export.export(folder, "numpy", tmp_path / "policy.npz")
    policy = NumpyPolicy.from_npz(out)
    obs = random_obs()
    logits, ref = policy.logits(obs), reference(obs)
    np.testing.assert_allclose(logits, ref, atol=1e-5, rtol=0)
    assert_same_greedy_actions(logits, policy(obs), ref)
    with jax.default_matmul_precision("highest"):  # float32, as the file computes
        jax_actions = np.asarray(jaxnav.load_policy(folder).act(obs, jax.random.PRNGKey(0)))
    assert_same_greedy_actions(logits, jax_actions, ref)
    single = policy(obs[0])
    assert isinstance(single, int) and single == int(policy(obs[:1])[0])
    assert policy.action_names == ("forward", "left", "right")
    assert policy.sensor.num_sectors == 8 and policy.sensor.range_max == 8.0
    # The rows and the floor rule's mount, for `observation.ray_pixels` and `floor_mask`.
    rows = tuple(float(e) for e in SensorConfig().elevations)
    assert policy.sensor.elevations == pytest.approx(rows) and policy.sensor.camera_height == 0.295
    assert policy.sensor.floor_margin == 0.02 and policy.sensor.camera_pitch == 0.0
    # The default task's speeds: 0.5 m/s forward, 1.5 rad/s turning in place.
    np.testing.assert_array_equal(policy.commands, [[0.5, 0.0], [0.0, 1.5], [0.0, -1.5]])


def test_the_check_runs_jax_in_float32(one_run, tmp_path, monkeypatch):
    """The export's check computes JAX's logits at float32's full precision, as the robot side
    does, not at a GPU's default (TF32 inputs: logits 1e-2 off on an H200, every export refused)."""
    from jaxnav import runs as runs_module

    seen = []

    def read_policy(path):  # whose logits say the precision they are traced at
        saved = runs_module.read_policy(path)
        logits = saved.logits

        def traced(obs):
            seen.append(jax.config.values["jax_default_matmul_precision"])
            return logits(obs)

        object.__setattr__(saved, "logits", traced)
        return saved

    monkeypatch.setattr(export, "read_policy", read_policy)
    export.export(one_run[0], "numpy", tmp_path / "policy.npz")
    assert seen and set(seen) == {"highest"}, seen


def test_an_avoid_policy_with_stacked_frames_exports_its_history(tmp_path):
    """An avoid policy with `history` 2 exports as format 3 with its history, reads 24 entries
    on the robot side, matches JAX there, and names a wrong-sized observation in one line."""
    folder, reference = make_run(tmp_path / "run", preset("cpu"), 5, AvoidConfig(history=2))
    policy = NumpyPolicy.from_npz(export.export(folder, "numpy", tmp_path / "policy.npz"))
    with np.load(tmp_path / "policy.npz") as data:
        assert int(data["format_version"]) == 3 and int(data["history"]) == 2
        assert "extra_observations" not in data.files
    assert (policy.history, policy.observation_size) == (2, 24)
    obs = np.random.default_rng(0).uniform(0.0, 10.0, (1000, 24)).astype(np.float32)
    logits, ref = policy.logits(obs), reference(obs)
    np.testing.assert_allclose(logits, ref, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="reads 24 entries .with history: stack the frames"):
        policy(obs[0, :8])


def test_onnx_export_matches_jax(run, tmp_path):
    pytest.importorskip("onnx", reason="the onnx package is not installed (pip install onnx)")
    ort = pytest.importorskip(
        "onnxruntime", reason="onnxruntime is not installed (pip install onnxruntime)"
    )
    folder, reference = run
    out = export.export(folder, "onnx", tmp_path / "policy.onnx")
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    obs = random_obs(seed=1)
    logits, actions = session.run(["logits", "action"], {"obs": obs})
    assert logits.shape == (1000, 3) and actions.shape == (1000,)
    ref = reference(obs)
    np.testing.assert_allclose(logits, ref, atol=1e-5, rtol=0)
    assert_same_greedy_actions(logits, actions, ref)
    props = session.get_modelmeta().custom_metadata_map
    assert props["action_names"] == "forward,left,right"
    assert json.loads(props["commands"]) == [[0.5, 0.0], [0.0, 1.5], [0.0, -1.5]]


def test_bundle_runs_on_a_robot_without_jax(one_run, tmp_path):
    """The bundle's folder alone (no jaxnav, no jax) loads the policy and acts as JAX does."""
    folder = export.bundle(one_run[0], tmp_path / "robot")
    package = sorted(p.name for p in (folder / "jaxnav_robot").glob("*.py"))
    assert package == [
        "__init__.py",
        "bag.py",
        "calibrate.py",
        "memory.py",
        "observation.py",
        "policy.py",
        "ros_node.py",
    ]
    readme = (folder / "README.txt").read_text()
    assert "python3 -m jaxnav_robot.ros_node --policy policy.npz" in readme
    assert "--ros-args -r cmd_vel:=commands/velocity" in readme
    commands = " ".join(readme.replace("\\\n", " ").split("\n"))  # continued lines joined
    assert "policy.npz --ros-args" in " ".join(commands.split())
    for line in readme.splitlines():  # a command's words one space apart, or a continuation
        if line.strip().startswith("python3 -m"):
            assert not re.search(r"\S {2,}\S", line), line
    obs = random_obs(n=200, seed=3)
    np.save(tmp_path / "obs.npy", obs)
    code = f"""
        import json
        import numpy as np
        import jaxnav_robot.ros_node
        from jaxnav_robot import Controller, NumpyPolicy

        policy = NumpyPolicy.from_npz("policy.npz")
        twist = Controller(policy).image_to_twist(np.full((4, 64), 3.0, np.float32))
        actions = policy(np.load({str(tmp_path / "obs.npy")!r})).tolist()
        jaxnav = sorted(m for m in sys.modules if m.partition(".")[0] == "jaxnav")
        print(json.dumps({{"actions": actions, "twist": list(twist), "jaxnav": jaxnav}}))
    """
    proc = run_without_jax(code, cwd=folder)  # no PYTHONPATH: only what is in the folder
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    want = jaxnav.load_policy(one_run[0]).act(obs, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(got["actions"], np.asarray(want))
    assert got["twist"] in ([0.5, 0.0], [0.0, 1.5], [0.0, -1.5]) and got["jaxnav"] == []


def test_cli_bundle(one_run, tmp_path, capsys):
    assert export_cli.main([str(one_run[0]), "--bundle", str(tmp_path / "robot")]) == 0
    out = capsys.readouterr()
    assert "(bundle)" in out.out and "greedy actions agree on 1000/1000" in out.out
    assert out.err.startswith("note: the policy trained with each speed's change limited")
    assert (tmp_path / "robot" / "policy.npz").exists()
    argv = [str(one_run[0]), "--bundle", str(tmp_path / "b"), "--format", "onnx"]
    assert export_cli.main(argv) == 2
    assert_one_error_line(capsys.readouterr().err, "--format", "not with --bundle")
    (tmp_path / "file").write_text("")
    assert export_cli.main([str(one_run[0]), "--bundle", str(tmp_path / "file")]) == 2
    assert_one_error_line(capsys.readouterr().err, "--bundle", "not a folder")


def test_bundle_is_complete_or_absent(one_run, tmp_path, capsys, monkeypatch):
    """A bundle is made beside its folder and renamed into place: a previous bundle is replaced
    whole but for the robot's own calibration, and a write that fails halfway leaves the previous one (or none) and nothing else."""
    folder = tmp_path / "robot"
    assert export_cli.main([str(one_run[0]), "--bundle", str(folder)]) == 0
    (folder / "jaxnav_robot" / "stale.py").write_text("")  # gone once replaced
    (folder / "config" / "mount.yaml").write_text("calibrated on the robot\n")  # kept
    assert export_cli.main([str(one_run[0]), "--bundle", str(folder)]) == 0
    assert sorted(p.name for p in folder.iterdir()) == sorted(export.BUNDLE)
    assert not (folder / "jaxnav_robot" / "stale.py").exists()
    assert (folder / "config" / "mount.yaml").read_text() == "calibrated on the robot\n"
    before = {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export.shutil, "copytree", disk_full)
    capsys.readouterr()
    for target in (folder, tmp_path / "new"):
        assert export_cli.main([str(one_run[0]), "--bundle", str(target)]) == 1
        err = capsys.readouterr().err
        assert_one_error_line(err, f"{target}: cannot write (No space left on device)")
    assert [p.name for p in tmp_path.iterdir()] == ["robot"]  # no half bundle, no temporaries
    after = {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert after == before


@pytest.fixture(scope="module")
def cli(one_run, tmp_path_factory):
    """{case: (returncode, stdout, stderr, out file)} of `python -m jaxnav.export` runs.

    The runs are started together: each spends seconds importing jax, and they overlap.
    """
    tmp = tmp_path_factory.mktemp("cli")
    fmt = "onnx" if importlib.util.find_spec("onnxruntime") else "numpy"
    cases = {
        "ok": [one_run[0], "--format", fmt, "--out", tmp / f"policy.{fmt}"],
        "missing": [tmp / "missing", "--out", tmp / "p.npz"],
        "format": [one_run[0], "--format", "tflite"],
    }
    procs = {
        case: subprocess.Popen(
            [sys.executable, "-m", "jaxnav.export", *map(str, args)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for case, args in cases.items()
    }
    results = {}
    for case, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        results[case] = (proc.returncode, stdout, stderr, Path(str(cases[case][-1])))
    return results


def test_cli_exports_and_checks(cli):
    code, stdout, stderr, out = cli["ok"]
    assert code == 0, stderr
    assert out.stat().st_size > 1000
    assert "check: max |logit - JAX logit|" in stdout and "(ok," in stdout
    assert "greedy actions agree on 1000/1000" in stdout


def assert_one_error_line(stderr: str, *needles):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert all(n in lines[0] for n in needles), lines[0]


def test_cli_user_errors(cli):
    code, _, stderr, _ = cli["missing"]
    assert code == 2
    assert_one_error_line(stderr, "missing", "no such checkpoint")
    code, _, stderr, _ = cli["format"]
    assert code == 2
    assert_one_error_line(stderr, "--format", "tflite")


def test_cli_unreadable_checkpoint_and_missing_onnx(one_run, tmp_path, capsys, monkeypatch):
    broken = tmp_path / "broken"
    shutil.copytree(checkpoint.resolve(one_run[0]), broken)
    (broken / "policy.msgpack").write_bytes(b"not msgpack")
    assert export_cli.main([str(broken), "--out", str(tmp_path / "p.npz")]) == 2
    assert_one_error_line(capsys.readouterr().err, "policy.msgpack")
    monkeypatch.setitem(sys.modules, "onnx", None)  # as if not installed
    assert (
        export_cli.main([str(one_run[0]), "--format", "onnx", "--out", str(tmp_path / "p.onnx")])
        == 2
    )
    assert_one_error_line(capsys.readouterr().err, "--format onnx", "pip install onnx")
    assert export_cli.main([str(one_run[0])]) == 0  # default: policy.npz inside the checkpoint
    assert (checkpoint.resolve(one_run[0]) / "policy.npz").exists()


def test_a_policy_the_robot_would_refuse_is_not_exported(one_run, tmp_path, monkeypatch):
    """Weights that are not finite (a diverged run) are refused even without the JAX check."""
    real = export.actor_arrays

    def poisoned(*args, **kwargs):
        arrays = real(*args, **kwargs)
        return {k: (v * np.nan if k == "W1" else v) for k, v in arrays.items()}

    monkeypatch.setattr(export, "actor_arrays", poisoned)
    with pytest.raises(export.CheckFailed, match="robot side refuses it: policy.npz: W1"):
        export.export(one_run[0], "numpy", tmp_path / "policy.npz", check=False)
    assert list(tmp_path.iterdir()) == []
