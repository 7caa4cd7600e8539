"""Line model-error terms estimated from a log's own scans (``data/datasets/line_noise.py``).

Hand-made logs whose line errors are known: the fit's stated noise plus a model error
of stated σ, drawn independently or correlated from scan to scan (AR(1) per wall).
The estimate recovers the σ of independent errors, and for correlated ones the
autocorrelation time of an AR(1) process and the σ that time calls for.  The shared
covariance term is held equal to what the extractor adds, and the CARMEN loader's
choice (estimated, the profile's, the fallback) is checked on snippets and, where the
shared data is present, on all seven logs.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.data.datasets import CarmenOptions, load_carmen
from mapfuse_core.data.datasets.common import empty_map
from mapfuse_core.data.datasets.line_noise import (
    MIN_LENGTH_M,
    MIN_OBSERVATIONS,
    LineModelError,
    LineTerms,
    estimate_line_model_error,
    with_line_model_error,
)
from mapfuse_core.geometry.features import FeatureKind, line_from_normal
from mapfuse_core.geometry.se2 import FloatArray, relative
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.perception.extraction import ExtractionParams, extract_features
from mapfuse_core.perception.extraction.noise import line_model_cov
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.world import WallSegment, World

_WALLS: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = (
    ((-6.0, -4.0), (6.0, -4.0)),
    ((6.0, -4.0), (6.0, 4.0)),
    ((6.0, 4.0), (-6.0, 4.0)),
    ((-6.0, 4.0), (-6.0, -4.0)),
    ((-2.0, -1.0), (2.0, -1.5)),
)
"""A room with one slanted wall inside it (no two walls parallel and close)."""

_FIT_SIGMA = (0.004, math.radians(0.15))
"""Stated σ of the fit (ρ m, α rad): every observation's covariance says this."""


def _poses(n: int) -> FloatArray:
    """(n, 3) a slow loop around the room, 0.1 m a scan."""
    s = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    out: FloatArray = np.c_[3.5 * np.cos(s), 2.5 * np.sin(s), s + math.pi / 2]
    return out


def _observe(
    pose: FloatArray, p1: tuple[float, float], p2: tuple[float, float]
) -> tuple[float, float, float, float]:
    """Wall ``p1``–``p2`` seen from ``pose``: ``(ρ, α, t_mid, length)``, ρ ≥ 0."""
    a = relative(pose, np.array([*p1, 0.0]))[0][:2]
    b = relative(pose, np.array([*p2, 0.0]))[0][:2]
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([d[1], -d[0]])
    rho = float(n @ a)
    if rho < 0.0:
        n, rho = -n, -rho
    alpha = math.atan2(n[1], n[0])
    tangent = np.array([-math.sin(alpha), math.cos(alpha)])
    t_mid = float(tangent @ (0.5 * (a + b)))
    return rho, alpha, t_mid, float(np.linalg.norm(b - a))


