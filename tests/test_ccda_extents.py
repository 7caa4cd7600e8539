"""CCDA with line extents (segment overlap tests) and with ambiguous partners left
unpaired; the bounded k-truss peeling."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.matching.ccda import CCDAParams, ccda_match
from mapfuse_core.matching.ccda import clique as clique_mod
from mapfuse_core.matching.ccda.inspect import CorrespondenceGraph, correspondence_graph
from mapfuse_core.matching.ccda.params import _check_params
from mapfuse_core.matching.ccda.prepare import _prepare
from mapfuse_core.matching.ccda.verification import _segments_overlap
from mapfuse_core.measlog import KnownMapArrays
from tests.ccda_helpers import LINE, line_cov, move, perturb, random_overlap, rotate_cov

S_LAT, S_TH = 0.02, 0.005
"""Line noise of the hand-made maps: centimetres and a fraction of a degree, so that
only the extents decide what these tests check."""


def walls_map(
    walls: list[np.ndarray], extents: list[tuple[float, float]], T: np.ndarray | None = None
) -> KnownMapArrays:
    """Lines ``walls`` (origin and angle) with the given extents from their origins,
    moved by ``T``."""
    T = np.zeros(3) if T is None else T
    params = [move(LINE, T, w) for w in walls]
    covs = [rotate_cov(LINE, T, line_cov(float(w[2]), S_LAT, S_TH)) for w in walls]
    return KnownMapArrays(
        ids=np.arange(len(walls), dtype=np.int64),
        kinds=np.full(len(walls), LINE, dtype=np.int8),
        params=np.array(params),
        covs=np.array(covs),
        extents=np.array(extents, dtype=float),
    )


def corner(extents: list[tuple[float, float]], T: np.ndarray | None = None) -> KnownMapArrays:
    """Two perpendicular walls meeting at the origin (along +x and +y), with the
    given extents from the origin, moved by ``T``."""
    return walls_map([np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, math.pi / 2])], extents, T)


def without_extents(m: KnownMapArrays) -> KnownMapArrays:
    return dataclasses.replace(m, extents=None)


def nodes(a: KnownMapArrays, b: KnownMapArrays, params: CCDAParams) -> dict[tuple[int, int], int]:
    """Node index of every pairing ``(i, j)`` of the correspondence graph."""
    g = correspondence_graph(a, b, params)
    return {(int(i), int(j)): n for n, (i, j) in enumerate(zip(g.node_a, g.node_b, strict=True))}


def has_edge(
    a: KnownMapArrays,
    b: KnownMapArrays,
    na: tuple[int, int],
    nb: tuple[int, int],
    params: CCDAParams | None = None,
) -> bool:
    """Whether the pairings ``na[0]→nb[0]`` and ``na[1]→nb[1]`` share an edge (both
    must be nodes)."""
    params = CCDAParams() if params is None else params
    g = correspondence_graph(a, b, params)
    node = nodes(a, b, params)
    u, v = node[(na[0], nb[0])], node[(na[1], nb[1])]
    edges = set(zip(g.edge_u.tolist(), g.edge_v.tolist(), strict=True))
    return (u, v) in edges or (v, u) in edges


OVERLAP = CCDAParams(extent_rule="overlap")
"""Segments need only overlap (the default)."""
WITHIN = CCDAParams(extent_rule="within")
"""``map_a``'s segments lie within ``map_b``'s walls (a known map of whole walls)."""

MOTIONS = pytest.mark.parametrize(
    "T",
    [np.zeros(3), np.array([7.0, -3.0, 0.4]), np.array([-2.0, 5.0, math.pi])],
    ids=["identity", "turned", "reversed"],
)
"""The motions between the maps: none, a turn, and a turn by π (every line reversed)."""


@MOTIONS
def test_perpendicular_walls_whose_segments_meet_alike_share_an_edge(T: np.ndarray) -> None:
    # A rigid motion keeps each segment's interval measured from the corner (a turn
    # by π reverses both lines' directions, which the test must allow).
    a = corner([(0.0, 5.0), (0.0, 3.0)])
    b = corner([(-1.0, 6.0), (0.0, 3.2)], T)
    for params in (OVERLAP, WITHIN):
        assert has_edge(a, b, (0, 1), (0, 1), params)
    # Overlapping without lying within: A's second wall runs 1 m past B's end.
    c = corner([(0.0, 5.0), (0.0, 4.0)])
    d = corner([(-1.0, 6.0), (0.5, 3.0)], T)
    assert has_edge(c, d, (0, 1), (0, 1), OVERLAP)
    assert (1, 1) not in nodes(c, d, WITHIN)


def test_perpendicular_walls_whose_segments_lie_apart_share_no_edge() -> None:
    # The same corner, but B's first wall lies 10–15 m from the corner: the local
    # map's segment would have to be on the wall's extension past its end.
    a = corner([(0.0, 5.0), (0.0, 4.0)])
    b = corner([(10.0, 15.0), (0.0, 4.0)])
    for params in (WITHIN, OVERLAP):
        assert not has_edge(a, b, (0, 1), (0, 1), params)
        # Without extents only the angle is tested, and the edge is there.
        assert has_edge(without_extents(a), without_extents(b), (0, 1), (0, 1), params)
    # Beyond the margin plus noise only: 0.3 m apart passes with the default margin.
    assert has_edge(a, corner([(5.3, 9.0), (0.0, 4.0)]), (0, 1), (0, 1), OVERLAP)


def test_a_segment_reaching_past_its_known_walls_end_shares_no_edge() -> None:
    # Within: the part of a wall a run saw lies on the known wall.  A's first wall
    # runs 0–5 m from the corner, B's 0–3.5 m: 1.5 m past its end, beyond the 0.5 m
    # margin and the centimetres of noise.  The wall lengths alone (5 m against
    # 3.5 m) already rule the node out.
    a = corner([(0.0, 5.0), (0.0, 3.0)])
    b = corner([(0.0, 3.5), (0.0, 3.0)])
    assert (0, 0) not in nodes(a, b, WITHIN)
    assert has_edge(a, b, (0, 1), (0, 1), OVERLAP)
    # As long as B's wall, but shifted 1.5 m along it: the node stands, the corner
    # test refuses the edge.
    c = corner([(1.5, 6.5), (0.0, 3.0)])
    assert (0, 0) in nodes(a, c, WITHIN)
    assert not has_edge(a, c, (0, 1), (0, 1), WITHIN)
    assert has_edge(a, c, (0, 1), (0, 1), OVERLAP)
    # Within the margin: 0.3 m past the end passes.
    assert has_edge(a, corner([(0.3, 5.3), (0.0, 3.0)]), (0, 1), (0, 1), WITHIN)


def test_a_segment_reaching_past_its_partner_is_not_reassociated_within() -> None:
    p = CCDAParams()
    A = _prepare(corner([(0.0, 5.0), (0.0, 4.0)]), "map_a", p)
    B = _prepare(corner([(0.0, 3.0), (0.0, 4.0)]), "map_b", p)
    ii, jj = np.array([0]), np.array([0])
    assert _segments_overlap(A, B, np.zeros(3), ii, jj, 0.5)[0]
    assert not _segments_overlap(A, B, np.zeros(3), ii, jj, 0.5, within=True)[0]
    # Shifted by 2 m along the wall, B's segment covers 2–5 m: A (0–5 m) starts 2 m
    # before it.
    B6 = _prepare(corner([(0.0, 6.0), (0.0, 4.0)]), "map_b", p)
    assert _segments_overlap(A, B6, np.zeros(3), ii, jj, 0.5, within=True)[0]
    assert not _segments_overlap(A, B6, np.array([2.0, 0.0, 0.0]), ii, jj, 0.5, within=True)[0]


def test_an_unknown_extent_rule_is_refused() -> None:
    with pytest.raises(ValueError, match="extent_rule"):
        _check_params(CCDAParams(extent_rule="inside"))  # type: ignore[arg-type]


def test_segment_overlap_under_a_transform_follows_the_along_line_shift() -> None:
    p = CCDAParams()
    A = _prepare(corner([(0.0, 5.0), (0.0, 4.0)]), "map_a", p)
    B = _prepare(corner([(20.0, 25.0), (0.0, 4.0)]), "map_b", p)
    ii, jj = np.array([0]), np.array([0])
    assert not _segments_overlap(A, B, np.zeros(3), ii, jj, 0.5)[0]
    # Shifting B by −18 m along the wall puts its segment at 2–7 m: overlap.
    assert _segments_overlap(A, B, np.array([-18.0, 0.0, 0.0]), ii, jj, 0.5)[0]
    # Turned by π about the wall's far end, the segment runs back over A's.
    assert _segments_overlap(A, B, np.array([25.0, 0.0, math.pi]), ii, jj, 0.5)[0]


def test_a_feature_with_two_partners_in_the_gate_is_counted_but_not_paired() -> None:
    case = random_overlap(4)
    ref = ccda_match(case.map_a, case.map_b)
    assert ref.accepted
    lines = [(i, j) for i, j in ref.pairings if int(case.map_b.kinds[j]) == LINE]
    i, j = lines[0]
    # A second known wall 1 mm beside the paired one: both pass the gate.
    twin = case.map_b.params[j].copy()
    th = float(twin[2])
    twin[:2] += 1e-3 * np.array([-math.sin(th), math.cos(th)])
    b = dataclasses.replace(
        case.map_b,
        ids=np.append(case.map_b.ids, 10_000),
        kinds=np.append(case.map_b.kinds, LINE).astype(np.int8),
        params=np.vstack([case.map_b.params, twin]),
        covs=np.concatenate([case.map_b.covs, case.map_b.covs[j : j + 1]]),
    )
    res = ccda_match(case.map_a, b)
    assert res.accepted, res.reason
    paired_a = {p for p, _ in res.pairings}
    assert i not in paired_a
    assert set(res.pairings) == set(ref.pairings) - {(i, j)}
    # With the rule off, the feature goes to one of the two.
    loose = ccda_match(case.map_a, b, CCDAParams(unique_partners=False))
    assert i in {p for p, _ in loose.pairings}


def test_distinct_partner_counts_agree_between_the_table_and_the_hash(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(0)
    n, m = 300, 40
    u = rng.integers(0, n, 5000)
    v = rng.integers(0, n, 5000)
    feat = rng.integers(0, m, n)
    dense = clique_mod._distinct_partners(n, u, v, feat)
    monkeypatch.setattr(clique_mod, "_DENSE_CELLS", 0)
    hashed = clique_mod._distinct_partners(n, u, v, feat)
    np.testing.assert_array_equal(dense, hashed)
    assert dense.max() <= m


def test_a_negative_extent_margin_is_refused() -> None:
    with pytest.raises(ValueError, match="extent_margin_m"):
        _check_params(CCDAParams(extent_margin_m=-1.0))


def corridor(extents: list[tuple[float, float]], T: np.ndarray | None = None) -> KnownMapArrays:
    """Two parallel walls 2 m apart (along +x at y = 0 and y = 2, origins at x = 0),
    with the given extents along x, moved by ``T``."""
    return walls_map([np.array([0.0, 0.0, 0.0]), np.array([0.0, 2.0, 0.0])], extents, T)


@MOTIONS
def test_parallel_walls_whose_segments_fit_one_shift_share_an_edge(T: np.ndarray) -> None:
    # Both pieces of the local map lie on their walls at one shift along the corridor.
    a = corridor([(0.0, 4.0), (10.0, 14.0)])
    b = corridor([(-1.0, 5.0), (9.0, 16.0)], T)
    # The same walls, each line stated in the opposite direction (angle + π, its
    # extent mirrored): lines fix the rotation only modulo π.
    assert b.extents is not None
    flipped = dataclasses.replace(
        b,
        params=b.params + np.array([0.0, 0.0, math.pi]),
        extents=-b.extents[:, ::-1],
    )
    for params in (OVERLAP, WITHIN):
        assert has_edge(a, b, (0, 1), (0, 1), params)
        assert has_edge(a, flipped, (0, 1), (0, 1), params)


def test_parallel_walls_whose_segments_need_two_shifts_share_no_edge() -> None:
    # A's pieces lie 10 m apart along the corridor, B's side by side: the first
    # pairing needs a shift near 0, the second one near 10 m.  Only the angle and the
    # distance between the walls agree, which once let pairings of walls along a
    # corridor shifted by any length form large chance cliques.
    a = corridor([(0.0, 4.0), (10.0, 14.0)])
    b = corridor([(0.0, 4.0), (0.0, 4.0)], np.array([3.0, 1.0, 0.7]))
    for params in (OVERLAP, WITHIN):
        assert not has_edge(a, b, (0, 1), (0, 1), params)
        assert has_edge(without_extents(a), without_extents(b), (0, 1), (0, 1), params)
    # Overlapping within 0.5 m, the first pairing allows shifts of −4.5 to 4.5 m; the
    # second, from 4.5 m less the lever of the angle noise (0.09 m) with A's piece at
    # 9–13 m, from 4.8 m with it at 9.3–13 m.
    d = corridor([(0.0, 4.0), (0.0, 4.0)])
    assert has_edge(corridor([(0.0, 4.0), (9.05, 13.0)]), d, (0, 1), (0, 1), OVERLAP)
    assert not has_edge(corridor([(0.0, 4.0), (9.3, 13.0)]), d, (0, 1), (0, 1), OVERLAP)
    # Within: A's pieces must lie inside B's at one shift; here the second needs a
    # shift of −2 m and the first one near 0, though both pairings overlap at 0.
    a = corridor([(0.0, 4.0), (0.0, 4.0)])
    b = corridor([(0.0, 4.0), (2.0, 6.0)])
    assert has_edge(a, b, (0, 1), (0, 1), OVERLAP)
    assert not has_edge(a, b, (0, 1), (0, 1), WITHIN)


def test_pieces_far_apart_on_one_wall_keep_their_edge_under_an_angle_error() -> None:
    # One wall seen as two pieces 200 m apart; B's wall is turned by 0.06 rad about
    # its middle, inside the angle gate of 0.02 rad of noise in each map, and each of
    # B's pieces ends 0.49 m short of its partner (inside the 0.5 m margin) under the
    # identity.  Along A's line B's coordinates shrink by cos 0.06, 0.36 m over the
    # 200 m: the one offset must allow for that foreshortening.
    eps, gap = 0.06, 0.49
    c = math.cos(eps)
    wall = np.array([100.0, 0.0, eps])
    a = walls_map([np.zeros(3), np.array([200.0, 0.0, 0.0])], [(0.0, 4.0), (0.0, 4.0)])
    b = walls_map(
        [wall, wall],
        [((-104.0 - gap) / c, (-100.0 - gap) / c), ((104.0 + gap) / c, (108.0 + gap) / c)],
    )
    noisy = [line_cov(float(w[2]), 0.05, 0.02) for w in (a.params[0], a.params[1])]
    a = dataclasses.replace(a, covs=np.array(noisy))
    b = dataclasses.replace(b, covs=np.array([line_cov(eps, 0.05, 0.02)] * 2))
    assert has_edge(without_extents(a), without_extents(b), (0, 1), (0, 1), OVERLAP)
    assert has_edge(a, b, (0, 1), (0, 1), OVERLAP)


def _walls_with_pieces(
    seed: int, s_th: float = 0.02
) -> tuple[KnownMapArrays, KnownMapArrays, set[tuple[int, int]]]:
    """A known map of 8–20 walls up to 120 m long (most of them axis-parallel, as in a
    building) and a local map holding a piece of 60–90 % of them, moved by a random
    motion, each piece's ends up to 0.49 m past its wall's (the drift along a wall,
    just inside the 0.5 m margin).  Both maps are noisy (lateral 2 cm, angle ``s_th``)
    and state some lines in the opposite direction (angle + π, extent mirrored).
    Returns both maps and the true pairings (local index, known index)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(8, 21))
    th = np.where(rng.random(n) < 0.8, rng.integers(0, 4, n) * math.pi / 2, rng.uniform(-3, 3, n))
    true_b = np.column_stack([rng.uniform(-60.0, 60.0, (n, 2)), th])
    length = rng.uniform(2.0, 120.0, n)
    ext_b = np.column_stack([-rng.uniform(0.0, 1.0, n) * length, np.zeros(n)])
    ext_b[:, 1] = ext_b[:, 0] + length
    T = np.array([*rng.uniform(-20.0, 20.0, 2), rng.uniform(-math.pi, math.pi)])
    seen = np.sort(rng.choice(n, size=int(rng.uniform(0.6, 0.9) * n), replace=False))
    ext_a = []
    for j in seen.tolist():
        lo, hi = ext_b[j]
        a0, a1 = np.sort(rng.uniform(lo, hi, 2))
        a1 = max(a1, min(a0 + 1.0, hi))
        ext_a.append((a0 - rng.uniform(0.0, 0.49), a1 + rng.uniform(0.0, 0.49)))

    def noisy(lines: np.ndarray, extents: np.ndarray) -> KnownMapArrays:
        params, covs = [], []
        for f in lines:
            S = line_cov(float(f[2]), S_LAT, s_th)
            f2, S2 = perturb(rng, LINE, f, S, along_m=0.0)
            params.append(f2)
            covs.append(S2)
        P, ext = np.array(params), np.array(extents, dtype=float)
        flip = rng.random(len(P)) < 0.3
        P[flip, 2] += math.pi
        ext[flip] = -ext[flip, ::-1]
        return KnownMapArrays(
            ids=np.arange(len(P), dtype=np.int64),
            kinds=np.full(len(P), LINE, dtype=np.int8),
            params=P,
            covs=np.array(covs),
            extents=ext,
        )

    moved = np.array([move(LINE, T, true_b[j]) for j in seen.tolist()])
    truth = {(i, int(j)) for i, j in enumerate(seen.tolist())}
    return noisy(moved, np.array(ext_a)), noisy(true_b, ext_b), truth


