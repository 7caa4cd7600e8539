"""A floor plan (wall map) built from every scan at the reference poses (``docs/real-data.md``).

Each line observation of a log with a reference trajectory is put in the reference
frame ``W`` at its step's reference pose: the line through its segment's midpoint and
the segment's interval along it.  Observations are clustered greedily, longest first:
one joins the wall whose first member's line passes within ``rho_tol_m`` of its
midpoint, at most ``alpha_tol_rad`` from its direction (modulo π), and whose extent
overlaps its segment or lies within ``gap_m`` of it.  A wall is kept when it has at
least ``min_observations`` observations and no parallel wall closer than
``min_parallel_separation_m`` beside it.  It is the mean of its members (offset and
angle in its first member's frame), its covariance the members' scatter divided by
their number (the standard error of the mean, which includes the walls' real
roughness) plus a stated survey σ about its midpoint; its extent the union of its
members' segments.  Every test is made where the walls are, never on a normal's
distance from ``W``'s origin, so the plan does not depend on where the log starts.

:func:`line_nees` measures each labelled observation against its wall at the
reference pose: how honest the extracted line covariances are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2 as chi2_dist

from mapfuse_core.geometry.features import FeatureKind, canonical_line, express_line_in
from mapfuse_core.geometry.se2 import FloatArray, compose, rot2, wrap_angle_half
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.measlog.log import IntArray
from mapfuse_core.models import line_pairing

__all__ = [
    "FloorPlan",
    "FloorPlanParams",
    "build_floor_plan",
    "label_with_plan",
    "line_nees",
    "reference_labels",
    "same_wall",
    "survey_cov",
    "wall_d2",
]


@dataclass(frozen=True)
class FloorPlanParams:
    """Thresholds of :func:`build_floor_plan`."""

    rho_tol_m: float = 0.10
    """An observation joins a wall only if its segment's midpoint lies within this (m)
    of the wall's line."""
    alpha_tol_rad: float = math.radians(3.0)
    """… and its direction is within this (rad) of the wall's, modulo π (a line has no
    face: the two faces of a thin wall are one wall, or a parallel pair left out)."""
    gap_m: float = 0.3
    """… and the gap between its segment and the wall's extent is at most this (m)."""
    min_observations: int = 5
    """A wall is kept only when this many observations joined it (clutter, people and
    doors that moved are seen a few times)."""
    survey_sigma_m: float = 0.02
    """σ (m) added to the position of every wall's midpoint, across the wall and along
    it: a plan drawn from a survey is no better than a few centimetres
    (:func:`survey_cov`)."""
    survey_sigma_rad: float = math.radians(0.3)
    """σ (rad) added to every wall's direction, a rotation about its midpoint."""
    min_parallel_separation_m: float = 0.5
    """Of two parallel, overlapping walls nearer than this (m) to each other (a recess,
    a cupboard front before a wall), the one seen less often is left out of the plan:
    a match with the known map cannot tell the two apart until it is better than their
    separation."""

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


@dataclass(frozen=True)
class _Segments:
    """Line segments in ``W``, each the SPmap frame of its line at the segment's
    midpoint (x axis along it) with its extent along that axis."""

    lines: FloatArray
    """(N, 3) ``(x, y, θ)``."""
    extents: FloatArray
    """(N, 2) ends along the line, from the midpoint (m)."""

    def take(self, sel: IntArray) -> _Segments:
        return _Segments(self.lines[sel], self.extents[sel])


def _world_segments(log: MeasurementLog, idx: IntArray) -> _Segments:
    """The line observations ``idx`` of ``log`` placed in ``W`` at their reference poses."""
    assert log.true_poses is not None
    poses = log.true_poses[log.feat_step[idx]]
    lines = [compose(x, z) for x, z in zip(poses, log.feat_params[idx], strict=True)]
    return _Segments(np.asarray(lines).reshape(-1, 3), log.feat_extent[idx].reshape(-1, 2))


