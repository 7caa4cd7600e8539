"""A floor plan (wall map) built from every scan at the reference poses (``docs/real-data.md``).

Each line observation of a log with a reference trajectory is put in the reference
frame ``W`` at its step's reference pose, in normal form ``(ρ, α)`` with its world
segment.  Observations are clustered greedily, longest first: one joins the wall
whose ``(ρ, α)`` is within ``rho_tol_m`` / ``alpha_tol_rad`` and whose extent along the
wall overlaps its segment or lies within ``gap_m`` of it.  A wall is kept when it has
at least ``min_observations`` observations and no parallel wall closer than
``min_parallel_separation_m`` beside it.  Its ``(ρ, α)`` is the mean of its
members', its covariance the members' scatter divided by their number (the standard
error of the mean, which includes the walls' real roughness) plus a stated survey
σ; its extent the union of its members' segments.

:func:`line_nees` measures each labelled observation against its wall at the
reference pose: how honest the extracted line covariances are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2 as chi2_dist

from mapfuse_core.geometry.features import (
    FeatureKind,
    express_line_in,
    line_from_normal,
    line_to_normal,
    transform_line,
)
from mapfuse_core.geometry.se2 import FloatArray, wrap_scalar
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.models import line_pairing

__all__ = [
    "FloorPlan",
    "FloorPlanParams",
    "build_floor_plan",
    "label_with_plan",
    "line_nees",
    "reference_labels",
    "same_wall",
]


@dataclass(frozen=True)
class FloorPlanParams:
    """Thresholds of :func:`build_floor_plan`."""

    rho_tol_m: float = 0.10
    """An observation joins a wall only if their ρ (in ``W``) differ by at most this (m)."""
    alpha_tol_rad: float = math.radians(3.0)
    """… and their α by at most this (rad); a wall's two faces differ by π and stay apart."""
    gap_m: float = 0.3
    """… and the gap between its segment and the wall's extent is at most this (m)."""
    min_observations: int = 5
    """A wall is kept only when this many observations joined it (clutter, people and
    doors that moved are seen a few times)."""
    survey_sigma_m: float = 0.02
    """σ (m) added to every wall's ρ and to its reference point along the wall: a plan
    drawn from a survey is no better than a few centimetres."""
    survey_sigma_rad: float = math.radians(0.3)
    """σ (rad) added to every wall's direction."""
    min_parallel_separation_m: float = 0.5
    """Walls with a parallel, same-facing wall nearer than this (m) beside them are left
    out of the plan (a recess, a cupboard front before a wall): a match with the known
    map cannot tell the two apart until it is better than their separation."""

    def __post_init__(self) -> None:
        for name in (
            "rho_tol_m",
            "alpha_tol_rad",
            "gap_m",
            "survey_sigma_m",
            "survey_sigma_rad",
            "min_parallel_separation_m",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0.0:
                raise ValueError(f"FloorPlanParams.{name} must be a number > 0, got {v!r}")
        m = self.min_observations
        if isinstance(m, bool) or not isinstance(m, int) or m < 2:
            raise ValueError(f"FloorPlanParams.min_observations must be an int >= 2, got {m!r}")


@dataclass(frozen=True)
class FloorPlan:
    """The walls of a floor plan and which observation built which wall."""

    walls: KnownMapArrays
    """Walls in the reference frame ``W``, ids ``0 … W−1``, in the known-map format."""
    obs_wall: np.ndarray
    """(M,) int64 wall id of every feature of the log, −1 for none (unkept or not a line)."""
    n_obs: np.ndarray
    """(W,) int64 observations per wall."""


def _world_normal(
    pose: FloatArray, line: FloatArray, extent: FloatArray
) -> tuple[float, float, float, float]:
    """``(ρ, α, s0, s1)`` of a sensor-frame line seen from ``pose``: normal form in ``W``
    and the segment's interval along the wall (tangent ``α + π/2``)."""
    w, _, _ = transform_line(pose, line)
    (rho, alpha), _ = line_to_normal(w)
    t = np.array([-math.sin(alpha), math.cos(alpha)])
    th = float(w[2])
    ends = [w[:2] + e * np.array([math.cos(th), math.sin(th)]) for e in extent]
    s = sorted(float(p @ t) for p in ends)
    return float(rho), float(alpha), s[0], s[1]


def build_floor_plan(log: MeasurementLog, params: FloorPlanParams | None = None) -> FloorPlan:
    """The floor plan of ``log``'s lines at its reference poses (``log.true_poses``)."""
    p = FloorPlanParams() if params is None else params
    if log.true_poses is None:
        raise ValueError("build_floor_plan needs a log with a reference trajectory (true_poses)")
    lines = np.flatnonzero(log.feat_kind == FeatureKind.LINE)
    obs = np.array(
        [
            _world_normal(log.true_poses[log.feat_step[i]], log.feat_params[i], log.feat_extent[i])
            for i in lines
        ]
    ).reshape(-1, 4)
    order = np.argsort(-(obs[:, 3] - obs[:, 2]), kind="stable")
    # Running cluster state: ρ, α of the first (longest) member, extent union.
    c_rho: list[float] = []
    c_alpha: list[float] = []
    c_ext: list[list[float]] = []
    member = np.full(lines.size, -1, dtype=np.int64)
    for j in order:
        rho, alpha, s0, s1 = obs[j]
        best, best_d = -1, math.inf
        for c in range(len(c_rho)):
            da = abs(wrap_scalar(alpha - c_alpha[c]))
            dr = abs(rho - c_rho[c])
            if da > p.alpha_tol_rad or dr > p.rho_tol_m:
                continue
            if s0 > c_ext[c][1] + p.gap_m or s1 < c_ext[c][0] - p.gap_m:
                continue
            d = (dr / p.rho_tol_m) ** 2 + (da / p.alpha_tol_rad) ** 2
            if d < best_d:
                best, best_d = c, d
        if best < 0:
            c_rho.append(float(rho))
            c_alpha.append(float(alpha))
            c_ext.append([float(s0), float(s1)])
            best = len(c_rho) - 1
        else:
            c_ext[best][0] = min(c_ext[best][0], float(s0))
            c_ext[best][1] = max(c_ext[best][1], float(s1))
        member[j] = best
    _merge_clusters(member, c_rho, c_alpha, c_ext, obs, p)

    ids: list[int] = []
    params_out: list[FloatArray] = []
    covs: list[FloatArray] = []
    extents: list[tuple[float, float]] = []
    counts: list[int] = []
    obs_wall = np.full(log.n_features, -1, dtype=np.int64)
    kept = [c for c in range(len(c_rho)) if np.count_nonzero(member == c) >= p.min_observations]
    for c in _unambiguous(kept, member, c_alpha, c_ext, obs, p):
        sel = np.flatnonzero(member == c)
        rho_m = obs[sel, 0]
        a_m = c_alpha[c] + np.array([wrap_scalar(a - c_alpha[c]) for a in obs[sel, 1]])
        rho, alpha = float(rho_m.mean()), float(a_m.mean())
        # Re-express the members' intervals about the mean direction's foot point.
        lo = float(obs[sel, 2].min())
        hi = float(obs[sel, 3].max())
        scatter = np.cov(np.vstack((rho_m, a_m))) / sel.size
        C = np.zeros((3, 3))
        C[:2, :2] = scatter
        C[0, 0] += p.survey_sigma_m**2
        C[1, 1] += p.survey_sigma_rad**2
        C[2, 2] = p.survey_sigma_m**2
        t_mid = 0.5 * (lo + hi)
        line, J = line_from_normal(rho, alpha, t_mid)
        cov = J @ C @ J.T
        wid = len(ids)
        ids.append(wid)
        params_out.append(line)
        covs.append(0.5 * (cov + cov.T))
        extents.append((lo - t_mid, hi - t_mid))
        counts.append(int(sel.size))
        obs_wall[lines[sel]] = wid
    w = len(ids)
    walls = KnownMapArrays(
        ids=np.asarray(ids, dtype=np.int64).reshape(w),
        kinds=np.full(w, int(FeatureKind.LINE), dtype=np.int8),
        params=np.asarray(params_out, dtype=np.float64).reshape(w, 3),
        covs=np.asarray(covs, dtype=np.float64).reshape(w, 3, 3),
        extents=np.asarray(extents, dtype=np.float64).reshape(w, 2),
    )
    return FloorPlan(walls=walls, obs_wall=obs_wall, n_obs=np.asarray(counts, dtype=np.int64))


def _unambiguous(
    kept: list[int],
    member: np.ndarray,
    c_alpha: list[float],
    c_ext: list[list[float]],
    obs: FloatArray,
    p: FloorPlanParams,
) -> list[int]:
    """The clusters of ``kept`` without a parallel, same-facing wall closer than
    ``min_parallel_separation_m`` whose extent overlaps theirs (within ``gap_m``).

    A wall face and a recess or cupboard front 10–30 cm in front of it are told apart
    only by a map match already better than that; pairing a landmark with the wrong
    one of them biases the match by their separation, so both are left out.
    """
    rho = {c: float(obs[member == c, 0].mean()) for c in kept}
    n_obs = {c: int(np.count_nonzero(member == c)) for c in kept}
    out = []
    for a in kept:
        clash = False
        for b in kept:
            if b == a or (n_obs[b], -b) < (n_obs[a], -a):
                continue
            if abs(wrap_scalar(c_alpha[a] - c_alpha[b])) > 2.0 * p.alpha_tol_rad:
                continue
            if abs(rho[a] - rho[b]) >= p.min_parallel_separation_m:
                continue
            if c_ext[a][0] <= c_ext[b][1] + p.gap_m and c_ext[b][0] <= c_ext[a][1] + p.gap_m:
                clash = True
                break
        if not clash:
            out.append(a)
    return out


def _compatible(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float], p: FloorPlanParams
) -> bool:
    """Whether two walls ``(ρ, α, s0, s1)`` are one: close in ``(ρ, α)``, extents near."""
    return (
        abs(a[0] - b[0]) <= p.rho_tol_m
        and abs(wrap_scalar(a[1] - b[1])) <= p.alpha_tol_rad
        and a[2] <= b[3] + p.gap_m
        and b[2] <= a[3] + p.gap_m
    )


