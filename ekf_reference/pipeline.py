"""The paper's Algorithm 1 over a measurement log: local maps, joins, CCDA, fusion."""

from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ekf_reference.anchor_watch import AnchorWatch, GateState, Verdict
from ekf_reference.anchoring import (
    JOINTLY_INCONSISTENT,
    PAIRING_INCONSISTENT,
    insert_ccda_estimate,
    match_arrays,
    match_arrays_in_global,
    vet_match,
)
from ekf_reference.association import (
    Candidate,
    IteratedUpdate,
    Query,
    apply,
    choose,
    evaluate,
    individual_candidates,
    predict_all_targets,
    segment_end_sd,
)
from ekf_reference.config import EKFConfig
from ekf_reference.final_map import final_map
from ekf_reference.increment import Increment, update_through_increment
from ekf_reference.known_frame import centred_known_map, uncentred
from ekf_reference.known_gating import KnownGate, Targets
from ekf_reference.loops import LoopClosureParams, accepted, register_circles
from ekf_reference.maps import (
    CIContext,
    _wrap_diff,
    bind_line_cov,
    compose_into,
    copied_local_map,
    extend_line,
    new_global_map,
    new_local_map,
    predict,
    shared_in_global_frame,
    tie_anchor_copy,
    vehicle_in_global,
)
from ekf_reference.result import EKFDetails, InnovationTotals, LoopClosure, UndoneAnchor
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from ekf_reference.tentative import Tentatives
from ekf_reference.threads import single_threaded_blas
from ekf_reference.tracks import Tracks
from mapfuse_core.estimate import (
    Anchor,
    AnchorDecision,
    AssociationDecisions,
    EstimatorResult,
    MatchAttempts,
    PoseTrack,
)
from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.geometry.se2 import (
    FloatArray,
    compose,
    compose_jacobians,
    inverse_jacobian,
    wrap_angle,
)
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.matching.ccda import CCDAResult, ccda_match
from mapfuse_core.measlog import MeasurementLog

__all__ = [
    "ANCHOR_CONTRADICTED",
    "JOINTLY_INCONSISTENT",
    "PAIRING_INCONSISTENT",
    "UNDONE_BEFORE",
    "run_ekf",
]

ANCHOR_CONTRADICTED = "anchor contradicted"
"""Outcome of a CCDA call whose match was fused and later undone by the anchor watch
(:mod:`ekf_reference.anchor_watch`); the call is counted here instead of
``"accepted"``."""
UNDONE_BEFORE = "compatible with an undone anchor"
"""Refusal reason of a match whose anchor is compatible (χ²₃ at ``gate_prob``, the
two covariances summed) with one the anchor watch has undone."""

_STATE = (
    "tracks",
    "obs_track",
    "obs_known",
    "global_map",
    "local",
    "ctx",
    "tentative",
    "anchor_step",
    "anchor_pairings",
    "known_tracks",
    "loop_closures",
    "gate",
    "innovation_chi2",
    "innovation_dof",
    "ambiguous_skipped",
    "step",
)
"""Attributes of :class:`_Run` that filtering changes: what a snapshot keeps.  The
matching counters (attempts, reasons, refusals, undone anchors) are not among them: a
call made before an anchor is undone was made."""


def _beam_spacing(log: MeasurementLog) -> float:
    """Median spacing of the log's beams (rad); ``inf`` when it keeps no raw scans."""
    b = log.scan_bearings
    if b is None or len(b) < 2:
        return math.inf
    return float(np.median(np.abs(np.diff(np.asarray(b, dtype=float)))))


