"""Training as a library: `train(...)` (the Python API, `jaxnav.train`), `run` and `resume` of a
run folder (config, metrics CSV, reward curve, checkpoints), and the checks before anything is
written. `python -m jaxnav.train` is its command line (`jaxnav.cli.train`).

Several processes (hosts): each runs the same call with `jax.distributed` started (the command
line does it); the robots are split over every device of every process, and process 0 writes the
run folder, which must be on a filesystem all hosts share for `resume` (see jaxnav/distributed.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import threading
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jaxnav import distributed, programs, runs
from jaxnav.io import checkpoint, files, runlog
from jaxnav.io.layouts import layout_to_dict, load_layouts, parse_layouts
from jaxnav.ppo.config import derived_minibatch, preset
from jaxnav.ppo.train import make_train
from jaxnav.process import Interrupts, Waiting, interruptible
from jaxnav.runconfig import GROUPS, RunConfig, group_class
from jaxnav.tasks.registry import make_env, task_defaults


def build_config(
    preset_name="cpu", seed=0, layout_files=None, overrides=None, env="avoid"
) -> RunConfig:
    """A RunConfig of task `env` from a preset, layout files and {group: {field: value}}
    overrides (the randomisation's start from the task's training distribution)."""
    overrides = overrides or {}
    task = task_defaults(env, preset_name)
    ppo = {**task.get("ppo", {}), **overrides.get("ppo", {})}
    if "minibatch_size" not in overrides.get("ppo", {}):  # follows --num-envs, --rollout-length
        base = preset(preset_name, **task.get("ppo", {}))
        sizes = [ppo.get(k, getattr(base, k)) for k in ("num_envs", "rollout_length")]
        if min(sizes) >= 1 and sizes != [base.num_envs, base.rollout_length]:
            ppo["minibatch_size"] = derived_minibatch(base, *sizes)
    groups = {"ppo": preset(preset_name, **ppo)}
    defaults = {"randomize": RunConfig.randomize, "robot": RunConfig.robot}
    for attr, cls, _ in GROUPS[1:]:
        cls = group_class(attr, cls, env)
        base = defaults.get(attr) or cls()
        fields = {**task.get(attr, {}), **overrides.get(attr, {})}
        groups[attr] = dataclasses.replace(base, **fields)
    layouts = None
    if layout_files:
        radius = getattr(groups["task"], "success_radius", None)  # goal tasks: goals off the spawn
        rooms = load_layouts(layout_files, success_radius=radius)
        layouts = tuple(layout_to_dict(room) for room in rooms)
    return RunConfig(**groups, layouts=layouts, seed=seed, preset=preset_name, env=env)


def make_run_env(config: RunConfig):
    layouts = None if config.layouts is None else parse_layouts(list(config.layouts), "config")
    return make_env(config.env, layouts, randomize=config.randomize, **config.env_kwargs())


class Interrupted(Exception):
    """Training stopped on SIGINT/SIGTERM after writing a checkpoint."""


class RunFailed(Exception):
    """Training stopped by the machine (disk full, no permission, no memory); the one-line message
    names the path and says what was saved."""


# ---------------------------------------------------------------- before anything is written


def _meminfo_available() -> int | None:
    """MemAvailable of /proc/meminfo, bytes (None where there is none)."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    return None


