"""``benchmarks/join_association.py``: its summary pairs every rule's run with the
default rule's run of the same seed and fusion."""

from __future__ import annotations

import pytest

from tests.scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():  # type: ignore[no-untyped-def]
    return load_benchmark("join_association")


def _row(seed: int, rule: str, fusion: bool, rmse: float, nees: float) -> dict[str, object]:
    return {
        "seed": seed,
        "rule": rule,
        "fusion": fusion,
        "rmse_m": rmse,
        "nees_mean": nees,
        "inside": 0.9,
        "line_landmarks": 40,
        "line_features": 36,
        "line_wrong_obs": 0,
        "circle_wrong_obs": 0,
    }


def test_summary_ratios_are_paired_by_seed_and_fusion(bench) -> None:  # type: ignore[no-untyped-def]
    rows = [
        _row(0, "nn/nearest", False, 0.04, 3.0),
        _row(1, "nn/nearest", False, 0.05, 3.2),
        _row(0, "jcbb/refuse", False, 0.044, 3.3),
        _row(1, "jcbb/refuse", False, 0.055, 3.5),
    ]
    (base, new) = bench.summarise(rows)
    assert base["rmse_ratio_95"] == pytest.approx([1.0, 1.0])
    # Both seeds 10 % worse: the ratio is 1.1 exactly, the interval has no width.
    assert new["rmse_ratio_95"] == pytest.approx([1.1, 1.1])
    assert new["nees_difference_95"] == pytest.approx([0.3, 0.3])
    assert new["runs"] == 2
