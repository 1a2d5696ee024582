"""Reading and writing the files of jaxnav safely: regular files only and of bounded size, atomic
writes, and the lock of a run folder.

Every reader here refuses what is not a regular file (a FIFO would block forever, `/dev/zero` would
fill memory) and anything over its size limit, with a `FileProblem` whose message names the file.
Every writer writes a temporary file beside its target and renames it into place, so a reader (or a
crash) sees the old content or the new one, never half of either.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import sys
import uuid
from pathlib import Path

MAX_TEXT_BYTES = 16 * 2**20  # layout, config and metrics files: far larger than any real one
MAX_BINARY_BYTES = 2**30  # checkpoint weights (policy.msgpack)
LOCK = "run.lock"  # in a run folder: the pid of the process writing it


class FileProblem(ValueError):
    """A file that cannot be read as asked; `path` and `detail` make the one-line message."""

    def __init__(self, path, detail: str):
        self.path, self.detail = os.fspath(path), detail
        super().__init__(f"{self.path}: {detail}")


# ---------------------------------------------------------------- reading


def _kind(mode: int) -> str:
    kinds = {stat.S_ISDIR: "a directory", stat.S_ISFIFO: "a FIFO (named pipe)"}
    kinds |= {stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device"}
    kinds |= {stat.S_ISSOCK: "a socket"}
    return next((name for test, name in kinds.items() if test(mode)), "not a regular file")


def read_bytes(path, limit: int = MAX_TEXT_BYTES) -> bytes:
    """The content of regular file `path` (at most `limit` bytes), or FileProblem naming it.

    Opened without blocking and checked with fstat before reading, so a FIFO or a device is
    refused at once, whatever the path was swapped for after a check.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise FileProblem(path, "no such file") from None
    except OSError as err:
        raise FileProblem(path, f"cannot read ({err.strerror})") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise FileProblem(path, f"is {_kind(mode)}, expected a regular file")
    with os.fdopen(fd, "rb") as fh:
        try:
            data = fh.read(limit + 1)
        except OSError as err:
            raise FileProblem(path, f"cannot read ({err.strerror})") from None
    if len(data) > limit:
        raise FileProblem(path, f"larger than {limit // 2**20} MB: not a jaxnav file")
    return data


def read_text(path, limit: int = MAX_TEXT_BYTES) -> str:
    """A regular UTF-8 text file (a byte-order mark is tolerated), or FileProblem naming it."""
    try:
        return read_bytes(path, limit).decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise FileProblem(path, f"not UTF-8 text ({err.reason})") from None


def parse_json(text: str, path, **kwargs):
    """JSON `text` read from `path`; any way it can fail is a FileProblem naming the file."""
    try:
        return json.loads(text, **kwargs)
    except json.JSONDecodeError as err:
        detail = f"invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}"
        raise FileProblem(path, detail) from None
    except RecursionError:
        raise FileProblem(path, "invalid JSON: nested too deeply") from None
    except ValueError as err:  # e.g. an integer of more than 4300 digits
        raise FileProblem(path, f"invalid JSON: {' '.join(str(err).split())}") from None


def read_json(path, **kwargs):
    """The JSON value in regular file `path`, or FileProblem naming the file."""
    return parse_json(read_text(path), path, **kwargs)


# ---------------------------------------------------------------- writing


def write_atomic(path, data: str | bytes) -> None:
    """Writes `data` to a temporary file beside `path`, syncs it, then renames it over `path`."""
    target = os.fspath(path)
    tmp = f"{target}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    raw = data.encode("utf-8") if isinstance(data, str) else data
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # umask applies
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def check_writable(folder, flag: str) -> None:
    """Creates and removes a file in `folder` (made if missing): a UsageError-style ValueError
    naming `flag` and the folder now, rather than after minutes of work."""
    folder = Path(folder)
    probe = folder / f".jaxnav-probe-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.touch(exist_ok=False)
        probe.unlink()
    except OSError as err:
        raise ValueError(f"{flag} {folder}: cannot write there ({err.strerror or err})") from None


# ---------------------------------------------------------------- the lock of a run folder


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


class RunLock:
    """`run.lock` in a run folder: the pid of the one process that writes it.

    A lock whose process is gone (a kill -9, a power cut) is taken over with a warning; a live one
    is a ValueError naming the folder and the process.
    """

    def __init__(self, folder):
        self.file = Path(folder) / LOCK

    def acquire(self) -> None:
        try:
            fd = os.open(self.file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            self._take_over()
            return
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{os.getpid()}\n")

    def _take_over(self) -> None:
        try:
            pid = int(read_text(self.file, 64).strip())
        except (FileProblem, ValueError):
            pid = None
        if pid is not None and pid != os.getpid() and _alive(pid):
            raise ValueError(
                f"{self.file.parent}: in use by process {pid} (its {LOCK}); wait for it to end "
                f"or stop it first"
            )
        owner = f"process {pid}" if pid is not None else "an unreadable lock"
        print(f"warning: {self.file}: {owner} is gone; taking the run over", file=sys.stderr)
        write_atomic(self.file, f"{os.getpid()}\n")

    def release(self) -> None:
        with contextlib.suppress(OSError):
            self.file.unlink()
