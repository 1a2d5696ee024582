"""The training metrics log of a run folder: `metrics.csv` and TensorBoard events in `tb/`.

One row per update. Its columns come from the task's declared metrics: `update`, `env_steps`,
`episode_reward`, `episode_length`, then one column per task metric (e.g. `collision` for `avoid`:
the share of finished episodes that collided), then the PPO losses and the speed.

Nothing already logged is lost: on resume the file is cut back to the checkpoint's update by writing
the kept rows to a temporary file renamed over it (never truncated in place), then rows are
appended and flushed after every chunk.
"""

from __future__ import annotations

import csv
import io
import math
import sys
from pathlib import Path

import numpy as np

from jaxnav.io.files import FileProblem, read_text, write_atomic

# metrics.csv grows by ~140 bytes an update: 256 MB is about 1.9 M updates, far beyond any run.
MAX_METRICS_BYTES = 256 * 2**20

LOSSES = ("total_loss", "policy_loss", "value_loss", "entropy", "approx_kl")
_LOSS_KEYS = {"total_loss": "total"}  # metrics key of a column where the two differ
_INTEGER = ("update", "env_steps", "steps_per_second")


def columns(metric_names) -> tuple[str, ...]:
    """The CSV header for a task with `metric_names`."""
    head = ("update", "env_steps", "episode_reward", "episode_length", *metric_names)
    return (*head, *LOSSES, "steps_per_second", "elapsed_s")


def chunk_rows(metrics, fields, first_update, batch_size, rate, elapsed) -> list[dict]:
    """CSV rows of one chunk's metrics (arrays [updates_per_chunk]); skipped updates left out."""
    rows = []
    for i in np.flatnonzero(metrics["live"]):
        update = first_update + len(rows) + 1
        row = {
            "update": update,
            "env_steps": update * batch_size,
            "steps_per_second": round(rate),
            "elapsed_s": round(elapsed, 2),
        }
        for key in fields[2:-2]:
            row[key] = float(metrics[_LOSS_KEYS.get(key, key)][i])
        rows.append(row)
    return rows


def read_rows(path: Path, upto: int | None = None) -> list[dict]:
    """The rows of an existing metrics.csv (numbers; empty cells nan); [] if there is none.

    With `upto` (a checkpoint's update), the rows up to that update: whatever follows it is
    dropped unread, as a resume from that checkpoint writes those updates anew (a half row that a
    full disk left included). A row before it that is not numbers is a FileProblem naming the
    file, its line and column.
    """
    if not Path(path).exists():
        return []
    reader = csv.DictReader(io.StringIO(read_text(path, MAX_METRICS_BYTES), newline=""))
    rows = []
    for row in reader:
        if upto is not None and rows and rows[-1]["update"] >= upto:
            break
        try:
            rows.append({k: _cell(k, v) for k, v in row.items()})
        except (TypeError, ValueError) as err:
            raise FileProblem(path, f"line {reader.line_num}: {err}; fix or delete it") from None
    return rows


def _cell(key, value):
    if key is None or value is None:
        raise ValueError("the row has a different number of cells than the header")
    try:
        return int(value) if key in _INTEGER else float(value or "nan")
    except ValueError:
        raise ValueError(f"column {key}: not a number: {value[:40]!r}") from None


def _csv_text(fields, rows) -> str:
    buffer = io.StringIO(newline="")
    writer = csv.DictWriter(buffer, fields)
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


class MetricsLog:
    """metrics.csv (`rows` kept, then appended) and TensorBoard events in out/tb; with
    `write=False` (the processes of a run other than process 0) the rows are kept in memory only."""

    def __init__(self, out: Path, fields: tuple[str, ...], rows: list[dict], write: bool = True):
        self.out, self.fields, self.rows, self.write = out, fields, list(rows), write
        self.fh = self.tb = None

    def __enter__(self):
        if not self.write:
            return self
        file = self.out / "metrics.csv"
        text = _csv_text(self.fields, self.rows)
        if not file.exists() or read_text(file, MAX_METRICS_BYTES) != text:  # atomically: the
            write_atomic(file, text)  # old rows stay on disk until the kept ones replace them
        self.fh = open(file, "a", newline="")
        self.writer = csv.DictWriter(self.fh, self.fields)
        self.tb = _tensorboard(self.out / "tb")
        return self

    def add(self, rows: list[dict]) -> None:
        self.rows += rows
        if self.fh is None:
            return
        self.writer.writerows(rows)
        self.fh.flush()
        for row in rows if self.tb else ():
            for key in self.fields[2:]:
                if not math.isnan(row[key]):
                    self.tb.add_scalar(f"train/{key}", row[key], row["env_steps"])
        if self.tb:
            self.tb.flush()

    def last(self, key) -> float:
        """The newest finite value of column `key` (nan if none)."""
        values = [r[key] for r in self.rows if not math.isnan(r[key])]
        return values[-1] if values else math.nan

    def __exit__(self, *exc):
        if self.fh is not None:
            self.fh.close()
        if self.tb:
            self.tb.close()


def _tensorboard(logdir: Path):
    """A TensorBoard writer for `logdir`, or None without tensorboardX (its logs are optional; the
    CSV always exists). tensorboardX imports torch where it is installed, only to accept torch
    tensors, which jaxnav never logs; on a GPU host that import took seconds of a warm start
    (docs/results.md, "Start-up"), so unless torch is already loaded it is imported without it."""
    blocked = "torch" not in sys.modules
    if blocked:
        sys.modules["torch"] = None  # `import torch` raises ImportError: tensorboardX goes without
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    finally:
        if blocked:
            del sys.modules["torch"]
    return SummaryWriter(str(logdir))
