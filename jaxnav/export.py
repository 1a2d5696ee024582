"""`python -m jaxnav.export RUN --bundle DIR` (or `--format numpy|onnx --out FILE`): ship the actor.

python -m jaxnav.export runs/avoid-cpu --bundle robot/   # all the robot needs, see robot/README.txt
python -m jaxnav.export runs/avoid-cpu --format numpy --out policy.npz   # for jaxnav.robot_side
python -m jaxnav.export runs/avoid-cpu --format onnx --out policy.onnx   # for onnxruntime & co.

RUN is a run folder (its latest intact checkpoint is taken) or one checkpoint folder. A bundle is one
folder holding `jaxnav_robot/` (a copy of `jaxnav.robot_side`: numpy, and rclpy for the ROS 2 node),
`policy.npz`, the ROS 2 launch file, its configuration and a Dockerfile (`jaxnav.bundle`), and
`README.txt` with the commands to run on the robot; it is made in a temporary
folder beside DIR and renamed into place when complete (a previous bundle there is replaced
whole, except what the robot wrote into it: its camera calibration, `config/mount.yaml`, is kept),
so DIR never holds half a bundle. Both formats hold the actor MLP and the observation
normaliser, so they take raw sector distances (metres; the goal task's goal and last
command after them, see `jaxnav.robot_side.policy.goal_observation`). The ONNX model maps `obs`
float32 [N, D] to `logits` float32 [N, A] and `action` int64 [N] (greedy), or for continuous actions
`action` float32 [N, 2] (the command, m/s and rad/s, within the bounds); it is built node by node with
`onnx.helper` (opset 17, IR 8, loadable by onnxruntime >= 1.10), which needs only the `onnx` package.
Before the file gets its name, it is written beside it under a temporary name, run on random
observations and compared with the JAX network; only a file that passes is renamed into place (a
failing one is removed: nothing is left that does not match). The command line (`jaxnav.cli.export`)
prints the check.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np

from jaxnav.bundle import FILES, FOLDERS, KEPT, ROBOT_PACKAGE, Deployment, write_deployment
from jaxnav.core.types import ContinuousActions
from jaxnav.io.checkpoint import CheckpointError, resolve
from jaxnav.ppo.networks import LEAKY_SLOPE, normalize
from jaxnav.robot_side.policy import FORMAT_VERSION, MEMORY_FORMAT, NumpyPolicy
from jaxnav.runs import SavedPolicy, read_policy

FORMATS = ("numpy", "onnx")
SUFFIX = {"numpy": ".npz", "onnx": ".onnx"}
NORM_EPS = np.float32(1e-8)  # as in jaxnav.ppo.networks.normalize
NORM_CLIP = float(inspect.signature(normalize).parameters["clip"].default)
TOLERANCE = 1e-4  # max |exported logit - JAX logit| accepted by the check
CHECK_OBS = 1000
ONNX_OPSET, ONNX_IR = 17, 8


class ExportError(ValueError):
    """A user mistake (format, file, missing package); the message names the flag or file."""


class CheckFailed(ExportError):
    """The exported file's logits differ from JAX's: it was not written."""


def actor_arrays(saved: SavedPolicy) -> dict[str, np.ndarray]:
    """The actor weights, normaliser, sensor and action table of a checkpoint's policy (the .npz)."""
    config = saved.config
    spec = config.task.action_spec
    continuous = isinstance(spec, ContinuousActions)
    if continuous:  # the rows of `commands` are the lowest and the highest command
        names = ("lowest", "highest")
        commands = np.array([spec.low, spec.high], np.float32)
    else:
        names, commands = spec.names, spec.table()
    if saved.num_actions != len(names):
        raise CheckpointError(
            f"{saved.ckpt / 'policy.msgpack'}: the actor has {saved.num_actions} outputs, but the "
            f"task of {saved.ckpt / 'config.json'} has {len(names)} actions"
        )
    actor = saved.params["params"]["actor"]
    out = {}
    for i in range(len(actor)):  # Dense_0, Dense_1, ...: read_policy checked them
        layer = actor[f"Dense_{i}"]
        out[f"W{i}"] = np.asarray(layer["kernel"], np.float32)
        out[f"b{i}"] = np.asarray(layer["bias"], np.float32)
    size = saved.observation_size
    if config.ppo.normalize_obs:
        mean = np.asarray(saved.obs_stats.mean, np.float32)
        var, clip = np.asarray(saved.obs_stats.var, np.float32), NORM_CLIP
        std = np.sqrt(var + NORM_EPS)  # float32, as JAX computes it
    else:  # training fed raw observations: identity normaliser, no clipping
        mean, var, clip = np.zeros(size, np.float32), np.ones(size, np.float32), np.inf
        std = np.ones(size, np.float32)
    arrays = dict(
        out,
        obs_mean=mean,
        obs_var=var,
        obs_std=std,
        clip=np.float32(clip),
        leaky_slope=np.float32(LEAKY_SLOPE),
        action_names=np.array(names),
        commands=commands,
        fov=np.float32(config.sensor.fov),
        range_min=np.float32(config.sensor.range_min),
        range_max=np.float32(config.sensor.range_max),
        num_sectors=np.int32(config.sensor.num_sectors),
        # The rows and the floor rule: the robot reads the same pixels (observation.ray_pixels).
        elevations=np.asarray(config.sensor.elevations, np.float64),
        camera_height=np.float64(config.robot.camera_height),
        camera_pitch=np.float64(config.robot.camera_pitch),
        floor_margin=np.float64(config.sensor.floor_margin),
        floor_margin_slope=np.float64(config.sensor.floor_margin_slope),
        far_reads_max=np.int32(config.sensor.far_reads_max),
        control_period=np.float64(config.scene.control_period),  # s; float64: exact 10 Hz
        format_version=np.int32(2),  # what a format-2 reader reads right
    )
    return {**arrays, **_format3(config, spec, size)}


