"""Test helpers for researchers: assert a run is no worse than a recorded baseline.

Use in your own pytest tests::

    from mapfuse.runner import run
    from mapfuse.testing import assert_no_worse_than_baseline

    def test_my_change_keeps_the_ekf_accurate(my_log):
        result = run(my_log, "ekf", fusion=True)
        assert_no_worse_than_baseline(result.metrics, "tests/baselines/my_scenario.json")

Record the baseline once with :func:`mapfuse.baseline.record_baseline` and
:func:`mapfuse.baseline.save_baseline` (or ``mapfuse baseline record``).  The
rules and default tolerances are those of :mod:`mapfuse.baseline`.  No pytest
import: a plain :class:`AssertionError` works under any test runner.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mapfuse.baseline import BaselineReport, Tolerance, check_baseline

__all__ = ["assert_no_worse_than_baseline"]


def assert_no_worse_than_baseline(
    run_metrics: Mapping[str, Any],
    baseline_path: str | Path,
    metrics: Sequence[str] | None = None,
    tolerance: Tolerance | Mapping[str, Tolerance] | None = None,
) -> BaselineReport:
    """Raise :class:`AssertionError` if ``run_metrics`` is worse than its baseline.

    ``run_metrics``: a ``metrics.json`` object (``Run.metrics``).
    ``baseline_path``: a baseline file; its entry of the same backend and fusion
    setting is used.  ``metrics``: dotted metric names to check (default
    :data:`mapfuse.baseline.DEFAULT_METRICS`).  ``tolerance``: one
    :class:`~mapfuse.baseline.Tolerance` for all of them, or one per metric
    (others keep their defaults).  The error message names every failing metric with
    its baseline value, its new value and the tolerance.  Returns the report when
    the run passes.
    """
    __tracebackhide__ = True  # pytest: show the caller's line, not this helper's
    report = check_baseline(run_metrics, baseline_path, tolerances=tolerance, which=metrics)
    if not report.passed:
        raise AssertionError(
            f"{report.run} is worse than its baseline {baseline_path}:\n" + report.failure_message()
        )
    return report
