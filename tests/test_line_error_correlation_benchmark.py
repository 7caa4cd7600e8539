"""``benchmarks/line_error_correlation.py``: the correlations it reports are those of the
errors it is given (a shared error within a scan, a persistent one along a wall)."""

from __future__ import annotations

import numpy as np

from tests.scripts import load_benchmark


def _drive(rng: np.random.Generator, shared: float, persist: float) -> list:
    """Three walls seen at 400 steps; each error is ``shared`` parts a per-scan draw,
    ``persist`` parts a per-wall random walk step kept from scan to scan, and the rest
    independent (unit variance)."""
    out = []
    wall_state = rng.standard_normal((3, 2))
    for step in range(400):
        common = rng.standard_normal(2)
        for wall in range(3):
            wall_state[wall] = persist * wall_state[wall] + np.sqrt(1 - persist**2) * (
                rng.standard_normal(2)
            )
            z = np.sqrt(shared) * common + np.sqrt(1 - shared) * wall_state[wall]
            out.append((step, wall, z, float(z @ z)))
    return out


def test_independent_errors_read_no_correlation_and_shared_ones_read_theirs() -> None:
    bench = load_benchmark("line_error_correlation")
    rng = np.random.default_rng(5)
    clean = bench.summarise([_drive(rng, 0.0, 0.0) for _ in range(3)], [1, 5])
    # 3 drives × 400 scans × 3 wall pairs: a correlation's standard error is about 0.02.
    assert abs(clean["within_scan"]["offset"]) < 0.08
    assert abs(clean["lagged"]["1"]["angle"]) < 0.08
    assert abs(clean["mean"]["offset"]) < 0.08
    assert abs(clean["variance"]["angle"] - 1.0) < 0.1
    assert abs(clean["nees_per_dof"] - 1.0) < 0.1
    shared = bench.summarise([_drive(rng, 0.5, 0.0) for _ in range(3)], [1])
    assert abs(shared["within_scan"]["offset"] - 0.5) < 0.08
    persistent = bench.summarise([_drive(rng, 0.0, 0.9) for _ in range(3)], [1, 5])
    # An AR(1) with coefficient 0.9: lag 1 reads 0.9, lag 5 0.9⁵ = 0.59.
    assert abs(persistent["lagged"]["1"]["angle"] - 0.9) < 0.05
    assert abs(persistent["lagged"]["5"]["offset"] - 0.59) < 0.08