def _log(
    sigma: tuple[float, float],
    phi: float,
    n: int = 400,
    seed: int = 0,
    sigma_m_metre: float = 0.0,
    pieces: bool = False,
) -> MeasurementLog:
    """A log of the walls seen from every pose: the fit's noise (as stated) plus a model
    error of σ ``sigma`` (ρ m, α rad), AR(1) with coefficient ``phi`` per wall.

    ``pieces``: each observation is a piece of its wall ``L ~ U(0.4, min(4, wall))`` m
    long, and its ``ρ`` takes a further independent error of σ ``sigma_m_metre / L``."""
    rng = np.random.default_rng(seed)
    poses = _poses(n)
    e = np.zeros((len(_WALLS), 2))
    steps, params, covs, extents = [], [], [], []
    scale = np.array(sigma) * math.sqrt(1.0 - phi * phi)
    for k, pose in enumerate(poses):
        e = (
            phi * e + scale * rng.standard_normal(e.shape)
            if k
            else np.array(sigma) * rng.standard_normal(e.shape)
        )
        for w, (p1, p2) in enumerate(_WALLS):
            rho, alpha, t_mid, length = _observe(pose, p1, p2)
            noise = np.array(_FIT_SIGMA) * rng.standard_normal(2)
            if pieces:
                length = float(rng.uniform(0.4, min(4.0, length)))
                noise[0] += sigma_m_metre / length * rng.standard_normal()
            line, J = line_from_normal(rho + noise[0] + e[w, 0], alpha + noise[1] + e[w, 1], t_mid)
            C = np.diag([_FIT_SIGMA[0] ** 2, _FIT_SIGMA[1] ** 2, length * length / 12.0])
            steps.append(k)
            params.append(line)
            covs.append(J @ C @ J.T)
            extents.append((-0.5 * length, 0.5 * length))
    m = len(steps)
    inc = np.array([np.zeros(3)] + [relative(poses[k - 1], poses[k])[0] for k in range(1, n)])
    return MeasurementLog(
        scenario="line-noise",
        seed=seed,
        timestamps=np.arange(n, dtype=float),
        odometry=inc,
        odometry_cov=np.array([np.eye(3) * 1e-4] * n),
        feat_step=np.array(steps, dtype=np.int64),
        feat_kind=np.full(m, int(FeatureKind.LINE), dtype=np.int8),
        feat_params=np.array(params),
        feat_cov=np.array(covs),
        feat_true_id=np.full(m, -1, dtype=np.int64),
        feat_n_points=np.full(m, 50, dtype=np.int64),
        feat_extent=np.array(extents),
        known_map=empty_map(),
        true_poses=poses,
    )


def test_independent_model_error_is_recovered() -> None:
    sigma = (0.03, math.radians(0.6))
    est = estimate_line_model_error(_log(sigma, phi=0.0))
    # 2,000 observations: the σ of a variance estimate is about 3 %, so 10 % on σ²
    # (5 % on σ) is over three standard errors.
    assert est.sigma_m == pytest.approx(sigma[0], rel=0.05)
    assert est.sigma_rad == pytest.approx(sigma[1], rel=0.05)
    # Independent errors: lag-1 correlations are noise around 0.
    assert est.iact[0] < 1.15
    assert est.iact[1] < 1.15
    assert est.observations == 400 * len(_WALLS)
    assert est.nees_without[0] > 10.0  # the fit's σ alone is far too small


def test_honest_covariances_need_no_term() -> None:
    est = estimate_line_model_error(_log((0.0, 0.0), phi=0.0))
    # Whitened variances within sampling noise of 1 (±0.1 is over three standard
    # errors of a mean of 2,000 χ²₁), so any term found is small against the fit's σ:
    # under half of it adds under a quarter of its variance.
    assert est.nees_without[0] == pytest.approx(1.0, abs=0.1)
    assert est.nees_without[1] == pytest.approx(1.0, abs=0.1)
    assert est.sigma_m < 0.5 * _FIT_SIGMA[0]
    assert est.sigma_rad < 0.5 * _FIT_SIGMA[1]


def test_correlated_model_error_gets_its_autocorrelation_time() -> None:
    sigma, phi = (0.03, math.radians(0.6)), 0.6
    est = estimate_line_model_error(_log(sigma, phi=phi, n=800))
    # AR(1): τ = (1 + φ)/(1 − φ) = 4 for the model error alone; the fit's independent
    # share (3 % of the lateral variance) and the sum's cut where the correlation
    # falls to 0.05 (lag 6) bring it to about 3.7.
    for tau in est.iact:
        assert 3.2 < tau < 4.3
    # Each observation is worth 1/τ: σ² ≈ τ (σ_model² + σ_fit²) − σ_fit².
    want = math.sqrt(est.iact[0] * (sigma[0] ** 2 + _FIT_SIGMA[0] ** 2) - _FIT_SIGMA[0] ** 2)
    assert est.sigma_m == pytest.approx(want, rel=0.15)