def _in_frame(
    ref: FloatArray, lines: FloatArray, extents: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Segments seen from the frame of a line ``ref`` (arrays broadcast over their
    leading axes): their midpoints ``(x, y)`` (``y`` the offset from ``ref``'s line),
    their angle to it modulo π in ``(−π/2, π/2]``, and their ends' interval
    ``(s0, s1)`` along it.

    Nothing here refers to ``W``'s origin: two walls are compared where they are, so
    the plan is the same wherever the reference trajectory starts.
    """
    c, s = np.cos(ref[..., 2]), np.sin(ref[..., 2])
    dx, dy = lines[..., 0] - ref[..., 0], lines[..., 1] - ref[..., 1]
    x = c * dx + s * dy
    y = -s * dx + c * dy
    turn = lines[..., 2] - ref[..., 2]
    u = np.cos(turn)
    e0, e1 = x + extents[..., 0] * u, x + extents[..., 1] * u
    return x, y, wrap_angle_half(turn), np.minimum(e0, e1), np.maximum(e0, e1)


def _one_wall(
    a: FloatArray,
    ea: FloatArray,
    b: FloatArray,
    eb: FloatArray,
    rho_tol: float,
    alpha_tol: float,
    gap: float,
) -> np.ndarray:
    """Whether segment ``a`` and each segment ``b`` (lines at their midpoints,
    extents; either pair may be stacked, the other broadcast) lie on one wall:
    directions within ``alpha_tol`` (modulo π), each midpoint within ``rho_tol`` of the
    other's line, and the extents, measured along ``a``, at most ``gap`` apart."""
    _, y, phi, s0, s1 = _in_frame(a, b, eb)
    _, y_back, _, _, _ = _in_frame(b, a, ea)
    out: np.ndarray = (
        (np.abs(phi) <= alpha_tol)
        & (np.maximum(np.abs(y), np.abs(y_back)) <= rho_tol)
        & (s0 <= ea[..., 1] + gap)
        & (s1 >= ea[..., 0] - gap)
    )
    return out


@dataclass(frozen=True)
class _Wall:
    """The mean of a cluster's segments."""

    line: FloatArray
    """(3,) at the middle of the members' extent."""
    cov: FloatArray
    """(3, 3) the standard error of the mean (the members' scatter over their number)."""
    extent: FloatArray
    """(2,) the union of the members' extents."""


def _mean_wall(ref: FloatArray, members: _Segments) -> _Wall:
    """The mean wall of ``members`` (its covariance zero for one member), averaged in
    the frame of ``ref`` (a member near them): each member's offset from ``ref``'s line
    at ``ref``'s midpoint and its angle to it."""
    x, y, phi, s0, s1 = _in_frame(ref, members.lines, members.extents)
    y0 = y - x * np.tan(phi)
    m_y, m_phi = float(y0.mean()), float(phi.mean())
    scatter = np.cov(np.vstack((y0, phi))) / y0.size if y0.size > 1 else np.zeros((2, 2))
    lo, hi = float(s0.min()), float(s1.max())
    x_mid = 0.5 * (lo + hi)
    t = math.tan(m_phi)
    local = np.array([x_mid, m_y + x_mid * t, m_phi])
    # ∂(x, y, θ)/∂(offset at ref's midpoint, angle) in ref's frame, then turned into W.
    J = np.array([[0.0, 0.0], [1.0, x_mid * (1.0 + t * t)], [0.0, 1.0]])
    R = np.eye(3)
    R[:2, :2] = rot2(float(ref[2]))
    JR = R @ J
    half = 0.5 * (hi - lo) / math.cos(m_phi)
    line = canonical_line(compose(ref, local))
    return _Wall(line, JR @ scatter @ JR.T, np.array([-half, half]))


def survey_cov(sigma_m: float, sigma_rad: float) -> FloatArray:
    """(3, 3) covariance a survey tolerance adds to a wall ``(x, y, θ)`` given at its
    midpoint: ``sigma_m`` on the midpoint's position in every direction (across the
    wall and along it) and ``sigma_rad`` on the direction, a rotation about the
    midpoint.  It is the same in every frame the plan is expressed in: a wall far
    from the frame's origin is no less certain than one beside it."""
    return np.diag([sigma_m * sigma_m, sigma_m * sigma_m, sigma_rad * sigma_rad])


def build_floor_plan(log: MeasurementLog, params: FloorPlanParams | None = None) -> FloorPlan:
    """The floor plan of ``log``'s lines at its reference poses (``log.true_poses``)."""
    p = FloorPlanParams() if params is None else params
    if log.true_poses is None:
        raise ValueError("build_floor_plan needs a log with a reference trajectory (true_poses)")
    lines = np.flatnonzero(log.feat_kind == FeatureKind.LINE)
    seg = _world_segments(log, lines)
    member, refs = _cluster(seg, p)
    means = _merge_clusters(member, refs, seg, p)
    n_members = np.bincount(member, minlength=len(refs))
    kept = [c for c in sorted(means) if n_members[c] >= p.min_observations]
    counts = {c: int(n_members[c]) for c in kept}
    survey = survey_cov(p.survey_sigma_m, p.survey_sigma_rad)
    walls_out: list[_Wall] = []
    n_obs: list[int] = []
    obs_wall = np.full(log.n_features, -1, dtype=np.int64)
    for c in _unambiguous(kept, means, counts, p):
        obs_wall[lines[member == c]] = len(walls_out)
        walls_out.append(means[c])
        n_obs.append(counts[c])
    w = len(walls_out)
    walls = KnownMapArrays(
        ids=np.arange(w, dtype=np.int64),
        kinds=np.full(w, int(FeatureKind.LINE), dtype=np.int8),
        params=np.asarray([m.line for m in walls_out], dtype=np.float64).reshape(w, 3),
        covs=np.asarray([_sym(m.cov + survey) for m in walls_out], dtype=np.float64).reshape(
            w, 3, 3
        ),
        extents=np.asarray([m.extent for m in walls_out], dtype=np.float64).reshape(w, 2),
    )
    return FloorPlan(walls=walls, obs_wall=obs_wall, n_obs=np.asarray(n_obs, dtype=np.int64))


def _sym(c: FloatArray) -> FloatArray:
    out: FloatArray = 0.5 * (c + c.T)
    return out


def _cluster(seg: _Segments, p: FloorPlanParams) -> tuple[IntArray, list[int]]:
    """Greedy clusters of the segments, longest first: each joins the cluster whose
    first member's line it lies on (:class:`FloorPlanParams` tolerances, measured in
    that member's frame) and whose extent it overlaps or nears within ``gap_m``, the
    nearest in ``(offset, angle)`` of those.  Returns each segment's cluster and each
    cluster's first member."""
    order = np.argsort(-(seg.extents[:, 1] - seg.extents[:, 0]), kind="stable")
    member = np.full(seg.lines.shape[0], -1, dtype=np.int64)
    refs: list[int] = []
    ext = np.empty((0, 2))
    for j in order.tolist():
        best = -1
        if refs:
            _, y, phi, s0, s1 = _in_frame(seg.lines[refs], seg.lines[j], seg.extents[j])
            ok = (
                (np.abs(phi) <= p.alpha_tol_rad)
                & (np.abs(y) <= p.rho_tol_m)
                & (s0 <= ext[:, 1] + p.gap_m)
                & (s1 >= ext[:, 0] - p.gap_m)
            )
            if ok.any():
                d = np.where(ok, (y / p.rho_tol_m) ** 2 + (phi / p.alpha_tol_rad) ** 2, np.inf)
                best = int(np.argmin(d))
                ext[best] = (min(ext[best, 0], float(s0[best])), max(ext[best, 1], float(s1[best])))
        if best < 0:
            refs.append(j)
            e = seg.extents[j]
            ext = np.vstack((ext, [min(e), max(e)]))
            best = len(refs) - 1
        member[j] = best
    return member, refs


def _unambiguous(
    kept: list[int], means: dict[int, _Wall], counts: dict[int, int], p: FloorPlanParams
) -> list[int]:
    """The clusters of ``kept`` without a parallel wall beside them, seen at least as
    often (ties: the earlier cluster), whose extent overlaps theirs (within ``gap_m``)
    and whose line passes within ``min_parallel_separation_m`` of their midpoint and
    theirs of its midpoint (:func:`_one_wall`).

    A wall face and a recess or cupboard front 10–30 cm in front of it are told apart
    only by a map match already better than that; pairing a landmark with the wrong
    one of them biases the match by their separation, so the one seen less often is
    left out.
    """
    out = []
    for a in kept:
        wa = means[a]
        clash = False
        for b in kept:
            if b == a or (counts[b], -b) < (counts[a], -a):
                continue
            wb = means[b]
            if _one_wall(
                wa.line,
                wa.extent,
                wb.line,
                wb.extent,
                p.min_parallel_separation_m,
                2.0 * p.alpha_tol_rad,
                p.gap_m,
            ):
                clash = True
                break
        if not clash:
            out.append(a)
    return out


def _merge_clusters(
    member: IntArray, refs: list[int], seg: _Segments, p: FloorPlanParams
) -> dict[int, _Wall]:
    """Merge clusters whose mean walls are one wall (``member`` relabelled in place);
    returns the mean wall of every cluster left.

    The greedy pass compares each segment with a cluster's first member; a wall
    seen in pieces from far apart can end up in two clusters whose means agree.  The
    earliest cluster takes the first later one it agrees with.  No cluster before it
    agrees with any after it, and only the merged cluster's mean moved, so the scan
    goes on from the first earlier cluster that now agrees with the merged one (it
    takes it), or else from the merged one itself: what a scan from the start would
    do, without repeating the comparisons that cannot have changed.
    """

    def mean(c: int) -> _Wall:
        return _mean_wall(seg.lines[refs[c]], seg.take(np.flatnonzero(member == c)))

    alive = sorted(set(int(c) for c in member if c >= 0))
    means = {c: mean(c) for c in alive}
    i = 0
    while i < len(alive) - 1:
        a, rest = alive[i], alive[i + 1 :]
        wa = means[a]
        lines = np.array([means[b].line for b in rest])
        extents = np.array([means[b].extent for b in rest])
        hit = np.flatnonzero(
            _one_wall(wa.line, wa.extent, lines, extents, p.rho_tol_m, p.alpha_tol_rad, p.gap_m)
        )
        if hit.size == 0:
            i += 1
            continue
        b = rest[int(hit[0])]
        member[member == b] = a
        alive.remove(b)
        del means[b]
        means[a] = mean(a)
        if i:
            before = alive[:i]
            back = np.flatnonzero(
                _one_wall(
                    np.array([means[c].line for c in before]),
                    np.array([means[c].extent for c in before]),
                    means[a].line,
                    means[a].extent,
                    p.rho_tol_m,
                    p.alpha_tol_rad,
                    p.gap_m,
                )
            )
            if back.size:
                i = int(back[0])
    return means


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
    lines = plan.walls.params
    return bool(
        _one_wall(lines[a], ext[a], lines[b], ext[b], p.rho_tol_m, p.alpha_tol_rad, p.gap_m)
    )


def _extents(plan: FloorPlan) -> FloatArray:
    if plan.walls.extents is None:
        raise ValueError("the floor plan's walls have no extents")
    return plan.walls.extents


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


def wall_d2(log: MeasurementLog, i: int, walls: KnownMapArrays, w: int) -> float:
    """Squared Mahalanobis distance of line observation ``i`` to wall ``w`` at the
    reference pose (:func:`wall_residual`)."""
    r, S, _ = wall_residual(log, i, walls, w)
    return float(r @ np.linalg.solve(S, r))


def reference_labels(
    log: MeasurementLog, plan: FloorPlan, params: FloorPlanParams | None = None
) -> np.ndarray:
    """(M,) int64 wall of every line observation judged at the reference pose, −1 for none.

    The wall nearest in Mahalanobis distance among those within the χ²(2) 99.9 % gate
    whose extent overlaps the observed segment (within ``gap_m``); walls far from the
    segment (its midpoint's offset, its angle) are ruled out first.  Unlike
    :attr:`FloorPlan.obs_wall` (cluster membership) this labels observations of walls
    left out of the plan with a wall of the plan they lie on.
    """
    p = FloorPlanParams() if params is None else params
    if log.true_poses is None:
        raise ValueError("reference_labels needs a log with a reference trajectory (true_poses)")
    gate = float(chi2_dist.ppf(0.999, 2))
    walls = plan.walls
    ext = _extents(plan)
    out = np.full(log.n_features, -1, dtype=np.int64)
    lines = np.flatnonzero(log.feat_kind == FeatureKind.LINE)
    seg = _world_segments(log, lines)
    for n, i in enumerate(lines.tolist()):
        _, y, phi, s0, s1 = _in_frame(walls.params, seg.lines[n], seg.extents[n])
        cand = np.flatnonzero(
            (np.abs(phi) <= 3.0 * p.alpha_tol_rad)
            & (np.abs(y) <= 3.0 * p.rho_tol_m)
            & (s0 <= ext[:, 1] + p.gap_m)
            & (s1 >= ext[:, 0] - p.gap_m)
        )
        best, best_d2 = -1, gate
        for w in cand:
            d2 = wall_d2(log, int(i), walls, int(w))
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
    return np.array([wall_d2(log, int(i), plan.walls, int(plan.obs_wall[i])) for i in idx])