def memory_check(config: RunConfig, env, shapes) -> None:
    """Refuses a --num-envs whose robots cannot fit in memory, before anything is written.

    Bytes per robot come from the `shapes` of a fresh TrainState (`jax.eval_shape`: nothing is
    allocated) and of the rollout buffers, plus the network's own (`--hidden`); compared with
    MemAvailable on the CPU (all devices share it) or the first accelerator's `bytes_limit`. Where
    neither is known, nothing is checked.
    """
    cfg, devices = config.ppo, jax.local_devices()
    state = _bytes(shapes.env_state) / cfg.num_envs
    # The network on every device: weights, optimizer state, and the gradient and update of a step.
    model = _bytes(shapes.params) * 3 + _bytes(shapes.opt_state)
    # Activations per robot (actor and critic): acting, and its share of a minibatch (forward and
    # backward; a minibatch is num_envs x rollout_length / num_minibatches samples).
    width = 4 * 2 * sum(cfg.hidden)
    width *= 1 + 2 * cfg.rollout_length / cfg.num_minibatches
    # A Transition per step: raw and normalised obs, 6 scalars, the episode sums (float32/int32).
    step = 4 * (2 * env.observation_size + 8 + len(env.metric_names))
    # The state, the next one and a step's auto-reset merge, and with `reset_ahead` a rollout's
    # draws (rollout_length x reset_pool episodes over num_envs robots); the rollout and its
    # shuffled copy.
    drawn = cfg.rollout_length * cfg.reset_pool / cfg.num_envs if cfg.reset_ahead else 0.0
    per_robot = (3 + drawn) * state + 2 * cfg.rollout_length * step + width
    # `share`: robots per memory = num_envs / share. The CPU's devices share this process's memory
    # (one process per host); an accelerator holds its own device's robots.
    if devices[0].platform == "cpu":
        available, share = _meminfo_available(), jax.process_count()
        where = "free CPU memory (MemAvailable)"
    else:
        stats = devices[0].memory_stats() or {}
        available, share = stats.get("bytes_limit"), jax.device_count()
        where = f"memory of one {devices[0].device_kind}"
    if available is None or per_robot * cfg.num_envs / share + model <= available:
        return
    if model > available / 2:
        raise ValueError(
            f"--hidden {' '.join(map(str, cfg.hidden))}: the network alone needs about "
            f"{model / 1e9:.1f} GB (weights, optimizer state, gradients) but the {where} is "
            f"{available / 1e9:.1f} GB; choose smaller layers"
        )
    available -= model
    fits = int(available * share / per_robot) // jax.device_count() * jax.device_count()
    raise ValueError(
        f"--num-envs {cfg.num_envs}: needs about {per_robot * cfg.num_envs / share / 1e9:.1f} GB "
        f"({per_robot / 1e3:.1f} kB per robot) but the {where} holds {available / 1e9:.1f} GB "
        "beside the network; "
        f"the largest --num-envs that fits is about {fits:,}"
    )


def _bytes(tree) -> int:
    return sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(tree))


# What a run writes at the top of its folder; an interrupted start removes these and nothing else.
RUN_ENTRIES = ("config.json", "metrics.csv", "tb", "reward_curve.png", checkpoint.CKPT_DIR)


def check_new_out(out: Path) -> None:
    """Refuses an `--out` that holds anything: a run (continue it with --resume) or files that
    are not jaxnav's, which a new run must never overwrite or delete."""
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    try:
        entries = sorted(p.name for p in out.iterdir())
    except OSError as err:
        raise ValueError(f"--out {out}: cannot read the folder ({err.strerror})") from None
    if not entries:
        return
    if checkpoint.list_checkpoints(out) or _is_run_config(out / "config.json"):
        raise ValueError(
            f"--out {out}: already holds a training run; use --resume {out} or choose another folder"
        )
    shown = ", ".join(repr(name) for name in entries[:3]) + (", ..." if len(entries) > 3 else "")
    raise ValueError(
        f"--out {out}: not empty and not a jaxnav run ({len(entries)} entries: {shown}); "
        "choose a new or empty folder"
    )


def _is_run_config(path: Path) -> bool:
    try:
        runs.load_config(path.parent)
    except (ValueError, OSError, KeyError, TypeError):
        return False
    return True


class _RunFolder:
    """A run folder as this process starts it: the lock, then config.json.

    `remove()` takes back what a failed or interrupted start wrote while no checkpoint exists: for
    a new run (`fresh`), the entries of `RUN_ENTRIES` that this process created, then the folder if
    this process made it and nothing else is in it; a resumed run keeps everything. With
    `write=False` (processes other than 0 of a run) it touches nothing.
    """

    def __init__(self, out: Path, config: RunConfig, write: bool = True, fresh: bool = True):
        self.out, self.config, self.write, self.fresh = out, config, write, fresh
        self.lock = files.RunLock(out)
        self.made, self.found = False, set()

    def create(self) -> None:
        if not self.write:
            return
        try:
            self.made = not self.out.exists()
            self.out.mkdir(parents=True, exist_ok=True)
            self.found = {p.name for p in self.out.iterdir()}
            self.lock.acquire()
            files.write_atomic(
                self.out / "config.json", json.dumps(self.config.to_dict(), indent=2)
            )
        except OSError as err:
            self.remove()
            flag = "--out" if self.fresh else "--resume"
            raise ValueError(
                f"{flag} {self.out}: cannot write the run folder ({err.strerror or err})"
            ) from None

    def remove(self) -> None:
        if self.write and self.fresh and not checkpoint.list_checkpoints(self.out):
            for name in set(RUN_ENTRIES) - self.found:
                path = self.out / name
                with contextlib.suppress(OSError):
                    if path.is_dir() and not path.is_symlink():
                        shutil.rmtree(path)
                    elif path.exists() or path.is_symlink():
                        path.unlink()
        self.release()
        if self.write and self.fresh and self.made:
            with contextlib.suppress(OSError):
                self.out.rmdir()  # only if empty: never what someone else put there

    def release(self) -> None:
        if self.write:
            self.lock.release()


