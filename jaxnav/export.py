"""`python -m jaxnav.export DIR --format numpy|onnx --out FILE`: ship the trained actor out of JAX.

python -m jaxnav.export runs/avoid-cpu --format numpy --out policy.npz   # for jaxnav/numpy_policy.py
python -m jaxnav.export runs/avoid-cpu --format onnx --out policy.onnx   # for onnxruntime & co.

DIR is a run folder (its latest checkpoint is taken) or one checkpoint folder. Both formats hold the
actor MLP and the observation normaliser, so they take raw sector distances (metres). The ONNX model
maps `obs` float32 [N, 8] to `logits` float32 [N, 3] and `action` int64 [N] (greedy); it is built
node by node with `onnx.helper` (opset 17, IR 8, loadable by onnxruntime >= 1.10), which needs only
the `onnx` package. After writing, the file is run on random observations and compared with the JAX
network; the check is printed.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import warnings
from pathlib import Path

import numpy as np

from jaxnav.core import robot
from jaxnav.io.checkpoint import CheckpointError, load_config, load_policy, resolve
from jaxnav.ppo.networks import LEAKY_SLOPE, normalize
from jaxnav.robot_side.policy import FORMAT_VERSION, NumpyPolicy

FORMATS = ("numpy", "onnx")
SUFFIX = {"numpy": ".npz", "onnx": ".onnx"}
NORM_EPS = np.float32(1e-8)  # as in jaxnav.ppo.networks.normalize
NORM_CLIP = float(inspect.signature(normalize).parameters["clip"].default)
TOLERANCE = 1e-4  # max |exported logit - JAX logit| accepted by the check
CHECK_OBS = 1000
ONNX_OPSET, ONNX_IR = 17, 8


class ExportError(ValueError):
    """A user mistake (format, file, missing package); the message names the flag or file."""


def actor_arrays(ckpt: Path) -> dict[str, np.ndarray]:
    """The actor weights, normaliser and robot settings of checkpoint folder `ckpt` (the .npz)."""
    from flax import serialization

    config = load_config(ckpt)
    file = ckpt / "policy.msgpack"
    try:
        raw = serialization.msgpack_restore(file.read_bytes())
        actor, stats = raw["params"]["params"]["actor"], raw["obs_stats"]
        names = sorted(actor, key=lambda k: int(k.split("_")[1]))  # Dense_0, Dense_1, ...
        layers = [(actor[n]["kernel"], actor[n]["bias"]) for n in names]
        mean, var = stats["mean"], stats["var"]
    except (OSError, KeyError, TypeError, ValueError, IndexError) as err:
        raise CheckpointError(
            f"{file}: unreadable actor weights ({type(err).__name__}: {err})"
        ) from None
    _check_layers(file, ckpt, config, layers)
    out = {}
    for i, (w, b) in enumerate(layers):
        out[f"W{i}"], out[f"b{i}"] = np.asarray(w, np.float32), np.asarray(b, np.float32)
    size = out["W0"].shape[0]
    if config.ppo.normalize_obs:
        mean, var, clip = np.asarray(mean, np.float32), np.asarray(var, np.float32), NORM_CLIP
        std = np.sqrt(var + NORM_EPS)  # float32, as JAX computes it
    else:  # training fed raw observations: identity normaliser, no clipping
        mean, var, clip = np.zeros(size, np.float32), np.ones(size, np.float32), np.inf
        std = np.ones(size, np.float32)
    sensor, task = config.sensor, config.task
    return dict(
        out,
        obs_mean=mean,
        obs_var=var,
        obs_std=std,
        clip=np.float32(clip),
        leaky_slope=np.float32(LEAKY_SLOPE),
        action_names=np.array(robot.ACTION_NAMES),
        forward_speed=np.float32(task.forward_speed),
        turn_rate=np.float32(task.turn_rate),
        fov=np.float32(sensor.fov),
        range_min=np.float32(sensor.range_min),
        range_max=np.float32(sensor.range_max),
        num_sectors=np.int32(sensor.num_sectors),
        format_version=np.int32(FORMAT_VERSION),
    )


def _check_layers(file: Path, ckpt: Path, config, layers) -> None:
    """The actor's layer shapes are the ones config.json describes (else the check and the robot
    would fail later, far from the cause)."""
    shapes = [tuple(np.shape(w)) for w, _ in layers]
    widths = [config.sensor.num_sectors, *config.ppo.hidden, len(robot.ACTION_NAMES)]
    expected = list(zip(widths[:-1], widths[1:], strict=True))
    if shapes != expected:
        raise CheckpointError(
            f"{file}: actor layers {shapes} do not match {ckpt / 'config.json'} "
            f"(sensor.num_sectors {widths[0]}, ppo.hidden {list(config.ppo.hidden)}, "
            f"{widths[-1]} actions: {expected})"
        )


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
    nodes.append(helper.make_node("ArgMax", ["logits"], ["action"], axis=1, keepdims=0))
    graph = helper.make_graph(
        nodes,
        "jaxnav_actor",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", d_in])],
        [
            helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", d_out]),
            helper.make_tensor_value_info("action", TensorProto.INT64, ["N"]),
        ],
        initializer=[numpy_helper.from_array(np.asarray(v), k) for k, v in inits.items()],
    )
    model = helper.make_model(
        graph, producer_name="jaxnav", opset_imports=[helper.make_opsetid("", ONNX_OPSET)]
    )
    model.ir_version = ONNX_IR  # older runtimes on robots refuse newer IR versions
    meta = {k: arrays[k] for k in ("forward_speed", "turn_rate", "fov", "range_min", "range_max")}
    meta["action_names"] = ",".join(str(a) for a in arrays["action_names"])
    meta["num_sectors"] = int(arrays["num_sectors"])
    helper.set_model_props(model, {k: str(v) for k, v in meta.items()})
    onnx.checker.check_model(model)
    return model


def write(arrays: dict[str, np.ndarray], fmt: str, out: Path) -> None:
    """Writes the arrays as `fmt` into `out`."""
    model = onnx_model(arrays) if fmt == "onnx" else None  # before opening: may raise ExportError
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "wb") as fh:  # a handle: np.savez would append .npz to other names
            if model is None:
                np.savez(fh, **arrays)
            else:
                fh.write(model.SerializeToString())
    except OSError as err:
        raise ExportError(f"--out {out}: cannot write ({err.strerror or err})") from None


def exported_logits(out: Path, fmt: str):
    """obs [N, D] float32 -> logits [N, A] of the exported file (ImportError without onnxruntime)."""
    if fmt == "numpy":
        return NumpyPolicy.from_npz(out).logits
    import onnxruntime as ort

    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    return lambda obs: session.run(["logits"], {"obs": obs})[0]


def jax_logits(ckpt: Path):
    """obs [N, D] -> logits [N, A] of the checkpoint's JAX actor (as `load_policy` computes them)."""
    import jax
    import jax.numpy as jnp
    from flax import serialization
    from flax.errors import FlaxError

    from jaxnav.ppo.networks import RunningStats
    from jaxnav.ppo.train import make_network

    config = load_config(ckpt)
    raw = serialization.msgpack_restore((ckpt / "policy.msgpack").read_bytes())
    params = jax.tree_util.tree_map(jnp.asarray, raw["params"])
    stats = RunningStats(**{k: jnp.asarray(v) for k, v in raw["obs_stats"].items()})
    network = make_network(config.ppo, len(robot.ACTION_NAMES))
    try:  # actor_arrays checked the actor; this checks the critic too (tracing only, no compile)
        obs = jax.ShapeDtypeStruct((1, config.sensor.num_sectors), jnp.float32)
        jax.eval_shape(network.apply, params, obs)
    except FlaxError as err:
        detail = str(err).split(" (https://")[0]
        raise CheckpointError(
            f"{ckpt / 'policy.msgpack'}: does not fit the network of its config.json ({detail})"
        ) from None

    @jax.jit
    def logits(obs):
        return network.apply(params, normalize(stats, obs) if config.ppo.normalize_obs else obs)[0]

    return lambda obs: np.asarray(logits(obs))


