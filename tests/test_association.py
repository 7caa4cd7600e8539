"""Pairings of the EKF with known walls and estimated lines, and the iterated update used when
CCDA accepts."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from ekf_reference.association import (
    Candidate,
    IteratedUpdate,
    Query,
    apply,
    apply_iterated,
    element_pairings,
    evaluate,
    joint_compatible,
    predict_all_targets,
    prefilter,
    segment_end_sd,
    stack,
    weighed_d2,
    within_known_wall,
)
from ekf_reference.known_frame import known_element
from ekf_reference.state import Element, ElementKind, GaussianMap, Role, bind_line_cov
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, compose_jacobians, wrap_angle
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.models import pairing_residual
from tests.jacobians import ATOL, RTOL, numerical_jacobian, poses

# Measurement-like noise: 1 cm lateral, 5 mrad, and an along-line pseudo-variance of
# a 10 m segment (L²/12) that no residual may see.
LINE_SIGMA = (0.01, 0.005)
PSEUDO = 100.0 / 12.0

offsets = st.floats(min_value=-0.05, max_value=0.05, allow_nan=False)
slides = st.floats(min_value=-40.0, max_value=40.0, allow_nan=False)


def _line_cov(line: np.ndarray, along: float) -> np.ndarray:
    """Covariance of an SPmap line: lateral and angle σ, ``along`` on the along-line axis."""
    c, s = math.cos(line[2]), math.sin(line[2])
    Rm = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out: np.ndarray = Rm @ np.diag([along, LINE_SIGMA[0] ** 2, LINE_SIGMA[1] ** 2]) @ Rm.T
    return out


def _map_with_known_wall(anchor: np.ndarray, wall: np.ndarray) -> GaussianMap:
    """Anchor ``x^R_Wknown`` (σ 5 cm, 2 mrad) and one known wall (bound, in ``Wknown``)."""
    m = GaussianMap()
    m.add(
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
        anchor,
        np.diag([0.05**2, 0.05**2, 0.002**2]),
    )
    m.add(
        Element(ElementKind.LINE, Role.KNOWN, moving=False, track=0),
        wall,
        bind_line_cov(wall, np.diag([0.02**2, 0.02**2, 0.001**2])),
    )
    return m


def _slid(wall: np.ndarray, cov: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The same line with its reference point ``s`` metres along it (covariance moved)."""
    new, J, _ = compose_jacobians(wall, np.array([s, 0.0, 0.0]))
    return new, bind_line_cov(new, J @ cov @ J.T)


def _measurement(m: GaussianMap, along: float, lat: float, ang: float) -> Query:
    """A measured segment of the known wall, ``along`` metres from its reference point."""
    pred = transform_feature(FeatureKind.LINE, m.mean[0], m.mean[1])[0]
    z = compose(pred, np.array([along, lat, ang]))
    return Query(ElementKind.LINE, z, _line_cov(z, PSEUDO), (-5.0, 5.0))


@st.composite
def known_wall_cases(draw: st.DrawFn) -> tuple[GaussianMap, Query]:
    """A map with an anchor and a known wall, and a measured segment of that wall."""
    m = _map_with_known_wall(draw(poses()), draw(poses()))
    return m, _measurement(m, draw(slides), draw(offsets), draw(offsets))


@settings(max_examples=60, deadline=None)
@given(known_wall_cases(), slides)
def test_known_wall_pairing_ignores_where_the_walls_reference_point_lies(
    case: tuple[GaussianMap, Query], s: float
) -> None:
    # The anchor's translation is uncertain along the wall: a residual measured at the
    # wall's reference point would change with s (by s·sin Δθ) and pass information
    # about that translation to the anchor.
    m1, q = case
    m2 = _map_with_known_wall(m1.mean[0], m1.mean[1])
    m2.mean[1], m2.cov[3:6, 3:6] = _slid(m1.mean[1], m1.block(1), s)
    c1, c2 = evaluate(m1, q, 1), evaluate(m2, q, 1)
    np.testing.assert_allclose(c2.residual, c1.residual, atol=1e-9)
    # The anchor's columns and the innovation's χ² do not depend on s either.
    np.testing.assert_allclose(c2.H[:, :3], c1.H[:, :3], atol=1e-8, rtol=1e-8)
    assert math.isclose(c2.d2, c1.d2, rel_tol=1e-6, abs_tol=1e-9)