def _with_second_pieces(log: MeasurementLog, sigma: tuple[float, float]) -> MeasurementLog:
    """``log`` with wall 0 seen in a second piece at every scan: a copy of its
    observation moved by an independent error of 3 ``sigma`` (a piece beyond a door,
    erring apart from the first)."""
    rng = np.random.default_rng(7)
    first = np.flatnonzero(np.r_[True, np.diff(log.feat_step) > 0])  # wall 0 of each scan
    extra = log.feat_params[first].copy()
    th = extra[:, 2]
    d = 3.0 * sigma[0] * rng.standard_normal(first.size)
    extra[:, 0] -= d * np.sin(th)
    extra[:, 1] += d * np.cos(th)
    extra[:, 2] += 3.0 * sigma[1] * rng.standard_normal(first.size)
    order = np.argsort(np.r_[log.feat_step, log.feat_step[first]], kind="stable")

    def both(a: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.concatenate([a, a[first]])[order]
        return out

    return dataclasses.replace(
        log,
        feat_step=both(log.feat_step),
        feat_kind=both(log.feat_kind),
        feat_params=np.concatenate([log.feat_params, extra])[order],
        feat_cov=both(log.feat_cov),
        feat_true_id=both(log.feat_true_id),
        feat_n_points=both(log.feat_n_points),
        feat_extent=both(log.feat_extent),
    )


def test_a_wall_seen_in_two_pieces_in_a_scan_leaves_tau_alone() -> None:
    sigma, phi = (0.03, math.radians(0.6)), 0.6
    log = _with_second_pieces(_log(sigma, phi=phi, n=800), sigma)
    est = estimate_line_model_error(log)
    # Both pieces join wall 0 of the plan, but for the moved ones beyond its tolerances.
    assert est.observations > 0.9 * 6 * 800
    # The four other walls' AR(1) τ, as in the test above: the two pieces of wall 0
    # take no part in the sum (paired across scans they would read as a correlation
    # lost in one scan and pull τ towards 1).
    for tau in est.iact:
        assert 3.2 < tau < 4.3


def test_independent_estimate_whitens_each_observation_and_reports_tau() -> None:
    sigma = (0.03, math.radians(0.6))
    est = estimate_line_model_error(_log(sigma, phi=0.6, n=800), correlated=False)
    assert not est.correlated
    # The model error's own σ (AR(1) with a stationary σ), within 10 %: 800 scans of
    # correlated errors are worth about 200 independent ones per wall.
    assert est.sigma_m == pytest.approx(sigma[0], rel=0.1)
    assert est.sigma_rad == pytest.approx(sigma[1], rel=0.1)
    for tau in est.iact:
        assert 3.2 < tau < 4.3


def test_applied_terms_are_self_consistent() -> None:
    log = _log((0.03, math.radians(0.6)), phi=0.6, n=800)
    est = estimate_line_model_error(log)
    again = estimate_line_model_error(with_line_model_error(log, est.terms))
    assert again.sigma_m < 1e-3
    assert again.sigma_rad < math.radians(0.01)
    for nees, tau in zip(again.nees_without, again.iact, strict=True):
        assert nees * tau == pytest.approx(1.0, abs=0.03)


def test_gate_terms_are_those_that_whiten_each_observation() -> None:
    # The gate's terms are step 1 of the correlated estimate: the independent estimate,
    # smaller than the correlated terms where consecutive errors are correlated (τ ≈ 3.7).
    log = _log((0.03, math.radians(0.6)), phi=0.6, n=800)
    corr = estimate_line_model_error(log)
    indep = estimate_line_model_error(log, correlated=False)
    assert (corr.gate_sigma_m, corr.gate_sigma_rad) == (indep.sigma_m, indep.sigma_rad)
    assert (indep.gate_sigma_m, indep.gate_sigma_rad) == (indep.sigma_m, indep.sigma_rad)
    assert corr.gate_sigma_m < 0.7 * corr.sigma_m
    assert corr.gate_sigma_rad < 0.7 * corr.sigma_rad
    assert "gates" in corr.summary(gated=True)
    assert "gates" not in corr.summary()


def test_gate_terms_make_the_gate_covariances() -> None:
    log = _log((0.03, 0.01), phi=0.0, n=20)
    assert log.feat_gate_cov is None
    assert with_line_model_error(log, LineTerms(0.02, 0.01)).feat_gate_cov is None
    out = with_line_model_error(log, LineTerms(0.05, 0.02), gate=LineTerms(0.02, 0.01))
    assert out.feat_gate_cov is not None
    for j in range(log.n_features):
        z, base = log.feat_params[j], log.feat_cov[j]
        np.testing.assert_allclose(out.feat_cov[j], base + line_model_cov(z, 0.05, 0.02))
        np.testing.assert_allclose(out.feat_gate_cov[j], base + line_model_cov(z, 0.02, 0.01))
    # Terms added later widen both.
    again = with_line_model_error(out, LineTerms(0.01, 0.0))
    assert again.feat_gate_cov is not None
    np.testing.assert_allclose(
        again.feat_gate_cov[0], out.feat_gate_cov[0] + line_model_cov(log.feat_params[0], 0.01, 0.0)
    )


def test_the_loader_gates_alone_only_when_asked_and_says_so() -> None:
    from mapfuse_core.data.datasets.carmen import _estimated_terms

    log = _log((0.03, math.radians(0.6)), phi=0.6, n=800)
    est = estimate_line_model_error(log)
    weight = _estimated_terms(log, CarmenOptions(line_model_error="correlated"))
    assert weight.feat_gate_cov is None
    alone = _estimated_terms(
        log, CarmenOptions(line_model_error="correlated", line_model_gate="alone")
    )
    np.testing.assert_array_equal(alone.feat_cov, weight.feat_cov)
    expected = with_line_model_error(log, est.gate_terms).feat_cov
    assert alone.feat_gate_cov is not None
    np.testing.assert_allclose(alone.feat_gate_cov, expected, rtol=1e-12, atol=1e-18)
    assert f"gates {est.gate_sigma_m:.3f} m" in alone.metadata["line_model_error"]
    # Too few observations on the plan: the profile's terms, no gate covariances.
    short = _estimated_terms(
        log.head(5), CarmenOptions(line_model_error="correlated", line_model_gate="alone")
    )
    assert short.feat_gate_cov is None
    assert short.metadata["line_model_error"].startswith("extraction profile's (")


def _by_length(log: MeasurementLog, est: LineModelError) -> list[float]:
    """Mean whitened squared lateral residual with ``est``'s terms, for segments under
    1 m, 1–2 m and over 2 m."""
    from mapfuse_core.data.datasets import build_floor_plan
    from mapfuse_core.data.datasets.floorplan import FloorPlanParams
    from mapfuse_core.data.datasets.line_noise import _NEGLIGIBLE_SURVEY, _residuals

    # The plan as the estimate builds it: no survey σ.
    tiny = _NEGLIGIBLE_SURVEY
    params = dataclasses.replace(FloorPlanParams(), survey_sigma_m=tiny, survey_sigma_rad=tiny)
    res = _residuals(log, build_floor_plan(log, params))
    t = est.terms
    share = t.sigma_m_metre**2 / (t.sigma_m**2 + t.sigma_m_metre**2)
    z = res.whitened(t.sigma_m**2 + t.sigma_m_metre**2, t.sigma_rad**2, share)[:, 0]
    length = 1.0 / np.sqrt(res.inv_length2)
    bins = ((0.0, 1.0), (1.0, 2.0), (2.0, np.inf))
    return [float(np.mean(z[(length >= a) & (length < b)] ** 2)) for a, b in bins]


def test_a_lateral_error_falling_with_length_is_recovered() -> None:
    # σ_ρ² = 1 cm² + (3 cm / L)²: 7.6 cm at 0.4 m, 1.3 cm at 4 m.
    log = _log((0.01, math.radians(0.3)), phi=0.0, n=800, sigma_m_metre=0.03, pieces=True)
    est = estimate_line_model_error(log, correlated=False, shape="length")
    # 4,000 observations, a third of them under 1 m where the 1/L part dominates: the
    # metre part within 10 % (about three standard errors of its variance); the
    # constant part, against the fit's σ and the angle's lever arm, within 20 % (8
    # seeds: within 10 %).
    assert est.sigma_m_metre == pytest.approx(0.03, rel=0.1)
    assert est.sigma_m == pytest.approx(0.01, rel=0.2)
    assert est.sigma_rad == pytest.approx(math.radians(0.3), rel=0.1)
    # Whitened by length, every band within 0.15 of 1 (over 1,000 χ²₁ a band: about
    # three standard errors); one σ for every line leaves short pieces far above 1 and
    # long ones far below.
    for m2 in _by_length(log, est):
        assert m2 == pytest.approx(1.0, abs=0.15)
    flat = _by_length(log, estimate_line_model_error(log, correlated=False))
    assert flat[0] > 2.0
    assert flat[2] < 0.6
    assert "m / length" in est.summary()
    # One σ for every line where the error does not fall with length: too little
    # evidence for a 1/L part, and the terms are those of one σ.
    flat_log = _log((0.03, math.radians(0.3)), phi=0.0, n=800, pieces=True)
    const = estimate_line_model_error(flat_log, correlated=False, shape="length")
    assert const.sigma_m_metre == 0.0
    assert const.terms == estimate_line_model_error(flat_log, correlated=False).terms
    assert const.sigma_m == pytest.approx(0.03, rel=0.1)
    # Every segment equally long: nothing tells the two parts apart (the likelihood is
    # flat over the split), so no 1/L part.
    same = dataclasses.replace(
        flat_log, feat_extent=np.tile((-0.75, 0.75), (flat_log.n_features, 1))
    )
    assert estimate_line_model_error(same, correlated=False, shape="length").sigma_m_metre == 0.0


def test_applied_length_terms_are_self_consistent() -> None:
    # Correlated errors, and a seventh of the pieces' extents cut to 0.1 m (below
    # MIN_LENGTH_M): estimating again on the log with its own terms finds none left,
    # which holds only if the residuals and the terms floor a length alike.
    log = _log((0.01, math.radians(0.3)), phi=0.6, n=800, sigma_m_metre=0.03, pieces=True)
    ext = log.feat_extent.copy()
    ext[::7] = (-0.05, 0.05)
    log = dataclasses.replace(log, feat_extent=ext)
    est = estimate_line_model_error(log, shape="length")
    assert est.sigma_m_metre > 0.0
    again = estimate_line_model_error(with_line_model_error(log, est.terms), shape="length")
    assert again.sigma_m < 1e-3
    assert again.sigma_m_metre < 1e-3
    for nees, tau in zip(again.nees_without, again.iact, strict=True):
        assert nees * tau == pytest.approx(1.0, abs=0.03)


def test_length_terms_widen_each_line_by_its_own_length() -> None:
    t = LineTerms(0.01, 0.02, sigma_m_metre=0.03)
    assert t.sigma_rho(1.0) == pytest.approx(math.hypot(0.01, 0.03))
    assert t.sigma_rho(3.0) == pytest.approx(math.hypot(0.01, 0.01))
    # Shorter than MIN_LENGTH_M (a degenerate extent included): MIN_LENGTH_M's.
    assert t.sigma_rho(0.0) == t.sigma_rho(MIN_LENGTH_M / 2) == t.sigma_rho(MIN_LENGTH_M)
    log = _log((0.03, 0.01), phi=0.0, n=20, sigma_m_metre=0.03, pieces=True)
    out = with_line_model_error(log, t, gate=LineTerms(0.005, 0.01, sigma_m_metre=0.01))
    assert out.feat_gate_cov is not None
    for j in range(log.n_features):
        z, base = log.feat_params[j], log.feat_cov[j]
        length = float(log.feat_extent[j, 1] - log.feat_extent[j, 0])
        s_rho = math.sqrt(0.01**2 + (0.03 / length) ** 2)
        np.testing.assert_allclose(out.feat_cov[j], base + line_model_cov(z, s_rho, 0.02))
        s_gate = math.sqrt(0.005**2 + (0.01 / length) ** 2)
        np.testing.assert_allclose(out.feat_gate_cov[j], base + line_model_cov(z, s_gate, 0.01))


def test_the_loader_takes_the_length_shape_when_asked() -> None:
    from mapfuse_core.data.datasets.carmen import _estimated_terms

    log = _log((0.01, math.radians(0.3)), phi=0.6, n=400, sigma_m_metre=0.03, pieces=True)
    opts = CarmenOptions(line_model_error="correlated", line_model_gate="alone")
    est = estimate_line_model_error(log, shape="length")
    out = _estimated_terms(log, dataclasses.replace(opts, line_model_shape="length"))
    np.testing.assert_allclose(
        out.feat_cov, with_line_model_error(log, est.terms).feat_cov, rtol=1e-12, atol=1e-18
    )
    assert out.feat_gate_cov is not None
    np.testing.assert_allclose(
        out.feat_gate_cov,
        with_line_model_error(log, est.gate_terms).feat_cov,
        rtol=1e-12,
        atol=1e-18,
    )
    assert f"{est.sigma_m_metre:.3f} m / length" in out.metadata["line_model_error"]
    assert "m / length" not in _estimated_terms(log, opts).metadata["line_model_error"]


def test_bad_input_is_named() -> None:
    log = _log((0.03, 0.01), phi=0.0, n=20)
    with pytest.raises(ValueError, match="reference trajectory"):
        estimate_line_model_error(dataclasses.replace(log, true_poses=None))
    with pytest.raises(ValueError, match=f"needs at least {MIN_OBSERVATIONS}"):
        estimate_line_model_error(log.head(5))
    for bad in (-0.01, math.nan, math.inf):
        for name in ("sigma_m", "sigma_rad", "sigma_m_metre"):
            with pytest.raises(ValueError, match=f"^{name} must be finite and >= 0"):
                LineTerms(**{"sigma_m": 0.0, "sigma_rad": 0.0, name: bad})
    with pytest.raises(ValueError, match="shape must be 'constant' or 'length'"):
        estimate_line_model_error(log, shape="guess")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="terms must be LineTerms"):
        with_line_model_error(log, 0.02)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="gate must be LineTerms"):
        with_line_model_error(log, LineTerms(0.02, 0.01), gate=(0.02, 0.01))  # type: ignore[arg-type]
    for bad_extent in ((0.5, -0.5), (math.nan, 0.5)):
        ext = log.feat_extent.copy()
        ext[3] = bad_extent
        with pytest.raises(ValueError, match=r"line feature 3 has extent .* finite and >= 0"):
            with_line_model_error(dataclasses.replace(log, feat_extent=ext), LineTerms(0.02, 0.01))


