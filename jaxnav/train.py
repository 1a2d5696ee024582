"""`python -m jaxnav.train`: train PPO on a task (default `avoid`) into one run folder.

python -m jaxnav.train                                  # the cpu preset into runs/avoid-cpu
python -m jaxnav.train --preset paper --out runs/paper  # the paper's Table II
python -m jaxnav.train --num-envs 1024 --task.near-threshold 0.8 --layouts my_rooms.json
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import signal
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jaxnav.cli import Parser, make_callable, print_error
from jaxnav.io import checkpoint, runlog
from jaxnav.io.layouts import LayoutError, layout_to_dict, load_layout, parse_layouts
from jaxnav.io.runconfig import GROUPS, RunConfig, add_flags, group_class, overrides_from_args
from jaxnav.ppo.config import PRESETS, preset
from jaxnav.ppo.train import make_train
from jaxnav.tasks.registry import TASKS, make_env


def build_config(
    preset_name="cpu", seed=0, layout_files=None, overrides=None, env="avoid"
) -> RunConfig:
    """A RunConfig of task `env` from a preset, layout files and {group: {field: value}}
    overrides (the randomisation's start from the training distribution)."""
    overrides = overrides or {}
    groups = {"ppo": preset(preset_name, **overrides.get("ppo", {}))}
    defaults = {"randomize": RunConfig.randomize, "robot": RunConfig.robot}
    for attr, cls, _ in GROUPS[1:]:
        cls = group_class(attr, cls, env)
        base = defaults.get(attr) or cls()
        groups[attr] = dataclasses.replace(base, **overrides.get(attr, {}))
    layouts = None
    if layout_files:
        layouts = tuple(layout_to_dict(lay) for f in layout_files for lay in load_layout(f))
    return RunConfig(**groups, layouts=layouts, seed=seed, preset=preset_name, env=env)


def make_run_env(config: RunConfig):
    layouts = None if config.layouts is None else parse_layouts(list(config.layouts), "config")
    return make_env(config.env, layouts, randomize=config.randomize, **config.env_kwargs())


class Interrupted(Exception):
    """Training stopped on SIGINT/SIGTERM after writing a checkpoint."""


@contextlib.contextmanager
def _stop_requests():
    """Turns SIGINT/SIGTERM into a flag checked between chunks (so a chunk always completes)."""
    requested = []
    handler = lambda signum, frame: requested.append(signal.Signals(signum).name)  # noqa: E731
    if threading.current_thread() is not threading.main_thread():
        yield requested
        return
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield requested
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def run(config: RunConfig, out: Path, progress: bool = True, stop: list | None = None) -> Path:
    """Trains `config` into a new run folder `out`; returns the final checkpoint folder."""
    out = Path(out)
    if checkpoint.list_checkpoints(out):
        raise ValueError(
            f"--out {out}: already holds a training run; use --resume {out} or "
            "choose another folder"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {out}: cannot create the run folder ({err.strerror})") from None
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    env = make_run_env(config)
    trainer = make_train(config.ppo, env)
    ts = trainer.init(jax.random.PRNGKey(config.seed))
    return _loop(config, out, trainer, ts, [], 0.0, progress, stop, env.metric_names)


def resume(
    out: Path, total_steps: int | None = None, progress: bool = True, stop: list | None = None
) -> Path:
    """Continues the run in `out` from its latest checkpoint, optionally to a new step budget."""
    out = Path(out)
    ckpt = checkpoint.resolve(out)
    config = checkpoint.load_config(ckpt)
    if total_steps is not None:
        config = dataclasses.replace(
            config, ppo=dataclasses.replace(config.ppo, total_steps=total_steps)
        )
        (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    env = make_run_env(config)
    trainer = make_train(config.ppo, env)
    ts = checkpoint.restore_train_state(ckpt, trainer.init(jax.random.PRNGKey(config.seed)))
    meta = json.loads((ckpt / "meta.json").read_text())
    rows = [r for r in runlog.read_rows(out / "metrics.csv") if r["update"] <= int(ts.update)]
    elapsed = meta.get("elapsed_s", 0.0)
    return _loop(config, out, trainer, ts, rows, elapsed, progress, stop, env.metric_names)


def _loop(config, out, trainer, ts, rows, elapsed, progress, stop, metric_names) -> Path:
    """Runs chunks until the budget is spent or a stop is requested; checkpoints on the way.

    `stop` is the list a caller's `_stop_requests()` fills; without one, the loop listens itself.
    """
    cfg = config.ppo
    start = time.perf_counter() - elapsed
    last_ckpt = (checkpoint.list_checkpoints(out) or [None])[-1]
    bar = tqdm(
        total=cfg.num_updates * cfg.batch_size,
        initial=int(ts.update) * cfg.batch_size,
        unit="step",
        unit_scale=True,
        disable=not progress,
        desc="training",
        dynamic_ncols=True,
    )
    listen = _stop_requests() if stop is None else contextlib.nullcontext(stop)
    fields = runlog.columns(metric_names)
    shown = metric_names[0] if metric_names else "episode_length"  # beside the reward in the bar
    with runlog.MetricsLog(out, fields, rows) as log, listen as stop:
        while int(ts.update) < cfg.num_updates:
            before, tick = int(ts.update), time.perf_counter()
            ts, metrics = trainer.run_chunk(ts)
            metrics = jax.device_get(metrics)
            rate = (int(ts.update) - before) * cfg.batch_size / (time.perf_counter() - tick)
            _check_finite(metrics, ts, last_ckpt)
            elapsed = time.perf_counter() - start
            log.add(runlog.chunk_rows(metrics, fields, before, cfg.batch_size, rate, elapsed))
            bar.update((int(ts.update) - before) * cfg.batch_size)
            bar.set_postfix(
                reward=f"{log.last('episode_reward'):.1f}",
                **{shown: f"{log.last(shown):.2f}"},
                sps=f"{rate:,.0f}",
            )
            update = int(ts.update)
            due = update // cfg.checkpoint_every > before // cfg.checkpoint_every
            if due or update >= cfg.num_updates or stop:
                meta = {
                    "env_steps": update * cfg.batch_size,
                    "elapsed_s": time.perf_counter() - start,
                }
                last_ckpt = checkpoint.save(out, ts, config, meta)
                _plot(out)
            if stop and update < cfg.num_updates:
                bar.close()
                raise Interrupted(
                    f"{stop[0]}: stopped at update {update} of {cfg.num_updates}; "
                    f"checkpoint {last_ckpt}; continue with: python -m jaxnav.train "
                    f"--resume {out}"
                )
    bar.close()
    return last_ckpt


def _check_finite(metrics, ts, last_ckpt) -> None:
    """Stops a diverged run before it is checkpointed; the last good checkpoint stays as it is."""
    live = np.asarray(metrics["live"], bool)
    bad = []
    if not np.isfinite(np.asarray(metrics["total"])[live]).all():
        bad.append("loss")
    if not all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(jax.device_get(ts.params))):
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


def parse_args(argv=None) -> argparse.Namespace:
    parser = Parser(
        prog="python -m jaxnav.train",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
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
    env = Parser(add_help=False)
    env.add_argument("--env", default="avoid")
    name = env.parse_known_args(argv)[0].env
    if name not in TASKS:
        raise ValueError(f"--env: unknown task '{name}'; valid: {', '.join(sorted(TASKS))}")
    add_flags(parser, name)  # the task's own flags
    return parser.parse_args(argv)


def _new_run_dir(root: Path, name: str) -> Path:
    """root/name, or root/name-2, -3, ... if taken: a plain re-run never collides with an old run."""
    candidates = (root / (name if i == 1 else f"{name}-{i}") for i in range(1, 10_000))
    return next(p for p in candidates if not p.exists())


def _start(args, stop: list) -> tuple[Path, Path]:
    """Runs what the flags ask for; returns (run folder, final checkpoint)."""
    overrides = overrides_from_args(args)
    if args.resume:
        others = [f"--{k}" for k in ("out", "preset", "seed", "layouts") if getattr(args, k)]
        others += ["--env"] if args.env != "avoid" else []
        others += [
            f"{g}.{k}"
            for g, fields in overrides.items()
            for k in fields
            if (g, k) != ("ppo", "total_steps")
        ]
        if others:
            raise ValueError(
                f"--resume: continues with the run's own config; drop {', '.join(others)}"
            )
        print(f"jaxnav: resuming {args.resume}", flush=True)
        total = overrides["ppo"].get("total_steps")
        return args.resume, resume(args.resume, total, not args.no_progress, stop)
    config = build_config(args.preset or "cpu", args.seed or 0, args.layouts, overrides, args.env)
    out = args.out or _new_run_dir(Path("runs"), f"{config.env}-{config.preset}")
    cfg = config.ppo
    print(
        f"jaxnav: training '{config.env}' with the {config.preset} preset: {cfg.num_envs} robots, "
        f"{cfg.num_updates} updates of {cfg.batch_size} steps, on {jax.device_count()} "
        f"{jax.devices()[0].platform} device(s)",
        flush=True,
    )
    return out, run(config, out, not args.no_progress, stop)


def main(argv=None) -> int:
    start = time.perf_counter()
    try:
        args = parse_args(argv)
        with _stop_requests() as stop:  # from here on, Ctrl-C ends with a checkpoint
            out, final = _start(args, stop)
    except Interrupted as stop:
        print(f"interrupted ({stop})")
        return 0
    except FloatingPointError as err:
        print_error(err)
        return 1
    except (ValueError, LayoutError, FileNotFoundError) as err:
        print_error(err)
        return 2
    meta = json.loads((final / "meta.json").read_text())
    print(
        f"done: {meta['env_steps']:,} env steps, {time.perf_counter() - start:.0f} s in this "
        f"session. Results in {out}/: metrics.csv, reward_curve.png, tb/, "
        f"{final.relative_to(out)}\nevaluate: python -m jaxnav.evaluate --checkpoint {out}"
    )
    return 0


make_callable(__name__, train)

if __name__ == "__main__":
    sys.exit(main())