def _merge_clusters(
    member: np.ndarray,
    c_rho: list[float],
    c_alpha: list[float],
    c_ext: list[list[float]],
    obs: FloatArray,
    p: FloorPlanParams,
) -> None:
    """Merge clusters whose mean walls are one wall (``member`` relabelled in place).

    The greedy pass compares each observation with a cluster's first member; a wall
    seen in pieces from far apart can end up in two clusters whose means agree.
    """

    def mean(c: int) -> tuple[float, float, float, float]:
        sel = member == c
        a0 = c_alpha[c]
        da = np.array([wrap_scalar(a - a0) for a in obs[sel, 1]])
        return (
            float(obs[sel, 0].mean()),
            wrap_scalar(a0 + float(da.mean())),
            c_ext[c][0],
            c_ext[c][1],
        )

    alive = sorted(set(int(c) for c in member if c >= 0))
    merged = True
    while merged:
        merged = False
        means = {c: mean(c) for c in alive}
        for i, a in enumerate(alive):
            for b in alive[i + 1 :]:
                if _compatible(means[a], means[b], p):
                    member[member == b] = a
                    c_ext[a] = [min(c_ext[a][0], c_ext[b][0]), max(c_ext[a][1], c_ext[b][1])]
                    alive.remove(b)
                    merged = True
                    break
            if merged:
                break


