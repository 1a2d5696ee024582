"""Reading and writing the files of jaxnav safely: regular files only and of bounded size, atomic
writes, and the lock of a run folder.

Every reader here refuses what is not a regular file (a FIFO would block forever, `/dev/zero` would
fill memory) and anything over its size limit, with a `FileProblem` whose message names the file.
Every writer writes a temporary file beside its target and renames it into place, so a reader (or a
crash) sees the old content or the new one, never half of either.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import stat
import sys
import uuid
from pathlib import Path

MAX_TEXT_BYTES = 16 * 2**20  # layout, config and metrics files: far larger than any real one
MAX_BINARY_BYTES = 2**30  # checkpoint weights (policy.msgpack)
LOCK = "run.lock"  # in a run folder: flock-held by the process writing it (and its pid)


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


def _read_pid(fd: int) -> int | None:
    with contextlib.suppress(OSError, ValueError):
        return int(os.pread(fd, 64, 0).decode("ascii").strip())
    return None


class RunLock:
    """`run.lock` in a run folder, held with `flock` by the one process that writes the run.

    The kernel releases a flock when its process ends, however it ends (kill -9, a power cut), so
    a lock file left by a dead process is free and the next process takes it, with a warning naming
    the pid the file held; a pid reused by an unrelated live process never blocks a run. Two
    processes that race for the lock: exactly one wins, the other gets a ValueError naming the
    folder and the holder. The pid in the file is for messages only.
    """

    def __init__(self, folder):
        self.file = Path(folder) / LOCK
        self.fd: int | None = None

    def acquire(self) -> None:
        fd = self._locked_fd()
        previous = _read_pid(fd)
        if previous is not None and previous != os.getpid():
            print(
                f"warning: {self.file}: process {previous} no longer holds it; taking the run over",
                file=sys.stderr,
            )
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        except OSError:
            os.close(fd)
            raise
        self.fd = fd
        remove_stale_temps(self.file.parent)

    def _locked_fd(self) -> int:
        """An open fd of `run.lock` holding its flock; the file it names is still the lock file
        (a holder that releases unlinks it: a lock taken on the unlinked file would be no lock)."""
        while True:
            fd = os.open(self.file, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_pid(fd)
                os.close(fd)
                who = f"process {holder}" if holder else "another process"
                raise ValueError(
                    f"{self.file.parent}: in use by {who} (its {LOCK}); wait for it to end "
                    "or stop it first"
                ) from None
            except OSError:
                os.close(fd)
                raise
            try:
                if os.path.samestat(os.fstat(fd), os.stat(self.file)):
                    return fd
            except FileNotFoundError:
                pass
            os.close(fd)

    def release(self) -> None:
        # Taken first: a signal's cleanup that releases it again meanwhile finds nothing to do.
        fd, self.fd = self.fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            self.file.unlink()  # while still holding it: a waiting process retries on the new file
        os.close(fd)


# `write_atomic`'s temporary files of the files a run folder's lock holder rewrites.
_TEMP = re.compile(r"^(config\.json|metrics\.csv)\.(\d+)\.[0-9a-f]{8}\.tmp$")


def remove_stale_temps(folder) -> None:
    """Removes temporary files that a killed rewrite of config.json or metrics.csv left in run
    folder `folder`: only those whose writer (the pid in the name) is gone."""
    with contextlib.suppress(OSError):
        for path in Path(folder).iterdir():
            match = _TEMP.match(path.name)
            if match and not _alive(int(match.group(2))):
                with contextlib.suppress(OSError):
                    path.unlink()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or no pid at all
        return False
    except PermissionError:  # another user's live process
        return True
    return True
