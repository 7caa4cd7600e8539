"""A floor plan's covariances do not depend on where its reference frame's origin is.

The plan of a log is built in the frame of its reference trajectory, whose origin is
wherever the log starts.  Moving that origin rigidly must move every wall rigidly and
leave each wall's covariance, seen in the wall's own frame, unchanged: a survey
tolerance stated in metres and degrees means the same for a wall beside the origin
and for one 100 m away.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.data.datasets.floorplan import (
    build_floor_plan,
    reference_labels,
    same_wall,
    survey_cov,
)
from mapfuse_core.geometry.se2 import compose, rot2, wrap_scalar_half
from tests.test_line_noise import _log

_MOVES = ((100.0, -40.0, 1.1), (-3.0, 250.0, -2.5))
"""Rigid moves of the reference frame: far enough that a covariance stated about the
origin instead of about each wall would grow by orders of magnitude."""


def _in_wall_frame(theta: float, cov: np.ndarray) -> np.ndarray:
    """A wall's (x, y, θ) covariance with its position axes turned along and across
    direction ``theta``."""
    R = np.eye(3)
    R[:2, :2] = rot2(theta).T
    out: np.ndarray = R @ cov @ R.T
    return out


@pytest.mark.parametrize("move", _MOVES)
def test_moving_the_reference_frame_moves_the_walls_and_keeps_their_covariances(
    move: tuple[float, float, float],
) -> None:
    log = _log((0.01, math.radians(0.3)), 0.0, n=200)
    assert log.true_poses is not None
    G = np.array(move)
    moved = dataclasses.replace(log, true_poses=np.array([compose(G, p) for p in log.true_poses]))
    here, there = build_floor_plan(log), build_floor_plan(moved)
    assert len(here.walls) == len(there.walls) == 5
    np.testing.assert_array_equal(here.obs_wall, there.obs_wall)
    for a, b, ca, cb in zip(
        here.walls.params, there.walls.params, here.walls.covs, there.walls.covs, strict=True
    ):
        # Positions to 1e-9 m: the clustering is the same, only the frame moved.
        np.testing.assert_allclose(compose(G, a)[:2], b[:2], atol=1e-9)
        # Directions modulo π: a wall's y axis points towards its frame's origin.
        assert abs(wrap_scalar_half(float(compose(G, a)[2] - b[2]))) < 1e-9
        # Covariances to 1e-12 (absolute; their entries are 1e-4 m² and below): the
        # normal form's (ρ, α) about the origin rounds no worse than this at 250 m.
        # Both turned along one direction (the walls' own may differ by π).
        th = float(a[2])
        np.testing.assert_allclose(
            _in_wall_frame(th, ca), _in_wall_frame(th + move[2], cb), atol=1e-12
        )


@pytest.mark.parametrize("move", _MOVES)
def test_labels_and_verdicts_do_not_move_with_the_frame(move: tuple[float, float, float]) -> None:
    log = _log((0.01, math.radians(0.3)), 0.0, n=200)
    assert log.true_poses is not None
    G = np.array(move)
    moved = dataclasses.replace(log, true_poses=np.array([compose(G, p) for p in log.true_poses]))
    here, there = build_floor_plan(log), build_floor_plan(moved)
    labels = reference_labels(log, here)
    assert np.count_nonzero(labels >= 0) >= 0.9 * labels.size
    np.testing.assert_array_equal(labels, reference_labels(moved, there))
    n = len(here.walls)
    for a in range(n):
        for b in range(n):
            assert same_wall(here, a, b) == same_wall(there, a, b) == (a == b)


def test_survey_term_is_isotropic_in_position_and_a_rotation_about_the_midpoint() -> None:
    C = survey_cov(0.02, math.radians(0.3))
    np.testing.assert_allclose(C, np.diag([4e-4, 4e-4, math.radians(0.3) ** 2]), rtol=1e-15)