def _format3(config, spec, size: int) -> dict:
    """The format-3 entries of continuous actions and goal inputs (none for the paper's task),
    and the format-4 entries of a memory."""
    out = {}
    if isinstance(spec, ContinuousActions):
        out["action_low"] = np.asarray(spec.low, np.float32)
        out["action_high"] = np.asarray(spec.high, np.float32)
    history = getattr(config.task, "history", 0)
    bins = getattr(config.task, "memory_bins", 0)
    extra = (size - bins) // (1 + history) - config.sensor.num_sectors
    if history:
        out["history"] = np.int32(history)
    if extra:
        out["extra_observations"] = np.int32(extra)
        out["command_scale"] = np.array(
            [config.task.forward_speed, config.task.turn_rate], np.float32
        )
        out["success_radius"] = np.float64(config.task.success_radius)
    if out:
        out["format_version"] = np.int32(FORMAT_VERSION)
    if bins:
        out["memory_bins"] = np.int32(bins)
        out["memory_steps"] = np.int32(config.task.memory_steps)
        out["memory_reach"] = np.float64(config.task.memory_reach)
        out["memory_forward"] = np.float64(config.robot.camera_forward)
        out["format_version"] = np.int32(MEMORY_FORMAT)
    return out


def onnx_model(arrays: dict[str, np.ndarray]):
    """An onnx.ModelProto: obs [N, D] -> logits [N, A], action [N] (int64, argmax)."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        raise ExportError("--format onnx: needs the 'onnx' package (pip install onnx)") from None
    n_layers = sum(1 for k in arrays if k.startswith("W"))
    d_in, d_out = arrays["W0"].shape[0], arrays[f"W{n_layers - 1}"].shape[1]
    inits = {f"{k}{i}": arrays[f"{k}{i}"] for i in range(n_layers) for k in "Wb"}
    nodes, x = [], "obs"
    if np.isfinite(arrays["clip"]):  # the normaliser; absent when training did not normalise
        clip = float(arrays["clip"])
        inits.update(mean=arrays["obs_mean"], std=arrays["obs_std"])
        inits.update(lo=np.float32(-clip), hi=np.float32(clip))
        nodes += [
            helper.make_node("Sub", ["obs", "mean"], ["centred"]),
            helper.make_node("Div", ["centred", "std"], ["scaled"]),
            helper.make_node("Clip", ["scaled", "lo", "hi"], ["z"]),
        ]
        x = "z"
    for i in range(n_layers):
        last = i == n_layers - 1
        nodes += [
            helper.make_node("MatMul", [x, f"W{i}"], [f"mm{i}"]),
            helper.make_node("Add", [f"mm{i}", f"b{i}"], ["logits" if last else f"pre{i}"]),
        ]
        if not last:
            slope = float(arrays["leaky_slope"])
            nodes.append(helper.make_node("LeakyRelu", [f"pre{i}"], [f"h{i}"], alpha=slope))
            x = f"h{i}"
    if "action_low" in arrays:  # the command: centre + half * mean, within the bounds
        low, high = arrays["action_low"], arrays["action_high"]
        inits.update(cmd_centre=0.5 * (high + low), cmd_half=0.5 * (high - low))
        inits.update(cmd_low=low, cmd_high=high)
        nodes += [
            helper.make_node("Mul", ["logits", "cmd_half"], ["cmd_spread"]),
            helper.make_node("Add", ["cmd_spread", "cmd_centre"], ["cmd_mean"]),
            helper.make_node("Max", ["cmd_mean", "cmd_low"], ["cmd_above"]),
            helper.make_node("Min", ["cmd_above", "cmd_high"], ["action"]),
        ]
        action = helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", d_out])
    else:
        nodes.append(helper.make_node("ArgMax", ["logits"], ["action"], axis=1, keepdims=0))
        action = helper.make_tensor_value_info("action", TensorProto.INT64, ["N"])
    graph = helper.make_graph(
        nodes,
        "jaxnav_actor",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", d_in])],
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", d_out]), action],
        initializer=[numpy_helper.from_array(np.asarray(v), k) for k, v in inits.items()],
    )
    model = helper.make_model(
        graph, producer_name="jaxnav", opset_imports=[helper.make_opsetid("", ONNX_OPSET)]
    )
    model.ir_version = ONNX_IR  # older runtimes on robots refuse newer IR versions
    meta = {k: arrays[k] for k in ("fov", "range_min", "range_max")}
    meta["action_names"] = ",".join(str(a) for a in arrays["action_names"])
    meta["commands"] = json.dumps(arrays["commands"].tolist())  # [A, 2] (forward m/s, yaw rad/s)
    meta["num_sectors"] = int(arrays["num_sectors"])
    for key in ("action_low", "action_high", "command_scale"):  # format-3 entries, where given
        if key in arrays:
            meta[key] = json.dumps(np.asarray(arrays[key]).tolist())
    memory = ("memory_bins", "memory_steps", "memory_reach", "memory_forward")
    for key in ("extra_observations", "success_radius", "history", *memory):
        if key in arrays:
            meta[key] = float(arrays[key])
    helper.set_model_props(model, {k: str(v) for k, v in meta.items()})
    onnx.checker.check_model(model)
    return model


def write(arrays: dict[str, np.ndarray], fmt: str, out: Path, flag: str = "--out") -> None:
    """Writes the arrays as `fmt` into `out`; errors name `flag`."""
    model = onnx_model(arrays) if fmt == "onnx" else None  # before opening: may raise ExportError
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "wb") as fh:  # a handle: np.savez would append .npz to other names
            if model is None:
                np.savez(fh, **arrays)
            else:
                fh.write(model.SerializeToString())
    except OSError as err:
        raise ExportError(f"{flag} {out}: cannot write ({err.strerror or err})") from None


def exported_logits(out: Path, fmt: str):
    """obs [N, D] float32 -> logits [N, A] of the exported file (ImportError without onnxruntime)."""
    if fmt == "numpy":
        return NumpyPolicy.from_npz(out).logits
    import onnxruntime as ort

    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    return lambda obs: session.run(["logits"], {"obs": obs})[0]


def verify(
    saved: SavedPolicy, out: Path, fmt: str, n: int = CHECK_OBS, seed: int = 0
) -> tuple[float, int]:
    """(max |exported - JAX| logit, greedy actions that agree with JAX's) on n random obs."""
    import jax

    sensor = saved.config.sensor
    rng = np.random.default_rng(seed)
    # Beyond the sensor's range on both sides too, so the normaliser's clipping is exercised.
    size = saved.observation_size
    obs = rng.uniform(0.0, 1.25 * sensor.range_max, (n, size)).astype(np.float32)
    exported = exported_logits(out, fmt)(obs)
    # What load_policy's greedy act reads (a continuous actor's means, without its log-stds), in
    # float32 throughout as the robot computes it: a GPU's matrix products round their inputs to
    # TF32 by default, which put the logits 1e-2 off on an H200.
    with jax.default_matmul_precision("highest"):
        reference = np.asarray(jax.jit(saved.logits)(obs))[:, : exported.shape[-1]]
    diff = float(np.max(np.abs(exported - reference)))
    return diff, int(np.sum(exported.argmax(-1) == reference.argmax(-1)))


def write_checked(
    saved: SavedPolicy, arrays, fmt: str, out: Path, check: bool = True, flag: str = "--out"
) -> tuple[float, int] | None:
    """Writes `out` through a temporary file beside it that is checked against JAX first; returns
    the check (max |logit difference|, greedy actions that agree), or None when it was not run
    (`check` off, or ONNX without onnxruntime). CheckFailed leaves no file behind."""
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    write(arrays, fmt, tmp, flag)
    try:
        result = None
        if fmt == "numpy":
            _robot_accepts(tmp, out, flag)
        if check:
            with contextlib.suppress(ImportError):  # onnxruntime is optional: said by the caller
                result = verify(saved, tmp, fmt)
        if result is not None and result[0] > TOLERANCE:
            raise CheckFailed(
                f"{flag} {out}: not written: its logits differ from JAX's by {result[0]:.2e} > "
                f"{TOLERANCE}"
            )
        os.replace(tmp, out)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    return result


def _robot_accepts(tmp: Path, out: Path, flag: str) -> None:
    """CheckFailed unless the robot side loads the file (`NumpyPolicy.from_npz`'s checks: finite
    weights, shapes, commands within bounds), which a diverged run's weights may fail."""
    try:
        NumpyPolicy.from_npz(tmp)
    except ValueError as err:
        detail = str(err).replace(str(tmp), out.name)
        raise CheckFailed(
            f"{flag} {out}: not written: the robot side refuses it: {detail}"
        ) from None


def export(path, fmt: str, out=None, check: bool = True) -> Path:
    """Exports the actor of run/checkpoint folder `path` as `fmt` to `out`; returns the file.

    `out` defaults to policy.npz / policy.onnx in the checkpoint folder. With `check`, the file is
    compared with the JAX network on random observations (ExportError beyond TOLERANCE; ONNX is
    only checked when onnxruntime is installed).
    """
    saved = read_policy(resolve(path))
    out, result = export_saved(saved, fmt, out, check)
    if check and result is None:
        warnings.warn("onnxruntime is not installed: the ONNX model was not run", stacklevel=2)
    return out


def export_saved(saved: SavedPolicy, fmt: str, out, check: bool = True):
    """(the file written, its check as `write_checked` returns it)."""
    if fmt not in FORMATS:
        raise ExportError(f"--format: unknown format '{fmt}'; valid: {', '.join(FORMATS)}")
    out = Path(out) if out is not None else saved.ckpt / f"policy{SUFFIX[fmt]}"
    check_out(out)
    return out, write_checked(saved, actor_arrays(saved), fmt, out, check)


def check_out(out: Path, flag: str = "--out") -> None:
    """`out` can be written as a file (its folder made if missing), before anything is read."""
    try:
        if out.is_dir():
            raise ExportError(
                f"{flag} {out}: is a folder; give a file name, e.g. {out / 'policy.npz'}"
            )
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out.parent):
            pass
    except OSError as err:
        raise ExportError(f"{flag} {out}: cannot write ({err.strerror or err})") from None


