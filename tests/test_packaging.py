"""Packaging: a non-editable install holds every module and scene file and works from any folder,
and every third-party module jaxnav imports is a declared dependency.

The install is `pip install --no-deps --target` from a copy of the sources, so the build leaves no
`build/` or `*.egg-info` folder in the repository. The installed copy then runs in subprocesses
whose working folder is elsewhere and whose PYTHONPATH is the install folder alone, so neither the
checkout nor an editable install of it can be imported instead.
"""

from __future__ import annotations

import ast
import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "jaxnav", "scenes")  # what the build reads
# Come with ROS 2, not from PyPI.
ROS_MODULES = {
    "rclpy",
    "sensor_msgs",
    "geometry_msgs",
    "nav_msgs",
    "std_msgs",
    "std_srvs",
    "diagnostic_msgs",
    "tf2_ros",
}

# Builds the default env from the installed package and resets it once.
_MAKE_ENV = """
import json, jax, jax.numpy as jnp, jaxnav
from jaxnav.core import assets
env = jaxnav.make_env("avoid")
state = jax.jit(env.reset)(jax.random.PRNGKey(0))  # jitted: compiles faster than eager runs
print(json.dumps({
    "module": jaxnav.__file__,
    "scenes": str(assets.scenes_dir()),
    "obs_shape": list(state.obs.shape),
    "finite": bool(jnp.isfinite(state.obs).all()),
}))
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The folder jaxnav is installed into (non-editable, without dependencies)."""
    root = tmp_path_factory.mktemp("packaging")
    src = root / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=ignore)
        else:
            shutil.copy2(REPO / name, src / name)
    target = root / "site"
    pip = [sys.executable, "-m", "pip", "install", "--no-deps", "--quiet", "--target", str(target)]
    proc = subprocess.run([*pip, str(src)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return target


def run_installed(target: Path, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`python *args` in `cwd` with only the install folder on PYTHONPATH."""
    env = {**os.environ, "PYTHONPATH": str(target), "JAX_PLATFORMS": "cpu"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def files_under(folder: Path, pattern: str) -> set[str]:
    """Paths of the files matching `pattern` under `folder`, relative to it."""
    return {p.relative_to(folder).as_posix() for p in folder.rglob(pattern) if p.is_file()}


def test_install_holds_every_module_and_scene_file(installed):
    missing = files_under(REPO / "jaxnav", "*.py") - files_under(installed / "jaxnav", "*.py")
    packages = sorted({"jaxnav." + str(Path(m).parent).replace("/", ".") for m in missing})
    assert not missing, f"not installed: {sorted(missing)}; add {packages} to pyproject's packages"
    scenes = files_under(REPO / "scenes", "*")
    assert scenes and scenes == files_under(installed / "jaxnav" / "scenes", "*")


@pytest.mark.slow
def test_installed_package_makes_an_env_from_another_folder(installed, tmp_path):
    """The installed package makes an env from another folder. Slow: a Python process that
    imports jax and compiles an env."""
    proc = run_installed(installed, ["-c", _MAKE_ENV], tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.splitlines()[-1])
    assert Path(out["module"]).is_relative_to(installed)
    assert Path(out["scenes"]) == installed / "jaxnav" / "scenes"
    assert out["obs_shape"] == [8] and out["finite"]


def test_installed_train_cli_runs_from_another_folder(installed, tmp_path):
    proc = run_installed(installed, ["-m", "jaxnav.train", "--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "--out" in proc.stdout


class _Imports(ast.NodeVisitor):
    """Collects the top-level names of imported modules.

    The robot-side files import each other by file name when copied flat onto the robot
    (`if __package__: ... else: from sibling import ...`); those branches import no distribution
    and are skipped.
    """

    def __init__(self):
        self.names = set()

    def visit_Import(self, node):
        self.names.update(alias.name.split(".")[0] for alias in node.names)

    def visit_ImportFrom(self, node):
        if node.level == 0 and node.module:
            self.names.add(node.module.split(".")[0])

    def visit_If(self, node):
        flat_copy = isinstance(node.test, ast.Name) and node.test.id == "__package__"
        for child in node.body if flat_copy else [node.test, *node.body, *node.orelse]:
            self.visit(child)


def imported_modules(folder: Path) -> set[str]:
    """Top-level names of the modules imported by the .py files under `folder`."""
    imports = _Imports()
    for path in folder.rglob("*.py"):
        imports.visit(ast.parse(path.read_text(), str(path)))
    return imports.names


def normalized(name: str) -> str:
    """A distribution name in PEP 503 normal form."""
    return re.sub(r"[-_.]+", "-", name).lower()


def declared_distributions() -> set[str]:
    """Every distribution pyproject.toml declares, runtime and extras alike."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    specs = [*project["dependencies"], *sum(project["optional-dependencies"].values(), [])]
    return {normalized(re.match(r"[A-Za-z0-9._-]+", spec).group()) for spec in specs}


def test_every_third_party_import_is_declared():
    third_party = imported_modules(REPO / "jaxnav") - set(sys.stdlib_module_names)
    third_party -= {"jaxnav", *ROS_MODULES}
    providers = importlib.metadata.packages_distributions()
    declared = declared_distributions()
    undeclared = sorted(
        module
        for module in third_party
        if not declared & {normalized(d) for d in providers.get(module, [module])}
    )
    assert not undeclared, f"imported by jaxnav but not declared in pyproject.toml: {undeclared}"


def test_constraints_pin_every_dependency_within_its_declared_range():
    """constraints.txt (the tested set CI installs) pins each dependency of the project and of its
    extras at a release that pyproject.toml's range allows."""
    from packaging.requirements import Requirement

    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pins[re.sub(r"[-_.]+", "-", name).lower()] = version
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    declared = [*project["dependencies"], *project["optional-dependencies"]["dev"]]
    for text in declared:
        req = Requirement(text.split("#")[0])
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        assert name in pins, f"constraints.txt pins no {req.name}"
        assert req.specifier.contains(pins[name], prereleases=True), (req, pins[name])
