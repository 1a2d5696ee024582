"""A training run's programs (`Trainer.programs`: the draws, start, rollout and learner, or init,
the rollout and the learner of a run whose steps draw their own new episodes), traced once and
kept on disk.

Before XLA compiles anything, a start traces the task's reset and step (under `vmap`, in a scan)
and lowers them to StableHLO: several seconds of Python on every start (7-9 s for the goal
task's), which JAX's persistent compilation cache cannot keep, since it keeps XLA's side only. So
a run on one device exports its programs with `jax.export` (StableHLO and the pytree structure of
their arguments and results) into the `programs/` folder of the compilation cache, under a key of
everything the trace depends on (`run_key`). A repeated run reads them back and hands them to
`jax.jit`, whose program (a call of the stored one) the first run compiled too, so XLA's side is a
lookup in the persistent cache.

The store is on with the compilation cache (`process.compile_cache`, which the commands call and
`--no-compile-cache` turns off), for one device. A program that cannot be exported (an XLA custom
call without a stability guarantee) is traced as before; a file that cannot be read back is traced
again and written anew. The store keeps within MAX_BYTES: after a program is kept, those used
longest ago go first (a program read back counts as used: its file's time is renewed).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import os
import pickle
import sys
from pathlib import Path

import jax
import mujoco
import numpy as np
from jax import export

from jaxnav.core.assets import scenes_dir
from jaxnav.core.xla import compiler_options, lowering, traced
from jaxnav.io import files

FORMAT = 1
"""The store's own format, part of the key: a change of it keys every run anew."""

LIBRARIES = (
    "jax",
    "jaxlib",
    "jax-cuda12-plugin",
    "jax-cuda12-pjrt",
    "jax-cuda13-plugin",
    "jax-cuda13-pjrt",
    "mujoco",
    "mujoco-mjx",
    "flax",
    "optax",
    "numpy",
)
"""The packages whose code a trace runs or lowers (their versions are in the key)."""

DONATED = {"rollout": (0,), "learn": (0,)}  # program: the arguments whose buffers it reuses

MAX_BYTES = 256 * 2**20
"""The store's size at most: a goal run's programs take about 0.7 MB (cpu preset), so this
keeps the last few hundred configs and code versions."""

_folder: Path | None = None


def use(folder: Path | None) -> None:
    """Keeps the programs of later runs in `folder` (None: nowhere; every run traces)."""
    global _folder
    _folder = None if folder is None else Path(folder)


def folder() -> Path | None:
    """Where programs are kept now (None: the store is off)."""
    return _folder


# ---------------------------------------------------------------- the key


def run_key(config, model=None) -> str:
    """A digest of everything that decides the traced programs of `config`'s run: the config but
    its seed (which only makes init's argument), jaxnav's own files (code and scenes), the MuJoCo
    `model` its env built (whatever files it came from), the versions of Python and of
    `LIBRARIES`, every JAX option, and the device."""
    digest = hashlib.sha256()
    device = jax.devices()[0]
    facts = {
        "format": FORMAT,
        "python": sys.version,
        "libraries": {name: _version(name) for name in LIBRARIES},
        "options": {name: str(value) for name, value in jax.config.values.items()},
        "device": [device.platform, device.device_kind, jax.device_count()],
        "config": {k: v for k, v in config.to_dict().items() if k != "seed"},
    }
    digest.update(json.dumps(facts, sort_keys=True, default=str).encode())
    package, scenes = Path(__file__).parent, scenes_dir()
    # Installed from a wheel, the scenes are inside the package: its tree holds them already.
    for root in (package,) if scenes.is_relative_to(package) else (package, scenes):
        _digest_tree(digest, root)
    if model is not None:
        saved = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
        mujoco.mj_saveModel(model, None, saved)
        digest.update(saved.tobytes())
    return digest.hexdigest()[:40]


