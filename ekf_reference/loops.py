"""Loop closure at a join: the local map's circles registered to the global map's.

*(choice, beyond the paper)*  The paper pairs a local map with the global map by the
filter's own individual compatibility tests.  That works while the filter's relative
covariance between the two maps is right.  After a long excursion it may not be: a
local map coming back can be degrees and metres off the global map while the filter
believes their relative heading to a fraction of a degree, so only a few of its trees
are paired and the rest become a second copy of trees already mapped, which the run
then follows.  A drift that the filter's white-noise models cannot represent shows up
as closures that all turn the same way; that sign is what calibrates Victoria Park's
sideways slip (``VICTORIA_PARK_ODOMETRY_NOISE``).  ``docs/results/victoria-park-calibration.md``
gives the measured cases.  The closures are in ``EKFResult.loop_closures``.

The registration here finds the rigid motion that puts the most local circle centres
on global ones, without using the filter's covariance (as CCDA does for the known map,
but 2-point hypotheses instead of a maximum clique, which takes minutes on a park's
trees): hypotheses from pairs of well-observed local circles and global circles at the
same distance, scored on those anchors, the best few (non-maximum suppressed) scored on
every local circle and refined by least squares.  It is deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mapfuse_core.evaluation import rigid_alignment
from mapfuse_core.geometry.se2 import FloatArray, transform_point

__all__ = ["LoopClosureParams", "Registration", "accepted", "register_circles"]


@dataclass(frozen=True)
class LoopClosureParams:
    """Tuning of :func:`register_circles` and of the acceptance of a loop closure."""

    search_m: float = 30.0
    """Largest displacement (m) of a local circle searched for: its global partner is
    looked for within this radius of its filtered position."""
    inlier_m: float = 0.6
    """A registered local centre within this distance (m) of a global centre is an
    inlier.  The join residuals of one trunk have a robust σ of about 0.2 m per axis on
    Victoria Park; 0.6 m keeps nearly all while staying below the trunk spacing."""
    n_anchors: int = 20
    """Local circles (the most observed) used to make and pre-score hypotheses."""
    n_partners: int = 4
    """Partners (the farthest anchors within ``min_sep_m``..``max_sep_m``) per anchor."""
    min_sep_m: float = 8.0
    """Shortest distance (m) between the two local circles of a hypothesis."""
    max_sep_m: float = 80.0
    """Longest distance (m) between the two local circles of a hypothesis."""
    n_refine: int = 10
    """Hypotheses (distinct after suppression) scored on every local circle."""
    min_inliers: int = 12
    """Fewest inliers of an accepted loop closure."""
    min_gain: int = 6
    """A loop closure must explain at least this many more local circles than the
    filtered relative pose does (identity), and at least a quarter more."""
    ambiguity_ratio: float = 2.0
    """The best hypothesis needs this many times the inliers of any distinct one."""
    inflation: float = 2.0
    """The relative pose of the two maps gets an extra covariance
    ``diag((inflation · δ)² + floor²)``, ``δ`` the registered correction: the
    discrepancy is then half a standard deviation, and the pairings can be gated."""
    floor_m: float = 0.1
    """Floor (m) of the extra translation σ."""
    floor_rad: float = math.radians(0.2)
    """Floor (rad) of the extra rotation σ."""

    def __post_init__(self) -> None:
        for name in ("search_m", "inlier_m", "min_sep_m", "max_sep_m", "ambiguity_ratio"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"LoopClosureParams.{name} must be > 0, got {v!r}")
        for name in ("inflation", "floor_m", "floor_rad"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0.0):
                raise ValueError(f"LoopClosureParams.{name} must be >= 0, got {v!r}")
        for name in ("n_anchors", "n_partners", "n_refine", "min_inliers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"LoopClosureParams.{name} must be an int >= 1, got {v!r}")
        if self.min_sep_m >= self.max_sep_m:
            raise ValueError("LoopClosureParams.min_sep_m must be below max_sep_m")


@dataclass(frozen=True)
class Registration:
    """Best rigid motion ``T`` (local → global: ``g ≈ T ⊕ l``) and its support."""

    T: FloatArray
    """(3,) ``(x, y, θ)``."""
    pairs: list[tuple[int, int]]
    """(local index, global index) of the inliers, one-to-one, nearest first."""
    inliers: int
    """``len(pairs)``."""
    runner_up: int
    """Inliers of the best hypothesis distinct from ``T`` (0 if none)."""
    at_identity: int
    """Inliers of the identity (the filtered relative pose)."""
    max_shift_m: float
    """Largest displacement of a local inlier centre by ``T``."""


def _one_to_one(tree: cKDTree, P: FloatArray, tol: float) -> list[tuple[int, int]]:
    """Inlier pairs (local, global), each global centre used once, nearest first."""
    d_, j_ = tree.query(P, distance_upper_bound=tol)
    d, j = np.asarray(d_, dtype=float), np.asarray(j_, dtype=np.int64)
    ok = np.nonzero(np.isfinite(d))[0]
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for i in ok[np.argsort(d[ok], kind="stable")].tolist():
        g = int(j[i])
        if g not in used:
            used.add(g)
            pairs.append((i, g))
    return pairs


def _distinct(
    moved: FloatArray, th: float, moved2: FloatArray, th2: float, spread: float, tol: float
) -> bool:
    """Two motions are distinct hypotheses when they put the anchors' centroid (``moved``)
    or turn the anchors (``th`` at lever ``spread``) more than ``2·tol`` apart."""
    return (
        math.hypot(*(moved - moved2)) > 2.0 * tol
        or abs(math.remainder(th - th2, 2 * math.pi)) * spread > 2.0 * tol
    )


def register_circles(
    L: FloatArray, G: FloatArray, n_obs: np.ndarray, params: LoopClosureParams
) -> Registration | None:
    """Register local centres ``L`` (n, 2) to global centres ``G`` (m, 2), one frame.

    ``n_obs`` ranks the local circles as anchors.  ``None`` when no hypothesis exists.
    """
    n = L.shape[0]
    if n < 3 or G.shape[0] < 3:
        return None
    tol = params.inlier_m
    tree = cKDTree(G)
    anchors = np.argsort(-np.asarray(n_obs), kind="stable")[: params.n_anchors]
    cands = [
        np.asarray(tree.query_ball_point(L[a], params.search_m), dtype=np.int64) for a in anchors
    ]
    hyps = []
    for ia, a in enumerate(anchors):
        ca = cands[ia]
        if ca.size == 0:
            continue
        d = np.hypot(*(L[anchors] - L[a]).T)
        ok = np.nonzero((d >= params.min_sep_m) & (d <= params.max_sep_m))[0]
        for ib in ok[np.argsort(-d[ok], kind="stable")][: params.n_partners].tolist():
            cb = cands[ib]
            if cb.size == 0:
                continue
            b = anchors[ib]
            vl = L[b] - L[a]
            dl = math.hypot(*vl)
            dg = G[cb][None, :, :] - G[ca][:, None, :]
            ii, jj = np.nonzero(np.abs(np.hypot(dg[..., 0], dg[..., 1]) - dl) < 2.0 * tol)
            if ii.size == 0:
                continue
            vg = dg[ii, jj]
            th = np.arctan2(
                vl[0] * vg[:, 1] - vl[1] * vg[:, 0], vl[0] * vg[:, 0] + vl[1] * vg[:, 1]
            )
            c, s = np.cos(th), np.sin(th)
            ga = G[ca[ii]]
            tx = ga[:, 0] - (c * L[a, 0] - s * L[a, 1])
            ty = ga[:, 1] - (s * L[a, 0] + c * L[a, 1])
            hyps.append(np.column_stack((tx, ty, th)))
    at_identity = len(_one_to_one(tree, L, tol))
    if not hyps:
        return None
    H = np.vstack(hyps)
    # Pre-score on the anchors: (h, k) transformed anchor centres at once.
    A = L[anchors]
    c, s = np.cos(H[:, 2])[:, None], np.sin(H[:, 2])[:, None]
    PX = H[:, 0:1] + c * A[None, :, 0] - s * A[None, :, 1]
    PY = H[:, 1:2] + s * A[None, :, 0] + c * A[None, :, 1]
    d, _ = tree.query(np.column_stack((PX.ravel(), PY.ravel())), distance_upper_bound=tol)
    score = np.isfinite(d).reshape(PX.shape).sum(axis=1)
    # Distinct hypotheses: suppress those moving the anchors' centroid within 2·tol of
    # (and turning within 2·tol / spread of) a better one.
    cen = A.mean(axis=0)
    spread = max(float(np.max(np.hypot(*(A - cen).T))), 1.0)
    moved = np.column_stack(
        (
            H[:, 0] + np.cos(H[:, 2]) * cen[0] - np.sin(H[:, 2]) * cen[1],
            H[:, 1] + np.sin(H[:, 2]) * cen[0] + np.cos(H[:, 2]) * cen[1],
        )
    )
    order = np.lexsort((np.arange(H.shape[0]), -score))
    picked: list[int] = []
    for h in order.tolist():
        if len(picked) >= params.n_refine:
            break
        if all(_distinct(moved[h], H[h, 2], moved[p], H[p, 2], spread, tol) for p in picked):
            picked.append(h)
    refined = []
    for h in picked:
        T = H[h]
        for _ in range(3):
            pairs = _one_to_one(tree, transform_point(T, L), tol)
            if len(pairs) < 2:
                break
            li, gi = np.array(pairs).T
            T = rigid_alignment(L[li], G[gi])
        pairs = _one_to_one(tree, transform_point(T, L), tol)
        refined.append((len(pairs), T, pairs))
    refined.sort(key=lambda r: -r[0])
    best_n, best_T, best_pairs = refined[0]
    best_moved = transform_point(best_T, cen[None])[0]
    runner = 0
    for n_in, T, _ in refined[1:]:
        m = transform_point(T, cen[None])[0]
        if _distinct(m, T[2], best_moved, best_T[2], spread, tol):
            runner = max(runner, n_in)
    li = np.array([p[0] for p in best_pairs], dtype=np.int64)
    shift = float(np.max(np.hypot(*(transform_point(best_T, L[li]) - L[li]).T))) if li.size else 0.0
    return Registration(
        T=best_T,
        pairs=best_pairs,
        inliers=best_n,
        runner_up=runner,
        at_identity=at_identity,
        max_shift_m=shift,
    )


def accepted(reg: Registration | None, params: LoopClosureParams) -> bool:
    """Whether ``reg`` is a loop closure the filtered relative pose missed."""
    if reg is None or reg.inliers < params.min_inliers:
        return False
    if reg.max_shift_m <= params.inlier_m:
        return False
    if reg.inliers < params.ambiguity_ratio * reg.runner_up:
        return False
    gain = reg.inliers - reg.at_identity
    return gain >= params.min_gain and reg.inliers >= 1.25 * reg.at_identity