class _Run:
    def __init__(self, log: MeasurementLog, config: EKFConfig, fusion: bool = True) -> None:
        self.log = log
        self.config = config
        self.fusion = bool(fusion)
        self.tracks = Tracks()
        self.obs_track = np.full(log.n_features, -1, dtype=np.int64)
        self.obs_known = np.full(log.n_features, -1, dtype=np.int64)
        self.global_map = new_global_map()
        self.known, self.known_centre = centred_known_map(log.known_map)
        self.known_tracks: dict[int, int] = {}
        """Track of each known feature (index into :attr:`known`), from the match on."""
        self.local_start = 0
        """First step of the current local map."""
        self.local_odometry_var = 0.0
        """Sum of the heading variances of the odometry increments the current local
        map has predicted (rad²)."""
        self.increment: Increment | None = None
        """The step's increment and the map before it, for an iterated update."""
        self.increment_unconverged = 0
        """Iterated updates through an increment that did not converge."""
        self.ambiguous_skipped = 0
        """Measurements the ``"skip"`` ambiguity rule left out."""
        self._begin_local_map([], 0)
        self.joins = 0
        """Local maps joined so far (:attr:`EKFDetails.joins`)."""
        self.ccda_attempts = 0
        self.ccda_reasons: dict[str, int] = {}
        self.ccda_refused: list[tuple[int, float, int]] = []
        self.ccda_excluded: list[tuple[int, int]] = []
        self.tentative = Tentatives(config.tentative_min_sightings, config.tentative_window_steps)
        self.anchor_step = -1
        self.anchor_pairings: list[tuple[int, int]] = []
        self.loop_closures: list[LoopClosure] = []
        self.innovation_chi2 = 0.0
        self.beam_spacing = _beam_spacing(log)
        """Spacing of the laser's beams (rad): sets how precisely a segment's ends are
        known (:func:`~ekf_reference.association.segment_end_sd`)."""
        self.innovation_dof = 0
        self.gate: KnownGate | None = None
        if self.fusion and config.known_map_gating:
            self.gate = KnownGate(config.known_gating, config.data_association)
        self.step = 0
        self.watch: AnchorWatch | None = None
        """The anchor watch, from the fusion of a match (with ``config.anchor_watch``)."""
        self.before_fusion: dict[str, object] | None = None
        """Snapshot of the state just before the watched anchor was fused."""
        self.fused_anchor: tuple[FloatArray, FloatArray] | None = None
        """``x^Wknown'_Wglobal`` (centred known frame) and covariance of the watched
        anchor when fused."""
        self.undone: list[UndoneAnchor] = []
        self.undone_poses: list[tuple[FloatArray, FloatArray]] = []
        """The undone anchors' :attr:`fused_anchor`: matches compatible with one are
        refused."""

    # ------------------------------------------------------------------ per step

    def observe(self, k: int) -> None:
        log, loc = self.log, self.local
        sl = log.feature_slice(k)
        if sl.stop == sl.start:
            return
        queries = []
        for j in range(sl.start, sl.stop):
            kind = ElementKind.of_feature(int(log.feat_kind[j]))
            ext = (float(log.feat_extent[j, 0]), float(log.feat_extent[j, 1]))
            end_sd = 0.0
            if kind == ElementKind.LINE:
                end_sd = segment_end_sd(log.feat_params[j], ext, self.beam_spacing)
            queries.append(
                Query(
                    kind=kind,
                    params=log.feat_params[j],
                    cov=log.feat_cov[j],
                    gate_cov=None if log.feat_gate_cov is None else log.feat_gate_cov[j],
                    extent=ext,
                    end_sd=end_sd,
                )
            )
        self.step = k
        # With copied known maps (the paper) observations update the local features
        # only; the known map enters through its ties with them (constrain_to_known).
        targets = self._gated(
            loc, predict_all_targets(loc, lambda e: e.moving, known=not self._copied())
        )
        skipped: list[int] = []
        chosen = choose(loc, queries, targets, self.config.data_association, skipped)
        self.ambiguous_skipped += len(skipped)
        self._record(k, loc, queries, chosen, targets)
        for q, c, j in zip(queries, chosen, range(sl.start, sl.stop), strict=True):
            if c is None:
                continue
            e = loc.elements[c.target]
            self.obs_track[j] = e.track
            e.n_obs += 1
            if e.role == Role.FEATURE and q.kind == ElementKind.LINE:
                extend_line(e, loc.mean[c.target], q.params, q.extent, q.end_sd)
        # No re-binding: an update only shrinks P, so a zero along-line variance stays 0.
        self._update_step(loc, [(q, c) for q, c in zip(queries, chosen, strict=True) if c])
        born: list[int] = []
        left_out = set(skipped)
        for i, (q, c, j) in enumerate(zip(queries, chosen, range(sl.start, sl.stop), strict=True)):
            if c is not None or i in left_out:
                continue
            # A wall first seen as two segments (a tree in front of it) would otherwise
            # become two landmarks at once, which later observations then split between
            # them by best fit: fold the second segment into the first.
            twin = self._same_step_twin(loc, q, born)
            if twin is not None:
                e = loc.elements[twin.target]
                self.obs_track[j] = e.track
                e.n_obs += 1
                extend_line(e, loc.mean[twin.target], q.params, q.extent, q.end_sd)
                self._apply_measurements(loc, [twin])
                continue
            t = self.tracks.new()
            self.obs_track[j] = t
            cov = bind_line_cov(q.params, q.cov) if q.kind == ElementKind.LINE else q.cov
            born.append(
                loc.add(
                    Element(
                        q.kind,
                        Role.FEATURE,
                        moving=True,
                        track=t,
                        extent=q.extent,
                        extent_sd=q.end_sd,
                        true_id=int(log.feat_true_id[j]),
                        n_obs=1,
                        in_local=True,
                    ),
                    q.params,
                    cov,
                )
            )
        self.tentative.review(k, loc, born, self.obs_track, self.obs_track[sl.start : sl.stop])
        if loc.has(Role.ANCHOR):
            # Only features touched at this step can have become pairable with a known
            # feature; the others were tested when last seen (saves ~80 % of the tests).
            # Tentative features are not, until promoted.
            seen = {int(t) for t in self.obs_track[sl.start : sl.stop]} - self.tentative.pending
            # Carried features are shared with the global map and stay until the join.
            self.constrain_to_known(loc, lambda e: e.in_local and e.track in seen)

    def _record(
        self,
        step: int,
        state: GaussianMap,
        queries: list[Query],
        chosen: list[Candidate | None],
        targets: Targets,
    ) -> None:
        """Hand one association's outcome to the known-map gate and the anchor watch."""
        if self.gate is not None:
            self.gate.record(step, state, queries, chosen, targets)
        if self.watch is not None:
            self.watch.record(step, state, chosen)

    def _update_step(self, loc: GaussianMap, pairs: list[tuple[Query, Candidate]]) -> None:
        """Update the local map with the step's measurement pairings: linearised at the
        predicted map, or through the step's increment
        (:func:`~ekf_reference.increment.update_through_increment`)."""
        inc, self.increment = self.increment, None
        if inc is None or not pairs:
            self._apply_measurements(loc, [c for _, c in pairs])
            return
        upd = update_through_increment(
            loc,
            inc,
            lambda state: [evaluate(state, q, c.target) for q, c in pairs],
            [c for _, c in pairs],
        )
        self.increment_unconverged += not upd.converged
        self.innovation_chi2 += upd.nis
        self.innovation_dof += upd.dims

    def _apply_measurements(self, loc: GaussianMap, chosen: list[Candidate]) -> None:
        """Update with measurement pairings and add their innovations to the run's."""
        self.innovation_chi2 += apply(loc, chosen)
        self.innovation_dof += sum(c.residual.size for c in chosen)

    def _gated(self, state: GaussianMap, targets: Targets) -> Targets:
        """``targets`` without the known features the gate has un-fused."""
        return targets if self.gate is None else self.gate.filter(state, targets)

    def _same_step_twin(self, loc: GaussianMap, q: Query, born: list[int]) -> Candidate | None:
        """Best individually compatible line among those created at this step.

        Circles are left alone: one scan sees a circle once, so two compatible circle
        measurements are two trees.
        """
        same = [i for i in born if loc.elements[i].kind == ElementKind.LINE]
        if q.kind != ElementKind.LINE or not same:
            return None
        cands = individual_candidates(loc, q, same, loc.mean[same], self.config.data_association)
        return cands[0] if cands else None

    def _copied(self) -> bool:
        """Whether every local map holds its own copy of the known map (the paper's)."""
        return self.config.known_map_in_local_maps == "copied"

    def _tie_query(self, state: GaussianMap, i: int) -> Query:
        """Map feature ``i`` as the query of a hard tie (``line_tie_residual_at``)."""
        e = state.elements[i]
        return Query(
            e.kind,
            state.mean[i],
            np.zeros((3, 3)),
            e.extent,
            element=i,
            residual_at=self.config.line_tie_residual_at,
            end_sd=e.extent_sd,
        )

    def _begin_local_map(self, carry: list[int], first_step: int) -> None:
        """Make :meth:`_start_local_map`'s map the current one, from ``first_step`` on."""
        self.local, self.ctx = self._start_local_map(carry)
        self.local_start = first_step
        self.local_odometry_var = 0.0
        self.increment = None

    def predict(self, k: int) -> None:
        """Move the local map by step ``k``'s odometry increment (kept for the update
        with ``odometry_linearisation="iterated"``)."""
        u, Q = self.log.odometry[k], self.log.odometry_cov[k]
        sl = self.log.feature_slice(k)
        # A step without observations has no update: the prediction is all it does.
        self.increment = None
        if self.config.odometry_linearisation == "iterated" and sl.stop > sl.start:
            self.increment = Increment(self.local.copy(), np.asarray(u, dtype=float), Q)
        predict(self.local, u, Q)
        self.local_odometry_var += float(Q[2, 2])

    def _start_local_map(self, carry: list[int]) -> tuple[GaussianMap, CIContext | None]:
        """The next local map: with the known map shared (and the ``carry`` features),
        or, matched with ``known_map_in_local_maps="copied"``, with its own copies."""
        if self._copied() and self.global_map.has(Role.ANCHOR):
            return copied_local_map(self.global_map, self.known, self.known_tracks), None
        return new_local_map(self.global_map, carry)

    def constrain_to_known(self, state: GaussianMap, which: Callable[[Element], bool]) -> None:
        """Tie map features to known features (hard constraints, the paper's eq. 20).

        A tied feature is absorbed (removed: the known feature stands for it) when the
        known map is shared, and kept when the local map holds a copy of it (which the
        join drops, eq. 14), so that it carries the tie into the global map; it is then
        not tied again."""
        copied = self._copied()
        queries = [
            self._tie_query(state, i)
            for i, e in enumerate(state.elements)
            if e.role == Role.FEATURE
            and which(e)
            and not (copied and self.tracks.root(e.track) in self.tracks.known)
        ]
        if not queries:
            return
        targets = self._gated(state, predict_all_targets(state, lambda e: False))
        chosen = choose(state, queries, targets, self.config.data_association)
        self._record(self.step, state, queries, chosen, targets)
        pairs = [(q, c) for q, c in zip(queries, chosen, strict=True) if c is not None]
        if not pairs:
            return
        apply(state, [c for _, c in pairs])
        for q, c in pairs:
            self.tracks.merge(state.elements[q.element].track, state.elements[c.target].track)
        if not copied:
            state.remove([q.element for q, _ in pairs])

    # ------------------------------------------------------------------ join

    def drop_rare_local_features(self) -> None:
        """Marginalise out local features seen fewer than ``min_obs_to_join`` times."""
        loc = self.local
        drop = [
            i
            for i, e in enumerate(loc.elements)
            if e.role == Role.FEATURE and e.in_local and e.n_obs < self.config.min_obs_to_join
        ]
        if not drop:
            return
        tracks = np.array([loc.elements[i].track for i in drop], dtype=np.int64)
        self.obs_track[np.isin(self.obs_track, tracks)] = -1
        loc.remove(drop)

    def join(self, k: int) -> None:
        last = k == self.log.n_steps - 1
        joined = self.tentative.flush(k, self.local, self.obs_track, last)
        if self.config.min_obs_to_join > 1:
            self.drop_rare_local_features()
        g, loc, ctx = self.global_map, self.local, self.ctx
        sv = self.config.join_circle_sigma_m
        if sv > 0.0:
            for i, e in enumerate(loc.elements):
                if e.role == Role.FEATURE and e.kind == ElementKind.CIRCLE:
                    loc.cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += sv * sv * np.eye(3)
        joint = self._stack(g, loc, ctx)
        n_g = len(g) if ctx is None else len(g) - len(ctx.shared_global)
        lb = n_g + loc.find(Role.BASE)
        frame_elems = [i for i in range(n_g) if joint.elements[i].role != Role.KNOWN]
        if ctx is not None:
            # x^Wlocal_Wknown and carried x^Wlocal_F after the CI correction.
            frame_elems += [n_g + ctx.shared_local[r] for r in ctx.moving]
        compose_into(joint, lb, frame_elems)
        joint.remove([lb])
        for e in joint.elements:
            e.moving = False
        joint.bind_lines()
        copies = ctx is None and loc.has(Role.ANCHOR)
        if copies:
            # The paper's global map holds no known feature (eq. 14): the local map's
            # copies go; the local features tied to them carry what they taught.
            joint.remove(joint.indices(Role.KNOWN))
        # Pair the local map's features with the global ones (and the known ones).
        pairs = self._pair_at_join(joint, k)
        for q, c in pairs:
            f, t = joint.elements[q.element], joint.elements[c.target]
            self.tracks.merge(f.track, t.track)
            t.n_obs += f.n_obs
            if t.role == Role.FEATURE and t.kind == ElementKind.LINE:
                extend_line(t, joint.mean[c.target], joint.mean[q.element], f.extent, f.extent_sd)
        joint.remove([q.element for q, _ in pairs])
        for e in joint.elements:
            e.in_local = False
        if copies:
            tie_anchor_copy(joint)
        joint.bind_lines()
        self.tentative.settle(joint, self.obs_track, self.tracks.root, joined)
        self.global_map = joint
        if self.fusion and not joint.has(Role.ANCHOR):
            self.try_ccda(k)
        self._begin_local_map(self._carried(k), k + 1)
        self.joins += 1

    def _carried(self, k: int) -> list[int]:
        """Global features the next local map holds from its start: those seen in steps
        ``k − carry_seen_steps + 1 … k`` (none by default, as in the paper)."""
        m = self.config.carry_seen_steps
        if m == 0:
            return []
        obs = self.obs_track[
            self.log.feature_slice(max(0, k - m + 1)).start : self.log.feature_slice(k).stop
        ]
        seen = {self.tracks.root(int(t)) for t in obs if t >= 0}
        return [
            i
            for i, e in enumerate(self.global_map.elements)
            if e.role == Role.FEATURE and self.tracks.root(e.track) in seen
        ]

    def _pair_at_join(self, joint: GaussianMap, k: int) -> list[tuple[Query, Candidate]]:
        """Pair the local features of ``joint`` with global (and known) ones and apply them.

        With ``loop_closure`` set, the local map is first registered to the global one
        (:meth:`_close_loop`); the features it pairs are left out of the usual association.
        """
        pairs: list[tuple[Query, Candidate]] = []
        if self.config.loop_closure is not None:
            pairs = self._close_loop(joint, self.config.loop_closure, k)
        paired = {q.element for q, _ in pairs}
        used = {c.target for _, c in pairs}
        queries = [
            self._tie_query(joint, i)
            for i, e in enumerate(joint.elements)
            if e.role == Role.FEATURE and e.in_local and i not in paired
        ]
        targets = self._gated(joint, predict_all_targets(joint, lambda e: not e.in_local))
        if used:
            for kind, (idx, preds) in list(targets.items()):
                keep = [r for r, t in enumerate(idx) if t not in used]
                targets[kind] = ([idx[r] for r in keep], preds[keep])
        chosen = choose(joint, queries, targets, self.config.data_association)
        self._record(k, joint, queries, chosen, targets)
        new = [(q, c) for q, c in zip(queries, chosen, strict=True) if c is not None]
        apply(joint, [c for _, c in new])
        return pairs + new

    def _close_loop(
        self, joint: GaussianMap, params: LoopClosureParams, k: int
    ) -> list[tuple[Query, Candidate]]:
        """Register the local circles to the global ones; on a loop closure the filter
        missed, widen the maps' relative pose and apply the registered pairings that
        pass their (widened) individual gates.  See :mod:`ekf_reference.loops`."""
        if joint.has(Role.ANCHOR):
            # Fused: every local map is held to the known map, as the global map is.
            return []
        kinds, roles = joint.kinds_roles()
        circ = (kinds == int(ElementKind.CIRCLE)) & (roles == int(Role.FEATURE))
        in_local = np.array([e.in_local for e in joint.elements], dtype=bool)
        loc = np.nonzero(circ & in_local)[0]
        glo = np.nonzero(circ & ~in_local)[0]
        if loc.size < params.min_inliers or glo.size < params.min_inliers:
            return []
        n_obs = np.array([joint.elements[i].n_obs for i in loc.tolist()])
        reg = register_circles(joint.mean[loc, :2], joint.mean[glo, :2], n_obs, params)
        if reg is None or not accepted(reg, params):
            return []
        li = loc[[p[0] for p in reg.pairs]]
        gi = glo[[p[1] for p in reg.pairs]]
        # Correction the registration asks of the global elements (frame R), about the
        # centroid of its global inliers: rotation −θ, then the centroids' difference.
        c = joint.mean[gi, :2].mean(axis=0)
        delta = np.array([*(joint.mean[li, :2].mean(axis=0) - c), -reg.T[2]])
        sig = params.inflation * np.abs(delta)
        sig = np.hypot(sig, [params.floor_m, params.floor_m, params.floor_rad])
        frame = [
            i
            for i, e in enumerate(joint.elements)
            if e.role == Role.BASE or (e.role == Role.FEATURE and not e.in_local)
        ]
        J = np.zeros((3 * len(joint), 3))
        for i in frame:
            J[3 * i : 3 * i + 2, 0:2] = np.eye(2)
            J[3 * i, 2] = -(joint.mean[i, 1] - c[1])
            J[3 * i + 1, 2] = joint.mean[i, 0] - c[0]
            if joint.elements[i].kind != ElementKind.CIRCLE:
                J[3 * i + 2, 2] = 1.0
        joint.cov += (J * sig**2) @ J.T
        joint.symmetrise()
        gate = chi2_gate(self.config.data_association.gate_prob, 3)
        pairs = []
        for i, g in zip(li.tolist(), gi.tolist(), strict=True):
            q = self._tie_query(joint, i)
            cand = evaluate(joint, q, g)
            if cand.d2 <= gate:
                pairs.append((q, cand))
        delta.setflags(write=False)
        self.loop_closures.append(
            LoopClosure(
                step=k,
                inliers=reg.inliers,
                inliers_at_identity=reg.at_identity,
                runner_up=reg.runner_up,
                pairings=len(pairs),
                correction=delta,
            )
        )
        apply(joint, [c_ for _, c_ in pairs])
        return pairs

    def _stack(self, g: GaussianMap, loc: GaussianMap, ctx: CIContext | None) -> GaussianMap:
        """Joint Gaussian of the global-only elements and the local map.

        Without fusion the two are independent.  With fusion the shared elements come
        from the local map (the newest information) and the global-only elements are
        corrected through ``A = P_gs P_ss⁺`` (conditional independence given the shared).
        """
        joint = GaussianMap()
        if ctx is None:
            joint.mean = np.vstack([g.mean, loc.mean])
            n1, n2 = 3 * len(g), 3 * len(loc)
            joint.cov = np.zeros((n1 + n2, n1 + n2))
            joint.cov[:n1, :n1] = g.cov
            joint.cov[n1:, n1:] = loc.cov
            joint.elements = g.elements + loc.elements
            return joint
        # Local map with its moving shared elements expressed as the global map holds
        # them (x^Wlocal_Wknown, x^Wlocal_F).
        s_L, Js, idx_L = shared_in_global_frame(loc, ctx)
        T = np.eye(3 * len(loc))
        moved = [ctx.shared_local[r] for r in ctx.moving]
        loc_mean = loc.mean.copy()
        for r, i in zip(ctx.moving, moved, strict=True):
            rows = loc.dofs([i])
            T[rows] = 0.0
            T[np.ix_(rows, loc.dofs(idx_L))] = Js[3 * r : 3 * r + 3]
            loc_mean[i] = s_L[r]
        loc_cov = T @ loc.cov @ T.T
        g_only = [i for i in range(len(g)) if i not in set(ctx.shared_global)]
        gd = g.dofs(g_only)
        A = ctx.A[gd]
        sd_L = loc.dofs(ctx.shared_local)
        d = _wrap_diff(
            (s_L - ctx.mu_s).reshape(-1), [g.elements[i].kind for i in ctx.shared_global]
        )
        s_dofs_g = g.dofs(ctx.shared_global)
        mean_g = g.mean[g_only] + (A @ d).reshape(-1, 3)
        P_gg = (
            g.cov[np.ix_(gd, gd)]
            - A @ g.cov[np.ix_(s_dofs_g, gd)]
            + A @ loc_cov[np.ix_(sd_L, sd_L)] @ A.T
        )
        P_gl = A @ loc_cov[sd_L, :]
        joint.cov = np.block([[P_gg, P_gl], [P_gl.T, loc_cov]])
        joint.mean = np.vstack([mean_g, loc_mean])
        joint.elements = [g.elements[i] for i in g_only] + loc.elements
        for i in moved:
            joint.elements[len(g_only) + i].moving = False
        joint.symmetrise()
        joint.wrap()
        return joint

    # ------------------------------------------------------------------ CCDA

    def try_ccda(self, k: int) -> None:
        feats = [
            i
            for i, e in enumerate(self.global_map.elements)
            if e.role == Role.FEATURE
            and e.n_obs >= self.config.data_association.min_obs_for_matching
        ]
        known = self.known
        if not feats or len(known) == 0:
            return
        assoc = self.config.data_association
        estimate = self.config.anchor_entry == "ccda_estimate"
        tie_at = self.config.line_tie_residual_at
        for rerun in range(assoc.match_exclusions + 1):
            # The paper's CCDA estimates x^Wglobal_Wknown (eq. 12): the map in Wglobal.
            arrays = (match_arrays_in_global if estimate else match_arrays)(self.global_map, feats)
            res = ccda_match(arrays, known, assoc.ccda)
            self.ccda_attempts += 1
            if not res.accepted:
                self._count(res.reason)
                return
            # Fused on a copy first: a match a test refuses leaves the map untouched.
            rerun_left = rerun < assoc.match_exclusions
            v = None
            if not estimate or assoc.match_joint_test:
                v = vet_match(
                    self.global_map, feats, known, self._in_local(res), assoc, rerun_left, tie_at
                )
            if v is None or v.refusal is None:
                if estimate:
                    shared = None if self._copied() else known
                    trial, known_index = insert_ccda_estimate(self.global_map, res, shared)
                    upd = None
                else:
                    assert v is not None
                    trial, known_index, upd = v.trial, v.known_index, v.update
                if self._undone_before(trial, assoc):
                    self._count(UNDONE_BEFORE)
                    return
                self._fuse_match(k, feats, res, trial, known_index, upd)
                return
            self._count(v.refusal)
            self.ccda_refused.append((k, v.chi2, v.dof))
            if v.culprit is None or not rerun_left:
                return
            # Match again at once without the map feature of the failing pairing (a
            # feature moved since the survey): CCDA's own checks apply to what is left.
            ia, jb = res.pairings[v.culprit]
            self.ccda_excluded.append((k, int(known.ids[jb])))
            feats = feats[:ia] + feats[ia + 1 :]

    def _in_local(self, res: CCDAResult) -> CCDAResult:
        """``res`` with its transform in the frame the global map holds its features in,
        ``x^Wlocal_Wknown``: with ``anchor_entry="ccda_estimate"`` CCDA matched the map
        in ``Wglobal``, and its ``x^Wglobal_Wknown`` is composed with the base (eq. 13);
        otherwise ``res`` is that already."""
        if self.config.anchor_entry != "ccda_estimate":
            return res
        base = self.global_map.mean[self.global_map.find(Role.BASE)]
        return replace(res, x_A_B=compose(base, res.x_A_B))

    def _count(self, reason: str, n: int = 1) -> None:
        self.ccda_reasons[reason] = self.ccda_reasons.get(reason, 0) + n
        if self.ccda_reasons[reason] == 0:
            del self.ccda_reasons[reason]

    def _undone_before(self, trial: GaussianMap, assoc: AssociationConfig) -> bool:
        """Whether the anchor fused in ``trial`` is compatible with an undone one."""
        if not self.undone_poses:
            return False
        x, P = anchor_pose(trial)
        gate = chi2_gate(assoc.gate_prob, 3)
        for xu, Pu in self.undone_poses:
            d = x - xu
            d[2] = wrap_angle(d[2])
            try:
                d2 = float(d @ np.linalg.solve(P + Pu, d))
            except np.linalg.LinAlgError:
                d2 = 0.0  # no information to tell them apart: the same hypothesis
            if d2 <= gate:
                return True
        return False

    def _fuse_match(
        self,
        k: int,
        feats: list[int],
        res: CCDAResult,
        trial: GaussianMap,
        known_index: dict[int, int],
        upd: IteratedUpdate | None,
    ) -> None:
        """Make ``trial`` (the global map with the match fused, ``known_index`` its known
        features, ``upd`` the pairings' update if they were fused) the global map, and
        join the matched features' tracks to the known features'."""
        g, known = self.global_map, self.known
        self._count(res.reason)
        params = self.config.anchor_watch
        if params is not None:
            self.before_fusion = self._snapshot()
        if upd is not None and not upd.converged:
            warnings.warn(
                f"step {k}: the update with CCDA's {len(res.pairings)} pairings did not "
                f"converge in {upd.iterations} iterations; the anchor is its last iterate",
                RuntimeWarning,
                stacklevel=3,
            )
        self.known_tracks = {}
        for j in range(len(known)):
            track = self.tracks.new()
            self.tracks.mark_known(track, int(known.ids[j]))
            self.known_tracks[j] = track
            if j in known_index:
                trial.elements[known_index[j]].track = track
        g.mean, g.cov, g.elements = trial.mean, trial.cov, trial.elements
        seen = self.log.feature_slice(k).stop
        labels = landmark_labels(
            self.tracks.roots(self.obs_track[:seen]),
            self.log.feat_true_id[:seen],
            [self.tracks.root(g.elements[feats[ia]].track) for ia, _ in res.pairings],
        )
        pairings = []
        for (ia, jb), label in zip(res.pairings, labels, strict=True):
            e = g.elements[feats[ia]]
            pairings.append((label, int(known.ids[jb])))
            self.tracks.merge(e.track, self.known_tracks[jb])
        if self._copied():
            # The paper's global map holds no known feature (eq. 14): the matched
            # features keep what the ties taught them.
            g.remove(list(known_index.values()))
        elif self.config.anchor_entry == "pairings":
            # The known features stand for the matched features they are tied to.
            g.remove([feats[ia] for ia, _ in res.pairings])
        g.bind_lines()
        self.anchor_step = k
        self.anchor_pairings = pairings
        if self.gate is not None:
            self.gate.anchor_known = [kid for _, kid in pairings]
        if params is not None:
            self.watch = AnchorWatch(params)
            self.fused_anchor = anchor_pose(g)

    # ------------------------------------------------------------------ anchor watch

    def _snapshot(self) -> dict[str, object]:
        """A deep copy of the filtering state (:data:`_STATE`), aliasing kept."""
        return copy.deepcopy({name: getattr(self, name) for name in _STATE})

    def check_anchor(self, k: int) -> int | None:
        """At the end of step ``k``: when the watch finds the anchor contradicted, undo
        it and return the step whose join fused it (filtering resumes after it);
        else ``None``."""
        if self.watch is None:
            return None
        gate = None
        if self.gate is not None:
            gate = GateState(
                paired=frozenset(self.gate.accepted),
                unfused=frozenset(self.gate.unfused),
                match=frozenset(self.gate.anchor_known),
            )
        verdict = self.watch.verdict(k, gate)
        if verdict is None:
            return None
        return self._undo(k, verdict)

    def _undo(self, k: int, verdict: Verdict) -> int:
        """Go back to the state before the anchor's fusion, without it, and finish that
        join (a new local map); the call that made it is counted as contradicted."""
        assert self.before_fusion is not None
        assert self.fused_anchor is not None
        fused_at = self.anchor_step
        x, P = self.fused_anchor
        self.undone.append(
            UndoneAnchor(
                fused_at_step=fused_at,
                undone_at_step=k,
                test=verdict.test,
                statistic=verdict.statistic,
                threshold=verdict.threshold,
                dof=verdict.dof,
                x_Wknown_Wglobal=uncentred(x, self.known_centre),
                cov=P,
                pairings=tuple(self.anchor_pairings),
            )
        )
        self.undone_poses.append((x, P))
        self._count("accepted", -1)
        self._count(ANCHOR_CONTRADICTED)
        for name, value in self.before_fusion.items():
            setattr(self, name, value)
        self.before_fusion, self.fused_anchor, self.watch = None, None, None
        self._begin_local_map(self._carried(fused_at), fused_at + 1)
        return fused_at

    def local_map_full(self, k: int) -> bool:
        """Whether the local map is joined at the end of step ``k``: it holds
        ``local_map_steps`` steps, or its odometry has accumulated a heading σ above
        ``local_map_heading_sigma_rad``."""
        c = self.config
        if k + 1 - self.local_start >= c.local_map_steps:
            return True
        if c.local_map_heading_sigma_rad is None:
            return False
        return self.local_odometry_var > c.local_map_heading_sigma_rad**2


