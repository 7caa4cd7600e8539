"""Map matching end to end on hostile worlds (``benchmarks/matching_mc.py``), one seed each.

Each case simulates its world, runs the estimators with fusion and judges every CCDA
call they make against the true anchor and the true ids.  Refusing is always
allowed; accepting a wrong match, or merging an observation with a known feature of
another id, never is.  The benchmark runs the same cases over 20 seeds
(``docs/results/ccda.md``, "Measured: hostile worlds").
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest

from tests.scripts import load_benchmark

#: Steps per run: enough for a few CCDA calls (the EKF calls it at every local-map
#: join, every 40 steps, until it accepts).
STEPS = 160


@pytest.fixture(scope="module")
def mc() -> ModuleType:
    return load_benchmark("matching_mc")


def _assert_no_wrong_match(rec: dict[str, Any]) -> None:
    assert rec["error"] is None, rec["error"]
    assert rec["calls"] >= 1, "CCDA was never called: the case tests nothing"
    assert rec["outcome"] != "wrong", rec
    assert rec["by_reason"].get("wrong", 0) == 0, rec
    assert rec["wrong_pairings"] == 0, rec
    assert rec["wrong_known_obs"] == 0, rec


@pytest.mark.parametrize("case", ["manhattan", "trees"])
def test_a_periodic_world_end_to_end_accepts_no_wrong_match(mc: ModuleType, case: str) -> None:
    row = mc.run_case(case, 0, STEPS)
    _assert_no_wrong_match(row["ekf"])


def test_clutter_and_outliers_end_to_end_give_no_wrong_pairing(mc: ModuleType) -> None:
    # loop600 with 5 spurious features per scan and 10 % displaced observations: the
    # EKF and the graph's own association both match (the world is not repetitive)
    # and neither pairs a wrong feature.
    row = mc.run_case("clutter", 0, 80)
    for est in ("ekf", "graph_own"):
        _assert_no_wrong_match(row[est])
        assert row[est]["outcome"] == "right", (est, row[est])


@pytest.fixture(scope="module")
def shifts(mc: ModuleType) -> dict[str, Any]:
    # 60 steps: loop600's first match is accepted after the join of step 39.
    row: dict[str, Any] = mc.run_case("shifts", 0, 60)
    return row


def test_ccda_decides_the_same_wherever_the_world_is(shifts: dict[str, Any]) -> None:
    # World, route and known map moved by 1e3, 1e6 and 1e7 m: every CCDA call gives
    # the same reason and the same pairings (true ids), and its transform moves with
    # the world to 1e-6 relative (round-off of 1e7 m coordinates is ~1e-16 relative).
    assert shifts["ekf"]["outcome"] == "right", shifts["ekf"]
    assert shifts["same_decisions"], shifts
    assert shifts["max_ccda_rel_diff"] <= 1e-6, shifts


def test_the_ekf_anchor_moves_with_the_world(shifts: dict[str, Any]) -> None:
    assert not shifts["errors"], shifts["errors"]
    assert shifts.get("same_anchor_presence", True)
    assert shifts["max_rel_diff"] <= 1e-6, shifts
    assert shifts["max_angle_diff_rad"] <= 1e-6, shifts


def test_recording_restores_the_estimators_ccda(mc: ModuleType) -> None:
    import ekf_reference.pipeline
    import mapfuse_core.matching.ccda as ccda

    calls: list[Any] = []
    with mc.recording(calls):
        assert getattr(ekf_reference.pipeline, "ccda_match") is not ccda.ccda_match  # noqa: B009
    assert getattr(ekf_reference.pipeline, "ccda_match") is ccda.ccda_match  # noqa: B009


def test_every_fused_match_is_judged_and_the_checks_counted(mc: ModuleType) -> None:
    # The constructed runs of tests/test_anchor_watch.py: a wrong match refused by the
    # joint test before fusion, and one fused without it and undone by the watch.
    from tests.test_anchor_watch import _log, _run

    refused = mc.judge_fused(_log(), _run(joint_test=True, watch=True))
    assert refused == {
        "fused_right": 1,
        "fused_right_undone": 0,
        "fused_wrong_kept": 0,
        "fused_wrong_undone": 0,
        "refused_before_fusion": 1,
        "undone_after_fusion": 0,
    }
    undone = mc.judge_fused(_log(), _run(joint_test=False, watch=True))
    assert undone == {
        "fused_right": 1,
        "fused_right_undone": 0,
        "fused_wrong_kept": 0,
        "fused_wrong_undone": 1,
        "refused_before_fusion": 0,
        "undone_after_fusion": 1,
    }
    kept = mc.judge_fused(_log(), _run(joint_test=False, watch=False))
    assert (kept["fused_wrong_kept"], kept["fused_right"]) == (1, 0)
    assert mc.judge_fused(_log(), "RuntimeError: boom")["fused_right"] == 0
