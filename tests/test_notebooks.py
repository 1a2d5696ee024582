"""The notebooks: they run from start to finish on tiny budgets, draw their figures, and are committed
without outputs.

Both notebooks run at once, one kernel each, so their compilations share the cores. The kernels use
this interpreter (the one jaxnav is installed in) through a kernel spec written to a temporary folder,
whatever kernels the machine has registered. They start in temporary folders with
`JAXNAV_NOTEBOOK_SMALL=1`, and their run folders go to a temporary folder too, so nothing lands in the
repository.
"""

import asyncio
from pathlib import Path

import nbformat
import pytest
from conftest import cpu_env
from ipykernel.kernelspec import write_kernel_spec
from jupyter_client.kernelspec import KernelSpecManager
from jupyter_client.manager import AsyncKernelManager
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

NOTEBOOKS_DIR = Path(__file__).resolve().parent.parent / "notebooks"
# Notebook -> the figures it draws: (a) quickstart: observation, training curve, paths;
# (b) domain_randomization: two room grids, two histogram rows, the run's reward_curve.png, paths.
FIGURES = {"quickstart": 3, "domain_randomization": 6}
CELL_TIMEOUT = 300  # s; a training cell compiles for ~40 s on 2 cores


def kernel_manager(kernels_dir: Path) -> AsyncKernelManager:
    """A manager for a `python3` kernel running this interpreter."""
    write_kernel_spec(kernels_dir / "python3")
    specs = KernelSpecManager(kernel_dirs=[str(kernels_dir)], ensure_native_kernel=False)
    return AsyncKernelManager(kernel_name="python3", kernel_spec_manager=specs)


async def execute(name: str, root: Path, env: dict):
    """Runs notebook `name` in its own folder under `root`: (executed notebook, error or None)."""
    nb = nbformat.read(NOTEBOOKS_DIR / f"{name}.ipynb", as_version=4)
    cwd = root / name
    cwd.mkdir()
    client = NotebookClient(
        nb,
        km=kernel_manager(root / f"{name}-kernels"),
        timeout=CELL_TIMEOUT,
        resources={"metadata": {"path": str(cwd)}},
    )
    try:
        # cleanup_kc: shut the kernel down afterwards, although the client did not make its manager.
        await client.async_execute(cleanup_kc=True, env={**env, "TMPDIR": str(cwd)}, cwd=str(cwd))
    except CellExecutionError as err:
        return nb, err
    return nb, None


@pytest.fixture(scope="module")
def executed(tmp_path_factory) -> dict:
    """Both notebooks, executed concurrently: {name: (notebook with outputs, error or None)}."""
    root = tmp_path_factory.mktemp("notebooks")
    # Tiny budgets make the kernels compile-bound: quicker XLA compiles (conftest.cpu_env).
    env = {**cpu_env(1), "JAXNAV_NOTEBOOK_SMALL": "1"}
    env.pop("MPLBACKEND", None)  # the kernel then draws inline, as in Jupyter

    async def run_all():
        runs = [execute(name, root, env) for name in FIGURES]
        return dict(zip(FIGURES, await asyncio.gather(*runs), strict=True))

    return asyncio.run(run_all())


def outputs(nb) -> list:
    return [out for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs]


@pytest.mark.slow
@pytest.mark.parametrize("name", FIGURES)
def test_notebook_runs_and_draws(executed, name):
    """Each notebook runs top to bottom in a kernel and draws. Slow: every notebook trains or
    evaluates in a kernel process of its own."""
    nb, err = executed[name]
    if err is not None:
        pytest.fail(f"{name}.ipynb failed:\n{err}", pytrace=False)
    assert not [out for out in outputs(nb) if out.output_type == "error"]
    images = [out for out in outputs(nb) if "image/png" in out.get("data", {})]
    assert len(images) >= FIGURES[name], f"{name}.ipynb drew {len(images)} figures"
    text = "".join(out.get("text", "") for out in outputs(nb) if out.output_type == "stream")
    assert "forward" in text and "collision-free" in text  # the evaluation table


@pytest.mark.parametrize("name", FIGURES)
def test_committed_notebook_has_no_outputs(name):
    nb = nbformat.read(NOTEBOOKS_DIR / f"{name}.ipynb", as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{name}.ipynb cell {i} holds outputs"
            assert cell.execution_count is None, f"{name}.ipynb cell {i} has an execution count"
        assert not {"execution", "widgets"} & set(cell.metadata), f"{name}.ipynb cell {i}"
    assert "widgets" not in nb.metadata
