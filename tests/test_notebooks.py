"""The notebooks: stored clean, all logic imported, and each runs without error.

Executing a notebook starts a kernel (``python3``, resolved by jupyter_client to this
interpreter) and runs every cell; a cell error or a timeout fails the test.  Each
notebook is meant to run in under two minutes on a laptop; the per-cell timeout is
looser so a loaded CI machine does not fail them spuriously.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import nbclient
import nbformat
import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
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
# Per-cell timeout (s): a whole notebook targets two minutes; the margin is for loaded
# machines, the timeout only catches a hung or runaway cell.
TIMEOUT_S = 600


def _read(name: str) -> object:
    return nbformat.read(NOTEBOOK_DIR / f"{name}.ipynb", as_version=4)


def _code(src: str) -> str:
    """Cell source without IPython magics, so that it parses as Python."""
    return "\n".join("" if line.lstrip().startswith("%") else line for line in src.splitlines())


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_clean(name: str) -> None:
    nb = _read(name)
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


@pytest.mark.slow
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_runs(
    name: str, request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> None:
    if name in NEEDS_DATA:
        # Skips with a message when the data directory is absent.  The kernel inherits
        # MAPFUSE_DATA, made absolute because it runs in the notebooks directory.
        data = request.getfixturevalue("data_dir")
        monkeypatch.setenv("MAPFUSE_DATA", str(Path(data).resolve()))
    nb = _read(name)
    client = nbclient.NotebookClient(
        nb,
        timeout=TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    # Raises CellExecutionError (naming the cell and the traceback) on any error.
    client.execute()
    errors = [
        out
        for cell in nb.cells  # type: ignore[attr-defined]
        if cell.cell_type == "code"
        for out in cell.outputs
        if out.output_type == "error"
    ]
    assert not errors