def test_added_term_equals_the_extractors() -> None:
    world = World(tuple(WallSegment(i + 1, p1, p2) for i, (p1, p2) in enumerate(_WALLS)), ())
    laser = LaserParams()
    scan = simulate_scan(world, np.array([1.0, 0.5, 0.3]), laser, np.random.default_rng(3))
    with_terms = ExtractionParams(line_model_sigma_m=0.03, line_model_sigma_rad=0.01)
    bare = extract_features(scan, laser, ExtractionParams())
    full = extract_features(scan, laser, with_terms)
    assert len(bare.features) == len(full.features) >= 2
    for a, b in zip(bare.features, full.features, strict=True):
        np.testing.assert_array_equal(a.params, b.params)
        np.testing.assert_allclose(
            a.cov + line_model_cov(a.params, 0.03, 0.01), b.cov, rtol=1e-12, atol=1e-18
        )


def test_added_term_is_the_normal_forms_variance_propagated() -> None:
    # Closed form: σ² on (ρ, α) through ∂(x, y, θ)/∂(ρ, α) of line_from_normal.
    rng = np.random.default_rng(7)
    for _ in range(200):
        rho, alpha, t = rng.uniform(0.0, 20.0), rng.uniform(-4.0, 4.0), rng.uniform(-10.0, 10.0)
        line, J = line_from_normal(rho, alpha, t)
        want = J[:, :2] @ np.diag([0.03**2, 0.01**2]) @ J[:, :2].T
        np.testing.assert_allclose(line_model_cov(line, 0.03, 0.01), want, rtol=1e-9, atol=1e-15)


