"""The loop600 Monte Carlo script's bookkeeping: seed ranges, resumable rows, summary.

The runs themselves are the EKF and graph runs tested elsewhere; these tests hold the
counting that the README's Monte Carlo figures come from.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from tests.scripts import load_benchmark


@pytest.fixture(scope="module")
def mc() -> ModuleType:
    return load_benchmark("mc_loop600")


def _row(seed: int, max_m: float, within: float, anchor_m: float | None) -> dict[str, Any]:
    fused = {
        "max_m": max_m,
        "nees_mean": 3.0,
        "nees_within": within,
        "anchor_m": anchor_m,
        "anchor_rad": None if anchor_m is None else 0.001,
        "wrong_pairings": None if anchor_m is None else 0,
    }
    plain = {**fused, "anchor_m": None, "anchor_rad": None, "wrong_pairings": None}
    return {"seed": seed, "ekf": {"fused": fused, "plain": plain}}


def test_seed_ranges_and_lists(mc: ModuleType) -> None:
    assert mc._parse_seeds("0-3") == [0, 1, 2, 3]
    assert mc._parse_seeds("5,2,7-8") == [5, 2, 7, 8]
    for bad in ("", "a-3", "1-", "-2", "1;2"):
        with pytest.raises(argparse.ArgumentTypeError, match="seeds"):
            mc._parse_seeds(bad)


def test_summary_counts_passes_and_names_the_failing_seeds(mc: ModuleType) -> None:
    rows = [
        _row(0, 0.10, 0.95, 0.02),
        _row(1, 0.16, 0.95, 0.05),  # max error and anchor fail
        _row(2, 0.15, 0.89, None),  # bound itself passes; NEES fails; no anchor fails
    ]
    s = mc.summarise(rows)["ekf"]
    assert s["max_error_le_0.15"] == {"pass": 2, "of": 3, "failing": [1]}
    assert s["nees_within_ge_0.90"] == {"pass": 2, "of": 3, "failing": [2]}
    assert s["anchor_le_4cm_2mrad"] == {"pass": 1, "of": 3, "failing": [1, 2]}
    assert s["max_m_median"] == 0.15
    rows[0]["ekf"]["fused"]["anchor_nees"] = 2.0
    rows[1]["ekf"]["fused"]["anchor_nees"] = 9.0
    s = mc.summarise(rows)["ekf"]
    assert s["anchor_nees_mean"] == 5.5
    assert s["anchor_nees_above_7.815"] == "1/2"
    # An estimator without a field (the filter has no anchor) is not counted on it.
    rows[0]["filter"] = {"fused": {"max_m": 0.2, "nees_mean": 3.0, "nees_within": 0.95}}
    f = mc.summarise(rows)["filter"]
    assert f["max_error_le_0.15"] == {"pass": 0, "of": 1, "failing": [0]}
    assert "anchor_le_4cm_2mrad" not in f


def test_rows_are_read_back_and_bad_lines_named(mc: ModuleType, tmp_path: Path) -> None:
    path = tmp_path / "mc.jsonl"
    assert mc._read(path) == []
    path.write_text(json.dumps(_row(3, 0.1, 0.95, 0.02)) + "\n")
    assert [r["seed"] for r in mc._read(path)] == [3]
    path.write_text(path.read_text() + "{not json\n")
    with pytest.raises(SystemExit, match=r"mc\.jsonl:2"):
        mc._read(path)