def _true_edges(
    g: CorrespondenceGraph, truth: set[tuple[int, int]]
) -> set[frozenset[tuple[int, int]]]:
    """Edges of ``g`` between two true pairings, as pairs of pairings."""
    node = list(zip(g.node_a.tolist(), g.node_b.tolist(), strict=True))
    pairs = zip(g.edge_u.tolist(), g.edge_v.tolist(), strict=True)
    return {
        frozenset((node[u], node[v])) for u, v in pairs if node[u] in truth and node[v] in truth
    }


def _parallel_cut(
    bare: CorrespondenceGraph, full: CorrespondenceGraph, a: KnownMapArrays, b: KnownMapArrays
) -> int:
    """Edges between pairings of two walls parallel in both maps that the extents cut."""

    def edges(g: CorrespondenceGraph) -> set[frozenset[tuple[int, int]]]:
        node = list(zip(g.node_a.tolist(), g.node_b.tolist(), strict=True))
        return {
            frozenset((node[u], node[v]))
            for u, v in zip(g.edge_u.tolist(), g.edge_v.tolist(), strict=True)
        }

    def parallel(m: KnownMapArrays, f: int, g: int) -> bool:
        d = (m.params[f, 2] - m.params[g, 2]) % math.pi
        return bool(min(d, math.pi - d) < 0.05)

    def both(e: frozenset[tuple[int, int]]) -> bool:
        (i, j), (k, j2) = tuple(e)
        return parallel(a, i, k) and parallel(b, j, j2)

    nodes = set(zip(full.node_a.tolist(), full.node_b.tolist(), strict=True))
    # Edges whose pairings are both nodes with extents (the unary length test of
    # "within" removes nodes, and their edges with them).
    return sum(1 for e in edges(bare) - edges(full) if both(e) and e <= nodes)


