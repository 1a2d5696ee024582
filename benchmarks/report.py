"""What a benchmark's result JSON says about its run, and writing that JSON: shared by the scripts
of benchmarks/ (`from report import run_info, write_json`; a script's own folder is on its path).

jax is imported only when a device or jax's version is asked for, so that a parent process that
must not hold a device (`scaling.py`) can use it too.
"""

from __future__ import annotations

import datetime
import json
import platform
import subprocess
import sys
from pathlib import Path


def _device() -> str:
    import jax

    device = jax.devices()[0]
    return f"{device.platform}: {device.device_kind}"


def _jax() -> str:
    import jax

    return jax.__version__


def _mujoco() -> str:
    import mujoco

    return mujoco.__version__


def _git(*args: str) -> str | None:
    """git's output in the checkout, stripped; None where git failed or is missing."""
    repo = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _commit() -> str:
    return _git("rev-parse", "HEAD") or "unknown"


# What the scripts write themselves (results, pictures, the README's table and the docs' figures):
# not the code measured, so a change there does not make a result dirty.
OUTPUTS = (":(exclude)benchmarks/results", ":(exclude)README.md", ":(exclude)docs")


def _dirty() -> bool | None:
    """Whether the tracked files of the code measured differ from the commit (the result may not
    be reproducible); `OUTPUTS`, which a script may be writing while it runs, are not counted.
    None where git cannot tell (no checkout, no git)."""
    changed = _git("status", "--porcelain", "--untracked-files=no", "--", ".", *OUTPUTS)
    return None if changed is None else bool(changed)


FIELDS = {
    "device": _device,  # the first JAX device, "platform: kind", e.g. "gpu: NVIDIA H200"
    "python": platform.python_version,
    "date": lambda: datetime.date.today().isoformat(),
    "jax": _jax,
    "command": lambda: " ".join(sys.argv),  # the command line, as run
    "commit": _commit,  # git HEAD of the checkout the script ran from
    "dirty": _dirty,  # tracked files changed since that commit
    "mujoco": _mujoco,
}
# Every result says where it came from: `write_json` adds these where a script did not.
ALWAYS = ("command", "commit", "dirty", "date", "python")


def run_info(*names: str) -> dict:
    """{name: value} for each of `names`, in that order, from `FIELDS`."""
    return {name: FIELDS[name]() for name in names}


def write_json(path, result: dict) -> None:
    """`result` as indented JSON at `path` (its folder made where missing), with the `ALWAYS`
    fields it lacks (the command, commit and date of this run)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    result = {**run_info(*(k for k in ALWAYS if k not in result)), **result}
    path.write_text(json.dumps(result, indent=2) + "\n")
