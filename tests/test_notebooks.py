"""The notebooks: stored clean, all logic imported, and each runs without error.

Executing a notebook starts a kernel and runs every cell (``tests/notebook_exec.py``);
a cell error or a timeout fails the test.  A notebook whose run a test also checks
values of runs there only (:data:`RUN_WITH_CHECKS`), once.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import nbformat
import pytest

from tests.notebook_exec import NOTEBOOK_DIR, execute_notebook, read_notebook

NOTEBOOKS = (
    "01_scenario_and_sensor",
    "02_ekf_reference",
    "03_graph_vs_ekf",
    "04_ccda_matching",
    "05_real_data_carpark",
    "06_victoria_park",
    "07_montecarlo",
    "08_indoor_lines",
)
# Notebooks that read the real datasets: skipped, like the real-data tests, without them.
NEEDS_DATA = ("05_real_data_carpark", "06_victoria_park", "08_indoor_lines")
RUN_WITH_CHECKS = {
    "06_victoria_park": (
        "tests/test_real_runs.py",
        "test_victoria_whole_run_closes_its_loops_without_a_systematic_turn",
    ),
}
"""Notebooks executed by the named test, which also checks what they compute."""


def _code(src: str) -> str:
    """Cell source without IPython magics, so that it parses as Python."""
    return "\n".join("" if line.lstrip().startswith("%") else line for line in src.splitlines())


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_clean(name: str) -> None:
    nb = read_notebook(name)
    nbformat.validate(nb)
    cells = nb.cells  # type: ignore[attr-defined]
    assert cells[0].cell_type == "markdown", "a notebook opens with its symbols and equations"
    assert re.search(r"symbols", cells[0].source, re.IGNORECASE)
    assert "$" in cells[0].source, "the opening cell states its equations"
    for i, cell in enumerate(cells):
        if cell.cell_type != "code":
            continue
        assert cell.outputs == [], f"cell {i} has stored outputs"
        assert cell.execution_count is None, f"cell {i} has an execution count"
        tree = ast.parse(_code(cell.source))
        defined = [
            n
            for n in ast.walk(tree)
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef | ast.Lambda)
        ]
        assert not defined, f"cell {i} defines logic; put it in a package and import it"


def test_every_notebook_runs_in_one_test() -> None:
    assert set(NOTEBOOKS) == {path.stem for path in NOTEBOOK_DIR.glob("*.ipynb")}
    assert set(RUN_WITH_CHECKS) <= set(NOTEBOOKS)
    for name, (module, test) in RUN_WITH_CHECKS.items():
        source = (Path(__file__).resolve().parents[1] / module).read_text()
        assert f"def {test}(" in source, name
        assert f'execute_notebook("{name}"' in source, name


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in NOTEBOOKS if n not in RUN_WITH_CHECKS])
def test_notebook_runs(
    name: str, request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> None:
    if name in NEEDS_DATA:
        # Skips with a message when the data directory is absent.
        data = request.getfixturevalue("data_dir")
        monkeypatch.setenv("MAPFUSE_DATA", str(Path(data).resolve()))
    nb = execute_notebook(name)
    errors = [
        out
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.outputs
        if out.output_type == "error"
    ]
    assert not errors
