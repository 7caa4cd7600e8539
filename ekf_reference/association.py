"""Data association inside one EKF map: individual compatibility, NN and JCBB.

A *query* is either a measurement (a feature in the vehicle frame with its
covariance) or a feature element of the map itself (for the hard pairing
constraints of map joining and of the known-map fusion).  A *target* is a feature
element expressed in the vehicle frame, or a known-map feature seen through the
anchor ``x^R_Wknown ⊕ x^Wknown_E``.  Both are paired with the measurement models
of :mod:`mapfuse_core.models` (through :mod:`mapfuse_core.geometry.features`).

This module linearises the pairings on a :class:`~ekf_reference.state.GaussianMap`;
the gates, the searches and their settings are the backend-independent ones of
:mod:`mapfuse_core.matching`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle
from mapfuse_core.matching import (
    AssociationConfig,
    chi2_gate,
    drop_ambiguous,
    line_overhang,
    pregate,
)
from mapfuse_core.matching import jcbb as jcbb_search
from mapfuse_core.matching import nearest_neighbour as nn_search
from mapfuse_core.models import pairing_cov, pairing_residual

__all__ = [
    "Candidate",
    "IteratedUpdate",
    "Query",
    "apply",
    "apply_iterated",
    "choose",
    "element_pairings",
    "evaluate",
    "exclusive",
    "individual_candidates",
    "jcbb",
    "joint_compatible",
    "nearest_neighbour",
    "predict_all_targets",
    "predict_targets",
    "prefilter",
    "segment_end_sd",
    "targets_distinct",
    "within_known_wall",
]


@dataclass(frozen=True)
class Query:
    """Something to associate: a measurement (``element`` = −1) or a map element."""

    kind: ElementKind
    """LINE or CIRCLE."""
    params: FloatArray
    """(3,) parameters in the vehicle frame ``R``."""
    cov: FloatArray
    """(3, 3) measurement covariance (ignored for a map element: its own is in the map)."""
    extent: tuple[float, float]
    """Along-line extent of a line (NaN for circles)."""
    element: int = -1
    """Index of the map element this query is, or −1 for a measurement."""
    residual_at: Literal["observed", "target"] = "observed"
    """Where a line's lateral residual is measured
    (:func:`mapfuse_core.models.line.line_residual`'s ``at``): at this query's reference
    point, or at the target's (a map element tied to another:
    ``EKFConfig.line_tie_residual_at``; a measurement's is always its own)."""
    end_sd: float = 0.0
    """σ (m) of where a line's ends lie along it: a measured segment's
    (:func:`segment_end_sd`), a map element's :attr:`~ekf_reference.state.Element.extent_sd`;
    ``inf`` when unknown (no rule then relies on the ends)."""
    gate_cov: FloatArray | None = None
    """(3, 3) covariance of the measurement's error taken alone, for its compatibility
    test (:attr:`~mapfuse_core.measlog.MeasurementLog.feat_gate_cov`); ``None``:
    :attr:`cov`.  The update weighs it with :attr:`cov`."""


@dataclass(frozen=True)
class Candidate:
    """An individually compatible (query, target) pair and its linearisation."""

    target: int
    """Index of the target element (a FEATURE or a KNOWN feature)."""
    residual: FloatArray
    """Pairing residual (2 for lines, 3 for circles)."""
    indices: list[int]
    """Map elements the residual depends on."""
    H: FloatArray
    """∂residual/∂(those elements), (m, 3·len(indices))."""
    R: FloatArray
    """Covariance of the residual due to the measurement (zeros for a map element), as
    the update weighs it."""
    d2: float
    """Mahalanobis distance ``rᵀ S⁻¹ r``, ``S`` with the measurement's error taken alone
    (:attr:`Query.gate_cov`)."""
    R_gate: FloatArray | None = None
    """The residual's covariance due to the measurement's error taken alone, which the
    compatibility tests use (:attr:`Query.gate_cov`); ``None``: :attr:`R`."""


def predict_targets(
    state: GaussianMap, kind: ElementKind, features: Callable[[Element], bool], known: bool = True
) -> tuple[list[int], FloatArray]:
    """Targets of ``kind`` and their parameters in the working frame.

    Feature elements pass when ``features(element)`` is true; known-map features are
    included (seen through the anchor) when ``known`` and the map has an anchor.
    """
    return predict_all_targets(state, features, known)[kind]


def predict_all_targets(
    state: GaussianMap, features: Callable[[Element], bool], known: bool = True
) -> dict[ElementKind, tuple[list[int], FloatArray]]:
    """:func:`predict_targets` for lines and circles, scanning the elements once."""
    anchor = state.find(Role.ANCHOR) if known and state.has(Role.ANCHOR) else -1
    kinds, roles = state.kinds_roles()
    passing = np.zeros(len(state), dtype=bool)
    for i in np.nonzero(roles == int(Role.FEATURE))[0].tolist():
        passing[i] = features(state.elements[i])
    out = {}
    known_el = roles == int(Role.KNOWN) if anchor >= 0 else np.zeros(len(state), dtype=bool)
    for kind in (ElementKind.LINE, ElementKind.CIRCLE):
        of_kind = kinds == int(kind)
        feat = np.nonzero(of_kind & passing)[0].tolist()
        kn = np.nonzero(of_kind & known_el)[0]
        preds = np.empty((len(feat) + kn.size, 3))
        preds[: len(feat)] = state.mean[feat]
        if kn.size:
            # x^R_Wknown ⊕ E for every known feature at once: transform_feature vectorised
            # (tests/test_models.py holds the two equal).
            a = state.mean[anchor]
            c, s = math.cos(a[2]), math.sin(a[2])
            E = state.mean[kn]
            pk = preds[len(feat) :]
            pk[:, 0] = a[0] + c * E[:, 0] - s * E[:, 1]
            pk[:, 1] = a[1] + s * E[:, 0] + c * E[:, 1]
            pk[:, 2] = E[:, 2] if kind == ElementKind.CIRCLE else wrap_angle(E[:, 2] + a[2])
        out[kind] = (feat + kn.tolist(), preds)
    return out


def _target_jacobian(state: GaussianMap, t: int) -> tuple[FloatArray, list[int], list[FloatArray]]:
    e = state.elements[t]
    if e.role == Role.KNOWN:
        a = state.find(Role.ANCHOR)
        pred, Ja, Je = transform_feature(e.kind.feature_kind(), state.mean[a], state.mean[t])
        return pred, [a, t], [Ja, Je]
    return state.mean[t], [t], [np.eye(3)]


def evaluate(state: GaussianMap, q: Query, t: int) -> Candidate:
    """Residual, Jacobian and Mahalanobis distance of pairing query ``q`` with target ``t``.

    The residual is the feature model's ``pairing(target, q)``
    (:func:`mapfuse_core.models.dispatch.pairing_residual`): for a line, the offset of the
    query's reference point (a measured segment's midpoint) from the target line and
    the angle between them, for an estimated line and a known wall alike, so the
    target's reference point along its line never enters.  A measurement's noise is
    the model's (:func:`mapfuse_core.models.dispatch.pairing_cov`: its covariance with the
    along-line pseudo-variance projected out, through ``∂r/∂q``): ``R`` from
    :attr:`Query.cov`, the distance from :attr:`Query.gate_cov` where given; a map
    element's own covariance is in the map, so its pairing has none.  docs/method.md says why the
    segment form.  A map element's query can ask for the offset at the target's
    reference point instead (:attr:`Query.residual_at`: the paper's ties).
    """
    if q.element < 0 and q.residual_at != "observed":
        raise ValueError("a measurement's residual is measured at the measured segment")
    pred, tidx, tJ = _target_jacobian(state, t)
    fk = q.kind.feature_kind()
    r, Jp, Jq = pairing_residual(fk, pred, q.params, q.residual_at)
    if q.element >= 0:
        indices = [q.element, *tidx]
        blocks = [Jq] + [Jp @ J for J in tJ]
        R = np.zeros((r.size, r.size))
    else:
        indices = tidx
        blocks = [Jp @ J for J in tJ]
        R = pairing_cov(fk, pred, q.params, q.cov)
    H = np.hstack(blocks)
    R_gate = None if q.gate_cov is None else pairing_cov(fk, pred, q.params, q.gate_cov)
    d2 = _mahalanobis(r, (R if R_gate is None else R_gate) + _project(state, indices, H))
    return Candidate(target=t, residual=r, indices=indices, H=H, R=R, d2=d2, R_gate=R_gate)


def weighed_d2(state: GaussianMap, c: Candidate) -> float:
    """``rᵀ S⁻¹ r`` of pairing ``c`` with ``S`` from the covariance the update weighs it
    with (:attr:`Candidate.R`): for tests that sum the pairings of consecutive scans,
    whose shared errors :attr:`Candidate.R` counts once."""
    if c.R_gate is None:
        return c.d2
    return _mahalanobis(c.residual, c.R + _project(state, c.indices, c.H))


def element_pairings(
    state: GaussianMap,
    pairs: list[tuple[int, int]],
    residual_at: Literal["observed", "target"] = "observed",
) -> list[Candidate]:
    """Hard pairings ``(map element, target)`` evaluated at the current ``state.mean``
    (a line's lateral residual measured ``residual_at``, :attr:`Query.residual_at`)."""
    out = []
    for i, t in pairs:
        e = state.elements[i]
        q = Query(
            e.kind, state.mean[i], np.zeros((3, 3)), e.extent, element=i, residual_at=residual_at
        )
        out.append(evaluate(state, q, t))
    return out


def _project(state: GaussianMap, indices: list[int], H: FloatArray) -> FloatArray:
    """``H P_II Hᵀ`` from covariance blocks (slices, not fancy indexing: this is hot)."""
    k = len(indices)
    if k == 1:
        i = 3 * indices[0]
        out: FloatArray = H @ state.cov[i : i + 3, i : i + 3] @ H.T
        return out
    P = np.empty((3 * k, 3 * k))
    for a, i in enumerate(indices):
        for b, j in enumerate(indices):
            P[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] = state.cov[
                3 * i : 3 * i + 3, 3 * j : 3 * j + 3
            ]
    out = H @ P @ H.T
    return out


def _mahalanobis(r: FloatArray, S: FloatArray) -> float:
    """``rᵀ S⁻¹ r`` for a 2×2 or 3×3 ``S``; inf when ``S`` is not positive definite."""
    if r.size == 2:
        det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
        if not det > 0.0 or not S[0, 0] > 0.0:
            return math.inf
        return float(
            (S[1, 1] * r[0] * r[0] - (S[0, 1] + S[1, 0]) * r[0] * r[1] + S[0, 0] * r[1] * r[1])
            / det
        )
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return math.inf
    y = np.linalg.solve(L, r)
    return float(y @ y)


def prefilter(
    q: Query,
    preds: FloatArray,
    targets: list[int],
    state: GaussianMap,
    config: AssociationConfig,
) -> list[int]:
    """Targets worth a χ² test with ``q``: :func:`mapfuse_core.matching.pregate`, and
    with ``config.known_wall_ends`` no known wall that ``q`` overhangs
    (:func:`within_known_wall`)."""
    if not targets:
        return []
    rows = pregate(
        q.kind.feature_kind(),
        q.params,
        q.extent,
        preds,
        lambda k: state.elements[targets[k]].extent,
        config,
    )
    if config.known_wall_ends and q.kind == ElementKind.LINE:
        rows = [k for k in rows if within_known_wall(state, q, targets[k], preds[k], config)]
    return [targets[k] for k in rows]


def within_known_wall(
    state: GaussianMap, q: Query, t: int, pred: FloatArray, config: AssociationConfig
) -> bool:
    """Whether line query ``q`` lies within target ``t``'s extent, when ``t`` is a known
    wall with a surveyed one (any other target: ``True``).

    ``pred`` is ``t`` in the working frame.  Each end of ``q`` may reach beyond ``t``'s
    by the ``config.gate_prob`` quantile (one dof) of the σ of where ``t``'s ends lie
    along it: the anchor's position covariance seen along the wall (the vehicle's
    uncertainty in the known map's frame; the anchor's angle moves the ends across the
    wall, not along it), the survey's own (:attr:`Element.extent_sd`) and the
    segment's (:attr:`Query.end_sd`).
    """
    e = state.elements[t]
    if e.role != Role.KNOWN or not all(math.isfinite(v) for v in (*q.extent, *e.extent)):
        return True
    overhang = line_overhang(q.params, q.extent, pred, e.extent)
    if overhang == 0.0:
        return True
    _, (a, _), (Ja, _) = _target_jacobian(state, t)
    u = np.array([math.cos(pred[2]), math.sin(pred[2])])
    g = u @ Ja[:2]
    var = float(g @ state.cov[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] @ g)
    var += e.extent_sd**2 + q.end_sd**2
    return overhang <= math.sqrt(chi2_gate(config.gate_prob, 1) * max(var, 0.0))


def segment_end_sd(params: FloatArray, extent: tuple[float, float], beam_spacing: float) -> float:
    """σ (m) of where a measured segment's ends lie along it: one beam's footprint,
    ``beam_spacing`` (rad) times the range of its farther end.

    The last return on a wall lies within a beam of its end, and the bearing noise
    blurs a return across the beam by a fraction of that footprint; at a grazing view
    both fall along the wall.  ``inf`` when the beam spacing is unknown.
    """
    if not math.isfinite(beam_spacing) or not all(math.isfinite(v) for v in extent):
        return math.inf
    c, s = math.cos(float(params[2])), math.sin(float(params[2]))
    far = max(math.hypot(float(params[0]) + t * c, float(params[1]) + t * s) for t in extent)
    return beam_spacing * far


def individual_candidates(
    state: GaussianMap,
    q: Query,
    targets: list[int],
    preds: FloatArray,
    config: AssociationConfig,
) -> list[Candidate]:
    """Individually compatible candidates of ``q``, best (smallest d²) first."""
    gate = chi2_gate(config.gate_prob, 2 if q.kind == ElementKind.LINE else 3)
    out = []
    for t in prefilter(q, preds, targets, state, config):
        if t == q.element:
            continue
        c = evaluate(state, q, t)
        if c.d2 <= gate:
            out.append(c)
    out.sort(key=lambda c: c.d2)
    return out


def targets_distinct(state: GaussianMap, a: int, b: int, gate_prob: float) -> bool:
    """Whether map elements ``a`` and ``b`` (features or known features of one kind)
    are not compatible with each other at the ``gate_prob`` χ² gate, their
    correlations included: they cannot be one feature.

    An estimated feature is tested as a query against the other (a known one seen
    through the anchor); two known features are compared where both are, in
    ``Wknown``.
    """
    ea, eb = state.elements[a], state.elements[b]
    if ea.role == Role.KNOWN and eb.role == Role.KNOWN:
        fk = ea.kind.feature_kind()
        r, Jp, Jq = pairing_residual(fk, state.mean[b], state.mean[a])
        S = _project(state, [a, b], np.hstack([Jq, Jp]))
        d2 = _mahalanobis(r, S)
    else:
        if ea.role == Role.KNOWN:
            a, b, ea = b, a, eb
        q = Query(ea.kind, state.mean[a], np.zeros((3, 3)), ea.extent, element=a)
        d2 = evaluate(state, q, b).d2
    gate = chi2_gate(gate_prob, 2 if ea.kind == ElementKind.LINE else 3)
    return d2 > gate


def choose(
    state: GaussianMap,
    queries: list[Query],
    targets_for: dict[ElementKind, tuple[list[int], FloatArray]],
    config: AssociationConfig,
    skipped: list[int] | None = None,
) -> list[Candidate | None]:
    """The pairing of every query (``None``: unpaired), measurements and map elements
    alike: individually compatible candidates, ambiguous queries left out where their
    rule refuses or skips (:attr:`~mapfuse_core.matching.AssociationConfig.ambiguity`
    for measurements, :attr:`~mapfuse_core.matching.AssociationConfig.map_ambiguity` for
    map elements), then nearest neighbour or JCBB (``config.method`` for measurements,
    ``config.map_method`` for map elements; a list mixing both takes ``method``).
    ``targets_for[kind]`` gives the targets of each kind and their predictions
    (:func:`predict_all_targets`).  The indices of the queries the ``"skip"`` rule
    leaves out (unpaired, and not to start a feature) are appended to ``skipped``."""
    cands = []
    for q in queries:
        targets, preds = targets_for[q.kind]
        cands.append(individual_candidates(state, q, targets, preds, config))
    maps = [k for k, q in enumerate(queries) if q.element >= 0]
    measurements = [k for k, q in enumerate(queries) if q.element < 0]

    def distinct(a: int, b: int) -> bool:
        return targets_distinct(state, a, b, config.gate_prob)

    def distinct_known(a: int, b: int) -> bool:
        known = state.elements[a].role == Role.KNOWN and state.elements[b].role == Role.KNOWN
        return known and distinct(a, b)

    rules = {"refuse": distinct, "refuse_known": distinct_known, "skip": distinct}
    for group, rule in ((maps, config.map_ambiguity), (measurements, config.ambiguity)):
        if rule not in rules or not group:
            continue
        kept = drop_ambiguous([cands[k] for k in group], rules[rule])
        for k, cs in zip(group, kept, strict=True):
            if rule == "skip" and cands[k] and not cs and skipped is not None:
                skipped.append(k)
            cands[k] = cs
    method = config.map_method if queries and len(maps) == len(queries) else config.method
    if method == "jcbb":
        return jcbb(state, cands, config)
    return nearest_neighbour(cands, config)


def exclusive(c: Candidate, config: AssociationConfig) -> bool:
    """Whether ``c``'s target may take only one query (``config``'s one-to-one rules:
    by default a circle takes one, a line several segments of one wall)."""
    kind = FeatureKind.LINE if c.residual.size == 2 else FeatureKind.CIRCLE
    return config.one_observation_per(kind)


def nearest_neighbour(
    cands: list[list[Candidate]], config: AssociationConfig
) -> list[Candidate | None]:
    """Greedy NN (:func:`mapfuse_core.matching.nearest_neighbour`): the globally best
    pairs first, under :func:`exclusive`."""
    return nn_search(cands, lambda c: exclusive(c, config))


def joint_compatible(state: GaussianMap, chosen: list[Candidate], gate_prob: float) -> bool:
    """Joint χ² test of a set of pairings (correlations through the map included), with
    each measurement's error taken alone (:attr:`Candidate.R_gate`), as its own gate."""
    if not chosen:
        return True
    r, H, R, idx = stack(state, chosen, gate=True)
    S = H @ state.cov[np.ix_(idx, idx)] @ H.T + R
    try:
        d2 = float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return False
    return d2 <= chi2_gate(gate_prob, r.size)


def jcbb(
    state: GaussianMap, cands: list[list[Candidate]], config: AssociationConfig
) -> list[Candidate | None]:
    """JCBB (:func:`mapfuse_core.matching.jcbb`) with the joint χ² test of
    :func:`joint_compatible` (correlations through the map included)."""
    return jcbb_search(
        cands,
        lambda trial: joint_compatible(state, trial, config.gate_prob),
        lambda c: exclusive(c, config),
        config.jcbb_max_nodes,
    )


def stack(
    state: GaussianMap, chosen: list[Candidate], gate: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Stack pairings into one residual, Jacobian over the union of elements, and R (the
    update's, or with ``gate`` the compatibility tests' :attr:`Candidate.R_gate`)."""
    elems = sorted({i for c in chosen for i in c.indices})
    pos = {e: k for k, e in enumerate(elems)}
    m = sum(c.residual.size for c in chosen)
    H = np.zeros((m, 3 * len(elems)))
    R = np.zeros((m, m))
    r = np.zeros(m)
    row = 0
    for c in chosen:
        k = c.residual.size
        r[row : row + k] = c.residual
        R[row : row + k, row : row + k] = c.R if not gate or c.R_gate is None else c.R_gate
        for j, e in enumerate(c.indices):
            H[row : row + k, 3 * pos[e] : 3 * pos[e] + 3] = c.H[:, 3 * j : 3 * j + 3]
        row += k
    return r, H, R, state.dofs(elems)


def apply(state: GaussianMap, chosen: list[Candidate]) -> float:
    """One batched EKF update with all chosen pairings; returns the normalised
    innovation squared ``rᵀ S⁻¹ r`` of the stacked pairings before it (χ² with their
    summed residual dimensions for a consistent filter; 0 without pairings)."""
    if not chosen:
        return 0.0
    r, H, R, idx = stack(state, chosen)
    elems = sorted({i for c in chosen for i in c.indices})
    del idx
    return state.update(elems, r, H, R)


@dataclass(frozen=True)
class IteratedUpdate:
    """Outcome of :func:`apply_iterated`."""

    iterations: int
    """Linearisations done (0 without pairings)."""
    converged: bool
    """Whether the last step moved no mean by more than the tolerance."""
    nis: float
    """Normalised innovation squared ``νᵀ S⁻¹ ν`` of the pairings at the last
    linearisation, against the prior: ``ν = r(x) + H (x0 − x)``, ``S = H P0 Hᵀ + R``.
    At the solution of a nearly linear problem it is the minimum of the Gauss–Newton
    cost, χ² with :attr:`dims` degrees of freedom less any the prior leaves free."""
    dims: int
    """Dimension of the stacked pairing residual."""


def apply_iterated(
    state: GaussianMap,
    pairings: Callable[[GaussianMap], list[Candidate]],
    max_iterations: int = 10,
    tol: float = 1e-9,
    rtol: float = 0.0,
) -> IteratedUpdate:
    """Iterated EKF update (Gauss–Newton on prior and pairings).

    ``pairings(state)`` evaluates the same pairings at ``state.mean``.  Each iteration
    relinearises them at the last estimate ``x`` and updates the prior ``(x0, P0)`` with
    the residual ``r(x) + H (x0 − x)``; it stops when no mean moves by more than
    ``tol`` (metres or radians) plus ``rtol`` times its prior σ; if it has not after
    ``max_iterations``, the last
    iterate is kept and ``converged`` is false.  For a prior much looser than its
    pairings (the anchor when CCDA accepts) one linearisation at the prior's mean is
    not the maximum of the posterior, and the posterior then depends on the form of
    the pairing residual: on loop600 the anchor's σ differed by up to 7 % between two
    first-order-equivalent forms of the line pairing, and iterated they agree.
    """
    chosen = pairings(state)
    if not chosen:
        return IteratedUpdate(0, True, 0.0, 0)
    x0 = state.mean.copy()
    angles = state.kinds_roles()[0] != int(ElementKind.CIRCLE)
    limit = tol + rtol * np.sqrt(np.maximum(np.diagonal(state.cov), 0.0)).reshape(-1, 3)
    # The iterations move the mean only (the covariance stays the prior's); the
    # covariance is updated once, at the last linearisation.
    for it in range(1, max_iterations + 1):
        x = state.mean.copy()
        if it > 1:
            chosen = pairings(state)
        r, H, R, idx = stack(state, chosen)
        dx = x0 - x
        dx[angles, 2] = wrap_angle(dx[angles, 2])
        elems = sorted({i for c in chosen for i in c.indices})
        nu = r + H @ dx.reshape(-1)[idx]
        state.mean = x0.copy()
        new, nis = state.updated_mean(elems, nu, H, R)
        step = new - x
        step[angles, 2] = wrap_angle(step[angles, 2])
        converged = bool(np.all(np.abs(step) <= limit))
        if converged or it == max_iterations:
            state.update(elems, nu, H, R)
            return IteratedUpdate(it, converged, nis, int(r.size))
        state.mean = new
    raise AssertionError("unreachable: the last iteration returns")
