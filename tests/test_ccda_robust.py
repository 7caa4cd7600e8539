"""CCDA on hostile inputs: periodic worlds, clutter, outliers, hard graphs, far origins.

A periodic world (city blocks of axis-aligned walls, a grid of identical trees) is
where a matcher that picks the best-supported hypothesis can pick the wrong one:
refusing is always allowed there, accepting a wrong transform never.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.evaluation import anchor_truth
from mapfuse_core.geometry.se2 import compose, inverse, transform_point
from mapfuse_core.matching.ccda import REASONS, CCDAParams, ccda_match
from mapfuse_core.measlog import KnownMapArrays, MeasurementLogError, load_log, save_log
from tests.ccda_helpers import (
    CIRCLE,
    LINE,
    circle_cov,
    line_cov,
    make_map,
    move,
    perturb,
    random_overlap,
    rotate_cov,
    transform_error,
)
from tests.test_measlog import small_log

#: The EKF's matching parameters (``ekf_reference`` uses ``CCDAParams(min_pairings=8)``).
EKF_PARAMS = CCDAParams(min_pairings=8)
#: A transform this far from the truth is a wrong match (the noise gives centimetres).
WRONG_XY_M = 1.0
WRONG_THETA_RAD = 0.05


@dataclass(frozen=True)
class World:
    """Features of a periodic world in ``W``, with their true ids."""

    kinds: list[int]
    params: list[np.ndarray]
    centre: np.ndarray
    """(2,) centre of the known map's region."""
    half: np.ndarray
    """(2,) half-size of the known map's region."""


def manhattan(n_x: int = 8, n_y: int = 3, period: float = 40.0, side: float = 28.0) -> World:
    """City blocks: ``n_x × n_y`` square buildings of ``side`` m every ``period`` m,
    four axis-aligned walls each (SPmap lines at the wall midpoints)."""
    kinds, params = [], []
    for ix in range(n_x):
        for iy in range(n_y):
            x0, y0 = ix * period, iy * period
            h = side / 2
            for mx, my, th in (
                (x0 + h, y0, 0.0),
                (x0 + h, y0 + side, math.pi),
                (x0, y0 + h, -math.pi / 2),
                (x0 + side, y0 + h, math.pi / 2),
            ):
                kinds.append(LINE)
                params.append(np.array([mx, my, th]))
    size = np.array([n_x * period, n_y * period])
    return World(kinds, params, size / 2 - (period - side) / 2, size / 2)


def tree_grid(n: int = 12, spacing: float = 10.0, radius: float = 0.3) -> World:
    """An orchard: ``n × n`` identical trees on a square grid."""
    params = [np.array([i * spacing, j * spacing, radius]) for i in range(n) for j in range(n)]
    half = np.array([(n - 1) * spacing / 2] * 2)
    return World([CIRCLE] * len(params), params, half.copy(), half)


@dataclass(frozen=True)
class Case:
    """Known map (a part of the world), local map (what the vehicle saw) and truth."""

    known: KnownMapArrays
    local: KnownMapArrays
    x_local_known: np.ndarray
    """True pose of the known map's frame in the local map's frame."""