@settings(max_examples=60, deadline=None)
@given(known_wall_cases())
def test_known_wall_residual_has_no_along_wall_jacobian(case: tuple[GaussianMap, Query]) -> None:
    m, q = case
    c = evaluate(m, q, 1)
    pred = transform_feature(FeatureKind.LINE, m.mean[0], m.mean[1])[0]
    u = np.array([math.cos(pred[2]), math.sin(pred[2])])
    # Translating the anchor along the wall moves the wall onto itself.
    assert abs(float(c.H[0, :2] @ u)) < 1e-12
    assert abs(float(c.H[1, :2] @ u)) < 1e-12


@settings(max_examples=40, deadline=None)
@given(known_wall_cases())
def test_known_wall_noise_ignores_the_along_line_pseudo_variance(
    case: tuple[GaussianMap, Query],
) -> None:
    m, q = case
    loose = Query(q.kind, q.params, _line_cov(q.params, 1e4 * PSEUDO), q.extent)
    c, c_loose = evaluate(m, q, 1), evaluate(m, loose, 1)
    np.testing.assert_allclose(c_loose.R, c.R, atol=1e-12)
    # What is left is the segment's lateral and angle noise (R is 2×2: lateral, angle).
    assert math.isclose(c.R[1, 1], LINE_SIGMA[1] ** 2, rel_tol=1e-9)
    assert LINE_SIGMA[0] ** 2 * 0.99 < c.R[0, 0] < LINE_SIGMA[0] ** 2 * 1.01 + 1e-10


@settings(max_examples=40, deadline=None)
@given(known_wall_cases())
def test_the_gate_takes_the_error_alone_and_the_update_its_weight(
    case: tuple[GaussianMap, Query],
) -> None:
    # A measurement whose covariance is inflated for errors it shares with its
    # neighbours in time (feat_gate_cov): its distance is tested against its error
    # taken alone, while the update still weighs it by the inflated covariance.
    m, q = case
    inflated = dataclasses.replace(q, cov=4.0 * q.cov)
    both = dataclasses.replace(q, cov=4.0 * q.cov, gate_cov=q.cov)
    alone, wide, gated = evaluate(m, q, 1), evaluate(m, inflated, 1), evaluate(m, both, 1)
    np.testing.assert_allclose(gated.R, wide.R, atol=1e-15)
    assert gated.R_gate is not None
    np.testing.assert_allclose(gated.R_gate, alone.R, atol=1e-15)
    np.testing.assert_allclose(gated.residual, alone.residual, atol=1e-15)
    assert math.isclose(gated.d2, alone.d2, rel_tol=1e-12, abs_tol=1e-12)
    assert wide.d2 <= alone.d2 + 1e-12
    # Tests summing consecutive scans take the update's weight; joint tests the gate's.
    assert math.isclose(weighed_d2(m, gated), wide.d2, rel_tol=1e-12, abs_tol=1e-12)
    assert weighed_d2(m, alone) == alone.d2
    R = stack(m, [gated], gate=True)[2]
    np.testing.assert_allclose(R, alone.R, atol=1e-15)
    np.testing.assert_allclose(stack(m, [gated])[2], wide.R, atol=1e-15)


def test_the_joint_test_takes_the_error_alone() -> None:
    # A segment 3 cm off its wall: a χ² gate between its distance with the error alone
    # and with the inflated covariance refuses it with the first only.
    m = _map_with_known_wall(np.array([1.0, 2.0, 0.3]), np.array([5.0, -3.0, 1.2]))
    q = _measurement(m, 1.0, 0.03, 0.002)
    alone = evaluate(m, q, 1)
    wide = evaluate(m, dataclasses.replace(q, cov=4.0 * q.cov), 1)
    gated = evaluate(m, dataclasses.replace(q, cov=4.0 * q.cov, gate_cov=q.cov), 1)
    assert alone.d2 > 1.2 * wide.d2
    gate_prob = float(chi2.cdf(0.5 * (alone.d2 + wide.d2), 2))
    assert 0.0 < gate_prob < 1.0
    assert not joint_compatible(m, [gated], gate_prob)
    assert joint_compatible(m, [wide], gate_prob)


def test_prefilter_measures_a_known_wall_where_the_residual_does() -> None:
    # A segment 40 m from the wall's reference point, 0.1 rad off its direction and on
    # it at its own midpoint: the reference point is 4 m from the segment's line,
    # beyond the 3 m pre-gate, yet the residual's offset is zero.
    m = _map_with_known_wall(np.array([1.0, 2.0, 0.3]), np.array([5.0, -3.0, 1.2]))
    q = _measurement(m, 40.0, 0.0, 0.1)
    targets, preds = predict_all_targets(m, lambda e: True)[ElementKind.LINE]
    assert targets == [1]
    assert prefilter(q, preds, targets, m, AssociationConfig(line_gap_m=math.inf)) == [1]
    assert abs(evaluate(m, q, 1).residual[0]) < 1e-9


