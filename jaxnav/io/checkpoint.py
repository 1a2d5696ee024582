"""Run folders and checkpoints: atomic, checksummed writes, restore by tree path, and the one policy
loader (`read_policy`, used by `load_policy` and by `jaxnav.export`).

A run folder holds `config.json`, `metrics.csv`, `reward_curve.png` and `checkpoints/update_NNNNNN/`,
each checkpoint with `policy.msgpack` (network weights and observation normaliser: all a robot needs),
`train_state.npz` (the whole TrainState, one entry per leaf named by its tree path, e.g.
`.params['params']['actor']['Dense_0']['kernel']`, plus `format_version`), `config.json`, `meta.json`
and, written last, `checksums.json` (sha256 of each of those). A checkpoint is written in a hidden
temporary folder and renamed into place, so a crash mid-write leaves the previous ones intact.
Hand-written rather than orbax: four plain files (numpy, msgpack, JSON) that numpy alone can read,
where orbax adds tensorstore (~66 MB) and async machinery for a few MB of state (in a run of several
processes, process 0 writes the state gathered from all: `jaxnav.distributed.to_host`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import tempfile
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxnav.io.files import FileProblem, read_json

CKPT_DIR = "checkpoints"
PREFIX = "update_"
FORMAT_VERSION = 2  # 1: train_state.npz by flatten order (leaf_00000, ...), no checksums
CHECKSUMS = "checksums.json"
# Found in a checkpoint folder, never directly in a run folder (which has config.json too).
CHECKPOINT_FILES = ("policy.msgpack", "train_state.npz", CHECKSUMS)


class CheckpointError(ValueError):
    """A checkpoint or run folder that cannot be used; the message names the path."""


# ---------------------------------------------------------------- writing


def save(run_dir: Path, ts, config, meta: dict, keep: int = 3) -> Path:
    """Writes checkpoint `update_<ts.update>` atomically; keeps the newest `keep` of them."""
    update = int(ts.update)
    target = path_of(run_dir, update)
    root = target.parent
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=root))
    try:
        host = jax.device_get(ts)
        policy = {"params": host.params, "obs_stats": serialization.to_state_dict(host.obs_stats)}
        (tmp / "policy.msgpack").write_bytes(
            serialization.msgpack_serialize(serialization.to_state_dict(policy))
        )
        save_tree(tmp / "train_state.npz", host)
        (tmp / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
        (tmp / "meta.json").write_text(json.dumps({"update": update, **meta}, indent=2))
        sums = {f.name: _sha256(f) for f in sorted(tmp.iterdir())}
        (tmp / CHECKSUMS).write_text(json.dumps(sums, indent=2))
        for f in tmp.iterdir():  # data on disk before the rename makes it visible
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _prune(root, target, keep)
    return target


def path_of(run_dir: Path, update: int) -> Path:
    """The folder of the checkpoint after `update` updates in run folder `run_dir`."""
    return Path(run_dir) / CKPT_DIR / f"{PREFIX}{update:06d}"


def remove_stale_writes(run_dir: Path) -> None:
    """Removes the temporary folders of checkpoint writes that never finished (killed processes);
    call it only while holding the run's lock, when no other write can be under way."""
    for stale in (Path(run_dir) / CKPT_DIR).glob(".tmp-*"):
        shutil.rmtree(stale, ignore_errors=True)