def known_and_local(
    world: World,
    seed: int,
    known_fraction: float = 0.75,
    radius: float = 45.0,
    clutter: int = 0,
    outlier_fraction: float = 0.0,
) -> Case:
    """Known map: the world features inside the central ``known_fraction`` of the
    world's extent in x (noisy, σ 5 cm / 0.005 rad).  Local map: every world feature
    within ``radius`` of a random point of the known map's region (so it can reach
    past the known map's edge), noisy (σ 10 cm / 0.01 rad), in a random frame, plus
    ``clutter`` random features and a ``outlier_fraction`` of its features moved
    by 2–10 m (gross outliers)."""
    rng = np.random.default_rng(seed)
    cx, hx = world.centre[0], world.half[0] * known_fraction
    k_kinds, k_params, k_covs = [], [], []
    for k, f in zip(world.kinds, world.params, strict=True):
        if abs(f[0] - cx) <= hx:
            S = line_cov(f[2], 0.05, 0.005) if k == LINE else circle_cov(0.05, 0.02)
            g, S = perturb(rng, k, f, S, along_m=0.0)
            k_kinds.append(k)
            k_params.append(g)
            k_covs.append(S)
    known = make_map(k_kinds, k_params, k_covs)
    T = np.array([*rng.uniform(-100.0, 100.0, size=2), rng.uniform(-math.pi, math.pi)])
    c = world.centre + rng.uniform(-1.0, 1.0, size=2) * np.array([hx, world.half[1]])
    l_kinds, l_params, l_covs = [], [], []
    for k, f in zip(world.kinds, world.params, strict=True):
        if math.hypot(f[0] - c[0], f[1] - c[1]) <= radius:
            S0 = line_cov(f[2], 0.1, 0.01) if k == LINE else circle_cov(0.1, 0.03)
            g, S = perturb(rng, k, move(k, T, f), rotate_cov(k, T, S0), along_m=2.0)
            if rng.random() < outlier_fraction:
                d = rng.uniform(2.0, 10.0) * np.array([*_unit(rng), 0.0])
                g = g + d
            l_kinds.append(k)
            l_params.append(g)
            l_covs.append(S)
    for _ in range(clutter):
        k = CIRCLE if rng.random() < 0.5 else LINE
        p = c + rng.uniform(-radius, radius, size=2)
        f = np.array([*p, rng.uniform(0.1, 1.0) if k == CIRCLE else rng.uniform(-3, 3)])
        S0 = line_cov(f[2], 0.1, 0.01) if k == LINE else circle_cov(0.1, 0.03)
        l_kinds.append(k)
        l_params.append(move(k, T, f))
        l_covs.append(rotate_cov(k, T, S0))
    perm = rng.permutation(len(l_kinds))
    local = make_map(
        [l_kinds[p] for p in perm], [l_params[p] for p in perm], [l_covs[p] for p in perm]
    )
    return Case(known, local, T)


