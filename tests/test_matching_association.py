"""The shared association pieces: settings, χ² gate, pre-gate, line gap, NN and JCBB."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import wrap_angle_half
from mapfuse_core.matching import (
    AssociationConfig,
    ScoredPair,
    chi2_gate,
    jcbb,
    line_gap,
    line_overhang,
    near,
    nearest_neighbour,
    pregate,
)
from mapfuse_core.matching.ccda import CCDAParams
from tests.jacobians import poses

# --------------------------------------------------------------------------- settings


def test_defaults_are_the_documented_choices() -> None:
    cfg = AssociationConfig()
    assert cfg.ccda == CCDAParams(min_pairings=8)
    assert cfg.method == "nn"
    assert cfg.one_observation_per(FeatureKind.CIRCLE)
    assert not cfg.one_observation_per(FeatureKind.LINE)
    assert cfg.gate_prob == 0.999
    assert cfg.line_gap_m == 4.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"gate_prob": 0.0}, "gate_prob must be in"),
        ({"gate_prob": 1.0}, "gate_prob must be in"),
        ({"gate_prob": math.nan}, "gate_prob must be in"),
        ({"prefilter_m": 0.0}, "prefilter_m must be a number > 0"),
        ({"prefilter_rad": -0.1}, "prefilter_rad must be a number > 0"),
        ({"line_gap_m": math.nan}, "line_gap_m must be a number > 0"),
        ({"known_gap_m": True}, "known_gap_m must be a number > 0"),
        ({"method": "magic"}, "method must be one of nn, jcbb, got 'magic'"),
        ({"jcbb_max_nodes": 0}, "jcbb_max_nodes must be an int >= 1"),
        ({"jcbb_max_nodes": 2.5}, "jcbb_max_nodes must be an int >= 1"),
        ({"min_obs_for_matching": 0}, "min_obs_for_matching must be an int >= 1"),
        ({"min_obs_for_matching": True}, "min_obs_for_matching must be an int >= 1"),
        ({"match_exclusions": -1}, "match_exclusions must be an int >= 0"),
        ({"match_exclusions": 1.5}, "match_exclusions must be an int >= 0"),
        ({"match_exclusions": False}, "match_exclusions must be an int >= 0"),
        ({"one_observation_per_circle": 1}, "one_observation_per_circle must be a bool"),
        ({"one_observation_per_line": "no"}, "one_observation_per_line must be a bool"),
        ({"ccda": {"min_pairings": 8}}, "ccda must be a CCDAParams, got dict"),
        ({"anchor_prior_sigma": (1.0, 1.0)}, "anchor_prior_sigma must be a tuple of 3"),
        ({"anchor_prior_sigma": (1.0, 1.0, 0.0)}, "anchor_prior_sigma must be a tuple of 3"),
        ({"anchor_prior_sigma": (1.0, math.inf, 1.0)}, "anchor_prior_sigma must be a tuple"),
        ({"anchor_prior_sigma": [1.0, 1.0, 1.0]}, "anchor_prior_sigma must be a tuple of 3"),
    ],
)
def test_bad_settings_are_refused_by_name(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        AssociationConfig(**kwargs)  # type: ignore[arg-type]


def test_infinite_gaps_mean_no_limit() -> None:
    cfg = AssociationConfig(line_gap_m=math.inf, prefilter_m=math.inf)
    q = np.array([0.0, 0.0, 0.0])
    far = np.array([[1000.0, 50.0, 0.1]])
    assert pregate(FeatureKind.LINE, q, (0.0, 1.0), far, lambda k: (0.0, 1.0), cfg) == [0]


def test_chi2_gate_is_the_quantile() -> None:
    for dof in (2, 3):
        assert chi2_gate(0.999, dof) == pytest.approx(float(chi2.ppf(0.999, dof)), rel=1e-15)
    assert chi2_gate(0.999, 2) == pytest.approx(13.815510557964274, rel=1e-12)


# --------------------------------------------------------------------------- line gap


def test_line_gap_along_one_line() -> None:
    t = np.array([0.0, 0.0, 0.0])
    # Target seen on [0, 5]; a query whose reference point is at x = 10, seen on [-1, 2].
    q = np.array([10.0, 0.0, 0.0])
    assert line_gap(q, (-1.0, 2.0), t, (0.0, 5.0)) == pytest.approx(4.0, abs=1e-12)
    # Reversed direction: the same segment, so the same gap.
    q_rev = np.array([10.0, 0.0, math.pi])
    assert line_gap(q_rev, (-2.0, 1.0), t, (0.0, 5.0)) == pytest.approx(4.0, abs=1e-12)
    # On the other side ([-4, -2.5]), and overlapping ([3, 6]).
    assert line_gap(np.array([-3.0, 0.0, 0.0]), (-1.0, 0.5), t, (0.0, 5.0)) == pytest.approx(
        2.5, abs=1e-12
    )
    assert line_gap(q, (-7.0, -4.0), t, (0.0, 5.0)) == 0.0
    # The reference point alone (extent (0, 0)).
    assert line_gap(q, (0.0, 0.0), t, (0.0, 5.0)) == pytest.approx(5.0, abs=1e-12)


def test_line_overhang_is_how_far_a_segment_reaches_beyond_the_target() -> None:
    t = np.array([0.0, 0.0, 0.0])
    # Target on [0, 5]; query reference point at x = 3.
    q = np.array([3.0, 0.0, 0.0])
    assert line_overhang(q, (-2.0, 1.0), t, (0.0, 5.0)) == 0.0  # [1, 4]: inside
    assert line_overhang(q, (-4.0, 1.0), t, (0.0, 5.0)) == pytest.approx(1.0, abs=1e-12)
    assert line_overhang(q, (-1.0, 3.5), t, (0.0, 5.0)) == pytest.approx(1.5, abs=1e-12)
    # Both ends beyond: the larger; reversed direction: the same segment.
    assert line_overhang(q, (-4.0, 4.0), t, (0.0, 5.0)) == pytest.approx(2.0, abs=1e-12)
    q_rev = np.array([3.0, 0.0, math.pi])
    assert line_overhang(q_rev, (-4.0, 4.0), t, (0.0, 5.0)) == pytest.approx(2.0, abs=1e-12)
    # Entirely beyond the target's end, with a gap: the whole far end counts.
    assert line_overhang(np.array([9.0, 0.0, 0.0]), (-1.0, 1.0), t, (0.0, 5.0)) == (
        pytest.approx(5.0, abs=1e-12)
    )
    assert line_overhang(q, (math.nan, math.nan), t, (0.0, 5.0)) == 0.0
    assert line_overhang(q, (-9.0, 9.0), t, (math.nan, math.nan)) == 0.0


def test_line_gap_is_zero_when_an_extent_is_unknown() -> None:
    t, q = np.array([0.0, 0.0, 0.0]), np.array([100.0, 0.0, 0.0])
    assert line_gap(q, (math.nan, math.nan), t, (0.0, 5.0)) == 0.0
    assert line_gap(q, (0.0, 1.0), t, (math.nan, math.nan)) == 0.0


@settings(max_examples=80, deadline=None)
@given(
    poses(),
    st.floats(-30.0, 30.0),
    st.floats(0.0, 10.0),
    st.floats(-30.0, 30.0),
    st.floats(0.0, 10.0),
)
def test_line_gap_does_not_depend_on_the_frame(
    frame: np.ndarray, q0: float, q_len: float, t0: float, t_len: float
) -> None:
    """Two segments on one line: the gap is the distance between the intervals, and moving
    both by any rigid transform leaves it unchanged (near θ = ±π included)."""
    t_line = np.array([2.0, -1.0, 0.4])
    u = np.array([math.cos(0.4), math.sin(0.4)])
    q_line = np.array([*(t_line[:2] + 7.0 * u), 0.4 + math.pi])  # same line, reversed
    q_ext, t_ext = (q0, q0 + q_len), (t0, t0 + t_len)
    # Query's points along the target line: 7 − s.
    lo, hi = 7.0 - q_ext[1], 7.0 - q_ext[0]
    expected = max(lo - t_ext[1], t_ext[0] - hi, 0.0)
    assert line_gap(q_line, q_ext, t_line, t_ext) == pytest.approx(expected, abs=1e-9)
    qw = transform_feature(FeatureKind.LINE, frame, q_line)[0]
    tw = transform_feature(FeatureKind.LINE, frame, t_line)[0]
    assert line_gap(qw, q_ext, tw, t_ext) == pytest.approx(expected, abs=1e-9)


# --------------------------------------------------------------------------- pre-gate


def _near_reference(
    kind: FeatureKind, q: np.ndarray, t: np.ndarray, max_dist: float, max_ang: float
) -> bool:
    """One target at a time, written from the definition."""
    d = t[:2] - q[:2]
    if kind == FeatureKind.CIRCLE:
        return bool(math.hypot(*d) < max_dist)
    n_t = np.array([-math.sin(t[2]), math.cos(t[2])])
    lateral = abs(float(n_t @ d))  # the query's point from the target's line
    return bool(lateral < max_dist and abs(float(wrap_angle_half(t[2] - q[2]))) < max_ang)


@pytest.mark.parametrize("kind", [FeatureKind.LINE, FeatureKind.CIRCLE])
def test_vectorised_near_equals_one_at_a_time(kind: FeatureKind) -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        q = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi)])
        t = np.column_stack(
            [
                rng.uniform(-8, 8, (20, 2)),
                q[2] + rng.normal(0.0, 0.4, 20) + rng.integers(0, 2, 20) * math.pi,
            ]
        )
        got = near(kind, q, t, 3.0, 0.3)
        want = [_near_reference(kind, q, row, 3.0, 0.3) for row in t]
        assert got.tolist() == want


def test_near_takes_lines_modulo_pi_and_the_querys_offset_from_the_target_line() -> None:
    q = np.array([0.0, 0.0, 0.0])
    targets = np.array(
        [
            [5.0, 1.0, math.pi],  # same line reversed, 1 m off
            [5.0, 1.0, 0.5],  # 0.5 rad off
            [40.0, 4.0, 0.1],  # 4 m from q's line, but q's point is on its line
            [40.0, 4.0, 0.0],  # q's point 4 m from its line
        ]
    )
    assert near(FeatureKind.LINE, q, targets, 3.0, 0.3).tolist() == [True, False, True, False]


def test_pregate_drops_collinear_walls_beyond_the_gap_and_asks_only_near_extents() -> None:
    cfg = AssociationConfig()
    q = np.array([0.0, 0.0, 0.0])  # seen on [0, 2]: [-10, -8] along the targets below
    targets = np.array(
        [
            [10.0, 0.1, 0.0],  # collinear, seen on [-7, -5]: 1 m gap
            [10.0, 0.1, 0.0],  # collinear, seen on [10, 20]: 18 m gap
            [0.0, 10.0, 0.0],  # parallel, 10 m off: never near
            [0.0, 0.0, math.pi / 2],  # crossing: never near
        ]
    )
    extents = [(-7.0, -5.0), (10.0, 20.0), (0.0, 1.0), (0.0, 1.0)]
    asked: list[int] = []

    def ext(k: int) -> tuple[float, float]:
        asked.append(k)
        return extents[k]

    assert pregate(FeatureKind.LINE, q, (0.0, 2.0), targets, ext, cfg) == [0]
    assert asked == [0, 1]
    assert pregate(FeatureKind.LINE, q, (0.0, 2.0), targets, ext, cfg, max_gap=20.0) == [0, 1]
    # A known wall without extents: its reference point (−10) within the gap of the
    # segment (3 m and 20 m away).
    assert pregate(FeatureKind.LINE, q, (0.0, 0.0), targets, ext, cfg, max_gap=20.0) == [0, 1]
    assert pregate(FeatureKind.LINE, q, (0.0, 0.0), targets, ext, cfg, max_gap=4.0) == [0]
    assert pregate(FeatureKind.LINE, q, (0.0, 0.0), targets, ext, cfg, max_gap=2.0) == []


def test_pregate_of_circles_is_the_centre_distance() -> None:
    cfg = AssociationConfig(prefilter_m=1.0)
    q = np.array([0.0, 0.0, 0.3])
    targets = np.array([[0.5, 0.5, 5.0], [0.8, 0.8, 0.3], [-0.9, 0.0, 0.3]])

    def no_extent(k: int) -> tuple[float, float]:
        raise AssertionError("circles have no extent")

    assert pregate(FeatureKind.CIRCLE, q, (math.nan, math.nan), targets, no_extent, cfg) == [0, 2]
    assert pregate(FeatureKind.CIRCLE, q, (0.0, 0.0), np.zeros((0, 3)), no_extent, cfg) == []


# --------------------------------------------------------------------------- nearest neighbour


def _exclusive_of(targets: set[int]) -> Callable[[ScoredPair], bool]:
    return lambda c: c.target in targets


def test_nn_gives_an_exclusive_target_to_its_best_query_only() -> None:
    cands = [
        [ScoredPair(0, 2.0), ScoredPair(1, 5.0)],
        [ScoredPair(0, 1.0)],
        [ScoredPair(0, 3.0)],
    ]
    chosen = nearest_neighbour(cands, _exclusive_of({0}))
    assert [c.target if c else None for c in chosen] == [1, 0, None]


def test_nn_lets_a_shared_target_take_several_queries() -> None:
    cands = [[ScoredPair(7, 2.0)], [ScoredPair(7, 1.0)], [ScoredPair(7, 3.0), ScoredPair(8, 4.0)]]
    chosen = nearest_neighbour(cands, _exclusive_of(set()))
    assert [c.target if c else None for c in chosen] == [7, 7, 7]


def test_nn_breaks_ties_by_query_then_candidate_order() -> None:
    cands = [[ScoredPair(1, 1.0)], [ScoredPair(1, 1.0)], [ScoredPair(2, 1.0), ScoredPair(3, 1.0)]]
    chosen = nearest_neighbour(cands, _exclusive_of({1, 2, 3}))
    assert [c.target if c else None for c in chosen] == [1, None, 2]


def test_nn_follows_the_configured_one_to_one_rules() -> None:
    kinds = {0: FeatureKind.LINE, 1: FeatureKind.CIRCLE}
    cands = [[ScoredPair(0, 1.0)], [ScoredPair(0, 2.0)], [ScoredPair(1, 1.0)], [ScoredPair(1, 2.0)]]
    for cfg, want in (
        (AssociationConfig(), [0, 0, 1, None]),
        (AssociationConfig(one_observation_per_line=True), [0, None, 1, None]),
        (AssociationConfig(one_observation_per_circle=False), [0, 0, 1, 1]),
    ):
        chosen = nearest_neighbour(
            cands, lambda c, cfg=cfg: cfg.one_observation_per(kinds[c.target])
        )
        assert [c.target if c else None for c in chosen] == want


# --------------------------------------------------------------------------- JCBB


def _random_case(
    rng: np.random.Generator,
) -> tuple[list[list[ScoredPair]], Callable[[list[ScoredPair]], bool], set[int]]:
    """Up to 5 queries with up to 3 candidates over 4 targets; compatibility is monotone:
    the summed d² within a bound and no pair of pairings from a random conflict list."""
    n_q = int(rng.integers(1, 6))
    cands = []
    for _ in range(n_q):
        ts = rng.choice(4, size=int(rng.integers(0, 4)), replace=False)
        cs = [ScoredPair(int(t), float(rng.uniform(0.0, 4.0))) for t in ts]
        cands.append(sorted(cs, key=lambda c: c.d2))
    flat = [(qi, c.target) for qi, cs in enumerate(cands) for c in cs]
    conflicts = {
        frozenset((flat[a], flat[b]))
        for a, b in itertools.combinations(range(len(flat)), 2)
        if rng.uniform() < 0.25
    }
    bound = float(rng.uniform(2.0, 10.0))
    where = {id(c): qi for qi, cs in enumerate(cands) for c in cs}

    def compatible(pairs: list[ScoredPair]) -> bool:
        keys = [(where[id(c)], c.target) for c in pairs]
        if any(frozenset(p) in conflicts for p in itertools.combinations(keys, 2)):
            return False
        return sum(c.d2 for c in pairs) <= bound

    exclusive = {int(t) for t in range(4) if rng.uniform() < 0.5}
    return cands, compatible, exclusive


def _valid(
    chosen: list[ScoredPair | None],
    compatible: Callable[[list[ScoredPair]], bool],
    exclusive: set[int],
) -> bool:
    pairs = [c for c in chosen if c is not None]
    ex = [c.target for c in pairs if c.target in exclusive]
    return len(ex) == len(set(ex)) and compatible(pairs)


def test_jcbb_finds_the_largest_compatible_set_of_brute_force() -> None:
    rng = np.random.default_rng(11)
    for _ in range(300):
        cands, compatible, exclusive = _random_case(rng)
        got = jcbb(cands, compatible, _exclusive_of(exclusive), max_nodes=100_000)
        assert _valid(got, compatible, exclusive)
        for qi, c in enumerate(got):
            assert c is None or any(c is x for x in cands[qi])
        best = 0
        for choice in itertools.product(*[[None, *cs] for cs in cands]):
            if _valid(list(choice), compatible, exclusive):
                best = max(best, sum(c is not None for c in choice))
        assert sum(c is not None for c in got) == best


def test_jcbb_within_its_node_budget_returns_a_valid_set() -> None:
    rng = np.random.default_rng(5)
    cands, compatible, exclusive = _random_case(rng)
    assert jcbb(cands, compatible, _exclusive_of(exclusive), max_nodes=1) == [None] * len(cands)
    for budget in (2, 5, 20):
        got = jcbb(cands, compatible, _exclusive_of(exclusive), max_nodes=budget)
        assert _valid(got, compatible, exclusive)


def test_jcbb_on_no_queries_is_empty() -> None:
    assert jcbb([], lambda pairs: True, lambda c: True, max_nodes=10) == []
