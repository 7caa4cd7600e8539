"""``benchmarks/consistency_regimes.py``: every regime is a world the generator can
draw, and one short run of a regime gives the four rows of the table."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from mapfuse.campaign.stats import anees_bounds
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario
from tests.scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():  # type: ignore[no-untyped-def]
    return load_benchmark("consistency_regimes")


@pytest.mark.parametrize(
    ("regime", "steps", "walls", "trees", "laser_m"),
    [
        ("dense", 2401, 39, 58, 80.0),
        ("sparse", 2333, 10, 45, 80.0),
        ("close", 2401, 12, 45, 80.0),
        ("figure8", 1601, 22, 50, 40.0),
    ],
)
def test_every_regime_is_a_world_the_generator_draws(
    bench, regime: str, steps: int, walls: int, trees: int, laser_m: float
) -> None:  # type: ignore[no-untyped-def]
    world = bench.parse_world_args(bench.REGIMES[regime])
    sc = generate_scenario(WorldParams(seed=0, **world), base=load_scenario("loop600"))
    assert sc.steps == steps
    assert (len(sc.world.segments), len(sc.world.circles)) == (walls, trees)
    assert sc.laser.max_range_m == laser_m


def test_a_short_run_gives_every_estimator_with_and_without_fusion(bench, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    rep = bench.run_regime("figure8", 1, tmp_path, workers=1, steps=60)
    rows = [(g["estimator"], g["fusion"]) for g in rep["groups"]]
    assert rows == [("ekf", True), ("batch", True), ("ekf", False), ("batch", False)]
    lo, hi = anees_bounds(1)
    for g in rep["groups"]:
        assert g["runs"] == 1
        assert g["failed"] == []
        assert math.isfinite(g["anees"])
        assert g["anees_bounds"] == [round(float(lo), 3), round(float(hi), 3)]
        assert 0.0 <= g["steps_inside"] <= 1.0
    # The EKF matches (or not) once; batch consumes its matchings and counts the same.
    ekf, batch = rep["groups"][0], rep["groups"][1]
    for key in ("matches_refused_before_fusion", "anchors_undone_after_fusion"):
        assert ekf[key] == batch[key]
    table = bench.markdown({"regimes": [rep]})
    assert table.count("\n| figure8 |") == 4
    assert (tmp_path / "figure8" / "runs.jsonl").exists()
