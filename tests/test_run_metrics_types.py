"""Typed metrics: ``RunMetrics.to_json`` is ``metrics.json``, and reads back exactly."""

from __future__ import annotations

import json
import math

import pytest

import mapfuse as mf
from mapfuse_core.estimate import RunMetrics

#: The keys of ``metrics.json`` in the README's table, in order, for a graph run.
GRAPH_KEYS = [
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