def bundle(path, folder, check: bool = True) -> Path:
    """Writes all the robot needs for the policy of run/checkpoint folder `path` into `folder`:
    `jaxnav_robot/` (a copy of jaxnav.robot_side), `policy.npz`, README.txt and the deployment
    files of `jaxnav.bundle` (launch file, configuration, Dockerfile); returns it."""
    saved = read_policy(resolve(path))
    return bundle_saved(saved, folder, check)[0]


BUNDLE = ("policy.npz", ROBOT_PACKAGE, "README.txt", *FOLDERS, *FILES)  # all a bundle folder holds


def check_bundle(folder: Path) -> None:
    """`folder` can take a bundle: new, empty or a previous bundle (nothing else is replaced),
    and its parent can be written; before anything is read."""
    try:
        if folder.exists() and not folder.is_dir():
            raise ExportError(f"--bundle {folder}: exists and is not a folder")
        held = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
        others = [name for name in held if name not in BUNDLE]
        if others:
            raise ExportError(
                f"--bundle {folder}: holds {', '.join(others[:3])}, not part of a bundle; give a "
                "new or empty folder, or a previous bundle (which is replaced)"
            )
        for name in (ROBOT_PACKAGE, *FOLDERS):
            if name in held and not (folder / name).is_dir():
                raise ExportError(
                    f"--bundle {folder}: its {name} is not a folder, so not a previous "
                    "bundle's; remove it or give another folder"
                )
        folder.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder.parent):
            pass
    except OSError as err:
        raise ExportError(f"--bundle {folder}: cannot write ({err.strerror or err})") from None