# ---------------------------------------------------------------- starting and continuing


def run(
    config: RunConfig,
    out: Path,
    progress: bool = True,
    stop: Interrupts | None = None,
    fresh: bool = True,
) -> Path:
    """Trains `config` into run folder `out`; returns the final checkpoint folder.

    A new run (`fresh`) needs `out` missing or empty. The env is built and the memory need checked
    before anything is written; a new run that fails or is interrupted before its first checkpoint
    removes what it wrote, and nothing else. `fresh=False` starts a run folder that holds only its
    config.json (a run killed before its first checkpoint), which is never removed. `stop` is the
    command line's `Interrupts` (None: the loop listens to SIGINT/SIGTERM itself once training runs).
    """
    out = Path(out)
    folder = _RunFolder(out, config, write=distributed.is_main(), fresh=fresh)
    created = False
    try:
        if fresh and distributed.is_main():
            check_new_out(out)
        env, trainer = interruptible(_build, config)
        key, since = jax.random.PRNGKey(config.seed), time.perf_counter()

        def check(shapes):  # before anything compiles: no compile outlives a refused start
            nonlocal created
            memory_check(config, env, shapes)
            folder.create()
            created = True
            if stop is not None:  # from the folder's first instant, a signal takes it back
                stop.at_once(_start_note(folder), folder.remove)
            distributed.ready()  # every process's start went well

        trainer, _, ahead = interruptible(
            lambda: find_programs(trainer, config, env, key, check=check)
        )
        compiling = _Compiling(since) if ahead else None
        ts = interruptible(trainer.init, key, waiting=compiling)
        args = (trainer, ts, [], 0.0, progress, stop, env.metric_names, compiling)
        return _loop(config, out, *args)
    except BaseException:
        if created:  # (not a folder that another run holds)
            folder.remove()
        raise
    finally:
        if created:
            folder.release()


def _start_note(folder: _RunFolder) -> str:
    """What an interrupt before the first checkpoint leaves (the `interrupted (...)` line)."""
    out = folder.out
    if not folder.fresh:
        return f"nothing was lost; continue with: python -m jaxnav.train --resume {out}"
    if folder.made:
        return f"removed the unfinished run folder {out}"
    return f"removed what this run had written in {out}; nothing else there was touched"


def _build(config: RunConfig):
    env = make_run_env(config)
    return env, make_train(config.ppo, env)


def _run_config(out: Path, ckpt: Path) -> RunConfig:
    """The run's config.json (the one source of its budget), checked against the checkpoint's copy:
    they may differ in ppo.total_steps only."""
    if not (out / "config.json").exists():
        return runs.load_config(ckpt)
    config, saved = runs.load_config(out), runs.load_config(ckpt)
    mine, theirs = config.to_dict(), saved.to_dict()
    mine["ppo"]["total_steps"] = theirs["ppo"]["total_steps"]
    differ = [k for k in mine if mine[k] != theirs[k]]
    if differ:
        key = differ[0]
        if isinstance(mine[key], dict):
            key += "." + next(k for k in mine[key] if mine[key][k] != theirs[key].get(k))
        raise checkpoint.CheckpointError(
            f"{out / 'config.json'}: {key} differs from the checkpoint's {ckpt / 'config.json'}; "
            "only ppo.total_steps may change (restore the run's config.json)"
        )
    return config


