"""The factor graph over a measurement log (docs/method.md §7), built step by step.

:class:`GraphBuilder` turns a :class:`~mapfuse_core.measlog.MeasurementLog` into the
factors and initial values of each step, so that one code path feeds both the
batch solver (all steps, then optimise) and iSAM2 (one update per step).

Per step ``k``:

* a Pose2 ``X_k`` = ``x^Wglobal_R_k``; ``X_0`` gets a tight prior at the origin of
  ``Wglobal`` (the EKF starts with a zero covariance there);
* ``BetweenFactorPose2(X_{k−1}, X_k)`` with the logged increment.  The log's
  covariance ``Q`` is of the raw ``(x, y, θ)`` increment; GTSAM's Between error is
  ``Log(u⁻¹ · (X_{k−1}⁻¹ X_k))``, which for ``u_true = u + e`` is ``(R(θ_u)ᵀ e_xy, e_θ)``
  to first order, so the factor gets ``Gᵀ Q G`` with ``G = blockdiag(R(θ_u), 1)``;
* a line or circle factor per associated observation (:mod:`mapfuse_graph.factors`);
  with :attr:`GraphOptions.split_circles` a circle observation is a centre factor plus
  a prior on the circle's separate radius variable.

With fusion, from the step the match is known (the *anchor step*): a Pose2 anchor
``A = x^Wglobal_Wknown`` with a loose prior (``data_association.anchor_prior_sigma``: the
tie factors, not the match's own covariance, fix it, so the information of the
matched features is counted once), every known feature as a variable with a prior
from its σ, and one tie factor per (landmark, known) pairing; a landmark first seen
after the anchor step gets its tie when it is created.

Association sources (:data:`~mapfuse_graph.options.ASSOCIATIONS`):

* ``"given"`` — decisions made elsewhere (e.g. the EKF's), handed over as
  :class:`~mapfuse_core.estimate.AssociationDecisions`: the same data association as
  that estimator, so differences come from the estimator alone.  Anchor step and
  initial value from the decisions' anchor; known features the decisions stopped
  fusing get no tie.  Decisions saved beside a run (``associations.npz``) load with
  :func:`mapfuse_core.estimate.load_associations`.
* ``"truth"`` — the simulator's world ids (observations with id −1 are dropped);
  a landmark is paired with the known feature of the same id.  The anchor takes its
  initial value and step from the decisions' anchor when decisions are given, else
  it is initialised by a weighted fit (:func:`mapfuse_core.matching.ccda.estimate_transform`)
  once enough paired landmarks exist to fix it.
* ``"own"`` — χ²-gated nearest neighbour against the solver's current estimate,
  made while the graph grows (needs an incremental solver), with the gates and the
  one-to-one rules of :mod:`mapfuse_core.matching` that the EKF uses; CCDA every
  ``ccda_every`` steps until it accepts a match, then χ²-gated pairing of the
  remaining landmarks with known features.

Everything is validated before any factor is built: an exception inside an iSAM2
update leaves it corrupt, so malformed input must never reach GTSAM.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
import numpy as np

from mapfuse_core.estimate.decisions import AssociationDecisions
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, compose, inverse
from mapfuse_core.matching import (
    chi2_gate,
)
from mapfuse_core.matching.ccda import estimate_transform
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_graph.estimate import Estimate, StepGraph, _Landmark, _WithStep
from mapfuse_graph.factors import (
    circle_centre_factor,
    circle_factor,
    circle_tie_factor,
    known_line_prior_factor,
    landmark_from_observation,
    line_factor,
    line_tie_factor,
    line_to_rho_alpha,
    make_noise,
    rho_alpha_along,
    to_spmap_feature,
)
from mapfuse_graph.keys import anchor_key, known_key, landmark_key, pose_key, radius_key
from mapfuse_graph.options import ASSOCIATIONS, AssociationName, GraphOptions
from mapfuse_graph.own_association import OwnAssociation
from mapfuse_graph.validation import (
    _check_assoc_arrays,
    _known_prior,
    _validate_log,
    centre_radius_correlated,
)

__all__ = ["GraphBuilder"]


class GraphBuilder(OwnAssociation):
    """Validated log + association → per-step factors and initial values.

    ``association``: a name of :data:`~mapfuse_graph.options.ASSOCIATIONS` (see the
    module docstring).  ``decisions`` are required for ``"given"``, optional for
    ``"truth"`` (their anchor only) and refused for ``"own"``.  ``fusion``: whether
    the known map enters the graph (anchor, known features, ties).
    """

    def __init__(
        self,
        log: MeasurementLog,
        options: GraphOptions | None = None,
        *,
        fusion: bool = True,
        association: AssociationName = "given",
        decisions: AssociationDecisions | None = None,
        steps: int | None = None,
    ) -> None:
        if association not in ASSOCIATIONS:
            raise ValueError(
                f"association must be one of {', '.join(ASSOCIATIONS)}, got {association!r}"
            )
        if association == "given" and decisions is None:
            raise ValueError(
                "association 'given' needs decisions (AssociationDecisions on this log)"
            )
        if association == "own" and decisions is not None:
            raise ValueError(
                "association 'own' makes its own decisions and anchor: decisions given "
                "would be ignored"
            )
        self.log = log
        self.fusion = bool(fusion)
        """Whether the known map is fused."""
        self.association: AssociationName = association
        """Where the data association comes from."""
        self.options = opts = options or GraphOptions()
        if association == "own" and opts.data_association.method != "nn":
            raise ValueError(
                "association 'own' searches by nearest neighbour only: "
                f"data_association.method must be 'nn', got {opts.data_association.method!r}"
            )
        self.n_steps = log.n_steps if steps is None else int(steps)
        if not 1 <= self.n_steps <= log.n_steps:
            raise ValueError(f"steps must be in 1..{log.n_steps}, got {steps}")
        self._noise = _validate_log(log, self.n_steps)
        self.known: KnownMapArrays = log.known_map
        self._known_row = {int(i): r for r, i in enumerate(self.known.ids)}
        self.landmarks: list[_Landmark] = []
        self.obs_landmark = np.full(log.n_features, -1, dtype=np.int64)
        """(M,) dense landmark index of each observation (−1: not in the graph)."""
        self.anchor_step = -1
        self.anchor_init: FloatArray | None = None
        self.anchor_source = ""
        self.ccda_reasons: dict[str, int] = {}
        """CCDA calls of the ``own`` association per outcome (``"anchor refused"``: an
        accepted match the anchor check turned down)."""
        self.pairings: list[tuple[int, int]] = []
        """(landmark index, known row) of every tie factor added."""
        self._next_step = 0
        self._gate = {d: chi2_gate(opts.data_association.gate_prob, d) for d in (2, 3)}
        self._label: dict[int, int] = {}
        self._planned: dict[int, tuple[FeatureKind, int, int]] = {}
        self._planned_known: dict[int, int] = {}
        self._fit_count = 0

        if association == "given":
            assert decisions is not None
            lm, kn = _check_assoc_arrays(log, decisions.arrays, self._known_row)
            unfused = sorted(decisions.unfused_known_ids)
            if unfused:
                # The decisions stopped fusing these known features: no tie, a plain landmark.
                kn = np.where(np.isin(kn, unfused), -1, kn)
            self._mode = "fixed"
            self._plan(lm, kn)
        elif association == "truth":
            tid = np.asarray(log.feat_true_id, dtype=np.int64).copy()
            if log.world is not None:
                # A segment labelled with a tree's id (or the reverse) is an extraction
                # mix-up, not a landmark of the other kind: drop it like an unlabelled one.
                world_kind = dict(
                    zip(log.world.ids.tolist(), log.world.kinds.tolist(), strict=True)
                )
                wrong = np.array(
                    [
                        t >= 0 and world_kind.get(int(t), k) != k
                        for t, k in zip(tid, log.feat_kind, strict=True)
                    ],
                    dtype=bool,
                )
                tid[wrong] = -1
            kn = np.array([i if int(i) in self._known_row else -1 for i in tid], dtype=np.int64)
            self._mode = "fixed"
            self._plan(tid, kn)
        else:
            self._mode = "own"

        if (
            self.fusion
            and len(self.known) > 0
            and decisions is not None
            and decisions.anchor is not None
            and self._mode == "fixed"
        ):
            # The anchor is the decisions'.  A graph of fewer steps than their maker
            # needed to match has none (nor fits one): the match is not known at its
            # last step.
            self.anchor_source = "given"
            if int(decisions.anchor.accepted_at_step) < self.n_steps:
                a = np.asarray(decisions.anchor.x_Wknown_Wglobal, dtype=float)
                self.anchor_init = inverse(a)
                self.anchor_step = max(int(decisions.anchor.accepted_at_step), 0)
        if opts.split_circles:
            self._check_split_circles()
        self._fix_prior_noise = make_noise(np.diag(np.square(opts.first_pose_sigma)))
        self._tie_noise = {
            FeatureKind.LINE: make_noise(np.diag(np.square(opts.tie_sigma))),
            FeatureKind.CIRCLE: make_noise(np.diag(np.square([opts.tie_sigma[0]] * 3))),
        }

    def _check_split_circles(self) -> None:
        opts, log = self.options, self.log
        if self._mode == "own":
            raise ValueError("split_circles needs a fixed association, not 'own'")
        if opts.robust is not None:
            raise ValueError(
                "split_circles cannot take a robust kernel (it would weigh "
                "the centre and the radius apart)"
            )
        if self.fusion and np.any(self.known.kinds == int(FeatureKind.CIRCLE)):
            raise ValueError("split_circles cannot fuse a known map with circles")
        j = centre_radius_correlated(log)
        if j is not None:
            raise ValueError(
                f"split_circles: observation {j} correlates its circle's centre and "
                "radius; the split would not be the same model"
            )

    @property
    def split_circles(self) -> bool:
        """Whether circle landmarks are a centre and a radius variable."""
        return self.options.split_circles

    def _plan(self, lm_ids: np.ndarray, kn_ids: np.ndarray) -> None:
        """Dense landmarks from the (validated) association arrays, in first-seen order."""
        log = self.log
        use = np.nonzero((lm_ids >= 0) & (log.feat_step < self.n_steps))[0]
        for j in use:
            label = int(lm_ids[j])
            kind = FeatureKind(int(log.feat_kind[j]))
            i = self._label.get(label)
            if i is None:
                i = len(self._label)
                self._label[label] = i
                self._planned[i] = (kind, int(log.feat_step[j]), int(j))
            elif self._planned[i][0] != kind:
                raise ValueError(
                    f"landmark {label} is observed both as a {self._planned[i][0].name.lower()} "
                    f"and as a {kind.name.lower()} (observation {j})"
                )
            self.obs_landmark[j] = i
            kid = int(kn_ids[j])
            if kid >= 0 and self.fusion:
                row = self._known_row[kid]
                if int(self.known.kinds[row]) != int(kind):
                    raise ValueError(
                        f"observation {j}: landmark {label} ({kind.name.lower()}) is merged with "
                        f"known feature {kid} of another kind"
                    )
                prev = self._planned_known.get(i)
                if prev is not None and prev != row:
                    raise ValueError(
                        f"landmark {label} is merged with two known features "
                        f"({int(self.known.ids[prev])} and {kid})"
                    )
                self._planned_known[i] = row
        rows = list(self._planned_known.values())
        if len(rows) != len(set(rows)):
            dup = next(r for r in rows if rows.count(r) > 1)
            raise ValueError(
                f"known feature {int(self.known.ids[dup])} is merged with several landmarks"
            )

    @property
    def anchor_added(self) -> bool:
        """Whether the anchor is in the graph."""
        return self.anchor_init is not None and 0 <= self.anchor_step < self._next_step

    def step(self, k: int, est: Estimate, pose_init: FloatArray | None = None) -> StepGraph:
        """Factors and new variables of step ``k`` (steps must come in order).

        ``est`` is the solver's estimate of the variables so far (used for initial
        values and, for ``own``, association); ``pose_init`` overrides the initial
        value of ``X_k`` (otherwise ``X_{k−1} ⊕ u_k``).
        """
        if k != self._next_step:
            raise ValueError(f"steps must be added in order: expected {self._next_step}, got {k}")
        if k >= self.n_steps:
            raise ValueError(f"step {k} beyond the {self.n_steps} steps of this graph")
        log, opts = self.log, self.options
        out = StepGraph(gtsam.NonlinearFactorGraph(), gtsam.Values())
        xk = pose_key(k)
        if pose_init is not None:
            x = np.asarray(pose_init, dtype=float)
            if x.shape != (3,) or not np.all(np.isfinite(x)):
                raise ValueError(f"pose_init of step {k} is not a finite (3,) pose: {pose_init!r}")
        elif k == 0:
            x = np.zeros(3)
        else:
            x = compose(est.pose(k - 1), log.odometry[k])
        out.values.insert(xk, gtsam.Pose2(float(x[0]), float(x[1]), float(x[2])))
        if k == 0:
            out.factors.add(gtsam.PriorFactorPose2(xk, gtsam.Pose2(), self._fix_prior_noise))
        else:
            u = log.odometry[k]
            noise = make_noise(self._noise.odometry[k], check=False)
            out.factors.add(
                gtsam.BetweenFactorPose2(
                    pose_key(k - 1), xk, gtsam.Pose2(float(u[0]), float(u[1]), float(u[2])), noise
                )
            )
        sl = log.feature_slice(k)
        if self._mode == "own" and sl.stop > sl.start:
            self._associate_own(k, x, est)
        for j in range(sl.start, sl.stop):
            i = int(self.obs_landmark[j])
            if i < 0:
                continue
            kind = FeatureKind(int(log.feat_kind[j]))
            z = log.feat_params[j]
            if i == len(self.landmarks) and self._mode == "fixed":
                self.landmarks.append(_Landmark(kind, k, j, known=self._planned_known.get(i, -1)))
            lmk = self.landmarks[i]
            key = landmark_key(i, kind)
            split = opts.split_circles and kind == FeatureKind.CIRCLE
            if not lmk.created:
                v = landmark_from_observation(kind, x, z)
                if split:
                    out.values.insert(key, v[:2].copy())
                    out.values.insert(radius_key(i), v[2:].copy())
                else:
                    out.values.insert(key, v)
                out.new_landmarks.append(i)
                lmk.created = True
            lmk.n_obs += 1
            S = self._noise.observation[j]
            if split:
                # Checked block-diagonal at construction: the two factors are the joint one.
                out.factors.add(
                    circle_centre_factor(xk, key, z, make_noise(S[:2, :2], check=False))
                )
                out.factors.add(
                    gtsam.PriorFactorVector(
                        radius_key(i), z[2:].copy(), make_noise(S[2:, 2:], check=False)
                    )
                )
                continue
            noise = make_noise(S, opts.robust, check=False)
            if kind == FeatureKind.LINE:
                out.factors.add(line_factor(xk, key, z, noise))
            else:
                out.factors.add(circle_factor(xk, key, z, noise))
        self._fusion_step(k, est, out)
        self._next_step = k + 1
        return out

    def _fusion_step(self, k: int, est: Estimate, out: StepGraph) -> None:
        opts = self.options
        if not self.fusion or len(self.known) == 0:
            return
        if self.anchor_init is None and self._mode == "fixed" and self.anchor_source != "given":
            self._try_fit_anchor(k, est, out)
        elif self.anchor_init is None and self._mode == "own" and (k + 1) % opts.ccda_every == 0:
            self._try_ccda(k, est, out)
        if self.anchor_init is None or k < self.anchor_step:
            return
        if k == self.anchor_step:
            self._add_anchor(out)
        if self._mode == "own" and (k + 1) % opts.ccda_every == 0 and not out.anchor_added:
            self._pair_own(k, est)
        for i, lmk in enumerate(self.landmarks):
            if lmk.known >= 0 and not lmk.tied:
                self._add_tie(i, out)

    def _add_anchor(self, out: StepGraph) -> None:
        assert self.anchor_init is not None
        a = self.anchor_init
        A = gtsam.Pose2(float(a[0]), float(a[1]), float(a[2]))
        out.values.insert(anchor_key(), A)
        out.factors.add(
            gtsam.PriorFactorPose2(
                anchor_key(),
                A,
                make_noise(np.diag(np.square(self.options.data_association.anchor_prior_sigma))),
            )
        )
        for r in range(len(self.known)):
            kind = FeatureKind(int(self.known.kinds[r]))
            f, f_cov = self.known.params[r], self.known.covs[r]
            mean, cov = _known_prior(kind, f, f_cov)
            out.values.insert(known_key(r, kind), mean)
            if kind == FeatureKind.LINE:
                out.factors.add(known_line_prior_factor(known_key(r, kind), f, f_cov))
            else:
                out.factors.add(gtsam.PriorFactorVector(known_key(r, kind), mean, make_noise(cov)))
        out.anchor_added = True

    def _add_tie(self, i: int, out: StepGraph) -> None:
        lmk = self.landmarks[i]
        r = lmk.known
        kind = lmk.kind
        if kind == FeatureKind.LINE:
            f = self.known.params[r]
            t_known = rho_alpha_along(line_to_rho_alpha(f)[0], f)
            fac = line_tie_factor(
                anchor_key(),
                landmark_key(i, kind),
                known_key(r, kind),
                t_known,
                self._tie_noise[kind],
            )
        else:
            fac = circle_tie_factor(
                anchor_key(), landmark_key(i, kind), known_key(r, kind), self._tie_noise[kind]
            )
        out.factors.add(fac)
        lmk.tied = True
        self.pairings.append((i, r))

    def landmark_map(
        self, est: Estimate, which: Sequence[int], covs: bool = True
    ) -> KnownMapArrays:
        """Landmarks ``which`` as a :class:`KnownMapArrays` in ``Wglobal`` (SPmap lines).

        Line origins sit at the foot of their first observation; covariances are the
        solver's marginals where available, else the first observation's covariance
        carried to ``Wglobal`` (enough for matching weights).
        """
        log = self.log
        params, cvs, kinds = [], [], []
        for i in which:
            lmk = self.landmarks[i]
            v = est.vector(landmark_key(i, lmk.kind))
            j = lmk.first_obs
            P = est.cov(landmark_key(i, lmk.kind)) if covs else None
            if lmk.kind == FeatureKind.LINE:
                x = est.pose(lmk.first_step)
                p = transform_feature(FeatureKind.LINE, x, log.feat_params[j])[0]
                t = rho_alpha_along(v, p)
            else:
                t = 0.0
            if P is None:
                _, _, Jf = transform_feature(lmk.kind, est.pose(lmk.first_step), log.feat_params[j])
                f, _ = to_spmap_feature(lmk.kind, v, np.zeros((v.size, v.size)), t)
                P3 = Jf @ log.feat_cov[j] @ Jf.T
            else:
                f, P3 = to_spmap_feature(lmk.kind, v, P, t)
            params.append(f)
            cvs.append(P3)
            kinds.append(int(lmk.kind))
        n = len(params)
        return KnownMapArrays(
            ids=np.asarray(list(which), dtype=np.int64),
            kinds=np.asarray(kinds, dtype=np.int8),
            params=np.asarray(params, dtype=float).reshape(n, 3),
            covs=np.asarray(cvs, dtype=float).reshape(n, 3, 3),
        )

    def _try_fit_anchor(self, k: int, est: Estimate, out: StepGraph) -> None:
        paired = [i for i, lmk in enumerate(self.landmarks) if lmk.known >= 0]
        if len(paired) < self.options.min_anchor_pairings or len(paired) == self._fit_count:
            return  # too few, or nothing new since the last (failed) attempt
        self._fit_count = len(paired)
        # The landmark created this step is initialised from X_k's initial value.
        est_now = _WithStep(est, k, out.values)
        map_a = self.landmark_map(est_now, paired, covs=False)
        pairs = [(n, self.landmarks[i].known) for n, i in enumerate(paired)]
        x, P = estimate_transform(map_a, self.known, pairs)
        if self._anchor_ok(x, P):
            self.anchor_init, self.anchor_step, self.anchor_source = x, k, "fit"

    def _anchor_ok(self, x: FloatArray, P: FloatArray) -> bool:
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            return False
        sxy, sth = self.options.max_anchor_std
        w = np.linalg.eigvalsh(P[:2, :2])
        return bool(math.sqrt(max(w.max(), 0.0)) <= sxy and math.sqrt(max(P[2, 2], 0.0)) <= sth)

    def planned_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Fixed association: ``(obs_landmark, obs_known_id)`` of every observation as
        planned (dense landmark index; known-map id of its pairing with fusion, else −1)."""
        if self._mode != "fixed":
            raise ValueError("planned_arrays needs a fixed association, not 'own'")
        lm = self.obs_landmark.copy()
        kn = np.full(lm.shape, -1, dtype=np.int64)
        for j in np.nonzero(lm >= 0)[0]:
            row = self._planned_known.get(int(lm[j]))
            if row is not None:
                kn[j] = int(self.known.ids[row])
        return lm, kn

    def landmark_kinds(self) -> np.ndarray:
        """(L,) int8 kinds of the landmarks created so far."""
        return np.array([int(lmk.kind) for lmk in self.landmarks], dtype=np.int8)

    def landmark_known_ids(self) -> np.ndarray:
        """(L,) known-map id each landmark is tied to (−1 if none)."""
        return np.array(
            [int(self.known.ids[lmk.known]) if lmk.tied else -1 for lmk in self.landmarks],
            dtype=np.int64,
        )

    def landmark_n_obs(self) -> np.ndarray:
        """(L,) observations per landmark."""
        return np.array([lmk.n_obs for lmk in self.landmarks], dtype=np.int64)

    def landmark_first_obs(self) -> np.ndarray:
        """(L,) log index of each landmark's first observation."""
        return np.array([lmk.first_obs for lmk in self.landmarks], dtype=np.int64)
