"""Where the scene files (robot MJCF, room layouts, benchmark rooms) are, however jaxnav is installed.

The repository keeps them in `scenes/` at its top, beside the `jaxnav/` package, and the build maps
that folder into the package as `jaxnav/scenes` (pyproject.toml, `[tool.setuptools]`). So:

- installed from a wheel or `pip install .`: `importlib.resources.files("jaxnav") / "scenes"`;
- a source checkout on `PYTHONPATH`, or `pip install -e .`: the repository's `scenes/` beside the
  package. Setuptools' editable install points `jaxnav` at the checkout's `jaxnav/` folder, which
  has no `scenes/` inside; its finder maps `jaxnav.scenes` to `scenes/` for imports only, and only
  for folders with an `__init__.py`, so `importlib.resources` cannot see the mapped folder.

MuJoCo reads the MJCF by file name, so jaxnav must be installed as files on disk (not zipped).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path


def scenes_dir() -> Path:
    """The folder holding the scene files: the installed `jaxnav/scenes`, else the checkout's `scenes/`.

    Raises FileNotFoundError naming both places if neither exists.
    """
    package = Path(str(importlib.resources.files("jaxnav")))
    candidates = (package / "scenes", package.parent / "scenes")
    for folder in candidates:
        if folder.is_dir():
            return folder
    tried = " and ".join(str(folder) for folder in candidates)
    raise FileNotFoundError(f"jaxnav's scene folder is missing: neither {tried} exists")


def scene_file(name: str) -> Path:
    """The path of scene file `name` (e.g. "train_room.json" or "benchmark/office.json").

    Raises FileNotFoundError naming the file and listing the scene files there are.
    """
    folder = scenes_dir()
    path = folder / name
    if not path.is_file():
        available = sorted(
            p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()
        )
        raise FileNotFoundError(
            f"no scene file {name!r} in {folder}; available: {', '.join(available) or 'none'}"
        )
    return path