def resume(
    out: Path,
    total_steps: int | None = None,
    progress: bool = True,
    stop: Interrupts | None = None,
) -> Path:
    """Continues the run in `out` from its latest checkpoint, optionally to a new step budget.

    A run folder with config.json but no checkpoint yet (a start killed early) starts from its
    config.json.
    """
    out = Path(out)
    if not checkpoint.list_checkpoints(out) and (out / "config.json").is_file():
        config = _with_budget(runs.load_config(out), total_steps)
        print(f"jaxnav: {out} has no checkpoint yet; starting it from its config.json", flush=True)
        return run(config, out, progress, stop, fresh=False)
    main, lock, locked = distributed.is_main(), files.RunLock(out), False
    try:
        ckpt, config, meta = _resume_point(out, total_steps)  # every process reads it
        env, trainer = interruptible(_build, config)
        if stop is not None:  # from the lock's first instant, a signal releases it
            note = f"nothing was lost; continue with: python -m jaxnav.train --resume {out}"
            stop.at_once(note, lock.release)  # a lock not (yet) taken: releases nothing
        if main:
            try:
                lock.acquire()
                locked = True
                checkpoint.remove_stale_writes(out)
                files.write_atomic(out / "config.json", json.dumps(config.to_dict(), indent=2))
            except OSError as err:
                raise RunFailed(
                    f"{err.filename or out}: cannot write ({err.strerror or err}); the run is as "
                    "it was: free space or fix permissions, then continue with: "
                    f"python -m jaxnav.train --resume {out}"
                ) from None
        distributed.ready()
        key, since = jax.random.PRNGKey(config.seed), time.perf_counter()
        trainer, _, ahead = interruptible(find_programs, trainer, config, env, key)
        compiling = _Compiling(since) if ahead else None
        template = interruptible(trainer.init, key, waiting=compiling)
        ts = checkpoint.restore_train_state(ckpt, template)
        rows = runlog.read_rows(out / "metrics.csv", upto=meta["update"]) if main else []
        elapsed = meta.get("elapsed_s", 0.0)
        args = (trainer, ts, rows, elapsed, progress, stop, env.metric_names, compiling)
        return _loop(config, out, *args)
    finally:
        if locked:
            lock.release()


def _resume_point(out: Path, total_steps: int | None) -> tuple[Path, RunConfig, dict]:
    """(checkpoint, config with the new budget, its meta.json) of the run in `out`; read-only."""
    ckpt = checkpoint.resolve(out)
    config = _run_config(out, ckpt)
    meta = checkpoint.load_meta(ckpt)
    done = meta["update"] * config.ppo.batch_size
    if total_steps is not None and total_steps < done:
        raise ValueError(
            f"--total-steps {total_steps}: below the run's progress ({done:,} env steps, "
            f"{ckpt}); give at least {done}"
        )
    checkpoint.verify(ckpt)  # resolve() found no intact one: this names the damaged file
    return ckpt, _with_budget(config, total_steps), meta


def _with_budget(config: RunConfig, total_steps: int | None) -> RunConfig:
    if total_steps is None:
        return config
    return dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, total_steps=total_steps))


# ---------------------------------------------------------------- compiling the first chunk

COMPILING = "jaxnav: compiling the training step (the first chunk)..."


class _Compiling:
    """The first chunk's compile as the user sees it: the `Waiting` line, shown from now and
    counting from `since` (`time.perf_counter()`; default now: the programs' tracing, if
    before); an `interruptible` wait's `waiting=` (init's, the first chunk's)."""

    def __init__(self, since: float | None = None):
        self.start = time.perf_counter() if since is None else since
        self.line = Waiting(COMPILING)

    def __call__(self, _waited: float) -> None:
        self.line(self.seconds())

    def seconds(self) -> float:
        return time.perf_counter() - self.start


class _CompiledAhead:
    """A program (jitted, or stored) lowered and compiled by XLA in a thread of its own from the
    abstract `args` it will be called with, from now on. A call waits for that compile, then runs
    the compiled program: the one the program would compile on its first call, so nothing
    compiles twice."""

    def __init__(self, program, args):
        self._compiled, self._error = None, None
        self._thread = threading.Thread(
            target=self._compile, args=(program, args), name="compile-ahead", daemon=True
        )
        self._thread.start()

    def _compile(self, program, args) -> None:
        try:
            self._compiled = program.lower(*args).compile()
        except BaseException as err:  # noqa: BLE001 (raised by the call that waits for it)
            self._error = err

    def wait(self) -> None:
        """Returns once the compile is done; raises its error."""
        self._thread.join()
        if self._error is not None:
            raise self._error

    def __call__(self, *args):
        self.wait()
        return self._compiled(*args)


