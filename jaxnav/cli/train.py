"""`python -m jaxnav.train`: train PPO on a task (default `avoid`) into one run folder.

python -m jaxnav.train                                  # the cpu preset into runs/avoid-cpu
python -m jaxnav.train --preset paper --out runs/paper  # the paper's Table II
python -m jaxnav.train --num-envs 1024 --task.near-threshold 0.8 --layouts my_rooms.json
python -m jaxnav.train --env goal                       # point-goal navigation
python -m jaxnav.train --env goal --actions continuous  # (forward m/s, yaw rad/s) commands
python -m jaxnav.train --out runs/big --coordinator host0:8476 --num-processes 2 --process-id 0
                                                        # one run over two hosts (see below)

Several processes (hosts): start the same command on each with its own --process-id (or set
JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID); the robots are split over every
device of every process, and process 0 writes the run folder, which must be on a filesystem all
hosts share for --resume (see jaxnav/distributed.py).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
import time
from pathlib import Path

import jax

from jaxnav import distributed
from jaxnav.cli import GroupHelp, Parser, print_error
from jaxnav.io import checkpoint
from jaxnav.io.layouts import LayoutError
from jaxnav.ppo.config import PRESETS, preset
from jaxnav.process import EXIT_INTERRUPTED, Interrupts, compile_cache
from jaxnav.runconfig import RunConfig, add_flags, overrides_from_args
from jaxnav.tasks.base import ACTIONS
from jaxnav.tasks.registry import TASKS, task_defaults
from jaxnav.training import Interrupted, RunFailed, build_config, resume, run


def parse_args(argv=None) -> argparse.Namespace:
    """The flags; `args.given` lists the flags typed (as typed: `--learning-rate`)."""
    parser = Parser(
        prog="python -m jaxnav.train",
        usage="%(prog)s [--env TASK] [--preset NAME] [--out DIR | --resume DIR] [FLAG ...]",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        add_help=False,
    )
    parser.add_argument("-h", "--help", action=GroupHelp, help="this help; GROUP: its flags")
    parser.add_argument(
        "--env", default="avoid", help=f"the task: {', '.join(TASKS)} (default avoid)"
    )
    parser.add_argument("--out", type=Path, help="run folder (default: runs/<env>-<preset>)")
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the run in DIR from its latest checkpoint (with its own "
        "config; only --total-steps may change)",
    )
    parser.add_argument("--preset", help=f"one of {', '.join(PRESETS)} (default cpu)")
    parser.add_argument("--seed", type=int, help="random seed (default 0)")
    parser.add_argument(
        "--layouts",
        nargs="+",
        metavar="FILE",
        help="training room files (default: scenes/train_room.json + sampled rooms)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="trace and compile everything anew (default: reuse the programs compiled for "
        "earlier runs of the same shapes, and those traced for earlier runs of the same config, "
        "code and libraries, kept in ~/.cache/jaxnav/xla or JAX_COMPILATION_CACHE_DIR)",
    )
    distributed.add_flags(parser)
    early = Parser(add_help=False)
    early.add_argument("--env", default="avoid")
    early.add_argument("--preset", default="cpu")
    known = early.parse_known_args(argv)[0]
    name = known.env
    if name not in TASKS:
        raise ValueError(f"--env: unknown task '{name}'; valid: {', '.join(sorted(TASKS))}")
    add_flags(parser, name, _help_defaults(name, known.preset))  # the task's own flags
    if "actions" in {f.name for f in dataclasses.fields(TASKS[name].config_cls)}:
        parser.add_argument(
            "--actions",
            dest="task.actions",
            choices=ACTIONS,
            help="short for --task.actions: the paper's three actions, those and a stop or a back "
            "(goal task), or continuous commands",
        )
    args = parser.parse_args(argv)
    args.given = [
        action.option_strings[0]
        for action in parser._actions
        if action.option_strings
        and action.dest != "help"
        and getattr(args, action.dest, None) != action.default
    ]
    return args


def _help_defaults(env: str, preset_name: str) -> RunConfig | None:
    """The config a run of `env` with `preset_name` and no flags would use (its values are the
    defaults --help shows); None for an unknown preset (parsing then names it)."""
    with contextlib.suppress(ValueError):
        return build_config(preset_name, env=env)
    return None


def _new_run_dir(root: Path, name: str) -> Path:
    """root/name, or root/name-2, -3, ... if taken: a plain re-run never collides with an old run."""
    candidates = (root / (name if i == 1 else f"{name}-{i}") for i in range(1, 10_000))
    return next(p for p in candidates if not p.exists())


# The flags --resume takes.
RESUME_FLAGS = (
    "--resume",
    "--total-steps",
    "--no-progress",
    "--no-compile-cache",
    *distributed.FLAGS,
)


def _start(args, stop: Interrupts) -> tuple[Path, Path]:
    """Runs what the flags ask for; returns (run folder, final checkpoint)."""
    overrides = overrides_from_args(args)
    if args.resume:
        others = [flag for flag in args.given if flag not in RESUME_FLAGS]
        if others:
            raise ValueError(
                f"--resume: continues with the run's own config; drop {', '.join(others)}"
            )
        print(f"jaxnav: resuming {args.resume}", flush=True)
        total = overrides["ppo"].get("total_steps")
        return args.resume, resume(args.resume, total, not args.no_progress, stop)
    config = build_config(args.preset or "cpu", args.seed or 0, args.layouts, overrides, args.env)
    if jax.process_count() > 1 and args.out is None:
        raise ValueError("--out: needed with several processes (all must name the same folder)")
    out = args.out or _new_run_dir(Path("runs"), f"{config.env}-{config.preset}")
    cfg = config.ppo
    processes = f" of {jax.process_count()} processes" if jax.process_count() > 1 else ""
    print(
        f"jaxnav: training '{config.env}' with the {config.preset} preset: {cfg.num_envs} robots, "
        f"{cfg.num_updates} updates of {cfg.batch_size} steps, on {jax.device_count()} "
        f"{jax.devices()[0].platform} device(s){processes}",
        flush=True,
    )
    if "minibatch_size" not in overrides["ppo"] and cfg.minibatch_size != _preset_minibatch(config):
        print(
            f"jaxnav: --minibatch-size {cfg.minibatch_size}: {cfg.num_minibatches} minibatches "
            f"of the {cfg.batch_size}-step batch, as the preset splits its own (give "
            "--minibatch-size to choose)",
            flush=True,
        )
    return out, run(config, out, not args.no_progress, stop)


def _preset_minibatch(config: RunConfig) -> int:
    return preset(
        config.preset, **task_defaults(config.env, config.preset).get("ppo", {})
    ).minibatch_size


def _out_of_memory(err: Exception) -> str | None:
    """The one-line message for XLA's RESOURCE_EXHAUSTED, else None."""
    text = " ".join(str(err).split())
    if "RESOURCE_EXHAUSTED" not in text:
        return None
    return f"out of memory ({text[:160]}); nothing new was saved; try a smaller --num-envs"


