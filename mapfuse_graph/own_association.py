"""The ``own`` association of the graph builder (:class:`OwnAssociation`).

χ²-gated nearest neighbour against the solver's current estimate, made while the graph
grows (it needs an incremental solver), with the gates and the one-to-one rules of
:mod:`mapfuse_core.matching` that the EKF uses; CCDA every ``ccda_every`` steps until
it accepts a match, then χ²-gated pairing of the remaining landmarks with known
features.  :class:`~mapfuse_graph.builder.GraphBuilder` inherits these methods.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, compose_jacobians
from mapfuse_core.matching import (
    ScoredPair,
    nearest_neighbour,
    pregate,
)
from mapfuse_core.matching.ccda import ccda_match
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_graph.estimate import Estimate, StepGraph, _Landmark, _WithStep
from mapfuse_graph.factors import (
    circle_observation_error,
    circle_tie_error,
    line_observation_error,
    line_tie_error,
    line_to_rho_alpha,
    residual_noise_cov,
    rho_alpha_along,
)
from mapfuse_graph.keys import landmark_key
from mapfuse_graph.options import GraphOptions
from mapfuse_graph.validation import _known_prior

__all__ = ["OwnAssociation"]


class OwnAssociation:
    """The ``own`` association steps of :class:`~mapfuse_graph.builder.GraphBuilder`
    (a mixin: the builder owns the state declared here)."""

    log: MeasurementLog
    options: GraphOptions
    known: KnownMapArrays
    landmarks: list[_Landmark]
    obs_landmark: np.ndarray
    anchor_init: FloatArray | None
    anchor_step: int
    anchor_source: str
    _gate: dict[int, float]
    ccda_reasons: dict[str, int]

    def landmark_map(
        self, est: Estimate, which: Sequence[int], covs: bool = True
    ) -> KnownMapArrays:
        raise NotImplementedError  # the builder's

    def _anchor_ok(self, x: FloatArray, P: FloatArray) -> bool:
        raise NotImplementedError  # the builder's

    def _try_ccda(self, k: int, est: Estimate, out: StepGraph) -> None:
        est_now = _WithStep(est, k, out.values)
        feats = [
            i
            for i, lmk in enumerate(self.landmarks)
            if lmk.n_obs >= self.options.data_association.min_obs_for_matching
        ]
        if len(feats) < 2:
            return
        map_a = self.landmark_map(est_now, feats)
        res = ccda_match(map_a, self.known, self.options.data_association.ccda)
        refused = res.accepted and not self._anchor_ok(res.x_A_B, res.cov)
        reason = "anchor refused" if refused else res.reason
        self.ccda_reasons[reason] = self.ccda_reasons.get(reason, 0) + 1
        if not res.accepted or refused:
            return
        for ia, jb in res.pairings:
            self.landmarks[feats[ia]].known = int(jb)
        self.anchor_init = np.asarray(res.x_A_B, dtype=float).copy()
        self.anchor_step = k
        self.anchor_source = "ccda"

    def _pair_own(self, k: int, est: Estimate) -> None:
        """``own``: χ²-pair unpaired, well-observed landmarks with unpaired known features.

        Known features are carried into ``Wglobal`` by the current anchor and pre-gated
        like observations (a known wall without extents by its reference point, within
        ``known_gap_m`` of the landmark's segment); the χ² test uses the landmark's
        (cached) marginal and the known feature's covariance (the anchor's own
        uncertainty is left out: it is far smaller than the known map's σ once the match
        is made).  Pairs are then taken by nearest neighbour, one-to-one both ways: a
        graph ties a known feature to one landmark.
        """
        cfg = self.options.data_association
        A = est.anchor()
        taken = {lmk.known for lmk in self.landmarks if lmk.known >= 0}
        free = [r for r in range(len(self.known)) if r not in taken]
        if not free:
            return
        by_landmark: dict[int, list[ScoredPair]] = {}
        for kind in (FeatureKind.LINE, FeatureKind.CIRCLE):
            rows = [r for r in free if int(self.known.kinds[r]) == int(kind)]
            idx = [
                i
                for i, lmk in enumerate(self.landmarks)
                if lmk.kind == kind
                and lmk.known < 0
                and lmk.created
                and lmk.n_obs >= cfg.min_obs_for_matching
            ]
            if not rows or not idx:
                continue
            dim = 2 if kind == FeatureKind.LINE else 3
            vals = np.array([est.vector(landmark_key(i, kind)) for i in idx]).reshape(-1, dim)
            feats = _as_spmap(kind, vals)
            for r in rows:
                kw = transform_feature(kind, A, self.known.params[r])[0]
                ext = None if self.known.extents is None else self.known.extents[r]
                if ext is not None and np.all(np.isfinite(ext)):
                    near = self._pregate(kind, kw, (float(ext[0]), float(ext[1])), idx, feats)
                else:
                    # No extents: the wall's reference point must lie near the segment.
                    near = self._pregate(kind, kw, (0.0, 0.0), idx, feats, cfg.known_gap_m)
                if not near:
                    continue
                kv, kP = _known_prior(kind, self.known.params[r], self.known.covs[r])
                for n in near:
                    i = idx[n]
                    P = self._landmark_cov(i, k, est)
                    if P is None:
                        continue
                    d2 = _tie_d2(kind, A, vals[n], P, kv, kP, self.known.params[r])
                    if d2 <= self._gate[dim]:
                        by_landmark.setdefault(i, []).append(ScoredPair(r, d2))
        order = sorted(by_landmark)
        chosen = nearest_neighbour([by_landmark[i] for i in order], lambda c: True)
        for i, c in zip(order, chosen, strict=True):
            if c is not None:
                self.landmarks[i].known = c.target

    def _pregate(
        self,
        kind: FeatureKind,
        fw: FloatArray,
        extent: tuple[float, float],
        idx: list[int],
        feats: FloatArray,
        max_gap: float | None = None,
    ) -> list[int]:
        """Positions in ``idx`` of the landmarks (``feats``: their SPmap form) that pass
        the pre-gate with feature ``fw`` (in ``Wglobal``, seen on ``extent``)."""
        return pregate(
            kind,
            fw,
            extent,
            feats,
            lambda n: self.landmarks[idx[n]].extent,
            self.options.data_association,
            max_gap,
        )

    def _landmark_cov(self, i: int, k: int, est: Estimate) -> FloatArray | None:
        """Landmark ``i``'s marginal, cached for ``cov_refresh_steps`` (iSAM2 marginals are
        costly; a stale one is larger, which only widens gates)."""
        lmk = self.landmarks[i]
        if lmk.cov is None or k - lmk.cov_step >= self.options.cov_refresh_steps:
            P = est.cov(landmark_key(i, lmk.kind))
            if P is not None:
                lmk.cov, lmk.cov_step = P, k
        return lmk.cov

    def _associate_own(self, k: int, x: FloatArray, est: Estimate) -> None:
        """χ²-gated nearest neighbour of step ``k``'s observations
        (:func:`mapfuse_core.matching.nearest_neighbour`) under the one-to-one rules of
        ``data_association``: by default a circle landmark takes one observation of the
        scan, a line landmark every segment of its wall.

        The innovation covariance is the observation noise plus the predicted pose's
        and the landmark's marginal covariances propagated through the residual
        (their correlation is ignored, which widens the gate).  Landmark marginals
        are refreshed at most every ``cov_refresh_steps`` steps: asking iSAM2 for them
        costs more than the whole update.
        """
        log = self.log
        cfg = self.options.data_association
        sl = log.feature_slice(k)
        Px = est.pose_cov(k - 1) if k > 0 else np.zeros((3, 3))
        if Px is not None and k > 0:
            _, J1, J2 = compose_jacobians(est.pose(k - 1), log.odometry[k])
            Px = J1 @ Px @ J1.T + J2 @ log.odometry_cov[k] @ J2.T
        # Current landmark estimates, fetched once per step for a vectorised pre-gate.
        by_kind: dict[FeatureKind, tuple[list[int], FloatArray, FloatArray]] = {}
        for kind in (FeatureKind.LINE, FeatureKind.CIRCLE):
            idx = [i for i, lmk in enumerate(self.landmarks) if lmk.kind == kind]
            dim = 2 if kind == FeatureKind.LINE else 3
            vals = np.array([est.vector(landmark_key(i, kind)) for i in idx]).reshape(-1, dim)
            by_kind[kind] = (idx, vals, _as_spmap(kind, vals))
        cands: list[list[ScoredPair]] = []
        for j in range(sl.start, sl.stop):
            kind = FeatureKind(int(log.feat_kind[j]))
            z = log.feat_params[j]
            zw = transform_feature(kind, x, z)[0]
            idx, vals, feats = by_kind[kind]
            ext = log.feat_extent[j]
            mine = []
            for n in self._pregate(kind, zw, (float(ext[0]), float(ext[1])), idx, feats):
                i = idx[n]
                d2 = self._obs_d2(k, kind, z, x, Px, i, vals[n], log.gate_covs[j], est)
                if d2 <= self._gate[2 if kind == FeatureKind.LINE else 3]:
                    mine.append(ScoredPair(i, d2))
            cands.append(mine)
        chosen = nearest_neighbour(
            cands, lambda c: cfg.one_observation_per(self.landmarks[c.target].kind)
        )
        for j, c in zip(range(sl.start, sl.stop), chosen, strict=True):
            kind = FeatureKind(int(log.feat_kind[j]))
            if c is None:
                # step() creates its variable; it is recorded now so that no other
                # observation of this scan can be matched to it.
                i = len(self.landmarks)
                self.landmarks.append(_Landmark(kind, k, j))
            else:
                i = c.target
            self.obs_landmark[j] = i
            if kind == FeatureKind.LINE:
                zw = transform_feature(kind, x, log.feat_params[j])[0]
                lmk = self.landmarks[i]
                v = est.vector(landmark_key(i, kind)) if lmk.created else line_to_rho_alpha(zw)[0]
                a, b = self._segment_on(v, zw, j)
                lo, hi = lmk.extent
                lmk.extent = (a, b) if not math.isfinite(lo) else (min(lo, a), max(hi, b))

    def _segment_on(self, v: FloatArray, zw: FloatArray, j: int) -> tuple[float, float]:
        """Along-line interval, on landmark line ``v``, of observation ``j`` (world ``zw``)."""
        ext = self.log.feat_extent[j]
        t0 = rho_alpha_along(v, zw)
        if not np.all(np.isfinite(ext)):
            return t0, t0
        # The observation's x axis may point either way along the landmark line.
        sign = math.cos(zw[2] - (v[1] + math.pi / 2.0))
        e = sorted((t0 + sign * float(ext[0]), t0 + sign * float(ext[1])))
        return e[0], e[1]

    def _obs_d2(
        self,
        k: int,
        kind: FeatureKind,
        z: FloatArray,
        x: FloatArray,
        Px: FloatArray | None,
        i: int,
        v: FloatArray,
        zcov: FloatArray,
        est: Estimate,
    ) -> float:
        if kind == FeatureKind.LINE:
            r, Jx, Jl = line_observation_error(z, x, v)
        else:
            r, Jx, Jl = circle_observation_error(z, x, v)
        S = residual_noise_cov(kind, z, zcov)
        if Px is not None:
            S = S + Jx @ Px @ Jx.T
        P = self._landmark_cov(i, k, est)
        if P is not None:
            S = S + Jl @ P @ Jl.T
        try:
            return float(r @ np.linalg.solve(S, r))
        except np.linalg.LinAlgError:
            return math.inf


def _as_spmap(kind: FeatureKind, vals: FloatArray) -> FloatArray:
    """(n, 3) SPmap features of landmark variables ``vals``: circles unchanged, a line
    ``(ρ, α)`` as the foot of its normal and the direction ``α + π/2``, the frame in
    which :func:`~mapfuse_graph.factors.rho_alpha_along` (and a landmark's extent)
    measures along the line."""
    if kind == FeatureKind.CIRCLE:
        return np.asarray(vals, dtype=float).reshape(-1, 3)
    rho, alpha = vals[:, 0], vals[:, 1]
    return np.column_stack([rho * np.cos(alpha), rho * np.sin(alpha), alpha + math.pi / 2.0])


def _tie_d2(
    kind: FeatureKind,
    A: FloatArray,
    v: FloatArray,
    P: FloatArray,
    kv: FloatArray,
    kP: FloatArray,
    kparams: FloatArray,
) -> float:
    if kind == FeatureKind.LINE:
        t = rho_alpha_along(kv, kparams)
        r, _, JL, JK = line_tie_error(A, v, kv, t)
    else:
        r, _, JL, JK = circle_tie_error(A, v, kv)
    S = JL @ P @ JL.T + JK @ kP @ JK.T
    try:
        return float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return math.inf
