"""Issue 3 acceptance on loop600, seeds 0–4: accuracy, anchor, consistency (slow)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ekf_reference import ekf_metrics
from tests.loop600 import SEEDS, loop600_ekf, loop600_log

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("seed", SEEDS)
def test_fusion_bounds_the_error_and_finds_the_anchor(seed: int) -> None:
    log = loop600_log(seed)
    m = ekf_metrics(loop600_ekf(seed, True), log)
    # The paper: fused position error stays under 0.15 m along the loop.
    assert m["position_error_m"]["max"] <= 0.15, m["position_error_m"]
    a = m["anchor"]
    assert a is not None, "CCDA never accepted a match"
    # Paper: 3.8 cm; the bounds.
    assert a["position_error_m"] <= 0.04, a
    assert a["heading_error_rad"] <= 0.002, a
    assert a["pairings"] >= 4
    assert a["correct_pairings"] == a["pairings"], "a wrong pairing was accepted"


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("fusion", [True, False])
def test_vehicle_nees_within_chi2_bound_on_90_percent_of_steps(seed: int, fusion: bool) -> None:
    m = ekf_metrics(loop600_ekf(seed, fusion), loop600_log(seed))
    assert m["nees"]["fraction_within_chi2_95"] >= 0.90, m["nees"]


@pytest.mark.parametrize("seed", SEEDS)
def test_without_fusion_the_error_is_larger(seed: int) -> None:
    log = loop600_log(seed)
    fused = ekf_metrics(loop600_ekf(seed, True), log)
    plain = ekf_metrics(loop600_ekf(seed, False), log)
    assert plain["anchor"] is None
    assert plain["position_error_m"]["rmse"] > fused["position_error_m"]["rmse"]
    assert math.isfinite(plain["position_error_m"]["max"])
    assert np.isfinite(plain["nees"]["mean"])