# --------------------------------------------------------------------------- the CARMEN loader

_LOGS = ("acapulco", "belgioioso", "csail", "fhw", "freiburg-101", "intel", "seattle")

_LENGTH_GATES_CM = {
    "acapulco": (0.8, 0.0),
    "belgioioso": (1.2, 0.5),
    "csail": (1.1, 1.2),
    "fhw": (1.0, 0.8),
    "freiburg-101": (2.0, 0.0),
    "intel": (2.0, 0.0),
    "seattle": (0.5, 1.8),
}
"""Gate terms of ``shape="length"`` per log, (σ_m, σ_1) in cm, as the results page
gives them."""


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.parametrize("name", _LOGS)
def test_carmen_logs_carry_their_own_estimate(data_dir: Path, name: str) -> None:
    path = data_dir / "carmen" / f"{name}-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"CARMEN log not found ({path})")
    log = load_carmen(
        path, options=CarmenOptions(line_model_error="correlated", line_model_gate="alone")
    )
    assert log.metadata["line_model_error"].startswith("estimated from the log (correlated):")
    bare = ExtractionParams.indoor_sick()
    bare = dataclasses.replace(bare, line_model_sigma_m=0.0, line_model_sigma_rad=0.0)
    bare_log = load_carmen(path, options=CarmenOptions(extraction=bare, line_model_error="profile"))
    first = estimate_line_model_error(bare_log)
    assert f"{first.sigma_m:.3f} m" in log.metadata["line_model_error"]
    # Its gates take each observation's error alone: the independent terms.
    assert log.feat_gate_cov is not None
    assert f"gates {first.gate_sigma_m:.3f} m" in log.metadata["line_model_error"]
    gate = with_line_model_error(bare_log, first.gate_terms)
    np.testing.assert_allclose(log.feat_gate_cov, gate.feat_cov, rtol=1e-12, atol=1e-18)
    # The length shape's gate terms (σ_m, σ_1) as docs/results/carmen.md states them
    # (cm, rounded to 0.1): a 1/L part on four logs, too little evidence on three.
    by_length = estimate_line_model_error(bare_log, shape="length")
    gate_cm = (100 * by_length.gate_sigma_m, 100 * by_length.gate_sigma_m_metre)
    assert gate_cm == pytest.approx(_LENGTH_GATES_CM[name], abs=0.051)
    # The terms it carries whiten its residuals to 1/τ: estimating again adds under 5 %
    # of their variance (τ moves a little with the terms' own reweighting).
    again = estimate_line_model_error(log)
    assert again.sigma_m**2 <= 0.05 * first.sigma_m**2 + 1e-8
    assert again.sigma_rad**2 <= 0.05 * first.sigma_rad**2 + 1e-10
    for nees, tau, term in zip(
        again.nees_without, again.iact, (first.sigma_m, first.sigma_rad), strict=True
    ):
        if term > 0.0:
            assert nees * tau == pytest.approx(1.0, abs=0.05)
        else:
            # No term on this dof: the other's (the angle's, which widens the lateral
            # offset too) already whitens it below 1/τ (FHW's lateral offset).
            assert nees * tau <= 1.05