@single_threaded_blas
def run_ekf(
    log: MeasurementLog,
    config: EKFConfig | None = None,
    *,
    fusion: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> EstimatorResult:
    """Run the EKF reference over ``log``, fusing its known map when ``fusion`` (the
    paper's method; ``False`` is SLAM without map fusion).

    Returns the :class:`~mapfuse_core.estimate.EstimatorResult` every estimator returns
    (estimator ``"ekf"``: filtered poses, the final map, the anchor, the association
    decisions and the map matchings), with :class:`~ekf_reference.result.EKFDetails` as
    its ``details``.  BLAS runs on one thread during the run
    (:mod:`ekf_reference.threads`).
    """
    config = config or EKFConfig()
    run = _Run(log, config, fusion)
    n = log.n_steps
    poses = np.zeros((n, 3))
    covs = np.zeros((n, 3, 3))
    times = np.zeros(n)
    poses_known = np.full((n, 3), np.nan)
    covs_known = np.full((n, 3, 3), np.nan)
    k, reported = 0, -1
    while k < n:
        t0 = time.perf_counter()
        if k > 0:
            run.predict(k)
        run.observe(k)
        first = k > reported
        if first:
            # A step filtered again after an anchor is undone keeps the output the
            # filter gave the first time: what it knew then.
            reported = k
            poses[k], covs[k] = vehicle_in_global(run.global_map, run.local, run.ctx)
            if run.local.has(Role.ANCHOR):
                a = run.local.find(Role.ANCHOR)
                x, J = inverse_jacobian(run.local.mean[a])
                poses_known[k] = uncentred(x, run.known_centre)
                covs_known[k] = J @ run.local.block(a) @ J.T
        if k == n - 1 or run.local_map_full(k):
            run.join(k)
        resume = run.check_anchor(k)
        times[reported] += time.perf_counter() - t0
        if first and progress is not None:
            progress(k + 1, n)
        k = k + 1 if resume is None else resume + 1
    return _result(log, config, run, poses, covs, poses_known, covs_known, times)


def _result(
    log: MeasurementLog,
    config: EKFConfig,
    run: _Run,
    poses: FloatArray,
    covs: FloatArray,
    poses_known: FloatArray,
    covs_known: FloatArray,
    times: FloatArray,
) -> EstimatorResult:
    roots = run.tracks.roots(run.obs_track)
    obs_known = np.array(
        [run.tracks.known.get(int(r), -1) if r >= 0 else -1 for r in roots], dtype=np.int64
    )
    anchor = _anchor(run)
    gating = None if run.gate is None else run.gate.report()
    decisions = AssociationDecisions(
        roots.astype(np.int64),
        obs_known,
        None
        if anchor is None
        else AnchorDecision(
            np.asarray(anchor.x_Wknown_Wglobal, dtype=float), anchor.accepted_at_step
        ),
        gating,
    )
    return EstimatorResult(
        estimator="ekf",
        scenario=log.scenario,
        seed=log.seed,
        fusion=run.fusion,
        timestamps=np.asarray(log.timestamps[: poses.shape[0]], dtype=float),
        step_time_s=times,
        map=final_map(run.global_map, run.tracks, run.known_centre, obs_known),
        filtered=PoseTrack(poses, covs),
        anchor=anchor,
        decisions=decisions,
        matching=MatchAttempts(run.ccda_attempts, dict(run.ccda_reasons)) if run.fusion else None,
        tentative_dropped=run.tentative.dropped,
        details=EKFDetails(
            config=config,
            poses_in_known=poses_known,
            covs_in_known=covs_known,
            loop_closures=tuple(run.loop_closures),
            ccda_refused=tuple(run.ccda_refused),
            ccda_excluded=tuple(run.ccda_excluded),
            tentative_promoted=run.tentative.promoted,
            anchors_undone=tuple(run.undone),
            innovations=InnovationTotals(run.innovation_chi2, run.innovation_dof),
            joins=run.joins,
            increment_unconverged=run.increment_unconverged,
            ambiguous_skipped=run.ambiguous_skipped,
            obs_local_track=run.obs_track.copy(),
        ),
    )


def anchor_pose(g: GaussianMap) -> tuple[FloatArray, FloatArray]:
    """``x^Wknown'_Wglobal`` (the centred known frame) and its covariance, from a global
    map with an anchor."""
    a = g.find(Role.ANCHOR)
    gb = g.find(Role.BASE)
    # x^Wknown_Wglobal = ⊖x^Wlocal_Wknown ⊕ x^Wlocal_Wglobal
    inv, Ji = inverse_jacobian(g.mean[a])
    est, J1, J2 = compose_jacobians(inv, g.mean[gb])
    Jfull = np.hstack([J1 @ Ji, J2])
    P = g.marginal([a, gb])
    return est, Jfull @ P @ Jfull.T


def _anchor(run: _Run) -> Anchor | None:
    """The anchor ``x^Wknown_Wglobal`` at the end of the run, from the global map."""
    g = run.global_map
    if not g.has(Role.ANCHOR):
        return None
    est, cov = anchor_pose(g)
    return Anchor(
        x_Wknown_Wglobal=uncentred(est, run.known_centre),
        cov=cov,
        accepted_at_step=int(run.anchor_step),
        pairings=tuple(run.anchor_pairings),
    )
