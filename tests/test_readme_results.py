"""The README's Results table is exactly what benchmarks/readme_results.py made of its last JSON."""

import json
from pathlib import Path

import pytest
from conftest import benchmark_script

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def script():
    return benchmark_script("readme_results")


def test_readme_table_matches_results_json(script):
    results = json.loads(script.OUT.read_text())
    readme = (ROOT / "README.md").read_text()
    table = readme.split(script.BEGIN, 1)[1].split(script.END, 1)[0].strip()
    assert table == script.render(results), "run benchmarks/readme_results.py --write-readme"
    for line in results["lines"]:
        assert line["command"] and line["machine"] and line["date"], line


def test_render_names_command_machine_and_date(script):
    line = dict(what="w", command="python -m x", machine="m", date="2026-01-01", result="r")
    assert script.render({"lines": [line]}).splitlines()[-1] == (
        "| w | `python -m x` | m, 2026-01-01 | r |"
    )


def test_every_result_says_where_it_came_from():
    """Each result JSON in benchmarks/results names its command, its git commit and its date
    (`benchmarks/report.py`'s `write_json` adds them). The run folders `readme_results.py` trains
    there (git-ignored) are runs, not results."""
    folder = ROOT / "benchmarks" / "results"
    results = sorted(
        path
        for path in folder.rglob("*.json")
        if not path.relative_to(folder).parts[0].startswith("readme-run")
    )
    if not results:
        pytest.skip("benchmarks/ is not in this checkout")
    for path in results:
        data = json.loads(path.read_text())
        name = path.relative_to(ROOT)
        assert data.get("command"), f"{name}: no command"
        commit = data.get("commit", "")
        assert len(commit) == 40 and int(commit, 16) >= 0, f"{name}: commit {commit!r}"
        assert data.get("date"), f"{name}: no date"
