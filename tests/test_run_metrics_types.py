"""Typed metrics: ``RunMetrics.to_json`` is ``metrics.json``, and reads back exactly."""

from __future__ import annotations

import json
import math

import pytest

import mapfuse as mf
from mapfuse_core.estimate import METRICS_SCHEMA_VERSION, RunMetrics

#: The keys of ``metrics.json`` in the README's table, in order, for a graph run.
GRAPH_KEYS = [
    "schema_version",
    "scenario",
    "seed",
    "backend",
    "fusion",
    "steps",
    "position_error_m",
    "heading_error_rad",
    "nees",
    "anchor",
    "map",
    "runtime_s",
    "matching",
    "association",
    "known_map_rejections",
    "estimate",
    "nees_filtered",
    "position_error_filtered_m",
    "warnings",
]


@pytest.fixture(scope="module")
def isam2_run() -> mf.Run:
    return mf.run(mf.simulate("loop600", seed=1, steps=200), "isam2")


def test_to_json_has_the_documented_keys_in_order(isam2_run: mf.Run) -> None:
    obj = isam2_run.metrics.to_json()
    assert list(obj) == GRAPH_KEYS
    assert list(obj["position_error_m"]) == ["rmse", "mean", "median", "max", "final"]
    assert obj["backend"] == "isam2"
    assert obj["association"] == "ekf"


def test_json_round_trip_is_exact(isam2_run: mf.Run) -> None:
    text = json.dumps(isam2_run.metrics.to_json())
    back = RunMetrics.from_json(json.loads(text))
    assert back == isam2_run.metrics
    assert json.dumps(back.to_json()) == text


def test_scalars_are_dotted_json_paths(isam2_run: mf.Run) -> None:
    m = isam2_run.metrics
    flat = m.scalars()
    assert m.position_error is not None
    assert m.nees is not None
    assert flat["position_error_m.rmse"] == m.position_error.rmse
    assert flat["nees.mean"] == m.nees.mean
    assert flat["runtime_s.total"] == m.runtime.total
    assert all(math.isfinite(v) for v in flat.values())


def test_from_json_names_what_is_missing_or_mistyped(isam2_run: mf.Run) -> None:
    obj = isam2_run.metrics.to_json()
    missing = {k: v for k, v in obj.items() if k != "map"}
    with pytest.raises(ValueError, match="metrics has no 'map'"):
        RunMetrics.from_json(missing)
    mistyped = {**obj, "steps": "many"}
    with pytest.raises(ValueError, match=r"metrics.steps must be of type int, got 'many'"):
        RunMetrics.from_json(mistyped)
    bad_choice = {**obj, "estimate": "final"}
    with pytest.raises(ValueError, match=r"metrics\.estimate must be one of"):
        RunMetrics.from_json(bad_choice)


def test_a_field_with_a_default_may_be_absent(isam2_run: mf.Run) -> None:
    obj = {k: v for k, v in isam2_run.metrics.to_json().items() if k != "warnings"}
    assert RunMetrics.from_json(obj).warnings == ()


def test_schema_version_is_written_and_a_newer_one_refused(isam2_run: mf.Run) -> None:
    obj = isam2_run.metrics.to_json()
    assert obj["schema_version"] == METRICS_SCHEMA_VERSION == 2
    assert "schema_version" not in isam2_run.metrics.scalars()
    with pytest.raises(ValueError, match="schema version 3 is newer than this mapfuse reads"):
        RunMetrics.from_json({**obj, "schema_version": 3})
    with pytest.raises(ValueError, match="schema_version must be an integer"):
        RunMetrics.from_json({**obj, "schema_version": "2"})


def test_the_nees_acceptance_region_is_named_so_and_old_files_still_read(
    isam2_run: mf.Run,
) -> None:
    obj = isam2_run.metrics.to_json()
    region = obj["nees"]["mean_interval"]
    assert "interval_95" not in region
    lo, hi = region["acceptance_95"]
    # An acceptance region around the 3 degrees of freedom, not an interval around the
    # run's own mean.
    assert lo < 3.0 < hi
    # A schema-1 file (no schema_version, the old key) reads to the same metrics.
    old = json.loads(json.dumps(obj))
    del old["schema_version"]
    for block in ("nees", "nees_filtered"):
        mi = old[block]["mean_interval"]
        mi["interval_95"] = mi.pop("acceptance_95")
    back = RunMetrics.from_json(old)
    assert back == isam2_run.metrics
    assert back.nees is not None
    assert back.nees.mean_interval is not None
    assert back.nees.mean_interval.interval_95 == back.nees.mean_interval.acceptance_95
