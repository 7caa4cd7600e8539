"""``benchmarks/changes_summary.py``'s table of classification variants: each variant's
counts are summed over the runs from its own keys, beside the default's."""

from __future__ import annotations

from typing import Any

import pytest

from benchmarks.changes_summary import _variants_table


def _score(moved: tuple[int, int, int], removed: tuple[int, int, int]) -> dict[str, Any]:
    names = ("tp", "fp", "fn")
    return {
        "moved": dict(zip(names, moved, strict=True)),
        "removed": {**dict(zip(names, removed, strict=True)), "beyond_view_tp": 1},
        "added": {"tp": 5, "fp": 0, "fn": 1},
        "moved_surveyed_in_view": {"tp": moved[0], "fn": 1},
    }


def test_each_variant_sums_its_own_scores(capsys: pytest.CaptureFixture[str]) -> None:
    rows = [
        {
            "seed": seed,
            "changed_score": _score((3, 0, 1), (2, 0, 1)),
            "unchanged_score": _score((0, 0, 0), (0, 0, 0)),
            "changed_m0_score": _score((3, 0, 1), (3, 2, 0)),
            "unchanged_m0_score": _score((0, 1, 0), (0, 1, 0)),
            "changed_graph_score": _score((9, 9, 9), (9, 9, 9)),
            "changed_anchor": True,
        }
        for seed in (0, 1)
    ]
    _variants_table(rows)
    lines = capsys.readouterr().out.splitlines()
    table = {ln.split(" | ")[0].strip("| "): ln for ln in lines if ln.startswith("| ")}
    assert set(table) == {"variant", "default", "m0"}  # the graph's score is not a variant
    assert "P 1.000 R 0.750 (tp 6, fp 0, fn 2)" in table["default"]
    assert "P 1.000 R 0.667 (tp 4, fp 0, fn 2, 2 found out of view)" in table["default"]
    assert "P 0.667 R 1.000 (tp 6, fp 4, fn 0, 2 found out of view)" in table["m0"]
    # Moves whose surveyed place came into view: 6 of 8; false moves and false
    # missing on the unchanged maps: 2 each under m0.
    assert table["m0"].split(" | ")[2:4] == ["0.750", "2"]
    assert table["m0"].split(" | ")[5] == "2"


def test_a_variant_may_not_take_the_graph_run_s_keys() -> None:
    import argparse

    from benchmarks.changes_mc import _variant

    assert _variant("m1:missing_radius_sigmas=1.0") == ("m1", {"missing_radius_sigmas": 1.0})
    with pytest.raises(argparse.ArgumentTypeError, match="names the --graph run's keys"):
        _variant("graph:missing_radius_sigmas=1.0")