def same_wall(
    plan: FloorPlan, a: int, b: int, params: FloorPlanParams | None = None, gap_m: float = 4.0
) -> bool:
    """Whether walls ``a`` and ``b`` of ``plan`` lie on one line: ``a == b``, or their
    directions within the plan's ``alpha_tol_rad``, each segment's midpoint within its
    ``rho_tol_m`` of the other's line, and their extents at most ``gap_m`` apart.  How a
    pairing of a landmark labelled wall ``a`` (the wall most of its observations lie
    on, :func:`~mapfuse_core.evaluation.landmark_labels`) with known wall ``b`` is
    judged: a line pairing constrains only the lateral offset and the angle, so a
    pairing with a collinear piece (the wall beyond a door) is as right as one with the
    piece itself; ``gap_m`` defaults to ``AssociationConfig.line_gap_m``'s 4 m.

    The offsets are measured at the walls, not as ρ at ``W``'s origin: there two walls
    0.3° apart and 20 m from the foot of their normal differ by 0.1 m whether or not
    they meet, so the verdict would depend on where the reference frame starts."""
    p = replace(FloorPlanParams() if params is None else params, gap_m=gap_m)
    if a < 0 or b < 0:
        return False
    if a == b:
        return True
    ext = _extents(plan)
    wa, wb = (_wall_interval(plan.walls.params[w], ext[w]) for w in (a, b))
    wb = _facing(wb, wa[1])
    if abs(wrap_scalar(wa[1] - wb[1])) > p.alpha_tol_rad:
        return False
    if max(_offset_at_midpoint(wa, wb), _offset_at_midpoint(wb, wa)) > p.rho_tol_m:
        return False
    return wa[2] <= wb[3] + p.gap_m and wb[2] <= wa[3] + p.gap_m