def _version(name: str) -> str:
    """The installed version of distribution `name` ("none": not installed)."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "none"


def _digest_tree(digest, root: Path) -> None:
    """Adds the names and contents of the files under `root` to `digest`."""
    for path in sorted(root.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts:
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())


# ---------------------------------------------------------------- programs


class Stored:
    """A program exported with `jax.export`: called, lowered and compiled like the jitted function
    it was exported from, on the same pytrees. Its jitted wrapper is named `stored_<name>`; `run`
    is the key (`run_key`) of the run it is stored for; the buffers of its arguments `donate`
    (their indices) are handed to it."""

    def __init__(self, name: str, run: str, exported, in_tree, out_tree, donate: tuple = ()):
        self.name, self.run, self.exported = name, run, exported
        self.in_tree, self.out_tree = in_tree, out_tree

        def call(*leaves):
            return exported.call(*leaves)

        call.__name__ = call.__qualname__ = f"stored_{name}"
        ends = np.cumsum([0] + [arg.num_leaves for arg in in_tree.children()])  # per argument
        donated = tuple(i for a in donate for i in range(ends[a], ends[a + 1]))
        options = compiler_options(jax.devices()[0].platform, name)
        self._jitted = jax.jit(call, donate_argnums=donated, compiler_options=options)

    def _leaves(self, args) -> list:
        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self.in_tree:
            raise ValueError(f"stored program {self.name}: arguments {tree}, not {self.in_tree}")
        return leaves

    def __call__(self, *args):
        leaves = self._leaves(args)
        # Inside another trace, a call of the stored program, as a jitted function would be.
        out = (self.exported.call if traced(leaves) else self._jitted)(*leaves)
        return jax.tree_util.tree_unflatten(self.out_tree, out)

    def lower(self, *args):
        return _Lowered(self._jitted.lower(*self._leaves(args)), self.out_tree)


# Custom calls jax.export does not vouch for across versions, which the programs may hold: the
# Triton kernels of one GPU (`core.flood_kernel`, `ppo.fused`). A stored program is read back only by
# the same library versions and device (its key), for which they are the same kernels.
KERNELS = [export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")]


class _Lowered:
    """A lowered `Stored` program, whose compiled form takes and returns the pytrees."""

    def __init__(self, lowered, out_tree):
        self._lowered, self._out_tree = lowered, out_tree

    def compile(self):
        compiled, out_tree = self._lowered.compile(), self._out_tree
        return lambda *args: jax.tree_util.tree_unflatten(
            out_tree, compiled(*jax.tree_util.tree_leaves(args))
        )


def _export(name: str, fn, args) -> tuple[bytes, object, object]:
    """(serialized StableHLO, argument tree, result tree) of `fn(*args)`, exported as a function
    of the leaves (`args`: arrays or ShapeDtypeStructs)."""
    leaves, in_tree = jax.tree_util.tree_flatten(args)
    trees = []

    def flat(*xs):
        out, tree = jax.tree_util.tree_flatten(fn(*jax.tree_util.tree_unflatten(in_tree, xs)))
        trees.append(tree)
        return out

    flat.__name__ = flat.__qualname__ = name
    exported = export.export(jax.jit(flat), disabled_checks=KERNELS)(*leaves)
    return exported.serialize(), in_tree, trees[0]


def _load(name: str, run: str, entry) -> Stored:
    """The `Stored` program of a store entry (bytes, in_tree, out_tree)."""
    blob, in_tree, out_tree = entry
    exported = export.deserialize(bytearray(blob))
    return Stored(name, run, exported, in_tree, out_tree, donate=DONATED.get(name, ()))


def _read(path: Path, name: str, run: str, args) -> Stored | None:
    """The program stored at `path` for `args`' structure; None if there is none, or if the
    file cannot be read back (said on stderr)."""
    try:
        with open(path, "rb") as fh:
            entry = pickle.load(fh)
        stored = _load(name, run, entry["program"])
        if stored.in_tree != jax.tree_util.tree_structure(args):
            raise ValueError("its arguments differ")
        with contextlib.suppress(OSError):  # used now: the last to go (`_prune`)
            os.utime(path)
        return stored
    except FileNotFoundError:
        return None
    except Exception as err:  # noqa: BLE001 (a damaged or foreign file: traced again)
        print(f"jaxnav: {path}: not readable ({err}); tracing the program again", file=sys.stderr)
        return None


def _keep(path: Path, entry: tuple) -> None:
    """Writes `entry` to `path` at once (a reader sees the old file or the new one)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        files.write_atomic(path, pickle.dumps({"program": entry}))
    except Exception as err:  # noqa: BLE001 (not kept: the run goes on, traced next time too)
        print(f"jaxnav: {path}: cannot keep the traced program ({err})", file=sys.stderr)


def program(trainer, run: str, name: str, args) -> Stored | None:
    """The trainer's program `name` (of `Trainer.programs`, exported from `Trainer.parts`) for
    the run of key `run` (`run_of`), on `args` (arrays or ShapeDtypeStructs): read from the
    store, or exported now and kept there. None where the store is off or for a program that
    cannot be exported."""
    if _folder is None or run is None:
        return None
    path = _folder / f"{run}-{name}.program"
    stored = _read(path, name, run, args)
    if stored is not None:
        return stored
    try:
        with lowering((trainer.programs or {}).get(name)):  # as its jitted program lowers
            entry = _export(name, trainer.parts[name], args)
    except Exception as err:  # noqa: BLE001 (not exportable: jit traces it as before)
        line = str(err).splitlines()[0][:200] if str(err) else type(err).__name__
        print(f"jaxnav: the {name} program is traced on every start ({line})", file=sys.stderr)
        return None
    _keep(path, entry)
    _prune(_folder, spare=path)
    return _load(name, run, entry)


def _prune(store: Path, spare: Path) -> None:
    """Removes the programs of `store` used longest ago (by their file's time) until it holds
    at most MAX_BYTES, never `spare` (the one just kept). A file another process removed or
    holds is passed over."""
    found = []
    for path in store.glob("*.program"):
        with contextlib.suppress(OSError):
            info = path.stat()
            found.append((info.st_mtime, info.st_size, path))
    total = sum(size for _, size, _ in found)
    for _, size, path in sorted(found):
        if total <= MAX_BYTES:
            return
        if path != spare:
            with contextlib.suppress(OSError):
                path.unlink()
                total -= size


def run_of(config, env) -> str | None:
    """The key (`run_key`) under which `config`'s run on `env` keeps its programs; None where the
    store is off or with several devices."""
    if _folder is None or jax.device_count() > 1:
        return None
    return run_key(config, getattr(getattr(env, "scene", None), "mj_model", None))
