"""`python -m jaxnav.train`: train PPO on the `avoid` task and write everything into one run folder.

python -m jaxnav.train                                  # the cpu preset into runs/avoid-cpu
python -m jaxnav.train --preset paper --out runs/paper  # the paper's Table II
python -m jaxnav.train --num-envs 1024 --task.near-threshold 0.8 --layouts my_rooms.json
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
import types
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jaxnav import checkpoint
from jaxnav.config import GROUPS, RunConfig, add_flags, overrides_from_args
from jaxnav.envs import make_env
from jaxnav.layouts import LayoutError, layout_to_dict, load_layout, parse_layouts
from jaxnav.ppo.config import PRESETS, preset
from jaxnav.ppo.train import make_train

CSV_FIELDS = (
    "update",
    "env_steps",
    "episode_reward",
    "episode_length",
    "collision_rate",
    "total_loss",
    "policy_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "steps_per_second",
    "elapsed_s",
)


def build_config(preset_name="cpu", seed=0, layout_files=None, overrides=None) -> RunConfig:
    """A RunConfig from a preset, layout files and {group: {field: value}} overrides."""
    overrides = overrides or {}
    groups = {"ppo": preset(preset_name, **overrides.get("ppo", {}))}
    for attr, cls, _ in GROUPS[1:]:
        groups[attr] = cls(**overrides.get(attr, {}))
    layouts = None
    if layout_files:
        layouts = tuple(layout_to_dict(lay) for f in layout_files for lay in load_layout(f))
    return RunConfig(**groups, layouts=layouts, seed=seed, preset=preset_name)


def make_run_env(config: RunConfig):
    layouts = None if config.layouts is None else parse_layouts(list(config.layouts), "config")
    return make_env(config.env, layouts, randomize=config.randomize, **config.env_kwargs())


def run(config: RunConfig, out: Path, progress: bool = True) -> Path:
    """Trains `config` into run folder `out`; returns the final checkpoint folder."""
    out = Path(out)
    if checkpoint.list_checkpoints(out):
        raise ValueError(f"--out {out}: already holds a training run; choose another folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    cfg = config.ppo
    env = make_run_env(config)
    trainer = make_train(cfg, env)
    start = time.perf_counter()
    ts = trainer.init(jax.random.PRNGKey(config.seed))
    bar = tqdm(
        total=cfg.num_updates * cfg.batch_size,
        unit="step",
        unit_scale=True,
        disable=not progress,
        desc="training",
        dynamic_ncols=True,
    )
    last_ckpt, rows = None, []
    with open(out / "metrics.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, CSV_FIELDS)
        writer.writeheader()
        while int(ts.update) < cfg.num_updates:
            before, tick = int(ts.update), time.perf_counter()
            ts, metrics = trainer.run_chunk(ts)
            metrics = jax.device_get(metrics)
            done = int(ts.update) - before
            rate = done * cfg.batch_size / (time.perf_counter() - tick)
            new_rows = _csv_rows(metrics, before, cfg.batch_size, rate, time.perf_counter() - start)
            writer.writerows(new_rows)
            fh.flush()
            rows += new_rows
            _check_finite(metrics, ts, out, last_ckpt)
            bar.update(done * cfg.batch_size)
            bar.set_postfix(
                reward=f"{_last(rows, 'episode_reward'):.1f}",
                collisions=f"{_last(rows, 'collision_rate'):.2f}",
                sps=f"{rate:,.0f}",
            )
            update = int(ts.update)
            if (
                update // cfg.checkpoint_every > before // cfg.checkpoint_every
                or update >= cfg.num_updates
            ):
                last_ckpt = checkpoint.save(
                    out,
                    ts,
                    config,
                    {
                        "env_steps": update * cfg.batch_size,
                        "elapsed_s": time.perf_counter() - start,
                    },
                )
                _plot(out)
    bar.close()
    return last_ckpt


def _csv_rows(metrics, first_update, batch_size, rate, elapsed) -> list[dict]:
    rows = []
    for i in np.flatnonzero(metrics["live"]):
        update = first_update + len(rows) + 1
        row = {
            "update": update,
            "env_steps": update * batch_size,
            "steps_per_second": round(rate),
            "elapsed_s": round(elapsed, 2),
        }
        for key in (
            "episode_reward",
            "episode_length",
            "collision_rate",
            "policy_loss",
            "value_loss",
            "entropy",
            "approx_kl",
        ):
            row[key] = float(metrics[key][i])
        row["total_loss"] = float(metrics["total"][i])
        rows.append(row)
    return rows


def _last(rows, key) -> float:
    values = [r[key] for r in rows if not math.isnan(r[key])]
    return values[-1] if values else math.nan


def _check_finite(metrics, ts, out, last_ckpt) -> None:
    """Stops a diverged run; the last good checkpoint stays as it is."""
    losses = np.asarray(metrics["total"])[np.asarray(metrics["live"], bool)]
    params_ok = all(
        np.isfinite(x).all() for x in jax.tree_util.tree_leaves(jax.device_get(ts.params))
    )
    if not (np.isfinite(losses).all() and params_ok):
        kept = (
            f"last good checkpoint: {last_ckpt}" if last_ckpt else "no checkpoint was written yet"
        )
        raise FloatingPointError(
            f"training diverged (NaN/Inf in the loss or weights) at update "
            f"{int(ts.update)}; {kept}; try a lower --learning-rate"
        )


def _plot(out: Path) -> None:
    from jaxnav.plots import plot_reward_curve

    plot_reward_curve(out / "metrics.csv", out / "reward_curve.png")


def train(
    out: str | Path | None = None,
    preset: str = "cpu",
    seed: int = 0,
    layouts=None,
    progress: bool = True,
    task=None,
    randomize=None,
    sensor=None,
    scene=None,
    **ppo_overrides,
) -> Path:
    """Python API of `python -m jaxnav.train`; returns the final checkpoint folder.

    `layouts` are layout file paths; `task`/`randomize`/`sensor`/`scene` are dicts of field
    overrides; other keyword arguments override PPO fields (e.g. `num_envs=64`).
    """
    overrides = {
        "ppo": ppo_overrides,
        "task": task or {},
        "randomize": randomize or {},
        "sensor": sensor or {},
        "scene": scene or {},
    }
    config = build_config(preset, seed, layouts, overrides)
    return run(config, Path(out or f"runs/avoid-{preset}"), progress)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m jaxnav.train",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", type=Path, help="run folder (default: runs/avoid-<preset>)")
    parser.add_argument(
        "--preset", default="cpu", help=f"one of {', '.join(PRESETS)} (default cpu)"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--layouts",
        nargs="+",
        metavar="FILE",
        help="training room files (default: scenes/train_room.json + sampled rooms)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_flags(parser)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        config = build_config(args.preset, args.seed, args.layouts, overrides_from_args(args))
        out = args.out or Path(f"runs/avoid-{args.preset}")
        cfg = config.ppo
        print(
            f"jaxnav: training '{config.env}' with the {config.preset} preset: {cfg.num_envs} robots, "
            f"{cfg.num_updates} updates of {cfg.batch_size} steps, on {jax.devices()[0].platform}"
        )
        start = time.perf_counter()
        final = run(config, out, progress=not args.no_progress)
    except (ValueError, LayoutError, FileNotFoundError, FloatingPointError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    steps = cfg.num_updates * cfg.batch_size
    wall = time.perf_counter() - start
    print(
        f"done: {steps:,} env steps in {wall:.0f} s. Results in {out}/: metrics.csv, "
        f"reward_curve.png, {final.relative_to(out)}\n"
        f"evaluate: python -m jaxnav.evaluate --checkpoint {out}"
    )
    return 0


class _CallableModule(types.ModuleType):
    """Lets `jaxnav.train(...)` work whether `jaxnav.train` names this module or the function."""

    def __call__(self, *args, **kwargs):
        return train(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

if __name__ == "__main__":
    sys.exit(main())