def test_the_segment_tests_never_cut_an_edge_between_true_pairings() -> None:
    # On random noisy buildings (parallel and perpendicular walls, some stated reversed,
    # pieces up to 0.49 m past their wall's ends), every pair of true pairings keeps its
    # edge with extents; and the extents cut edges between wrong pairings of parallel
    # walls, which only the along-wall test does.
    kept = cut = 0
    for seed in range(30):
        a, b, truth = _walls_with_pieces(seed)
        for params in (OVERLAP, WITHIN):
            bare = correspondence_graph(without_extents(a), without_extents(b), params)
            full = correspondence_graph(a, b, params)
            lost = _true_edges(bare, truth) - _true_edges(full, truth)
            assert not lost, (seed, params.extent_rule, sorted(map(sorted, lost))[:3])
            kept += len(_true_edges(full, truth))
            cut += _parallel_cut(bare, full, a, b)
    assert kept > 2000
    assert cut > 1000


def _corners_reference(
    ca: np.ndarray, cb: np.ndarray, sign: float, g1: float, p: CCDAParams
) -> bool:
    """One row of the corner test, written out: the ``A`` segments along lines ``i`` and
    ``k`` against their partners', for both orientations of the rotation."""
    if not (np.all(np.isfinite(ca[:4])) and np.all(np.isfinite(cb[:4]))):
        return True

    def agrees(lo: float, hi: float, blo: float, bhi: float, s: float, m: float) -> bool:
        lo, hi = (lo, hi) if s > 0 else (-hi, -lo)
        if p.extent_rule == "within":
            return bool(blo - m <= lo and hi <= bhi + m)
        return bool(lo <= bhi + m and blo <= hi + m)

    m_i = p.extent_margin_m + math.sqrt(g1 * (ca[4] + cb[4]))
    m_k = p.extent_margin_m + math.sqrt(g1 * (ca[5] + cb[5]))
    return any(
        agrees(ca[0], ca[1], cb[0], cb[1], r, m_i)
        and agrees(ca[2], ca[3], cb[2], cb[3], r * sign, m_k)
        for r in (1.0, -1.0)
    )