@pytest.mark.realdata
def test_estimated_terms_change_covariances_only(data_dir: Path) -> None:
    # Seattle: the shortest of the logs to extract.
    path = data_dir / "carmen" / "seattle-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"CARMEN log not found ({path})")
    log = load_carmen(path, options=CarmenOptions(line_model_error="correlated"))
    assert log.metadata["line_model_error"].startswith("estimated from the log (correlated):")
    profile = load_carmen(path)  # the default: the extraction profile's terms
    assert profile.metadata["line_model_error"] == (
        "extraction profile's (as asked): 0.020 m, 0.80 deg"
    )
    np.testing.assert_array_equal(profile.feat_params, log.feat_params)
    assert not np.array_equal(profile.feat_cov, log.feat_cov)
    # The gates take the updates' terms unless asked otherwise (line_model_gate).
    assert log.feat_gate_cov is None
    assert "gates" not in log.metadata["line_model_error"]


def test_options_name_a_bad_choice() -> None:
    with pytest.raises(ValueError, match="line_model_error must be 'correlated', 'independent' or"):
        CarmenOptions(line_model_error="guess")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="line_model_gate must be 'weight' or 'alone'"):
        CarmenOptions(line_model_gate="guess")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="line_model_gate='alone' needs line_model_error"):
        CarmenOptions(line_model_gate="alone")
    with pytest.raises(ValueError, match="line_model_shape must be 'constant' or 'length'"):
        CarmenOptions(line_model_shape="guess")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="line_model_shape='length' needs line_model_error"):
        CarmenOptions(line_model_shape="length")


