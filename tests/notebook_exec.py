"""Executing a stored notebook in a fresh kernel, for the tests that run them.

The kernel (``python3``, resolved by jupyter_client to this interpreter) runs every
cell in the notebooks directory; a cell error raises ``CellExecutionError`` naming the
cell and its traceback, and a cell past the timeout fails alike.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import nbclient
import nbformat

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"

TIMEOUT_S = 600
"""Per-cell timeout (s): a whole notebook targets two minutes on a laptop; the margin is
for loaded machines, the timeout only catches a hung or runaway cell."""

RESULT_MARK = "NOTEBOOK-RESULT "
"""Prefix of the line an appended cell prints its JSON after."""


def read_notebook(name: str) -> Any:
    """The stored notebook ``notebooks/{name}.ipynb``."""
    return nbformat.read(NOTEBOOK_DIR / f"{name}.ipynb", as_version=4)


def execute_notebook(name: str, *, after: str = "") -> Any:
    """The notebook ``name`` as executed, every output in it.

    The kernel inherits this process's environment (a test sets ``MAPFUSE_DATA``, made
    absolute: the kernel runs in the notebooks directory).  ``after``: source of one more
    cell run after the stored ones (not stored: it reads what the notebook computed, for
    a test to check).
    """
    nb = read_notebook(name)
    if after:
        nb.cells.append(nbformat.v4.new_code_cell(after))
    client = nbclient.NotebookClient(
        nb,
        timeout=TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    client.execute()
    return nb


def printed_result(nb: Any) -> Any:
    """The JSON the last cell printed after :data:`RESULT_MARK`."""
    for out in nb.cells[-1].outputs:
        for line in out.get("text", "").splitlines():
            if line.startswith(RESULT_MARK):
                return json.loads(line[len(RESULT_MARK) :])
    outputs = nb.cells[-1].outputs
    raise AssertionError(f"the appended cell printed no {RESULT_MARK!r} line: {outputs}")