def main(argv=None) -> int:
    """`python -m jaxnav.train`; returns the exit code (2 for user mistakes, 130 for an interrupt
    before training started, 1 when the machine stops the run)."""
    start = time.perf_counter()
    try:
        with Interrupts() as stop:  # Ctrl-C: at once until training runs, then after a chunk
            args = parse_args(argv)
            compile_cache(not args.no_compile_cache)
            distributed.start(distributed.from_args(args))  # before anything touches a device
            with distributed.start_failed():  # an error before training: told to the others
                out, final = _start(args, stop)
    except Interrupted as stopped:
        print(f"interrupted ({stopped})")
        return 0
    except KeyboardInterrupt:  # outside the main thread, where Interrupts cannot listen
        print_error("interrupted")
        return EXIT_INTERRUPTED
    except ConnectionError as err:  # the processes of a run never met
        print_error(err)
        sys.stderr.flush()
        os._exit(1)  # a normal exit would log pages about the half-made link to the coordinator
    except (FloatingPointError, RunFailed, distributed.PeerFailed) as err:
        print_error(err)
        return 1
    except (ValueError, LayoutError, FileNotFoundError) as err:
        print_error(err)
        return 2
    except jax.errors.JaxRuntimeError as err:
        if _out_of_memory(err) is None:
            raise
        print_error(_out_of_memory(err))
        return 1
    if not distributed.is_main():
        print(f"done: process {jax.process_index()}; process 0 wrote the run into {out}/")
        return 0
    meta = checkpoint.load_meta(final)
    print(
        f"done: {meta['env_steps']:,} env steps, {time.perf_counter() - start:.0f} s in this "
        f"session. Results in {out}/: metrics.csv, reward_curve.png, tb/, "
        f"{final.relative_to(out)}\nevaluate: python -m jaxnav.evaluate --checkpoint {out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
