"""What a benchmark's result JSON says about its run, and writing that JSON: shared by the scripts
of benchmarks/ (`from report import run_info, write_json`; a script's own folder is on its path).

jax is imported only when a device or jax's version is asked for, so that a parent process that
must not hold a device (`scaling.py`) can use it too.
"""

from __future__ import annotations

import datetime
import json
import platform
import sys
from pathlib import Path


def _device() -> str:
    import jax

    device = jax.devices()[0]
    return f"{device.platform}: {device.device_kind}"


def _jax() -> str:
    import jax

    return jax.__version__


FIELDS = {
    "device": _device,  # the first JAX device, "platform: kind", e.g. "gpu: NVIDIA H200"
    "python": platform.python_version,
    "date": lambda: datetime.date.today().isoformat(),
    "jax": _jax,
    "command": lambda: " ".join(sys.argv),  # the command line, as run
}


def run_info(*names: str) -> dict:
    """{name: value} for each of `names`, in that order, from `FIELDS`."""
    return {name: FIELDS[name]() for name in names}


def write_json(path, result: dict) -> None:
    """`result` as indented JSON at `path` (its folder made where missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