def _prune(root: Path, newest: Path, keep: int) -> None:
    """Removes all but the newest `keep` checkpoints, and temporary folders of crashed writes."""
    for old in list_checkpoints(root.parent)[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    written = newest.stat().st_mtime
    for stale in root.glob(".tmp-*"):  # older than the newest checkpoint: no write is using them
        if stale.stat().st_mtime < written:
            shutil.rmtree(stale, ignore_errors=True)


def save_tree(file: Path, tree) -> None:
    """Writes every leaf of `tree` into the .npz `file`, named by its tree path (`keystr`)."""
    named = jax.tree_util.tree_flatten_with_path(tree)[0]
    arrays = {jax.tree_util.keystr(path): np.asarray(x) for path, x in named}
    with open(file, "wb") as fh:  # a handle: np.savez would append .npz to other names
        np.savez(fh, format_version=np.int32(FORMAT_VERSION), **arrays)


def _sha256(file: Path) -> str:
    with open(file, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


# ---------------------------------------------------------------- finding and checking


def list_checkpoints(run_dir: Path) -> list[Path]:
    """Checkpoints of a run, oldest first (intact or not: see `verify`)."""
    root = Path(run_dir) / CKPT_DIR
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.name.startswith(PREFIX) and p.is_dir())


def verify(ckpt: Path) -> None:
    """Raises CheckpointError naming what of `ckpt` its checksums.json disowns: the one file whose
    sha256 differs (corrupt), or checksums.json itself when several differ (another checkpoint's
    checksums, or damaged: one corrupt file is likely, several at once are not)."""
    file = ckpt / CHECKSUMS
    if not file.exists():
        raise CheckpointError(
            f"{file}: missing (an incomplete checkpoint, or written by an older jaxnav (format 1))"
        )
    try:
        sums = read_json(file)
    except FileProblem as err:
        raise CheckpointError(str(err)) from None
    if not isinstance(sums, dict):
        raise CheckpointError(f"{file}: not a JSON object of file name -> sha256")
    differ = [name for name, digest in sums.items() if _digest(ckpt / name) != digest]
    if len(differ) > 1:
        raise CheckpointError(
            f"{file}: does not match {', '.join(differ)} (of {len(sums)} files): a checksums "
            "file of another checkpoint, or damaged (or several files are)"
        )
    if differ:
        raise CheckpointError(f"{ckpt / differ[0]}: corrupt (its sha256 differs from {CHECKSUMS})")


def _digest(file: Path) -> str:
    """The sha256 of `file`; an unreadable one is a CheckpointError naming it."""
    try:
        return _sha256(file)
    except OSError as err:
        raise CheckpointError(f"{file}: unreadable ({one_line(err)})") from None


def resolve(path: str | os.PathLike) -> Path:
    """A checkpoint folder from a run folder (its newest intact checkpoint) or a checkpoint folder.

    A corrupt newest checkpoint is skipped with a one-line warning on stderr. When none is intact
    the newest is returned: loading it raises the error that names what is wrong.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint or run folder")
    if not (path / CKPT_DIR).is_dir() and (
        path.name.startswith(PREFIX) or any((path / f).exists() for f in CHECKPOINT_FILES)
    ):
        return path
    found = list_checkpoints(path)
    if not found:
        raise CheckpointError(
            f"{path}: no checkpoint in this folder (expected {CKPT_DIR}/{PREFIX}*)"
        )
    problem = None
    for ckpt in reversed(found):
        try:
            verify(ckpt)
        except CheckpointError as err:
            problem = problem or err
            continue
        if problem is not None:
            print(f"warning: {problem}; using the previous checkpoint {ckpt}", file=sys.stderr)
        return ckpt
    return found[-1]


def one_line(err: BaseException) -> str:
    return " ".join(f"{type(err).__name__}: {err}".split())


# ---------------------------------------------------------------- reading


def load_meta(ckpt: Path) -> dict:
    """meta.json of a checkpoint ({"update", "env_steps", "elapsed_s"}); errors name the file."""
    file = Path(ckpt) / "meta.json"
    try:
        meta = read_json(file)
    except FileProblem as err:
        raise CheckpointError(str(err)) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("update"), int):
        raise CheckpointError(f"{file}: not a JSON object with an integer 'update'")
    return meta


def load_tree(file: Path, template):
    """The tree saved by `save_tree` in `file`, shaped (and placed) like `template`, each leaf
    found by its path.

    A missing or extra entry, or a leaf whose shape or dtype differs, raises CheckpointError naming
    the file and the first such entry.
    """
    return _load(file, template)[0]


def _load(file: Path, template, renewable: str | None = None):
    """(`load_tree`'s tree, None); with `renewable`, a tree path (e.g. ".env_state"), any
    difference within that part keeps the whole part as `template` has it, and the second item
    says what differed there first (None: the saved part fitted and was restored)."""
    try:
        with np.load(file, allow_pickle=False) as data:
            saved = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise CheckpointError(f"{file}: unreadable ({one_line(err)})") from None
    version = saved.pop("format_version", None)
    if version is None and any(k.startswith("leaf_") for k in saved):
        raise CheckpointError(
            f"{file}: written by an older jaxnav (format 1); this one reads format "
            f"{FORMAT_VERSION}: start a new run (its policy.msgpack still holds the weights)"
        )
    if version is None or int(version) != FORMAT_VERSION:
        raise CheckpointError(f"{file}: format {version}; this jaxnav reads {FORMAT_VERSION}")
    named, treedef = jax.tree_util.tree_flatten_with_path(template)
    template_leaves = {jax.tree_util.keystr(path): leaf for path, leaf in named}

    def within(key: str) -> bool:  # in the renewable part
        if renewable is None:
            return False
        return key == renewable or key.startswith((renewable + ".", renewable + "["))

    mine = {k: leaf for k, leaf in template_leaves.items() if within(k)}
    renewed = _mismatch({k: v for k, v in saved.items() if within(k)}, mine) if mine else None
    wanted = template_leaves
    if renewed is not None:  # the template's part stands in for the saved one
        saved = {k: v for k, v in saved.items() if not within(k)}
        wanted = {k: leaf for k, leaf in template_leaves.items() if not within(k)}
    problem = _mismatch(saved, wanted)
    if problem is not None:
        if problem.startswith(("no entry ", "unexpected entry ")):  # other names
            problem += (
                " (the saved state does not match this configuration, or an older jaxnav wrote "
                "it: evaluate and export still read the run's policy.msgpack)"
            )
        raise CheckpointError(f"{file}: {problem}")
    leaves = [
        leaf if renewed is not None and k in mine else _place(saved[k], leaf)
        for k, leaf in template_leaves.items()
    ]
    return jax.tree_util.tree_unflatten(treedef, leaves), renewed


def _mismatch(saved: dict, wanted: dict) -> str | None:
    """What first differs between the `saved` arrays and the `wanted` leaves, by entry name (the
    message's tail after the file name); None where every entry matches in shape and dtype."""
    missing = [k for k in wanted if k not in saved]
    extra = sorted(set(saved) - set(wanted))
    if missing or extra:
        return f"no entry {missing[0]}" if missing else f"unexpected entry {extra[0]}"
    for key, leaf in wanted.items():
        dtype = leaf.dtype if hasattr(leaf, "dtype") else np.asarray(leaf).dtype
        want = (np.shape(leaf), np.dtype(dtype))
        if (saved[key].shape, saved[key].dtype) != want:
            return (
                f"{key} is {saved[key].dtype}{list(saved[key].shape)}, "
                f"this configuration needs {want[1]}{list(want[0])}"
            )
    return None


def _place(value: np.ndarray, like):
    """`value` laid out as `like` where that is a placed jax.Array (sharded over several
    processes, each keeps only its own part), else a plain device array."""
    sharding = getattr(like, "sharding", None)
    if not isinstance(sharding, jax.sharding.Sharding):
        return jnp.asarray(value)
    return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])


def restore_train_state(ckpt: Path, template):
    """The TrainState saved in `ckpt`, shaped like `template` (a fresh `Trainer.init` result).

    The robots' state (`env_state`: poses, episodes under way) is saved so that a resumed run
    goes on exactly as an unbroken one; where it no longer fits (another jaxnav's robots' state,
    e.g. one whose physics state had other fields), the robots start new episodes from
    `template`'s and everything learnt (weights, optimiser, normaliser, RNG, update count) is
    restored, with a warning."""
    ts, renewed = _load(ckpt / "train_state.npz", template, renewable=".env_state")
    verify(ckpt)  # after the content checks: their messages name the field at fault
    if renewed is not None:
        print(
            f"warning: {ckpt}: the robots' saved state does not fit this jaxnav's ({renewed}); "
            "the robots start new episodes, everything learnt is restored",
            file=sys.stderr,
            flush=True,
        )
    return ts
