"""``benchmarks/bench_isam2_sparse.py``: its world is the long, thin, sparse one it
describes (the run itself takes tens of seconds and is not repeated here)."""

from __future__ import annotations

import numpy as np
import pytest

from mapfuse_core.sim.worldgen import generate_scenario
from tests.scripts import load_benchmark


@pytest.mark.parametrize("seed", [1, 2])
def test_the_sparse_world_is_a_583_m_corridor_of_10_walls_and_45_trees(seed: int) -> None:
    bench = load_benchmark("bench_isam2_sparse")
    sc = generate_scenario(bench.sparse_world(seed))
    assert sc.steps == 2333  # 583 m at loop600's 0.25 m a step
    assert len(sc.world.seg_ids) == 10
    assert len(sc.world.circ_ids) == 45
    assert sc.laser.max_range_m == 80.0
    # Long and thin, whatever the drawn orientation: about 250 m along the principal axis
    # of the waypoints, the 24 m of the two 12 m turns across it.
    w = np.asarray(sc.waypoints, dtype=float)
    axes = np.linalg.svd(w - w.mean(axis=0), full_matrices=False)[2]
    length, width = np.ptp(w @ axes.T, axis=0)
    assert 24.0 <= width <= 28.0  # 24 m between the straights, measured 26.1 m on axes
    assert length > 8 * width