def find_programs(trainer, config, env, key, ahead: bool = True, check=None):
    """(trainer, the abstract TrainState of its init from `key`, whether its programs compile
    ahead): each of the trainer's programs (`Trainer.programs`) read from the program store or
    traced (and kept there: `programs.program`) in turn, on the abstract arguments the run will
    call it with (the outputs of those before it: `Trainer.arguments`). `check(state)` (e.g. the
    memory check) runs as soon as that TrainState is known, before anything compiles.

    With `ahead`, each program starts compiling in a thread of its own as soon as it is found
    and the check has passed (`_CompiledAhead`: XLA's compile lets go of the GIL, so the next
    one is traced meanwhile and they compile at once), and the trainer calls the compiled
    programs: the same program on the same inputs as when compiled at its first call. On several
    devices that needs the programs' shardings fixed in advance (`Trainer.laid_out`, as
    `make_train` lays them out); a trainer without them (or without programs) compiles each at
    its first call there.
    """
    if not trainer.programs:
        state = jax.eval_shape(trainer.init, key)
        if check is not None:
            check(state)
        return trainer, state, False
    run = programs.run_of(config, env)
    ahead = ahead and (jax.device_count() == 1 or trainer.laid_out)
    found, waiting, compiled, state = {}, [], {}, None
    for name, jitted in trainer.programs.items():
        waiting.append((name, trainer.arguments(name, found, key)))
        found[name] = programs.program(trainer, run, name, waiting[-1][1]) or jitted
        if state is None and all(n in found for n in trainer.state_from):
            state = trainer.arguments("state", found, key)
            if check is not None:
                check(state)
        if ahead and state is not None:
            compiled.update((n, _CompiledAhead(found[n], args)) for n, args in waiting)
            waiting = []
    return trainer.with_programs(**(compiled or found)), state, ahead


# ---------------------------------------------------------------- the loop


def _loop(
    config, out, trainer, ts, rows, elapsed, progress, stop, metric_names, compiling=None
) -> Path:
    """Runs chunks until the budget is spent or a stop is requested; checkpoints on the way.

    The first chunk (the compile; `compiling`: already under way, its line shown) runs
    interruptibly; then `stop` defers signals to the end of the chunk under way. Without `stop`,
    the loop listens itself. With several processes, all run it together and process 0 writes;
    a signal to any of them stops all after the chunk.
    """
    cfg, main = config.ppo, distributed.is_main()
    start = time.perf_counter() - elapsed
    last_ckpt = (checkpoint.list_checkpoints(out) or [None])[-1]
    update = int(interruptible(distributed.to_host, ts.update))  # waits for init: interruptible
    bar = tqdm(
        total=cfg.num_updates * cfg.batch_size,
        initial=update * cfg.batch_size,
        unit="step",
        unit_scale=True,
        disable=not (progress and main),
        desc="training",
        dynamic_ncols=True,
    )
    listen = Interrupts(deferred=True) if stop is None else contextlib.nullcontext(stop)
    fields = runlog.columns(metric_names)
    with (
        _writes(out, lambda: last_ckpt),
        runlog.MetricsLog(out, fields, rows, write=main) as log,
        listen as stop,
    ):

        def kept() -> str:  # a second signal's line
            saved = f"kept checkpoint {last_ckpt}" if last_ckpt else "no checkpoint yet"
            return (
                f"stopped at once, without the chunk under way; {saved}; "
                f"continue with: python -m jaxnav.train --resume {out}"
            )

        first = True
        while update < cfg.num_updates:
            before, tick = update, time.perf_counter()
            if first:
                ts, metrics = _first_chunk(trainer, ts, stop, kept, compiling)
            else:
                ts, metrics = trainer.run_chunk(ts)
            first = False
            metrics = interruptible(distributed.to_host, metrics)  # a second signal ends it
            update = int(distributed.to_host(ts.update))
            rate = (update - before) * cfg.batch_size / (time.perf_counter() - tick)
            _check_finite(metrics, ts, last_ckpt)
            elapsed = time.perf_counter() - start
            log.add(runlog.chunk_rows(metrics, fields, before, cfg.batch_size, rate, elapsed))
            _show(bar, log, metric_names, rate, update - before, cfg.batch_size)
            due = update // cfg.checkpoint_every > before // cfg.checkpoint_every
            stopping = distributed.any_process(bool(stop.requested))
            if due or update >= cfg.num_updates or stopping:
                meta = {
                    "env_steps": update * cfg.batch_size,
                    "elapsed_s": time.perf_counter() - start,
                }
                last_ckpt = _save(out, ts, config, meta, main)
            if stopping and update < cfg.num_updates:
                bar.close()
                signal = stop.requested[0] if stop.requested else "a signal to another process"
                raise Interrupted(
                    f"{signal}: stopped at update {update} of {cfg.num_updates}; "
                    f"checkpoint {last_ckpt}; continue with: python -m jaxnav.train "
                    f"--resume {out}"
                )
    bar.close()
    return last_ckpt


