"""The paper's per-seed criteria on loop600, seeds 0–4: accuracy, anchor, consistency (slow).

Where the EKF does not meet the paper's figure on a seed, the case is a strict ``xfail``
with the measured value, so the gap stays visible in every test run (and an
improvement fails the run as XPASS, to be looked at and the mark removed).

The extracted features are unbiased (``tests/test_extraction_consistency.py``) and the
odometry is white with its stated covariance.  ``tests/test_loop600_graph.py`` compares
the EKF with iSAM2's filtered estimates on the same inputs and the EKF's final
association decisions.  Where the remaining gaps come from (the paper's local maps, the
known-map draw, the autocorrelation of one run's NEES), with the per-seed and 40-seed
figures, is in ``docs/results/known-gaps.md``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapfuse.testing import assert_no_worse_than_baseline
from mapfuse_core.evaluation import anchor_truth, known_map_draw_offset
from mapfuse_core.geometry.se2 import compose, wrap_angle
from mapfuse_core.sim.scenario import build_known_map, load_scenario
from tests.loop600 import SEEDS, ekf_metrics, loop600_ekf, loop600_ekf_carry, loop600_log

pytestmark = pytest.mark.slow


def _seeds(known_gaps: dict[int, str]) -> list[object]:
    return [
        pytest.param(s, marks=pytest.mark.xfail(reason=known_gaps[s], strict=True))
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
            # Seed 1's known map is off by 5.6 cm as a whole at the anchor (NEES 16 on 3
            # dof, a one in a thousand draw): an ideal estimator is expected that far from
            # the truth; see test_anchor_is_near_what_the_known_map_allows.
            1: "anchor error 4.2 cm (the known-map draw itself puts it 5.6 cm off; the "
            "batch smoother on the same inputs 4.5 cm)",
        }
    ),
)
def test_anchor_accuracy(seed: int) -> None:
    a = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))["anchor"]
    # Paper: 3.8 cm; the per-seed bounds 4 cm and 2 mrad.
    assert a["position_error_m"] <= 0.04, a
    assert a["heading_error_rad"] <= 0.002, a


@pytest.mark.parametrize("seed", SEEDS)
def test_anchor_is_near_what_the_known_map_allows(seed: int) -> None:
    """The anchor against where an ideal estimator is expected to put it, given the
    seed's known-map draw (:func:`~mapfuse_core.evaluation.known_map_draw_offset`)."""
    log = loop600_log(seed)
    known = build_known_map(load_scenario("loop600"), np.random.default_rng(0))
    assert np.array_equal(known.ids, log.known_map.ids)
    k = log.known_map
    draw = known_map_draw_offset(k.kinds, k.params, k.covs, known.true_params)
    truth = anchor_truth(log.true_poses)
    ideal = compose(draw.offset, truth)
    est = loop600_ekf(seed, True).anchor
    assert est is not None
    # The per-seed bounds 4 cm and 2 mrad, held against what the map allows instead
    # of the truth.
    assert math.hypot(*(est.x_Wknown_Wglobal[:2] - ideal[:2])) <= 0.04
    assert abs(wrap_angle(est.x_Wknown_Wglobal[2] - ideal[2])) <= 0.002
    if seed == 1:
        # The draw behind the xfail of test_anchor_accuracy[1].
        assert math.hypot(*(ideal[:2] - truth[:2])) > 0.05
        assert draw.nees > 12.0


@pytest.mark.parametrize(
    "seed",
    _seeds(
        {
            4: "max error 0.172 m (iSAM2's filter 0.141 m)",
        }
    ),
)
def test_fusion_bounds_the_error(seed: int) -> None:
    m = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))
    # The paper: fused position error stays under 0.15 m along the loop.
    assert m["position_error_m"]["max"] <= 0.15, m["position_error_m"]


@pytest.mark.parametrize("seed", SEEDS)
def test_carrying_seen_features_across_joins_meets_the_papers_max_error(seed: int) -> None:
    """The ablation behind the max-error gaps: with ``carry_seen_steps=1`` (beyond the
    paper) a new local map holds the global features seen at the last step, and the
    fused EKF meets 0.15 m on every seed, 2 and 4 included (the filter's figures)."""
    m = ekf_metrics(loop600_ekf_carry(seed), loop600_log(seed))
    # Measured: 0.081, 0.114, 0.131, 0.095, 0.146 m (paper's local maps: 0.084, 0.121,
    # 0.151, 0.103, 0.175; iSAM2's filter 0.077, 0.109, 0.138, 0.097, 0.141).
    assert m["position_error_m"]["max"] <= 0.15, m["position_error_m"]
    a = m["anchor"]
    assert a is not None
    assert a["correct_pairings"] == a["pairings"]


@pytest.mark.parametrize(
    ("seed", "fusion"),
    [
        pytest.param(s, f, marks=pytest.mark.xfail(reason=why, strict=True))
        if (
            why := {
                (4, True): "86 % within; iSAM2's filter on the same inputs 84 % "
                "(test_the_ekf_is_as_consistent_as_the_nonlinear_filter)",
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


@pytest.mark.parametrize("seed", SEEDS)
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
