"""``compare --beside``: other scenarios' tables in the report, and the paper's regime
(``loop600-sparse``) named in a ``loop600`` report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from mapfuse.comparison import (
    PAPER_REGIME,
    Comparison,
    beside_lines,
    compare,
    report_markdown,
    write_comparison,
)
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import list_builtin_scenarios, load_scenario
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def main_cmp() -> Comparison:
    # A short synthetic log named as loop600, EKF only: the report path, not the numbers.
    log = dataclasses.replace(synthetic_log(80, 0), scenario="loop600")
    return compare(log, ("ekf",))


@pytest.fixture(scope="module")
def sparse_cmp() -> Comparison:
    log: MeasurementLog = dataclasses.replace(synthetic_log(60, 1), scenario="loop600-sparse")
    return compare(log, ("ekf",))


def test_the_paper_regime_is_a_builtin_scenario_beside_loop600() -> None:
    assert PAPER_REGIME == {"loop600": "loop600-sparse"}
    assert {"loop600", "loop600-sparse"} <= set(list_builtin_scenarios())
    dense, sparse = load_scenario("loop600"), load_scenario("loop600-sparse")
    # Same trajectory, sensor and noise; fewer features.
    assert sparse.steps == dense.steps
    assert sparse.laser == dense.laser
    assert sparse.vehicle == dense.vehicle
    assert len(sparse.world.segments) < len(dense.world.segments)


def test_a_loop600_report_names_the_paper_regime(main_cmp: Comparison) -> None:
    report = report_markdown(main_cmp)
    assert "`--beside loop600-sparse`" in report
    assert "## loop600-sparse" not in report
    assert beside_lines("carpark", ()) == []  # no paper regime for other sources


def test_beside_puts_the_other_table_and_metrics_in_the_report(
    main_cmp: Comparison, sparse_cmp: Comparison, tmp_path: Path
) -> None:
    paths = write_comparison(main_cmp, tmp_path, beside=(sparse_cmp,))
    report = (tmp_path / "report.md").read_text()
    main, other = report.split("## loop600-sparse, seed 1 (the paper's regime)")
    assert "--beside loop600-sparse" not in main  # the note gives way to the table
    rows = [ln for ln in other.splitlines() if ln.startswith("| ekf with")]
    assert [r.split(" | ")[0] for r in rows] == ["| ekf with fusion", "| ekf without fusion"]
    pe = sparse_cmp.get("ekf", False).metrics.position_error
    assert pe is not None
    rmse = pe.rmse
    assert f"| {rmse:.3f} |" in rows[1]
    assert "*paper: EKF without fusion*" in other
    beside = json.loads(Path(paths["beside"]).read_text())
    assert list(beside) == ["loop600-sparse"]
    assert [m["fusion"] for m in beside["loop600-sparse"]] == [True, False]
