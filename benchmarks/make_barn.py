"""Writes the BARN suite: the 300 static BARN worlds as jaxnav layouts, in three difficulty groups.

    git clone https://github.com/Daffan/the-barn-challenge
    python benchmarks/make_barn.py the-barn-challenge      # -> scenes/barn/

Reads `jackal_helper/worlds/BARN/world_N.world` and `path_files/path_N.npy` of a checkout of the
BARN Challenge repository and writes, into `--out`:

- `easy.json`, `medium.json`, `hard.json`: worlds 0-99, 100-199 and 200-299, rooms `world_N`
  converted by `jaxnav.io.barn.world_layout` (one suite family per file, see
  `jaxnav.evaluation.load_suite`). BARN's worlds are numbered in the order of its difficulty metrics
  (Perille et al. 2020), easiest first.
- `suite.json`: `{"score": "barn", "time_limit_s": 100, "rooms": {"world_N": {"optimal_path_m":
  ..., "difficulty_rank": N}}}`, the optimal path length as the challenge's run.py measures it
  (`barn.optimal_path_length`) for its score (`barn.barn_score`, which `python -m jaxnav.evaluate
  --suite barn` reports); the layout format has no field for these.
- `LICENSE`: the BARN repository's licence (MIT), copied.
- `sample/world_0.world.gz`, `sample/path_0.npy`: world 0 and its path file, unmodified (the world
  gzipped), which the tests read.

Every room is validated by jaxnav's layout parser before anything is written.
"""

from __future__ import annotations

import argparse
import gzip
import json
import shutil
from pathlib import Path

import numpy as np

from jaxnav.io import barn
from jaxnav.io.files import write_atomic
from jaxnav.io.layouts import parse_layouts, save_layouts

OUT = Path(__file__).resolve().parent.parent / "scenes" / "barn"
WORLDS = "jackal_helper/worlds/BARN"
COUNT = 300
GROUPS = {"easy": range(0, 100), "medium": range(100, 200), "hard": range(200, 300)}
META = "suite.json"  # jaxnav.evaluation.SUITE_META


def convert(root: Path) -> tuple[dict, dict]:
    """({group: [RoomLayout]}, {world: {optimal_path_m, difficulty_rank}}) of a BARN checkout."""
    folder = root / WORLDS
    groups, meta = {}, {}
    for group, indices in GROUPS.items():
        rooms = [barn.world_layout(folder / f"world_{i}.world") for i in indices]
        groups[group] = parse_layouts(rooms, source=f"{folder} ({group})")
        for i in indices:
            path = np.load(folder / "path_files" / f"path_{i}.npy")
            length = round(barn.optimal_path_length(path), 4)
            meta[f"world_{i}"] = {"optimal_path_m": length, "difficulty_rank": i}
    return groups, meta


def _write_meta(path: Path, meta: dict) -> None:
    """suite.json, one world per line."""
    lines = [f"    {json.dumps(k)}: {json.dumps(v)}" for k, v in meta.items()]
    head = f'{{\n  "score": "barn",\n  "time_limit_s": {barn.TIME_LIMIT_S:g},\n  "rooms": {{\n'
    write_atomic(path, head + ",\n".join(lines) + "\n  }\n}\n")


def _write_sample(root: Path, out: Path) -> None:
    """World 0 (gzipped, with no timestamp, so the bytes repeat) and its path file."""
    out.mkdir(parents=True, exist_ok=True)
    world = (root / WORLDS / "world_0.world").read_bytes()
    (out / "world_0.world.gz").write_bytes(gzip.compress(world, mtime=0))
    shutil.copyfile(root / WORLDS / "path_files" / "path_0.npy", out / "path_0.npy")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("barn", type=Path, help="checkout of github.com/Daffan/the-barn-challenge")
    p.add_argument("--out", type=Path, default=OUT, help=f"suite folder (default {OUT})")
    args = p.parse_args()
    found = len(list((args.barn / WORLDS).glob("world_*.world")))
    if found != COUNT:
        p.error(f"{args.barn / WORLDS}: expected {COUNT} world_N.world files, found {found}")
    groups, meta = convert(args.barn)
    args.out.mkdir(parents=True, exist_ok=True)
    for group, rooms in groups.items():
        save_layouts(args.out / f"{group}.json", rooms)
        counts = [len(r.obstacles) for r in rooms]
        print(f"{group:<7} {len(rooms)} rooms, {min(counts)}-{max(counts)} cylinders")
    _write_meta(args.out / META, meta)
    shutil.copyfile(args.barn / "LICENSE", args.out / "LICENSE")
    _write_sample(args.barn, args.out / "sample")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
