"""Regression baselines: a run passes against itself, a worsened estimator fails.

The committed baseline ``tests/baselines/synthetic_ring_seed0_200.json`` holds every
backend with and without fusion on ``synthetic_log(200, 0)``.  After an intended
change of the estimators, re-record it with::

    MAPFUSE_UPDATE_BASELINES=1 .venv/bin/python -m pytest tests/test_baseline.py
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ekf_reference import EKFConfig, run_ekf
from mapfuse.baseline import (
    DEFAULT_METRICS,
    METRICS,
    BaselineEntry,
    BaselineError,
    Tolerance,
    check_baseline,
    check_log_against_baseline,
    load_baseline,
    record_baseline,
    record_baselines,
    save_baseline,
)
from mapfuse.metrics import run_metrics
from mapfuse.runner import run
from mapfuse.testing import assert_no_worse_than_baseline
from mapfuse_core.estimate import PoseTrack, RunMetrics
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log

COMMITTED = Path(__file__).parent / "baselines" / "synthetic_ring_seed0_200.json"


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(200, 0)


@pytest.fixture(scope="module")
def metrics(log: MeasurementLog) -> RunMetrics:
    return run(log, "ekf", fusion=True).metrics


@pytest.fixture(scope="module")
def baseline(metrics: RunMetrics) -> BaselineEntry:
    return record_baseline(metrics, note="test")


def _worse_log(log: MeasurementLog, kind: str) -> MeasurementLog:
    if kind == "overconfident":
        # The estimator is told the odometry is 10× more precise than it is.
        return dataclasses.replace(log, odometry_cov=log.odometry_cov * 0.01)
    # Noisier odometry than its stated covariance (a badly calibrated robot).
    rng = np.random.default_rng(1)
    odo = log.odometry.copy()
    odo[1:] += rng.normal(0.0, 1.0, (log.n_steps - 1, 3)) * np.array([0.02, 0.01, 0.004])
    return dataclasses.replace(log, odometry=odo)


# --------------------------------------------------------------------------- real runs


def test_the_same_run_passes(log: MeasurementLog, baseline: BaselineEntry) -> None:
    again = run(log, "ekf", fusion=True).metrics
    report = check_baseline(again, baseline)
    assert report.passed, report.summary()
    assert [c.metric for c in report.checks] == list(DEFAULT_METRICS)
    assert all(c.status == "pass" for c in report.checks), report.summary()


@pytest.mark.parametrize(
    ("kind", "metric"),
    [
        ("overconfident", "nees.fraction_within_chi2_95"),
        ("overconfident", "nees.mean"),
        ("noisier", "position_error_m.rmse"),
        ("noisier", "nees.fraction_within_chi2_95"),
    ],
)
def test_a_worsened_estimator_fails_naming_the_metric(
    log: MeasurementLog, baseline: BaselineEntry, kind: str, metric: str
) -> None:
    worse = run(_worse_log(log, kind), "ekf", fusion=True).metrics
    report = check_baseline(worse, baseline)
    assert not report.passed
    failed = {c.metric: c for c in report.failures}
    assert metric in failed, report.summary()
    c = failed[metric]
    base = METRICS[metric]
    assert c.baseline is not None
    assert c.value is not None
    # The message names the metric, the baseline value, the new value and the tolerance.
    assert c.message.startswith(f"{metric} = {c.value:.6g}")
    assert f"baseline {c.baseline:.6g}" in c.message
    assert "tolerance" in c.message
    assert f"{c.limit:.6g}" in c.message
    assert base.better in ("lower", "higher", "target")
    assert metric in report.failure_message()


def test_perturbed_poses_fail_on_accuracy(log: MeasurementLog) -> None:
    res = run_ekf(log, EKFConfig(), fusion=True)
    base = record_baseline(run_metrics(res, log))
    # A bias along x on every pose after the first, twice the RMSE limit: the RMS of
    # (error + bias) is at least |bias| − RMSE > limit, whatever the baseline is.
    m = "position_error_m.rmse"
    assert base.metrics.position_error is not None
    limit = METRICS[m].tolerance.rel * base.metrics.position_error.rmse
    limit += base.metrics.position_error.rmse + METRICS[m].tolerance.abs
    poses = res.poses.copy()
    poses[1:, 0] += 2.0 * limit
    # The same run (its anchor among the rest) with the biased poses.
    biased = dataclasses.replace(res, filtered=PoseTrack(poses, res.covs))
    worse = run_metrics(biased, log)
    report = check_baseline(worse, base)
    assert m in {c.metric for c in report.failures}, report.summary()
    assert report.checks[DEFAULT_METRICS.index("anchor.position_error_m")].passed


def test_check_log_against_a_multi_run_baseline(log: MeasurementLog, tmp_path: Path) -> None:
    entries = record_baselines(log, estimators=("ekf", "isam2"), fusions=(False,))
    path = save_baseline(entries, tmp_path / "b.json")
    reports = check_log_against_baseline(log, path)
    assert [r.run.split(" on ")[0] for r in reports] == [
        "ekf without fusion",
        "isam2 without fusion, smoothed estimate",
    ]
    assert all(r.passed for r in reports), "\n".join(r.summary() for r in reports)
    bad = check_log_against_baseline(_worse_log(log, "noisier"), path)
    assert not any(r.passed for r in bad)


def test_committed_baseline(log: MeasurementLog) -> None:
    if os.environ.get("MAPFUSE_UPDATE_BASELINES") == "1":
        note = (
            "synthetic_log(200, 0) from tests/synthetic.py; re-record: see tests/test_baseline.py"
        )
        save_baseline(record_baselines(log, note=note), COMMITTED)
    entries = load_baseline(COMMITTED)
    assert {(e.metrics.estimator, e.metrics.fusion) for e in entries} == {
        (b, f) for b in ("ekf", "batch", "isam2") for f in (True, False)
    }
    reports = check_log_against_baseline(log, COMMITTED)
    assert all(r.passed for r in reports), "\n".join(r.summary() for r in reports)


# --------------------------------------------------------------------------- rules


def _metrics(**changes: Any) -> dict[str, Any]:
    """A complete ``metrics.json`` object of a fused EKF run, with ``changes`` made
    (``a__b=v`` sets ``m["a"]["b"] = v``)."""
    m: dict[str, Any] = {
        "scenario": "s",
        "seed": 0,
        "backend": "ekf",
        "fusion": True,
        "steps": 10,
        "position_error_m": {"rmse": 0.10, "mean": 0.1, "median": 0.1, "max": 0.2, "final": 0.1},
        "heading_error_rad": {"rmse": 0.01, "max": 0.02},
        "nees": {
            "mean": 3.0,
            "fraction_within_chi2_95": 0.95,
            "bound": 7.8,
            "steps": 10,
            "mean_interval": None,
        },
        "anchor": {
            "estimate": [0.03, 0.0, 0.001],
            "truth": [0.0, 0.0, 0.0],
            "position_error_m": 0.03,
            "heading_error_rad": 0.001,
            "accepted_at_step": 3,
            "pairings": 5,
            "correct_pairings": 5,
        },
        "map": {"features": 10, "matched_known": 5, "seen_once": 0, "tentative_dropped": 0},
        "runtime_s": {"total": 1.0, "per_step_p50": 0.01, "per_step_p99": 0.02},
        "matching": {
            "requested": True,
            "achieved": True,
            "ccda_by": "ekf",
            "ccda_attempts": 1,
            "ccda_reasons": {"accepted": 1},
            "search_limit": 0,
        },
        "warnings": [],
    }
    for path, value in changes.items():
        node = m
        *parents, leaf = path.split("__")
        for p in parents:
            node = node[p]
        node[leaf] = value
    return m


def _status(new: dict[str, Any], base: dict[str, Any], metric: str, **kw: Any) -> str:
    report = check_baseline(new, record_baseline(base), which=(metric,), **kw)
    return report.checks[0].status


def test_lower_is_better_limit() -> None:
    base = _metrics()
    # 0.10 × 1.1 + 0.01 = 0.12
    assert _status(_metrics(position_error_m__rmse=0.1199), base, "position_error_m.rmse") == "pass"
    assert _status(_metrics(position_error_m__rmse=0.1201), base, "position_error_m.rmse") == "fail"
    assert _status(_metrics(position_error_m__rmse=0.0), base, "position_error_m.rmse") == "pass"


def test_higher_is_better_limit() -> None:
    base = _metrics()
    m = "nees.fraction_within_chi2_95"
    assert _status(_metrics(nees__fraction_within_chi2_95=0.901), base, m) == "pass"
    assert _status(_metrics(nees__fraction_within_chi2_95=0.899), base, m) == "fail"
    assert _status(_metrics(nees__fraction_within_chi2_95=1.0), base, m) == "pass"


def test_nees_mean_may_not_move_away_from_three_either_way() -> None:
    base = _metrics(nees__mean=3.4)  # |3.4 − 3| × 1.25 + 0.5 = 1.0
    assert _status(_metrics(nees__mean=3.9), base, "nees.mean") == "pass"
    assert _status(_metrics(nees__mean=2.1), base, "nees.mean") == "pass"
    assert _status(_metrics(nees__mean=4.1), base, "nees.mean") == "fail"
    assert _status(_metrics(nees__mean=1.9), base, "nees.mean") == "fail"


def test_missing_and_absent_values() -> None:
    # The baseline found the anchor, the new run did not: fail.
    report = check_baseline(_metrics(anchor=None), record_baseline(_metrics()))
    failed = {c.metric: c for c in report.failures}
    assert set(failed) == {"anchor.position_error_m", "anchor.heading_error_rad"}
    assert "missing from the new run" in failed["anchor.position_error_m"].message
    # No anchor in the baseline (no fusion): skipped, and the run passes.
    report = check_baseline(_metrics(), record_baseline(_metrics(anchor=None)))
    assert report.passed
    assert {c.metric for c in report.checks if c.status == "skipped"} == {
        "anchor.position_error_m",
        "anchor.heading_error_rad",
    }
    # A NaN is as good as missing.
    report = check_baseline(_metrics(nees__mean=math.nan), record_baseline(_metrics()))
    assert [c.metric for c in report.failures] == ["nees.mean"]


def test_another_run_than_the_baseline_is_a_problem() -> None:
    report = check_baseline(_metrics(seed=3), record_baseline(_metrics()))
    assert not report.passed
    assert report.problems == ("seed: the baseline is of seed 0, the new run of 3",)
    assert all(c.passed for c in report.checks)
    assert "seed" in report.failure_message()


def test_entry_selection_from_several() -> None:
    entries = [
        record_baseline(_metrics(fusion=False, position_error_m__rmse=0.5)),
        record_baseline(_metrics()),
    ]
    assert check_baseline(_metrics(), entries).passed
    # Checked against the fused entry (0.1), not the unfused one (0.5).
    assert not check_baseline(_metrics(position_error_m__rmse=0.3), entries).passed
    assert check_baseline(_metrics(fusion=False, position_error_m__rmse=0.3), entries).passed
    report = check_baseline(_metrics(backend="batch"), entries)
    assert not report.passed
    assert report.problems[0].startswith("no baseline entry for batch with fusion")


def test_tolerance_overrides() -> None:
    base, new = _metrics(), _metrics(position_error_m__rmse=0.15)
    m = "position_error_m.rmse"
    assert _status(new, base, m) == "fail"
    assert _status(new, base, m, tolerances=Tolerance(rel=0.5)) == "pass"
    assert _status(new, base, m, tolerances={m: Tolerance(rel=0.0, abs=0.06)}) == "pass"
    # A tolerance for another metric leaves this one at its default.
    assert _status(new, base, m, tolerances={"nees.mean": Tolerance(abs=9.0)}) == "fail"
    with pytest.raises(ValueError, match="must be finite and >= 0"):
        Tolerance(rel=-0.1)


def test_unknown_metric_is_an_error() -> None:
    with pytest.raises(BaselineError, match="unknown metric"):
        check_baseline(_metrics(), record_baseline(_metrics()), which=("position_rmse",))
    with pytest.raises(BaselineError, match="unknown metric"):
        check_baseline(_metrics(), record_baseline(_metrics()), tolerances={"x": Tolerance()})


def test_runtime_is_checked_only_on_request() -> None:
    slow = _metrics(runtime_s__total=100.0)
    assert check_baseline(slow, record_baseline(_metrics())).passed
    report = check_baseline(slow, record_baseline(_metrics()), which=("runtime_s.total",))
    assert not report.passed


def test_record_from_log(log: MeasurementLog) -> None:
    calls: list[tuple[str, int, int]] = []
    entry = record_baseline(log, "ekf", fusion=False, note="n", progress=lambda *a: calls.append(a))
    assert entry.note == "n"
    assert entry.metrics.estimator == "ekf"
    assert entry.metrics.fusion is False
    assert calls[-1] == ("ekf without fusion", log.n_steps, log.n_steps)


def test_record_from_log_needs_an_estimator(log: MeasurementLog) -> None:
    with pytest.raises(ValueError, match="needs an estimator"):
        record_baseline(log)
    with pytest.raises(ValueError, match="not 'batch'"):
        record_baseline(_metrics(), estimator="batch")
    with pytest.raises(BaselineError, match=r"not a metrics\.json object: .* has no 'scenario'"):
        record_baseline({"backend": "ekf"})


def test_save_load_roundtrip(tmp_path: Path) -> None:
    entry = record_baseline(_metrics(), note="hello")
    path = save_baseline(entry, tmp_path / "sub" / "b.json")
    doc = json.loads(path.read_text())
    assert doc["format"] == "mapfuse.baseline"
    assert doc["version"] == 1
    assert load_baseline(path) == [entry]
    assert check_baseline(_metrics(), path).passed
    assert check_baseline(_metrics(), str(path)).passed


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (None, "no such baseline file"),
        ("{not json", "not a readable JSON baseline"),
        ('{"format": "other"}', "not a mapfuse baseline file"),
        ('{"format": "mapfuse.baseline", "version": 9, "entries": []}', "version 9"),
        ('{"format": "mapfuse.baseline", "version": 1, "entries": []}', "non-empty list"),
        ('{"format": "mapfuse.baseline", "version": 1, "entries": [{}]}', "entry 0 has no"),
    ],
)
def test_bad_baseline_files(tmp_path: Path, content: str | None, match: str) -> None:
    path = tmp_path / "b.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(BaselineError, match=match) as info:
        load_baseline(path)
    assert str(path) in str(info.value)


def test_report_forms() -> None:
    report = check_baseline(
        _metrics(position_error_m__rmse=1.0), record_baseline(_metrics(), note="n")
    )
    text = report.summary()
    assert text.startswith("FAIL: ekf with fusion on s seed 0 (10 steps)")
    assert "position_error_m.rmse = 1 m is worse than the baseline 0.1 m" in text
    d = report.to_dict()
    assert d["passed"] is False
    json.dumps(d)
    assert [c["metric"] for c in d["checks"]] == list(DEFAULT_METRICS)


# --------------------------------------------------------------------------- pytest helper


def test_assert_helper_passes_and_fails(tmp_path: Path) -> None:
    path = save_baseline(record_baseline(_metrics()), tmp_path / "b.json")
    report = assert_no_worse_than_baseline(_metrics(), path)
    assert report.passed
    worse = _metrics(position_error_m__rmse=0.5, nees__fraction_within_chi2_95=0.5)
    with pytest.raises(AssertionError) as info:
        assert_no_worse_than_baseline(worse, path)
    msg = str(info.value)
    assert "position_error_m.rmse = 0.5 m is worse than the baseline 0.1 m" in msg
    assert "nees.fraction_within_chi2_95" in msg
    assert str(path) in msg
    # Only the metrics asked for, with a tolerance of one's own.
    assert_no_worse_than_baseline(worse, path, metrics=("heading_error_rad.rmse",))
    assert_no_worse_than_baseline(
        worse, path, metrics=("position_error_m.rmse",), tolerance=Tolerance(rel=5.0)
    )


def test_helper_does_not_modify_its_input(tmp_path: Path) -> None:
    m = _metrics()
    before = copy.deepcopy(m)
    entry = record_baseline(m)
    entry.to_json()["metrics"]["seed"] = 99
    assert m == before
    # Nor does the entry change with its input.
    m["seed"] = 99
    m["map"]["features"] = 0
    assert (entry.metrics.seed, entry.metrics.map.features) == (0, 10)


def test_a_log_without_known_map_gets_one_unfused_baseline_entry(tmp_path: Path) -> None:
    from mapfuse.cli import main
    from mapfuse_core.measlog import KnownMapArrays, save_log

    log = synthetic_log(60, 2)
    k = log.known_map
    empty = KnownMapArrays(k.ids[:0], k.kinds[:0], k.params[:0], k.covs[:0])
    no_map = dataclasses.replace(log, known_map=empty)
    path = save_log(no_map, tmp_path / "log.npz")
    out = tmp_path / "base.json"
    assert main(["baseline", "record", str(path), "--estimator", "ekf", "--out", str(out)]) == 0
    entries = load_baseline(out)
    assert [e.metrics.fusion for e in entries] == [False]
    # Unambiguous: a run asked to fuse is reported without fusion and matches the entry.
    metrics = run(no_map, "ekf", fusion=True).metrics
    assert metrics.fusion is False
    assert_no_worse_than_baseline(metrics, out)
    assert record_baseline(no_map, "ekf", fusion=True).metrics.fusion is False
    # The harness decides it once: the estimator itself is asked not to fuse (the EKF
    # reports the fusion it was asked for, and made no map matching).
    alone = run(no_map, "ekf", fusion=True).result
    assert alone.fusion is False
    assert alone.matching is None