def _surveyed_wall_map(extent_sd: float) -> GaussianMap:
    """Anchor ``x^R_Wknown`` (σ 5 cm, 2 mrad) and a 13.2 m known wall through the known
    frame's origin, along its x axis (so the anchor's angle slides no end along it)."""
    m = GaussianMap()
    m.add(
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
        np.array([1.0, 2.0, 0.3]),
        np.diag([0.05**2, 0.05**2, 0.002**2]),
    )
    wall = np.zeros(3)
    m.add(
        Element(
            ElementKind.LINE,
            Role.KNOWN,
            moving=False,
            track=0,
            extent=(-6.6, 6.6),
            extent_sd=extent_sd,
        ),
        wall,
        bind_line_cov(wall, np.diag([0.1**2, 0.1**2, 0.05**2])),
    )
    return m


def _segment(m: GaussianMap, lo: float, hi: float, angle: float = 0.0) -> Query:
    """A measured segment from ``lo`` to ``hi`` along the known wall's line (in
    ``Wknown``), turned by ``angle`` about its midpoint."""
    mid = np.array([0.5 * (lo + hi), 0.0, angle])
    z = transform_feature(FeatureKind.LINE, m.mean[0], mid)[0]
    half = 0.5 * (hi - lo) / math.cos(angle)
    return Query(ElementKind.LINE, z, _line_cov(z, PSEUDO), (-half, half))


def test_a_segment_reaching_beyond_a_surveyed_wall_is_not_that_wall() -> None:
    # Where the wall's ends lie is known to σ = √(0.05² + 0.1²) m along it (anchor,
    # survey): each end of a segment may reach 3.29 σ = 0.368 m beyond them.
    m = _surveyed_wall_map(extent_sd=0.1)
    tol = math.sqrt(chi2_gate(0.999, 1) * (0.05**2 + 0.1**2))
    assert tol == pytest.approx(0.3679, abs=1e-4)
    targets, preds = predict_all_targets(m, lambda e: True)[ElementKind.LINE]
    on, off = AssociationConfig(), AssociationConfig(known_wall_ends=False)
    cases = {
        (-5.0, 5.0, 0.0): True,  # inside
        (-6.6 - 0.9 * tol, 3.0, 0.0): True,  # within the ends' uncertainty
        (-4.0, 6.6 + 1.1 * tol, 0.0): False,
        # The next wall, 7.7° off and beyond this one's end (a 12 m piece of it): it
        # passes the line's χ² test, whose angle the survey knows to 0.05 rad.
        (-20.0, -8.0, math.radians(7.7)): False,
    }
    for (lo, hi, ang), inside in cases.items():
        q = _segment(m, lo, hi, ang)
        assert within_known_wall(m, q, 1, preds[0], on) is inside, (lo, hi)
        assert prefilter(q, preds, targets, m, on) == ([1] if inside else [])
        assert prefilter(q, preds, targets, m, off) == [1]
    # Without the survey's σ the tolerance is the anchor's alone (3.29 × 0.05 m).
    bare = _surveyed_wall_map(extent_sd=0.0)
    q = _segment(bare, -6.6 - 0.2, 3.0)
    assert not within_known_wall(bare, q, 1, preds[0], on)
    assert within_known_wall(bare, _segment(bare, -6.6 - 0.15, 3.0), 1, preds[0], on)


def test_a_segments_end_sigma_is_a_beams_footprint_at_its_farther_end() -> None:
    # Midpoint 30 m ahead, the segment across the view: ends at √(30² + 5²) m.
    z = np.array([30.0, 0.0, math.pi / 2])
    step = math.radians(0.5)
    assert segment_end_sd(z, (-5.0, 5.0), step) == pytest.approx(step * math.hypot(30, 5))
    assert segment_end_sd(z, (-1.0, 5.0), step) == pytest.approx(step * math.hypot(30, 5))
    assert segment_end_sd(z, (-5.0, 5.0), math.inf) == math.inf
    # An unknown σ admits any overhang: the rule does not apply.
    m = _surveyed_wall_map(extent_sd=0.1)
    _, preds = predict_all_targets(m, lambda e: True)[ElementKind.LINE]
    far = _segment(m, -20.0, -8.0, math.radians(7.7))
    assert not within_known_wall(m, far, 1, preds[0], AssociationConfig())
    unknown = Query(far.kind, far.params, far.cov, far.extent, end_sd=math.inf)
    assert within_known_wall(m, unknown, 1, preds[0], AssociationConfig())
    # The segment's own σ widens the tolerance: 0.5 m over the end passes with 0.2 m.
    over = _segment(m, -6.6 - 0.5, 3.0)
    assert not within_known_wall(m, over, 1, preds[0], AssociationConfig())
    wide = Query(over.kind, over.params, over.cov, over.extent, end_sd=0.2)
    assert within_known_wall(m, wide, 1, preds[0], AssociationConfig())