@pytest.mark.parametrize("rule", ["overlap", "within"])
def test_the_vectorised_corner_test_is_the_written_out_rule(rule: str) -> None:
    from mapfuse_core.matching.ccda.graph import _corners_overlap
    from mapfuse_core.matching.ccda.params import _Gates

    rng = np.random.default_rng(7)
    n = 4000
    ca, cb = rng.normal(0.0, 2.0, (n, 6)), rng.normal(0.0, 2.0, (n, 6))
    ca[:, 4:], cb[:, 4:] = 0.02 * np.abs(ca[:, 4:]), 0.02 * np.abs(cb[:, 4:])
    ca[rng.random(n) < 0.05, :4] = np.nan  # unknown extents pass
    cb[rng.random(n) < 0.05, 2] = np.nan
    ca[rng.random(n) < 0.02, 5] = np.nan  # a known extent with no variance fails
    sign = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    p, gates = CCDAParams(extent_rule=rule), _Gates.of(0.999)  # type: ignore[arg-type]
    got = _corners_overlap(ca, cb, sign, gates, p)
    want = [_corners_reference(ca[r], cb[r], sign[r], gates.g1, p) for r in range(n)]
    assert got.tolist() == want
    assert 0.2 < got.mean() < 0.8  # both outcomes are exercised
    # No rows, all rows unknown, or all known: the short cuts.
    assert _corners_overlap(ca[:0], cb[:0], sign[:0], gates, p).size == 0
    unknown = np.full((5, 6), np.nan)
    assert _corners_overlap(unknown, cb[:5], sign[:5], gates, p).tolist() == [True] * 5
    known = np.isfinite(ca[:, :4]).all(axis=1) & np.isfinite(cb[:, :4]).all(axis=1)
    sub = _corners_overlap(ca[known], cb[known], sign[known], gates, p)
    assert sub.tolist() == [w for w, k in zip(want, known, strict=True) if k]


def test_common_neighbour_counts_are_those_of_the_adjacency_matrix() -> None:
    # Dense enough that rows hold several words and counts pass 255 (8-bit sums
    # would wrap).
    rng = np.random.default_rng(3)
    n = 700
    dense = np.triu(rng.random((n, n)) < 0.6, 1)
    u, v = (x.astype(np.int64) for x in np.nonzero(dense))
    adj = (dense | dense.T).astype(np.int64)
    W = clique_mod._packed_adjacency(n, u, v)
    got = clique_mod._common_neighbours(W, u, v)
    want = (adj @ adj)[u, v]
    assert np.array_equal(got, want)
    assert want.max() > 255
    # Row sums in 16 bits only where a row's count (≤ 64 per word) fits them.
    assert clique_mod._row_sum_dtype(1023) == np.uint16
    assert clique_mod._row_sum_dtype(1024) == np.int64
