"""``same_wall``, the judge of line pairings on real logs: two walls are one line when
they are one line where they are, whatever the reference frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapfuse_core.data.datasets import FloorPlan, same_wall
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import compose
from mapfuse_core.measlog import KnownMapArrays


def _plan(lines: list[tuple[float, float, float, float]], frame: np.ndarray) -> FloorPlan:
    """Walls ``(x, y, θ, half length)`` given in a frame whose pose in ``W`` is ``frame``."""
    params = np.array([compose(frame, np.array(line[:3])) for line in lines])
    n = len(lines)
    walls = KnownMapArrays(
        ids=np.arange(n, dtype=np.int64),
        kinds=np.full(n, int(FeatureKind.LINE), dtype=np.int8),
        params=params,
        covs=np.tile(np.diag([1e-4, 1e-4, 1e-6]), (n, 1, 1)),
        extents=np.array([(-h, h) for *_, h in lines]),
    )
    return FloorPlan(walls=walls, obs_wall=np.zeros(0, dtype=np.int64), n_obs=np.ones(n))


FRAMES = [np.zeros(3), np.array([25.0, -30.0, 0.0]), np.array([-40.0, 10.0, 1.1])]


@pytest.mark.parametrize("frame", FRAMES)
def test_pieces_of_one_line_half_a_degree_apart_are_one_line_in_any_frame(
    frame: np.ndarray,
) -> None:
    # Two 3 m pieces a 1 m doorway apart, 0.5° and 2 cm off each other where they meet.
    # At the origin of the last two frames their ρ differ by 0.2-0.4 m.
    lines = [(0.0, 0.0, 0.0, 1.5), (4.0, 0.02, math.radians(0.5), 1.5)]
    assert same_wall(_plan(lines, frame), 0, 1)


@pytest.mark.parametrize("frame", FRAMES)
def test_a_parallel_wall_30_cm_off_is_another_line_in_any_frame(frame: np.ndarray) -> None:
    lines = [(0.0, 0.0, 0.0, 1.5), (4.0, 0.3, 0.0, 1.5)]
    assert not same_wall(_plan(lines, frame), 0, 1)


@pytest.mark.parametrize("frame", FRAMES)
def test_a_wall_beyond_a_turn_is_another_line(frame: np.ndarray) -> None:
    lines = [(0.0, 0.0, 0.0, 1.5), (3.0, 0.0, math.radians(10.0), 1.5)]
    assert not same_wall(_plan(lines, frame), 0, 1)


def test_collinear_pieces_farther_apart_than_the_gap_are_not_one_wall() -> None:
    plan = _plan([(0.0, 0.0, 0.0, 1.5), (10.0, 0.0, 0.0, 1.5)], FRAMES[1])
    assert not same_wall(plan, 0, 1)
    assert same_wall(plan, 0, 1, gap_m=math.inf)
