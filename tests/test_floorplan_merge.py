"""The floor plan's cluster merge: the same clusters as a scan that restarts after
every merge, on walls seen in pieces that the greedy pass splits."""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.data.datasets.floorplan import (
    FloorPlanParams,
    _cluster,
    _mean_wall,
    _merge_clusters,
    _one_wall,
    _Segments,
    _Wall,
)


def _restarting_merge(
    member: np.ndarray, refs: list[int], seg: _Segments, p: FloorPlanParams
) -> dict[int, _Wall]:
    """The merge written plainly: after every merge, scan again from the first cluster."""

    def mean(c: int) -> _Wall:
        return _mean_wall(seg.lines[refs[c]], seg.take(np.flatnonzero(member == c)))

    alive = sorted(set(int(c) for c in member if c >= 0))
    means = {c: mean(c) for c in alive}
    i = 0
    while i < len(alive) - 1:
        a, rest = alive[i], alive[i + 1 :]
        hit = np.flatnonzero(
            _one_wall(
                means[a].line,
                means[a].extent,
                np.array([means[b].line for b in rest]),
                np.array([means[b].extent for b in rest]),
                p.rho_tol_m,
                p.alpha_tol_rad,
                p.gap_m,
            )
        )
        if hit.size == 0:
            i += 1
            continue
        b = rest[int(hit[0])]
        member[member == b] = a
        alive.remove(b)
        del means[b]
        means[a] = mean(a)
        i = 0
    return means


def _pieces(rng: np.random.Generator, walls: int, per_wall: int) -> _Segments:
    """Pieces of ``walls`` long walls, each piece's line off its wall by noise near the
    clustering tolerances, so that the greedy pass splits walls the merge then joins."""
    lines, extents = [], []
    for _ in range(walls):
        x0, y0 = rng.uniform(-20.0, 20.0, 2)
        th = rng.uniform(-math.pi, math.pi)
        u = np.array([math.cos(th), math.sin(th)])
        n = np.array([-u[1], u[0]])
        for _ in range(per_wall):
            along = rng.uniform(-8.0, 8.0)
            half = rng.uniform(0.3, 3.0)
            mid = np.array([x0, y0]) + along * u + rng.normal(0.0, 0.06) * n
            lines.append([*mid, th + rng.normal(0.0, math.radians(2.0))])
            extents.append([-half, half])
    return _Segments(np.array(lines), np.array(extents))


def test_the_merge_equals_a_scan_restarting_after_every_merge() -> None:
    p = FloorPlanParams()
    rng = np.random.default_rng(7)
    merges = 0
    for _ in range(40):
        seg = _pieces(rng, walls=int(rng.integers(2, 7)), per_wall=int(rng.integers(4, 25)))
        member, refs = _cluster(seg, p)
        before = np.unique(member).size
        expected_member = member.copy()
        expected = _restarting_merge(expected_member, refs, seg, p)
        means = _merge_clusters(member, refs, seg, p)
        np.testing.assert_array_equal(member, expected_member)
        assert sorted(means) == sorted(expected)
        for c, w in means.items():
            np.testing.assert_array_equal(w.line, expected[c].line)
            np.testing.assert_array_equal(w.cov, expected[c].cov)
            np.testing.assert_array_equal(w.extent, expected[c].extent)
        merges += before - len(means)
    # The cases exercise the merge, including merges after which an earlier cluster
    # takes the merged one (counted in the equality above).
    assert merges >= 20
