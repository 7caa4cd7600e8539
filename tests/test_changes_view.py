"""Where the known map predicts a feature in view: the extractor's rule (the log's
laser given) against the beam-count rule, and the move search's limits widened by the
known feature's own σ."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.changes import ChangeParams
from mapfuse_core.changes.visibility import scans_in_view
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.perception.extraction import ExtractionParams
from mapfuse_core.sensor import LaserParams

BEAMS = ChangeParams(view_stride=1)
EXTRACTOR = BEAMS.with_sensor(LaserParams())


def _tree(x: float, r: float) -> KnownMapArrays:
    return KnownMapArrays(
        ids=np.array([7], dtype=np.int64),
        kinds=np.array([1], dtype=np.int8),
        params=np.array([[x, 0.0, r]]),
        covs=np.zeros((1, 3, 3)),
        extents=np.full((1, 2), np.nan),
    )


def _wall(x: float, half: float) -> KnownMapArrays:
    """A wall across the sensor's view, ``x`` ahead, ``2 half`` long."""
    return KnownMapArrays(
        ids=np.array([3], dtype=np.int64),
        kinds=np.array([0], dtype=np.int8),
        params=np.array([[x, 0.0, math.pi / 2]]),
        covs=np.zeros((1, 3, 3)),
        extents=np.array([[-half, half]]),
    )


POSES = np.zeros((6, 3))


@pytest.mark.parametrize(("x", "r"), [(7.0, 0.46), (8.0, 0.46), (5.0, 0.3)])
def test_trunk_hit_by_many_beams_that_the_extractor_rejects_is_not_in_view(
    x: float, r: float
) -> None:
    # The beam rule counts it (at least 12 beams hit it) ...
    assert scans_in_view(_tree(x, r), POSES, BEAMS)[7] == 6
    # ... but the noise-free scan gives a circle below the extractor's predicted
    # signal-to-noise rule, so the extractor rule does not expect it.
    assert scans_in_view(_tree(x, r), POSES, EXTRACTOR)[7] == 0


@pytest.mark.parametrize(("x", "r"), [(6.0, 0.46), (10.0, 0.8)])
def test_trunk_the_extractor_returns_is_in_view_under_both_rules(x: float, r: float) -> None:
    assert scans_in_view(_tree(x, r), POSES, BEAMS)[7] == 6
    assert scans_in_view(_tree(x, r), POSES, EXTRACTOR)[7] == 6


def test_extractor_rule_takes_the_extractors_settings_and_stops_at_max_range() -> None:
    wall = _wall(20.0, 10.0)
    # A 20 m wall 20 m ahead is in view under both rules ...
    assert scans_in_view(wall, POSES, BEAMS)[3] == 6
    assert scans_in_view(wall, POSES, EXTRACTOR)[3] == 6
    # ... not for an extractor that wants walls of 25 m or more ...
    strict = BEAMS.with_sensor(LaserParams(), ExtractionParams(min_line_length_m=25.0))
    assert scans_in_view(wall, POSES, strict)[3] == 0
    # ... and not beyond max_range_m (30 m), though the laser reaches 80 m.
    assert scans_in_view(_wall(50.0, 10.0), POSES, EXTRACTOR)[3] == 0
    far = dataclasses.replace(EXTRACTOR, max_range_m=60.0)
    assert scans_in_view(_wall(50.0, 10.0), POSES, far)[3] == 6


def test_view_stride_counts_every_strideth_scan_times_the_stride() -> None:
    p = ChangeParams(view_stride=4).with_sensor(LaserParams())
    assert scans_in_view(_tree(6.0, 0.46), np.zeros((9, 3)), p)[7] == 12


def test_change_params_refuse_a_laser_or_extraction_of_the_wrong_type() -> None:
    with pytest.raises(ValueError, match=r"ChangeParams\.laser"):
        ChangeParams(laser="sick")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"ChangeParams\.extraction"):
        ChangeParams(extraction=3)  # type: ignore[arg-type]