def _facing(
    w: tuple[float, float, float, float], alpha: float
) -> tuple[float, float, float, float]:
    """Wall ``w`` ``(ρ, α, s0, s1)`` written with its normal within 90° of ``alpha``:
    ``(−ρ, α + π, −s1, −s0)`` when it points the other way.  The normal form takes
    ``ρ ≥ 0``, so two pieces of one line on either side of the origin's foot point
    can differ by π in ``α``."""
    if abs(wrap_scalar(w[1] - alpha)) <= math.pi / 2:
        return w
    return -w[0], wrap_scalar(w[1] + math.pi), -w[3], -w[2]


def _offset_at_midpoint(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> float:
    """Distance (m) from the midpoint of wall ``a`` ``(ρ, α, s0, s1)`` to ``b``'s line."""
    n = np.array([math.cos(a[1]), math.sin(a[1])])
    t = np.array([-n[1], n[0]])
    mid = a[0] * n + 0.5 * (a[2] + a[3]) * t
    return abs(float(mid @ np.array([math.cos(b[1]), math.sin(b[1])])) - b[0])


def _extents(plan: FloorPlan) -> FloatArray:
    if plan.walls.extents is None:
        raise ValueError("the floor plan's walls have no extents")
    return plan.walls.extents


def _wall_interval(line: FloatArray, extent: FloatArray) -> tuple[float, float, float, float]:
    (rho, alpha), _ = line_to_normal(line)
    t = np.array([-math.sin(alpha), math.cos(alpha)])
    u = np.array([math.cos(float(line[2])), math.sin(float(line[2]))])
    s = sorted(float((line[:2] + e * u) @ t) for e in extent)
    return float(rho), float(alpha), s[0], s[1]


def wall_residual(
    log: MeasurementLog, i: int, walls: KnownMapArrays, w: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Line observation ``i`` against wall ``w`` at the reference pose: the residual
    :func:`~mapfuse_core.models.dispatch.line_pairing` (observation first; lateral
    offset of the wall's midpoint from the observed line, angle), its covariance (the
    observation's plus the wall's, propagated) and ``∂r/∂(observation)``."""
    assert log.true_poses is not None
    pred, _, Jf = express_line_in(log.true_poses[log.feat_step[i]], walls.params[w])
    r, Jz, Jp = line_pairing(log.feat_params[i], pred)
    Jw = Jp @ Jf
    S = Jz @ log.feat_cov[i] @ Jz.T + Jw @ walls.covs[w] @ Jw.T
    return r, S, Jz


def _d2(log: MeasurementLog, i: int, walls: KnownMapArrays, w: int) -> float:
    """Squared Mahalanobis distance of line observation ``i`` to wall ``w`` at the
    reference pose (:func:`wall_residual`)."""
    r, S, _ = wall_residual(log, i, walls, w)
    return float(r @ np.linalg.solve(S, r))


def reference_labels(
    log: MeasurementLog, plan: FloorPlan, params: FloorPlanParams | None = None
) -> np.ndarray:
    """(M,) int64 wall of every line observation judged at the reference pose, −1 for none.

    The wall nearest in Mahalanobis distance among those within the χ²(2) 99.9 % gate
    whose extent overlaps the observed segment (within ``gap_m``); walls far in
    ``(ρ, α)`` are ruled out first.  Unlike :attr:`FloorPlan.obs_wall` (cluster
    membership) this labels observations of walls left out of the plan with a wall
    of the plan they lie on.
    """
    p = FloorPlanParams() if params is None else params
    if log.true_poses is None:
        raise ValueError("reference_labels needs a log with a reference trajectory (true_poses)")
    gate = float(chi2_dist.ppf(0.999, 2))
    walls = plan.walls
    ext = _extents(plan)
    wi = np.array([_wall_interval(walls.params[w], ext[w]) for w in range(len(walls))])
    wi = wi.reshape(-1, 4)
    out = np.full(log.n_features, -1, dtype=np.int64)
    for i in np.flatnonzero(log.feat_kind == FeatureKind.LINE):
        rho, alpha, s0, s1 = _world_normal(
            log.true_poses[log.feat_step[i]], log.feat_params[i], log.feat_extent[i]
        )
        da = np.abs(np.remainder(wi[:, 1] - alpha + math.pi, 2.0 * math.pi) - math.pi)
        cand = np.flatnonzero(
            (da <= 3.0 * p.alpha_tol_rad)
            & (np.abs(wi[:, 0] - rho) <= 3.0 * p.rho_tol_m)
            & (wi[:, 2] <= s1 + p.gap_m)
            & (s0 <= wi[:, 3] + p.gap_m)
        )
        best, best_d2 = -1, gate
        for w in cand:
            d2 = _d2(log, int(i), walls, int(w))
            if d2 <= best_d2:
                best, best_d2 = int(w), d2
        out[i] = best
    return out


def label_with_plan(
    log: MeasurementLog, plan: FloorPlan, *, as_known_map: bool = True
) -> MeasurementLog:
    """``log`` with every observation labelled by its wall at the reference pose
    (:func:`reference_labels`, in ``feat_true_id``), and the plan as its known map when
    ``as_known_map``: the labels are what CCDA's pairings and ``correct_pairings`` are
    judged against."""
    if plan.obs_wall.shape != (log.n_features,):
        raise ValueError(
            f"the plan labels {plan.obs_wall.shape[0]} features, the log has {log.n_features}"
        )
    out = replace(log, feat_true_id=reference_labels(log, plan))
    return replace(out, known_map=plan.walls) if as_known_map else out


def line_nees(log: MeasurementLog, plan: FloorPlan) -> FloatArray:
    """(K,) NEES (2 dof) of every labelled line observation against its wall.

    The wall is expressed in the sensor frame at the reference pose (taken as exact);
    the residual is :func:`~mapfuse_core.models.dispatch.line_pairing` (observation first), its
    covariance the observation's plus the wall's, both propagated.
    """
    if log.true_poses is None:
        raise ValueError("line_nees needs a log with a reference trajectory (true_poses)")
    idx = np.flatnonzero(plan.obs_wall >= 0)
    return np.array([_d2(log, int(i), plan.walls, int(plan.obs_wall[i])) for i in idx])
