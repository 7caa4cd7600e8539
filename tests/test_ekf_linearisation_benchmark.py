"""``benchmarks/ekf_linearisation.py``: the regimes' odometry and the summary."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mapfuse_core.sim.simulate import simulate
from tests.scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():  # type: ignore[no-untyped-def]
    return load_benchmark("ekf_linearisation")


@pytest.mark.parametrize(
    ("regime", "lo", "hi"), [("rough", 0.015, 0.021), ("rougher", 0.025, 0.032)]
)
def test_rough_regimes_have_the_carmen_logs_heading_noise(bench, regime, lo, hi) -> None:  # type: ignore[no-untyped-def]
    """A scan a metre and the steering σ scaled: the median heading σ of a step lies in
    the range the docs state (0.018 and 0.029 rad), within the CARMEN logs' 0.018–0.032."""
    sc = dataclasses.replace(bench.scenario(regime), steps=80)
    log = simulate(sc, seed=0, workers=1).log
    sd = float(np.median(np.sqrt(log.odometry_cov[1:, 2, 2])))
    step = float(np.median(np.hypot(log.odometry[1:, 0], log.odometry[1:, 1])))
    assert lo < sd < hi
    assert step == pytest.approx(1.0, rel=0.05)


def test_loop600_regime_is_the_scenario(bench) -> None:  # type: ignore[no-untyped-def]
    from mapfuse_core.sim.scenario import load_scenario

    base = load_scenario("loop600")
    sc = bench.scenario("loop600")
    assert sc.vehicle == base.vehicle
    assert sc.steps == base.steps


def test_summary_pools_the_runs(bench) -> None:  # type: ignore[no-untyped-def]
    rows = [
        {
            "regime": "rough",
            "linearisation": "iterated",
            "fusion": True,
            "nees_mean": m,
            "effective_samples": 50.0,
            "rmse_m": 0.1 * m,
            "max_m": 0.3 * m,
            "anchored": True,
            "wrong_pairings": w,
            "unconverged_steps": 0,
            "runtime_s": 1.0,
        }
        for m, w in ((2.0, 0), (4.0, 1), (9.0, 0))
    ]
    s = bench.summarise(rows)
    assert s["anees"] == pytest.approx(5.0)
    assert s["run_median"] == 4.0
    assert s["run_max"] == 9.0
    assert s["wrong_pairings"] == 1
    lo, hi = s["interval"]
    # 150 effective samples of a 3-dof NEES: χ²(450) bounds over 150, 2.62 and 3.40.
    assert lo == pytest.approx(2.62, abs=0.01)
    assert hi == pytest.approx(3.40, abs=0.01)
    assert "| rough | iterated | plan | 5.00 [" in bench.markdown([s])