def bundle_saved(saved: SavedPolicy, folder, check: bool = True):
    """(the bundle folder, the check of its policy.npz)."""
    folder = Path(folder)
    check_bundle(folder)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        result = _fill_bundle(saved, tmp, check, folder.name)
        _keep_robot_files(folder, tmp)
        _put_in_place(tmp, folder)
    except ExportError as err:  # its message names the temporary folder: name the bundle
        raise type(err)(str(err).replace(str(tmp), str(folder))) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder, result


def _fill_bundle(saved: SavedPolicy, folder: Path, check: bool, name: str = "robot"):
    """Writes policy.npz (checked), the robot package and the deployment files (README.txt
    included) into `folder`, the bundle `name`; returns the check of policy.npz."""
    arrays = actor_arrays(saved)
    result = write_checked(saved, arrays, "numpy", folder / "policy.npz", check, "--bundle")
    source = Path(__file__).parent / "robot_side"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(source, folder / ROBOT_PACKAGE, ignore=ignore)
    write_deployment(folder, Deployment.from_policy(arrays, saved.config, saved.ckpt, name))
    return result


def _keep_robot_files(folder: Path, tmp: Path) -> None:
    """Copies the files the robot wrote into the previous bundle `folder` (`KEPT`: the camera
    calibration) into the new one, `tmp`, so replacing a bundle never loses them."""
    for name in KEPT:
        if (folder / name).is_file():
            shutil.copy2(folder / name, tmp / name)


def _put_in_place(tmp: Path, folder: Path) -> None:
    """Renames the complete bundle `tmp` to `folder`; a previous bundle there is moved aside
    first and removed after, so `folder` holds the old bundle or the new one, never half."""
    if not folder.exists():
        os.replace(tmp, folder)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
    try:
        os.replace(folder, old / folder.name)
        try:
            os.replace(tmp, folder)
        except BaseException:
            os.replace(old / folder.name, folder)
            raise
    finally:
        shutil.rmtree(old, ignore_errors=True)


def read_saved(path) -> SavedPolicy:
    """The policy of run or checkpoint folder `path`; a folder without permission on the way is a
    CheckpointError naming it."""
    try:
        return read_policy(resolve(path))
    except OSError as err:
        where = err.filename or path
        raise CheckpointError(f"{where}: cannot read ({err.strerror or err})") from None


if __name__ == "__main__":  # `python -m jaxnav.export`: the command line
    import sys

    from jaxnav.cli.export import main

    sys.exit(main())
