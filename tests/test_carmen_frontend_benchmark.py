"""``benchmarks/carmen_frontend.py``: the wrong re-observations of a run, and which of
them a join made, on constructed decisions against a constructed plan."""

from __future__ import annotations

import numpy as np
import pytest

from tests.scripts import load_benchmark
from tests.test_same_wall import FRAMES, _plan


@pytest.fixture(scope="module")
def bench():  # type: ignore[no-untyped-def]
    return load_benchmark("carmen_frontend")


def test_wrong_reobservations_tell_a_joins_merge_from_the_measurement_association(
    bench,  # type: ignore[no-untyped-def]
) -> None:
    # Walls 0 and 1: one line a doorway apart; wall 2: a parallel wall 1 m off.
    plan = _plan([(0.0, 0.0, 0.0, 1.5), (4.0, 0.0, 0.0, 1.5), (0.0, 1.0, 0.0, 1.5)], FRAMES[1])
    # Landmark 7 took local tracks 10 (wall 0, five observations, one of them really
    # wall 2: the measurement association's error) and 11 (wall 2 twice, then wall 1:
    # a join's merge, and a collinear piece that is no error).
    local = np.array([10, 10, 10, 10, 10, 10, 11, 11, 11])
    labels = np.array([0, 0, 0, 2, 0, 0, 2, 2, 1])
    steps = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8])
    landmark = np.full(9, 7)
    ro = bench.wrong_reobservations(landmark, labels, steps, plan, local)
    assert (ro.judged, ro.wrong, ro.wrong_strict, ro.wrong_at_join) == (8, 3, 4, 2)
    # Without local tracks every error is the measurement association's.
    ro = bench.wrong_reobservations(landmark, labels, steps, plan)
    assert (ro.wrong, ro.wrong_at_join) == (3, 0)