def test_residuals_are_those_the_estimators_form() -> None:
    # The terms are set on the residual the estimators' factors see: an observation's
    # reference point against its wall's line (``observe``), not the wall's midpoint
    # against the observed line, which lets the angle's lever arm stand in for the
    # lateral term.
    from mapfuse_core.data.datasets import build_floor_plan
    from mapfuse_core.data.datasets.line_noise import _residuals
    from mapfuse_core.models import observe
    from mapfuse_core.models.line import line_observation_cov

    log = _log((0.03, math.radians(0.6)), phi=0.0, n=60)
    plan = build_floor_plan(log)
    res = _residuals(log, plan)
    assert log.true_poses is not None
    idx = np.flatnonzero(plan.obs_wall >= 0)
    assert idx.size > 0.9 * log.n_features
    for n, i in enumerate(idx.tolist()):
        pose = log.true_poses[log.feat_step[i]]
        z, w = log.feat_params[i], plan.obs_wall[i]
        wall, wall_cov = plan.walls.params[w], plan.walls.covs[w]
        want, _, Jw = observe(FeatureKind.LINE, z, pose, wall)
        assert res.r[n] == pytest.approx(want, abs=1e-12)
        # Its variance: the observation's noise as the estimators take it, plus the
        # wall's through the residual's Jacobian; and what a unit term adds.
        S = line_observation_cov(pose, wall, z, log.feat_cov[i]) + Jw @ wall_cov @ Jw.T
        assert res.var[n] == pytest.approx(np.diag(S), rel=1e-12)
        for k, unit in enumerate(((1.0, 0.0), (0.0, 1.0))):
            added = line_observation_cov(pose, wall, z, line_model_cov(z, *unit))
            assert res.gain[n, :, k] == pytest.approx(np.diag(added), rel=1e-12)