def _save(out: Path, ts, config: RunConfig, meta: dict, main: bool) -> Path:
    """Checkpoints `ts` (gathered from every process) and draws the reward curve, on process 0;
    returns the checkpoint folder."""
    host = distributed.to_host(ts)
    if not main:
        return checkpoint.path_of(out, int(host.update))
    ckpt = checkpoint.save(out, host, config, meta)
    _plot(out)
    return ckpt


def _first_chunk(trainer, ts, stop: Interrupts, kept, compiling: _Compiling | None = None):
    """The first chunk of a session (XLA compiles it, or finishes compiling it: `compiling`),
    interruptible at once; then signals wait for the end of a chunk."""
    ready = ""  # when the programs were compiled ahead: the seconds to the start of the run
    if compiling is not None:
        for program in trainer.programs.values():
            interruptible(program.wait, waiting=compiling)
        ready = f" (compiled in {compiling.seconds():.1f} s)"
    compiling = compiling or _Compiling()
    out = interruptible(lambda: jax.block_until_ready(trainer.run_chunk(ts)), waiting=compiling)
    stop.defer(kept)  # before the line: a signal after it waits for the chunk and checkpoint
    compiling.line.end()
    seconds = compiling.seconds()
    print(f"jaxnav: compiled and ran the first chunk in {seconds:.1f} s{ready}", flush=True)
    return out


def _show(bar, log, metric_names, rate, updates, batch_size) -> None:
    shown = metric_names[0] if metric_names else "episode_length"  # beside the reward in the bar
    bar.update(updates * batch_size)
    bar.set_postfix(
        reward=f"{log.last('episode_reward'):.1f}",
        **{shown: f"{log.last(shown):.2f}"},
        sps=f"{rate:,.0f}",
    )


@contextlib.contextmanager
def _writes(out: Path, last_ckpt):
    """Turns a failed write of the loop (disk full, read-only) into RunFailed: one line naming
    the path and what is saved (`last_ckpt()`: the newest checkpoint written)."""
    try:
        yield
    except OSError as err:
        where = err.filename or out / checkpoint.CKPT_DIR
        saved = last_ckpt()
        kept = (
            f"saved: checkpoint {saved} and metrics.csv up to it; free space or fix permissions "
            f"and continue with: python -m jaxnav.train --resume {out}"
            if saved
            else "nothing was saved"
        )
        raise RunFailed(f"{where}: cannot write ({err.strerror or err}); {kept}") from None


def _check_finite(metrics, ts, last_ckpt) -> None:
    """Stops a diverged run before it is checkpointed; the last good checkpoint stays as it is."""
    live = np.asarray(metrics["live"], bool)
    bad = []
    if not np.isfinite(np.asarray(metrics["total"])[live]).all():
        bad.append("loss")
    params = distributed.to_host(ts.params)
    if not all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(params)):
        bad.append("weights")
    if not np.asarray(metrics["obs_finite"])[live].all():
        bad.append("observations")
    if bad:
        kept = (
            f"last good checkpoint: {last_ckpt}" if last_ckpt else "no checkpoint was written yet"
        )
        raise FloatingPointError(
            f"training diverged (NaN/Inf in the {' and '.join(bad)}) by update "
            f"{int(ts.update)}; {kept}; try a lower --learning-rate"
        )


def _plot(out: Path) -> None:
    from jaxnav.viz.plots import plot_reward_curve

    plot_reward_curve(out / "metrics.csv", out / "reward_curve.png")


def train(
    out: str | Path | None = None,
    preset: str = "cpu",
    seed: int = 0,
    layouts=None,
    progress: bool = True,
    env: str = "avoid",
    task=None,
    randomize=None,
    sensor=None,
    scene=None,
    robot=None,
    **ppo_overrides,
) -> Path:
    """Python API of `python -m jaxnav.train`; returns the final checkpoint folder.

    `env` is a registered task; `layouts` are layout file paths; `task`/`randomize`/`sensor`/
    `scene`/`robot` are dicts of field overrides; other keyword arguments override PPO fields
    (e.g. `num_envs=64`).
    """
    groups = {"task": task, "randomize": randomize, "sensor": sensor, "scene": scene}
    overrides = {"ppo": ppo_overrides, "robot": robot or {}}
    overrides.update({k: v or {} for k, v in groups.items()})
    config = build_config(preset, seed, layouts, overrides, env)
    return run(config, Path(out or f"runs/{env}-{preset}"), progress)