def verify(ckpt: Path, out: Path, fmt: str, n: int = CHECK_OBS, seed: int = 0) -> tuple[float, int]:
    """(max |exported - JAX| logit, greedy actions that agree with `load_policy`) on n random obs."""
    config = load_config(ckpt)
    rng = np.random.default_rng(seed)
    # Beyond the sensor's range on both sides too, so the normaliser's clipping is exercised.
    obs = rng.uniform(0.0, 1.25 * config.sensor.range_max, (n, config.sensor.num_sectors))
    obs = obs.astype(np.float32)
    exported = exported_logits(out, fmt)(obs)
    diff = float(np.max(np.abs(exported - jax_logits(ckpt)(obs))))
    import jax

    reference = np.asarray(load_policy(ckpt).act(obs, jax.random.PRNGKey(0)))
    return diff, int(np.sum(exported.argmax(-1) == reference))


def export(path, fmt: str, out=None, check: bool = True) -> Path:
    """Exports the actor of run/checkpoint folder `path` as `fmt` to `out`; returns the file.

    `out` defaults to policy.npz / policy.onnx in the checkpoint folder. With `check`, the file is
    compared with the JAX network on random observations (ExportError beyond TOLERANCE; ONNX is
    only checked when onnxruntime is installed).
    """
    if fmt not in FORMATS:
        raise ExportError(f"--format: unknown format '{fmt}'; valid: {', '.join(FORMATS)}")
    ckpt = resolve(path)
    out = Path(out) if out is not None else ckpt / f"policy{SUFFIX[fmt]}"
    write(actor_arrays(ckpt), fmt, out)
    if check:
        try:
            diff, _ = verify(ckpt, out, fmt)
        except ImportError:
            warnings.warn("onnxruntime is not installed: the ONNX model was not run", stacklevel=2)
            return out
        if diff > TOLERANCE:
            raise ExportError(f"{out}: logits differ from JAX's by {diff:.2e} > {TOLERANCE}")
    return out


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse prints usage and exits; we want one `error:` line
        raise ExportError(message)


def main(argv=None) -> int:
    parser = _Parser(prog="python -m jaxnav.export", description=__doc__.splitlines()[0])
    parser.add_argument("dir", metavar="DIR", help="a training run folder or a checkpoint in it")
    parser.add_argument("--format", default="numpy", help=f"one of {', '.join(FORMATS)}")
    parser.add_argument("--out", type=Path, help="output file (default: DIR's checkpoint/policy.*)")
    try:
        args = parser.parse_args(argv)
        out = export(args.dir, args.format, args.out, check=False)
        ckpt = resolve(args.dir)
    except (ExportError, CheckpointError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({args.format}) from {ckpt}")
    try:
        diff, agree = verify(ckpt, out, args.format)
    except ImportError:
        print("warning: onnxruntime is not installed; the ONNX model was not run", file=sys.stderr)
        return 0
    except CheckpointError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    ok = diff <= TOLERANCE
    print(
        f"check: max |logit - JAX logit| = {diff:.2e} on {CHECK_OBS} random observations "
        f"({'ok' if ok else 'FAILED'}, tolerance {TOLERANCE:.0e}); "
        f"greedy actions agree on {agree}/{CHECK_OBS}"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
