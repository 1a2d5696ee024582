"""What a long-running jaxnav process shares: Ctrl-C handling, interruptible waits, the
compilation cache.

Ctrl-C (SIGINT) and SIGTERM are honoured from the first instant of `python -m jaxnav.<command>`
(`jaxnav/__init__.py` calls `early_interrupts`, which installs `Interrupts` before jax is imported
and only under those commands): until a command defers them, the process cleans up what it started
(`Interrupts.at_once`) and ends at once with one line and exit status 130, even while XLA compiles
(long calls run in a worker thread: `interruptible`). Training defers them once it has something to
save: the chunk under way finishes and is checkpointed.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a Ctrl-C
COMMANDS = ("jaxnav.train", "jaxnav.evaluate", "jaxnav.export")


class Interrupts:
    """SIGINT/SIGTERM in two phases: at once (clean up, one line, exit 130) until `defer()`, then
    only recorded in `requested` for a loop to stop at its next safe point.

    A context manager: the handlers found on entry are put back on exit. Outside the main thread
    (where Python cannot catch signals) it does nothing.
    """

    def __init__(self, deferred: bool = False):
        self.requested: list[str] = []  # signal names received while deferred
        self.deferred = deferred
        self.note, self.cleanup = "nothing was written", None
        self.on_repeat: Callable[[], str] | None = None  # while deferred: a second signal's note
        self._previous: dict = {}

    def install(self) -> Interrupts:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous.setdefault(sig, signal.signal(sig, self._handle))
        return self

    def __enter__(self) -> Interrupts:
        return self.install()

    def __exit__(self, *exc) -> None:
        for sig, old in self._previous.items():
            signal.signal(sig, old)

    def at_once(self, note: str, cleanup: Callable[[], None] | None = None) -> None:
        """From now on a signal runs `cleanup`, prints `interrupted (SIG...): note` and exits 130."""
        self.note, self.cleanup, self.deferred = note, cleanup, False

    def defer(self, on_repeat: Callable[[], str] | None = None) -> None:
        """From now on a signal is only recorded in `requested`; with `on_repeat`, a second one
        ends the process at once, its line saying `on_repeat()` (what is kept)."""
        self.deferred, self.on_repeat = True, on_repeat

    def _handle(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self.deferred:
            self.requested.append(name)
            if self.on_repeat is None:
                return
            if len(self.requested) == 1:
                print(
                    f"\njaxnav: {name}: stopping after the chunk under way and its checkpoint; "
                    "send it again to stop at once",
                    file=sys.stderr,
                    flush=True,
                )
                return
            self.note, self.cleanup = self.on_repeat(), None
        if self.cleanup is not None:
            self.cleanup()
        end_children()
        sys.stdout.flush()
        print(f"interrupted ({name}): {self.note}", file=sys.stderr, flush=True)
        os._exit(EXIT_INTERRUPTED)


def end_children() -> None:
    """Kills this process's child processes (Linux; elsewhere nothing): a probe a library runs
    while it is imported (`import mujoco` starts pyGLFW's, a Python that prints the library's
    version to a pipe back to this process) would otherwise outlive it and print a
    BrokenPipeError traceback under the one line."""
    me = os.getpid()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:  # pid (comm) state ppid ...; comm may hold spaces and parentheses
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            if ppid == me:
                os.kill(int(stat.parent.name), signal.SIGKILL)
        except (OSError, ValueError, IndexError):
            continue


def interruptible(fn: Callable, *args, waiting: Callable[[float], None] | None = None):
    """`fn(*args)` in a worker thread while the main thread waits, so that a signal handler runs at
    once even while `fn` sits in a long C++ call (an XLA compile); its exception is re-raised.
    `waiting(seconds)` is called every 0.1 s of the wait (e.g. a `Waiting` line)."""
    if threading.current_thread() is not threading.main_thread():
        return fn(*args)
    box: dict = {}

    def work():
        try:
            box["value"] = fn(*args)
        except BaseException as err:  # noqa: BLE001 (handed to the main thread as it is)
            box["error"] = err

    worker = threading.Thread(target=work, daemon=True)
    start = time.perf_counter()
    worker.start()
    while worker.is_alive():
        worker.join(0.1)
        if waiting is not None:
            waiting(time.perf_counter() - start)
    if "error" in box:
        raise box["error"]
    return box["value"]


class Waiting:
    """Tells the user that a long wait (an XLA compile) goes on: `label`, then on a terminal the
    seconds so far on the same line, elsewhere (a log file) a line at 30 s, 1, 2, 4 ... minutes."""

    def __init__(self, label: str, stream=None):
        self.label, self.stream = label, stream or sys.stdout
        self.tty = self.stream.isatty()
        self.shown, self.next_line = 0, 30.0
        print(label, end="" if self.tty else "\n", file=self.stream, flush=True)

    def __call__(self, seconds: float) -> None:
        if self.tty and int(seconds) > self.shown:
            self.shown = int(seconds)
            print(f"\r{self.label} {self.shown} s", end="", file=self.stream, flush=True)
        elif not self.tty and seconds >= self.next_line:
            print(f"{self.label} still running after {seconds:.0f} s", file=self.stream, flush=True)
            self.next_line *= 2

    def end(self) -> None:
        if self.tty:
            print(file=self.stream, flush=True)


def compile_cache(enabled: bool = True) -> Path | None:
    """Turns on JAX's persistent compilation cache for a command, so that a run with the shapes of
    an earlier one skips XLA's compile: in JAX_COMPILATION_CACHE_DIR if the user set it, else
    `$XDG_CACHE_HOME/jaxnav/xla` (~/.cache/jaxnav/xla); and the store of traced training programs
    in its `programs/` folder (`jaxnav.programs`), so that such a run skips tracing too. Returns
    the folder (None: both off, by `enabled=False` or a folder that cannot be made)."""
    import jax

    from jaxnav import programs

    programs.use(None)
    if not enabled:
        jax.config.update("jax_compilation_cache_dir", None)
        return None
    folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not folder:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        folder = Path(base) / "jaxnav" / "xla"
    try:
        Path(folder).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"warning: {folder}: no compilation cache ({err.strerror})", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    programs.use(Path(folder) / "programs")
    return Path(folder)


def quiet_xla_logs() -> None:
    """Keeps XLA's C++ log lines (`slow_operation_alarm ... Very slow compile?`) out of a command's
    terminal: set before jax loads, unless the user set TF_CPP_MIN_LOG_LEVEL or JAXNAV_XLA_LOGS=1.
    Failures still reach the user as Python exceptions."""
    if os.environ.get("JAXNAV_XLA_LOGS", "") not in ("", "0"):
        return
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")


def early_interrupts() -> None:
    """Under `python -m jaxnav.<command>`: Ctrl-C ends the process at once from now on, before jax
    and the command's module are imported (a SIGINT during those imports could be swallowed)."""
    argv = getattr(sys, "orig_argv", [])
    if "-m" in argv[:-1] and argv[argv.index("-m") + 1] in COMMANDS:
        Interrupts().install()
        quiet_xla_logs()