def _unit(rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(-math.pi, math.pi)
    return np.array([math.cos(a), math.sin(a)])


def is_wrong(x: np.ndarray, truth: np.ndarray) -> bool:
    e = transform_error(x, truth)
    return bool(math.hypot(e[0], e[1]) > WRONG_XY_M or abs(e[2]) > WRONG_THETA_RAD)


def shifted(m: KnownMapArrays, S: np.ndarray) -> KnownMapArrays:
    """``m`` re-expressed in a frame in which its own frame is at ``S`` (``S ⊕ f``)."""
    P = [move(int(k), S, f) for k, f in zip(m.kinds, m.params, strict=True)]
    C = [rotate_cov(int(k), S, c) for k, c in zip(m.kinds, m.covs, strict=True)]
    return make_map(m.kinds, P, C)


# --------------------------------------------------------------------------- origin


@pytest.mark.parametrize("shift_m", [0.0, 1e3, 1e6, 1e7])
def test_matching_does_not_depend_on_the_maps_origins(shift_m: float) -> None:
    # Surveyed maps come in UTM-like coordinates: move both maps' origins far away
    # (and turn one); the pairings must not change and the transform must be the
    # moved one.  1e-6 relative to the shift is 10 m at 1e7 m; the match holds to
    # round-off of those coordinates (2e-9 m per coordinate at 1e7 m), far tighter.
    case = random_overlap(4)
    ref = ccda_match(case.map_a, case.map_b)
    assert ref.accepted
    S_a = np.array([shift_m, -0.5 * shift_m, 0.0])
    S_b = np.array([-0.8 * shift_m, 0.3 * shift_m, 0.7])
    res = ccda_match(shifted(case.map_a, S_a), shifted(case.map_b, S_b))
    assert res.accepted, res.reason
    assert res.pairings == ref.pairings
    want = compose(compose(S_a, ref.x_A_B), inverse(S_b))
    err = transform_error(res.x_A_B, want)
    tol = 1e-6 * max(1.0, shift_m)
    assert np.all(np.abs(err[:2]) <= tol), err
    assert abs(err[2]) <= 1e-9, err
    # Tighter than the brief's bound: centimetre geometry survives the far origin.
    assert np.all(np.abs(err[:2]) <= 1e-9 * max(1.0, shift_m) + 1e-9), err


# --------------------------------------------------------------------------- periodic worlds


def outcomes(world: World, params: CCDAParams, seeds: range, **kw: float) -> dict[str, int]:
    """Outcome counts over ``seeds``: ``"right"``, ``"wrong"`` or the refusal reason."""
    counts: dict[str, int] = {}
    for seed in seeds:
        case = known_and_local(world, seed, **kw)  # type: ignore[arg-type]
        res = ccda_match(case.local, case.known, params)
        assert res.reason in REASONS
        key = res.reason
        if res.accepted:
            key = "wrong" if is_wrong(res.x_A_B, case.x_local_known) else "right"
        counts[key] = counts.get(key, 0) + 1
    return counts


SEEDS = range(20)


@pytest.mark.parametrize("world", [manhattan(), tree_grid(8)], ids=["manhattan", "trees"])
def test_a_periodic_world_never_gives_a_wrong_match(world: World) -> None:
    counts = outcomes(world, EKF_PARAMS, SEEDS)
    assert counts.get("wrong", 0) == 0, counts


@pytest.mark.slow
@pytest.mark.parametrize("world", [manhattan(), tree_grid()], ids=["manhattan", "trees"])
def test_a_local_map_reaching_past_the_known_map_never_gives_a_wrong_match(world: World) -> None:
    # A local map wider than the known map's part of the world: shifted by one
    # period it explains more features than at the right place.  The margin rule
    # (ambiguity_margin=1) accepts such shifts; the rival-fraction rule refuses.
    params = CCDAParams(min_pairings=8, max_clique_work=300_000)
    counts = outcomes(world, params, SEEDS, radius=70.0)
    assert counts.get("wrong", 0) == 0, counts


@pytest.mark.parametrize("world", [manhattan(), tree_grid(8)], ids=["manhattan", "trees"])
def test_clutter_and_gross_outliers_never_give_a_wrong_match(world: World) -> None:
    counts = outcomes(world, EKF_PARAMS, SEEDS, clutter=5, outlier_fraction=0.1)
    assert counts.get("wrong", 0) == 0, counts


def test_clutter_and_outliers_in_a_unique_map_still_match() -> None:
    # The same hostile additions on a map without repetition: still the right match.
    case = random_overlap(7)
    rng = np.random.default_rng(7)
    kinds, params, covs = list(case.map_a.kinds), list(case.map_a.params), list(case.map_a.covs)
    for i in rng.choice(len(kinds), size=max(1, len(kinds) // 10), replace=False).tolist():
        params[i] = params[i] + np.array([*(rng.uniform(2.0, 10.0) * _unit(rng)), 0.0])
    for _ in range(5):
        kinds.append(CIRCLE)
        params.append(np.array([*rng.uniform(-80, 80, size=2), rng.uniform(0.1, 1.5)]))
        covs.append(circle_cov(0.1, 0.05))
    res = ccda_match(make_map(kinds, params, covs), case.map_b)
    assert res.accepted, res.reason
    assert not is_wrong(res.x_A_B, case.x_A_B)


# --------------------------------------------------------------------------- bounded search

#: Budget of the pathological search below (work units, see CCDAParams.max_clique_work).
HARD_BUDGET = 100_000


def test_the_likely_clique_first_ends_a_search_that_never_ended() -> None:
    # City blocks seen over 70 m: the exact search for the maximum clique of this graph
    # did not end within minutes.  The greedy clique is found first, its rival too,
    # and the periodic map is refused as ambiguous without any exact search.
    case = known_and_local(manhattan(), 1, radius=70.0)
    res = ccda_match(
        case.local, case.known, CCDAParams(min_pairings=8, max_clique_work=HARD_BUDGET)
    )
    assert res.reason == "ambiguous"
    assert res.search_work == 0


def test_a_search_that_never_ended_stops_at_its_budget() -> None:
    # The same graph, asked for 33 pairings: its greedy cliques hold 31, so the exact
    # search has to prove there is no clique of 32, which it cannot within minutes;
    # with a budget it stops with "search_limit", never a guess.
    case = known_and_local(manhattan(), 1, radius=70.0)
    t0 = time.perf_counter()
    res = ccda_match(
        case.local, case.known, CCDAParams(min_pairings=33, max_clique_work=HARD_BUDGET)
    )
    elapsed = time.perf_counter() - t0
    assert res.reason == "search_limit"
    assert not res.accepted
    # One expansion may overshoot by its candidates (at most the graph's nodes).
    assert HARD_BUDGET < res.search_work <= HARD_BUDGET + res.n_nodes + 1
    assert elapsed < 120.0  # generous: the point is "ends", not a timing
    again = ccda_match(
        case.local, case.known, CCDAParams(min_pairings=33, max_clique_work=HARD_BUDGET)
    )
    assert again.reason == res.reason
    assert again.search_work == res.search_work


def test_running_out_of_hypotheses_is_a_search_limit() -> None:
    # Four rotations of a square: one hypothesis allowed, three more candidates.
    B = make_map(
        [CIRCLE] * 4,
        [[0, 0, 0.5], [10, 0, 0.5], [10, 10, 0.5], [0, 10, 0.5]],
        [circle_cov(0.05, 0.05)] * 4,
    )
    res = ccda_match(B, B, CCDAParams(max_hypotheses=1, ambiguity_margin=0))
    assert res.reason == "search_limit"
    assert not res.accepted


def test_zero_covariances_use_the_documented_floors() -> None:
    # Noise-free maps with zero covariances: the floors (var_floor_m, var_floor_rad)
    # keep the gates invertible, and the match is exact.
    case = random_overlap(2)
    T = np.array([12.0, -7.0, 2.5])
    zero = make_map(case.map_b.kinds, case.map_b.params, np.zeros((len(case.map_b), 3, 3)))
    moved = shifted(zero, T)
    res = ccda_match(moved, zero)
    assert res.accepted, res.reason
    np.testing.assert_allclose(transform_error(res.x_A_B, T), 0.0, atol=1e-6)


@pytest.mark.parametrize("scale", [0.0, 1e-12])
def test_noisy_maps_stated_as_exact_do_not_explode_or_mislead(scale: float) -> None:
    # Noisy features with zero or 1e-12-scaled covariances: true pairs fail their
    # gates; the result is a documented refusal within the budget, never a wrong match.
    case = known_and_local(manhattan(), 3)
    local = make_map(case.local.kinds, case.local.params, case.local.covs * scale)
    known = make_map(case.known.kinds, case.known.params, case.known.covs * scale)
    res = ccda_match(local, known, EKF_PARAMS)
    assert res.reason in REASONS
    assert not (res.accepted and is_wrong(res.x_A_B, case.x_local_known))
    assert res.search_work <= EKF_PARAMS.max_clique_work + res.n_nodes + 1


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("max_clique_work", 0, "max_clique_work"),
        ("rival_fraction", 0.0, "rival_fraction"),
        ("rival_fraction", 1.5, "rival_fraction"),
        ("ambiguity_margin", -1, "ambiguity_margin"),
    ],
)
def test_bad_robustness_params_are_named(field: str, value: float, message: str) -> None:
    case = random_overlap(0)
    with pytest.raises(ValueError, match=message):
        ccda_match(case.map_a, case.map_b, CCDAParams(**{field: value}))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- anchor truth


@pytest.mark.parametrize(
    "frame",
    [[0.0, 0.0, math.pi / 2], [0.0, 0.0, math.pi], [250.0, -40.0, 0.0], [30.0, 12.0, -2.0]],
)
def test_anchor_truth_uses_the_known_maps_frame(frame: list[float]) -> None:
    F = np.array(frame)
    x0 = np.array([-29.0, -11.0, math.pi / 3])
    anchor = anchor_truth(np.array([x0, x0 + 1.0]), F)
    # A world point seen from the vehicle's start (Wglobal) and from the known map's
    # frame (Wknown): the anchor x^Wknown_Wglobal must carry one onto the other.
    p_W = np.array([7.0, 3.0])
    p_global = transform_point(inverse(x0), p_W)
    p_known = transform_point(inverse(F), p_W)
    np.testing.assert_allclose(transform_point(anchor, p_global), p_known, atol=1e-12)
    np.testing.assert_allclose(anchor_truth(np.array([x0]), None), x0)


def test_the_log_stores_the_known_maps_frame_and_logs_without_it_load(tmp_path: Path) -> None:
    log = small_log()
    assert log.known_frame is None
    old = load_log(save_log(log, tmp_path / "old.npz"))  # written without the field
    assert old.known_frame is None
    F = np.array([100.0, -20.0, math.pi / 2])
    new = load_log(save_log(replace(log, known_frame=F), tmp_path / "new.npz"))
    assert new.known_frame is not None
    np.testing.assert_array_equal(new.known_frame, F)
    with pytest.raises(MeasurementLogError, match="known_frame"):
        replace(log, known_frame=np.zeros(2))