def test_a_known_wall_carries_its_surveys_sigma_along_it() -> None:
    known = KnownMapArrays(
        ids=np.array([7, 8, 9]),
        kinds=np.array([int(FeatureKind.LINE), int(FeatureKind.LINE), int(FeatureKind.CIRCLE)]),
        params=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2], [1.0, 1.0, 0.3]]),
        covs=np.stack([np.diag([0.2**2, 0.05**2, 0.01**2])] * 3),
        extents=np.array([[-1.0, 1.0], [-2.0, 2.0], [math.nan, math.nan]]),
    )
    along_x, _, _ = known_element(known, 0, 7)
    along_y, _, _ = known_element(known, 1, 8)
    circle, _, _ = known_element(known, 2, 9)
    assert along_x.extent_sd == pytest.approx(0.2, abs=1e-12)
    assert along_y.extent_sd == pytest.approx(0.05, abs=1e-12)
    assert along_y.extent == (-2.0, 2.0)
    assert circle.extent_sd == 0.0


def _known_wall_residual(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    pred = transform_feature(FeatureKind.LINE, x[:3], x[3:6])[0]
    return pairing_residual(FeatureKind.LINE, pred, z)[0]


@settings(max_examples=60, deadline=None)
@given(known_wall_cases())
def test_known_wall_jacobian_matches_numerical_derivative(case: tuple[GaussianMap, Query]) -> None:
    m, q = case
    c = evaluate(m, q, 1)
    assert c.indices == [0, 1]
    x = np.concatenate([m.mean[0], m.mean[1]])
    J = numerical_jacobian(lambda v: _known_wall_residual(v, q.params), x, angle_rows=(1,))
    np.testing.assert_allclose(c.H, J, atol=ATOL, rtol=RTOL)
    # A map feature as the query: its own columns come first.
    feature = Element(ElementKind.LINE, Role.FEATURE, True, 1)
    m.add(feature, q.params, bind_line_cov(q.params, q.cov))
    ce = evaluate(m, Query(ElementKind.LINE, q.params, np.zeros((3, 3)), q.extent, element=2), 1)
    assert ce.indices == [2, 0, 1]
    Jz = numerical_jacobian(lambda z: _known_wall_residual(x, z), q.params, angle_rows=(1,))
    np.testing.assert_allclose(ce.H[:, :3], Jz, atol=ATOL, rtol=RTOL)
    np.testing.assert_allclose(ce.H[:, 3:], J, atol=ATOL, rtol=RTOL)


def _map_with_estimated_line(line: np.ndarray) -> GaussianMap:
    """One estimated line (σ 2 cm, 1 mrad, bound) in the vehicle frame."""
    m = GaussianMap()
    m.add(
        Element(ElementKind.LINE, Role.FEATURE, moving=True, track=0),
        line,
        bind_line_cov(line, np.diag([0.02**2, 0.02**2, 0.001**2])),
    )
    return m


@st.composite
def estimated_line_cases(draw: st.DrawFn) -> tuple[GaussianMap, Query]:
    """A map with one estimated line, and a measured segment of it."""
    line = draw(poses())
    z = compose(line, np.array([draw(slides), draw(offsets), draw(offsets)]))
    return _map_with_estimated_line(line), Query(
        ElementKind.LINE, z, _line_cov(z, PSEUDO), (-5.0, 5.0)
    )


@settings(max_examples=60, deadline=None)
@given(estimated_line_cases(), slides)
def test_estimated_line_pairing_ignores_where_the_lines_reference_point_lies(
    case: tuple[GaussianMap, Query], s: float
) -> None:
    m1, q = case
    m2 = _map_with_estimated_line(m1.mean[0])
    m2.mean[0], m2.cov[0:3, 0:3] = _slid(m1.mean[0], m1.block(0), s)
    c1, c2 = evaluate(m1, q, 0), evaluate(m2, q, 0)
    np.testing.assert_allclose(c2.residual, c1.residual, atol=1e-9)
    np.testing.assert_allclose(c2.R, c1.R, atol=1e-15)
    assert math.isclose(c2.d2, c1.d2, rel_tol=1e-6, abs_tol=1e-9)


@settings(max_examples=60, deadline=None)
@given(estimated_line_cases())
def test_estimated_line_jacobian_matches_numerical_derivative(
    case: tuple[GaussianMap, Query],
) -> None:
    m, q = case
    c = evaluate(m, q, 0)
    assert c.indices == [0]
    J = numerical_jacobian(
        lambda v: pairing_residual(FeatureKind.LINE, v, q.params)[0], m.mean[0], angle_rows=(1,)
    )
    np.testing.assert_allclose(c.H, J, atol=ATOL, rtol=RTOL)


@settings(max_examples=40, deadline=None)
@given(estimated_line_cases())
def test_estimated_line_noise_ignores_the_along_line_pseudo_variance(
    case: tuple[GaussianMap, Query],
) -> None:
    m, q = case
    loose = Query(q.kind, q.params, _line_cov(q.params, 1e4 * PSEUDO), q.extent)
    c, c_loose = evaluate(m, q, 0), evaluate(m, loose, 0)
    np.testing.assert_allclose(c_loose.R, c.R, atol=1e-12)
    assert math.isclose(c.R[1, 1], LINE_SIGMA[1] ** 2, rel_tol=1e-9)


@settings(max_examples=40, deadline=None)
@given(known_wall_cases())
def test_known_wall_and_estimated_line_are_one_model(case: tuple[GaussianMap, Query]) -> None:
    # A known wall seen through an exact anchor is an estimated line at the same place
    # with the same covariance: same residual, noise and χ².
    m, q = case
    m.cov[0:3, :] = 0.0
    m.cov[:, 0:3] = 0.0
    pred, _, JK = transform_feature(FeatureKind.LINE, m.mean[0], m.mean[1])
    e = _map_with_estimated_line(pred)
    e.cov[:, :] = JK @ m.block(1) @ JK.T
    ck, ce = evaluate(m, q, 1), evaluate(e, q, 0)
    np.testing.assert_allclose(ce.residual, ck.residual, atol=1e-9)
    np.testing.assert_allclose(ce.R, ck.R, atol=1e-15)
    assert math.isclose(ce.d2, ck.d2, rel_tol=1e-6, abs_tol=1e-9)


TRUTH = np.array([3.0, -2.0, 0.4])
FLAT = np.diag([1e4, 1e4, 10.0])
HALF_TURN = np.array([0.0, 0.0, math.pi])


def _anchor_map(
    anchor_guess: np.ndarray,
    truth: np.ndarray = TRUTH,
    prior: np.ndarray = FLAT,
    turned: bool = False,
) -> tuple[GaussianMap, list[tuple[int, int]]]:
    """A global map with four circles and a wall, the known map and an anchor prior.

    ``Wknown`` sits at ``truth`` in ``Wglobal``; the estimated features are offset from
    it by a few centimetres (fixed, not random: the tests compare updates of one map).
    ``turned`` states the same problem with ``Wknown`` turned by π: the anchor becomes
    ``x ⊕ (0, 0, π)`` and every known feature ``(0, 0, −π) ⊕ f``.
    """
    known = [
        (ElementKind.CIRCLE, np.array([10.0, 2.0, 0.3])),
        (ElementKind.CIRCLE, np.array([-6.0, 8.0, 0.4])),
        (ElementKind.CIRCLE, np.array([25.0, -12.0, 0.25])),
        (ElementKind.CIRCLE, np.array([-15.0, -20.0, 0.5])),
        (ElementKind.LINE, np.array([40.0, 30.0, 2.0])),
    ]
    offs = [(0.03, -0.02), (-0.04, 0.01), (0.02, 0.05), (-0.01, -0.03), (0.04, 0.006)]
    m = GaussianMap()
    guess = compose(anchor_guess, HALF_TURN) if turned else anchor_guess
    # Composing with a pure rotation on the right leaves the covariance unchanged.
    m.add(Element(ElementKind.POSE, Role.ANCHOR, False, -1), guess, prior)
    pairs: list[tuple[int, int]] = []
    for (kind, f), (a, b) in zip(known, offs, strict=True):
        fk = kind.feature_kind()
        seen = transform_feature(fk, truth, f)[0]
        if kind == ElementKind.LINE:
            seen = compose(seen, np.array([7.0, a, b]))
            cov = bind_line_cov(seen, _line_cov(seen, 1.0))
        else:
            seen = seen + np.array([a, b, 0.0])
            cov = np.diag([0.03**2, 0.03**2, 0.01**2])
        fi = m.add(Element(kind, Role.FEATURE, False, len(pairs)), seen, cov)
        kcov = np.diag([1e-4, 1e-4, 1e-6 if kind == ElementKind.LINE else 1e-4])
        if turned:
            f, Jf = transform_feature(fk, -HALF_TURN, f)[::2]
            kcov = Jf @ kcov @ Jf.T
        if kind == ElementKind.LINE:
            kcov = bind_line_cov(f, kcov)
        ki = m.add(Element(kind, Role.KNOWN, False, 100 + len(pairs)), f, kcov)
        pairs.append((fi, ki))
    return m, pairs


def _pairings(pairs: list[tuple[int, int]]) -> Callable[[GaussianMap], list[Candidate]]:
    return lambda state: element_pairings(state, pairs)


def test_iterated_update_does_not_depend_on_the_flat_priors_mean() -> None:
    # With a flat prior the posterior is the constrained optimum; one linearisation at
    # two different guesses (30 cm and 30 mrad apart) gives two different answers.
    guesses = (np.array([3.2, -2.1, 0.42]), np.array([2.9, -1.8, 0.37]))
    once, iterated = [], []
    for guess in guesses:
        m, pairs = _anchor_map(guess)
        apply(m, _pairings(pairs)(m))
        once.append((m.mean[0].copy(), m.block(0).copy()))
        m, pairs = _anchor_map(guess)
        upd = apply_iterated(m, _pairings(pairs))
        assert upd.converged
        assert 1 < upd.iterations < 10
        iterated.append((m.mean[0].copy(), m.block(0).copy()))
        # The pairings hold at the solution: every residual is (numerically) zero.
        for c in _pairings(pairs)(m):
            np.testing.assert_allclose(c.residual, 0.0, atol=1e-7)
    assert np.abs(once[0][0] - once[1][0]).max() > 1e-4
    np.testing.assert_allclose(iterated[0][0], iterated[1][0], atol=1e-9)
    np.testing.assert_allclose(iterated[0][1], iterated[1][1], rtol=1e-6, atol=1e-14)
    # Near the truth, whatever the guess (measured: 8 mm and 1.2 mrad; features a few
    # centimetres off, at 10–50 m from the origin).
    d = iterated[0][0] - TRUTH
    d[2] = wrap_angle(d[2])
    assert np.abs(d[:2]).max() < 0.02
    assert abs(d[2]) < 0.003


def test_iterated_update_is_the_same_across_the_angle_wrap() -> None:
    # A prior tight enough to matter, its mean just below +π and the solution just above
    # −π: x0 − x must be wrapped, or the prior pulls by 2π.
    truth = np.array([3.0, -2.0, 0.001])
    guess = np.array([3.1, -2.05, -0.003])
    prior = np.diag([0.1**2, 0.1**2, 0.002**2])
    out = []
    for turned in (False, True):
        m, pairs = _anchor_map(guess, truth, prior, turned)
        upd = apply_iterated(m, _pairings(pairs))
        assert upd.converged
        out.append((m.mean[0].copy(), m.block(0).copy(), upd.iterations))
    (x, P, _), (x_t, P_t, _) = out
    assert x_t[2] < -math.pi + 0.01  # crossed from +π to −π on the way
    np.testing.assert_allclose(compose(x, HALF_TURN), x_t, atol=1e-9)
    np.testing.assert_allclose(P_t, P, rtol=1e-6, atol=1e-14)


def test_iterated_update_reports_when_it_did_not_converge() -> None:
    m, pairs = _anchor_map(np.array([3.3, -2.3, 0.45]))
    upd = apply_iterated(m, _pairings(pairs), max_iterations=1)
    assert (upd.iterations, upd.converged) == (1, False)


def test_iterated_update_without_pairings_changes_nothing() -> None:
    m, _ = _anchor_map(np.zeros(3))
    mean, cov = m.mean.copy(), m.cov.copy()
    assert apply_iterated(m, lambda state: []) == IteratedUpdate(0, True, 0.0, 0)
    np.testing.assert_array_equal(m.mean, mean)
    np.testing.assert_array_equal(m.cov, cov)
