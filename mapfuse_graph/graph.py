"""The factor graph over a measurement log (method.md §7), built step by step.

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

Association sources:

* ``"ekf"`` — the EKF's final decisions, handed over as
  :class:`~mapfuse_core.decisions.AssociationDecisions`: the same data association as
  the reference, so differences come from the estimator alone.  Anchor step and
  initial value from the decisions' anchor.
* ``"truth"`` — the simulator's world ids (observations with id −1 are dropped);
  a landmark is paired with the known feature of the same id.  The anchor is
  initialised by a weighted fit (:func:`mapfuse_core.ccda.estimate_transform`) once
  enough paired landmarks exist to fix it.
* ``"own"`` — χ²-gated nearest neighbour against the solver's current estimate,
  made while the graph grows (needs an incremental solver), with the gates and the
  one-to-one rules of :mod:`mapfuse_core.matching` that the EKF uses; CCDA every
  ``ccda_every`` steps until it accepts a match, then χ²-gated pairing of the
  remaining landmarks with known features.
* explicit arrays ``(obs_landmark, obs_known_id)`` (e.g. the
  :attr:`~mapfuse_core.decisions.AssociationDecisions.arrays` of
  :func:`mapfuse_core.decisions.load_associations`).

Everything is validated before any factor is built: an exception inside an iSAM2
update leaves it corrupt, so malformed input must never reach GTSAM.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import gtsam
import numpy as np

from mapfuse_core.ccda import ccda_match, estimate_transform
from mapfuse_core.decisions import AssociationDecisions
from mapfuse_core.features import FeatureKind, transform_feature
from mapfuse_core.matching import (
    AssociationConfig,
    ScoredPair,
    chi2_gate,
    nearest_neighbour,
    pregate,
)
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.se2 import FloatArray, compose, compose_jacobians, inverse
from mapfuse_graph.factors import (
    circle_centre_factor,
    circle_factor,
    circle_observation_error,
    circle_tie_error,
    circle_tie_factor,
    known_line_prior_factor,
    landmark_from_observation,
    line_factor,
    line_observation_error,
    line_tie_error,
    line_tie_factor,
    line_to_rho_alpha,
    make_noise,
    residual_noise_cov,
    rho_alpha_along,
    to_spmap_feature,
)

__all__ = [
    "ASSOCIATIONS",
    "Estimate",
    "GraphBuilder",
    "GraphOptions",
    "StepGraph",
    "anchor_key",
    "centre_radius_correlated",
    "known_key",
    "landmark_key",
    "odometry_noise_cov",
    "pose_key",
    "radius_key",
]

AssociationName = Literal["ekf", "truth", "own"]
ASSOCIATIONS: tuple[str, ...] = ("ekf", "truth", "own")


def pose_key(k: int) -> int:
    """Key of the vehicle pose at step ``k``."""
    return int(gtsam.symbol("x", k))


def landmark_key(i: int, kind: FeatureKind) -> int:
    """Key of landmark ``i`` (dense index, in ``Wglobal``): ``l`` lines, ``c`` circles.

    Separate symbols per kind let iSAM2 take a relinearisation threshold per
    variable type (its threshold map is keyed by symbol character and dimension).
    """
    return int(gtsam.symbol("l" if kind == FeatureKind.LINE else "c", i))


def radius_key(i: int) -> int:
    """Key of circle landmark ``i``'s radius with :attr:`GraphOptions.split_circles`
    (its centre keeps :func:`landmark_key`)."""
    return int(gtsam.symbol("r", i))


def centre_radius_correlated(log: MeasurementLog) -> int | None:
    """First circle observation of ``log`` whose covariance correlates its centre and
    radius (then :attr:`GraphOptions.split_circles` would change the model), else ``None``."""
    circles = np.nonzero(log.feat_kind == int(FeatureKind.CIRCLE))[0]
    bad = circles[np.any(log.feat_cov[circles][:, :2, 2] != 0.0, axis=1)]
    return int(bad[0]) if bad.size else None


def known_key(j: int, kind: FeatureKind) -> int:
    """Key of known feature ``j`` (row of the known map, ``Wknown``): ``k`` lines, ``q`` circles."""
    return int(gtsam.symbol("k" if kind == FeatureKind.LINE else "q", j))


def anchor_key() -> int:
    """Key of the anchor ``A = x^Wglobal_Wknown``."""
    return int(gtsam.symbol("a", 0))


@dataclass(frozen=True)
class GraphOptions:
    """Everything that shapes the graph (not the solver)."""

    fusion: bool = True
    """Fuse the known map (anchor, known features, tie factors)."""
    association: str = "ekf"
    """``"ekf"``, ``"truth"`` or ``"own"`` (see the module docstring)."""
    robust: str | None = None
    """Robust kernel of the observation factors: ``None``, ``"huber[:k]"``, ``"cauchy[:k]"``."""
    first_pose_sigma: tuple[float, float, float] = (1e-6, 1e-6, 1e-6)
    """σ (m, m, rad) of the prior holding ``X_0`` at the origin of ``Wglobal``.  Tight
    but not a hard constraint, which the Cholesky of iSAM2 cannot take."""
    tie_sigma: tuple[float, float] = (1e-3, 1e-4)
    """σ (m, rad) of the tie factors.  The EKF applies the pairing as a hard constraint;
    1 mm / 0.1 mrad is two orders below the known map's σ, so the answer is that of a
    hard constraint to < 1e-4 relative, while the system stays well conditioned."""
    data_association: AssociationConfig = field(default_factory=AssociationConfig)
    """Settings shared with the EKF (:class:`~mapfuse_core.matching.AssociationConfig`):
    the anchor's loose prior (every fused run) and, for ``own``, the gates, the
    one-to-one rules, the CCDA match and which landmarks it takes.  ``own`` searches
    by nearest neighbour only (``method`` must be ``"nn"``)."""
    ccda_every: int = 40
    """``own``: steps between CCDA attempts (the EKF's local-map length), and between
    attempts to pair the remaining landmarks with known features once matched."""
    cov_refresh_steps: int = 100
    """``own``: a landmark marginal used for gating is re-read from the solver after
    this many steps (reading iSAM2 marginals costs more than an update)."""
    min_anchor_pairings: int = 4
    """``truth``: paired landmarks needed before the anchor is initialised."""
    max_anchor_std: tuple[float, float] = (1.0, 0.05)
    """``truth``/``own``: largest σ (m, rad) of the fitted anchor for it to be used."""
    split_circles: bool = False
    """*(speed option)* Each circle landmark as two variables, its centre (``c``, 2-vector)
    and its radius (``r``, 1-vector): an observation gives a centre factor
    (:func:`~mapfuse_graph.factors.circle_centre_factor`) and a ``PriorFactorVector`` on
    the radius.  Allowed only when that is the same model: every circle observation's
    residual covariance has no centre–radius correlation (true of Victoria Park's
    detections; then the radius is independent of everything else and the estimates,
    and the zero centre–radius covariance, are those of the 3-vector form), no robust
    kernel (it would weigh the two parts apart), a fixed association and no known
    circles.  iSAM2 then eliminates 2- instead of 3-dimensional landmark blocks, for less
    CPU (``docs/victoria-park.md``)."""

    def __post_init__(self) -> None:
        if self.association not in ASSOCIATIONS:
            raise ValueError(
                f"association must be one of {', '.join(ASSOCIATIONS)}, got {self.association!r}"
            )
        if not isinstance(self.data_association, AssociationConfig):
            raise ValueError(
                "data_association must be an AssociationConfig, got "
                f"{type(self.data_association).__name__}"
            )
        if self.association == "own" and self.data_association.method != "nn":
            raise ValueError(
                "association 'own' searches by nearest neighbour only: "
                f"data_association.method must be 'nn', got {self.data_association.method!r}"
            )
        for name in ("first_pose_sigma", "tie_sigma", "max_anchor_std"):
            v = getattr(self, name)
            if not all(math.isfinite(s) and s > 0 for s in v):
                raise ValueError(f"{name} must hold positive finite values, got {v}")
        if self.ccda_every < 1 or self.cov_refresh_steps < 1:
            raise ValueError("ccda_every and cov_refresh_steps must be >= 1")
        if self.min_anchor_pairings < 2:
            raise ValueError(f"min_anchor_pairings must be >= 2, got {self.min_anchor_pairings}")
        if self.robust is not None:
            make_noise(np.eye(2), self.robust)  # raises ValueError on a bad spec


class Estimate(Protocol):
    """What the builder needs from a solver's current estimate."""

    def pose(self, k: int) -> FloatArray:
        """``(x, y, θ)`` of ``X_k``."""
        ...

    def vector(self, key: int) -> FloatArray:
        """Value of a vector variable (landmark or known feature)."""
        ...

    def anchor(self) -> FloatArray:
        """``(x, y, θ)`` of the anchor."""
        ...

    def pose_cov(self, k: int) -> FloatArray | None:
        """Absolute ``(x, y, θ)`` covariance of ``X_k``, or ``None`` if unavailable."""
        ...

    def cov(self, key: int) -> FloatArray | None:
        """Marginal covariance of a vector variable, or ``None`` if unavailable."""
        ...


@dataclass
class StepGraph:
    """The new factors and variables of one step."""

    factors: gtsam.NonlinearFactorGraph
    """Factors added at this step."""
    values: gtsam.Values
    """Initial values of the variables created at this step."""
    new_landmarks: list[int] = field(default_factory=list)
    """Dense indices of landmarks created at this step."""
    anchor_added: bool = False
    """Whether the anchor and the known features were added at this step."""


def odometry_noise_cov(u: FloatArray, Q: FloatArray) -> FloatArray:
    """Raw-increment covariance ``Q`` → covariance of GTSAM's Between error, ``Gᵀ Q G``."""
    c, s = math.cos(u[2]), math.sin(u[2])
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = G.T @ Q @ G
    return 0.5 * (out + out.T)


def _is_pd(cov: FloatArray) -> bool:
    if not np.all(np.isfinite(cov)):
        return False
    w = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    return bool(w.min() > 1e-14 * max(w.max(), 1e-300) and w.min() > 0.0)


def _spmap_to_var(kind: FeatureKind, f: FloatArray) -> FloatArray:
    return f.copy() if kind == FeatureKind.CIRCLE else line_to_rho_alpha(f)[0]


def _known_prior(
    kind: FeatureKind, f: FloatArray, cov: FloatArray
) -> tuple[FloatArray, FloatArray]:
    if kind == FeatureKind.CIRCLE:
        return f.copy(), cov.copy()
    v, J = line_to_rho_alpha(f)
    return v, J @ cov @ J.T


@dataclass
class _Landmark:
    kind: FeatureKind
    first_step: int
    first_obs: int
    n_obs: int = 0
    known: int = -1
    """Row of the known map this landmark is tied to, −1 if none."""
    tied: bool = False
    created: bool = False
    """Whether its variable has been handed to the solver."""
    extent: tuple[float, float] = (math.nan, math.nan)
    """``own``: along-line interval (on the landmark's ``(ρ, α)`` line) it was seen on."""
    cov: FloatArray | None = None
    cov_step: int = -1


class GraphBuilder:
    """Validated log + association → per-step factors and initial values.

    ``association`` is a name of :data:`ASSOCIATIONS` or a pair of arrays
    ``(obs_landmark, obs_known_id)`` of the log's length (−1 = not associated /
    not merged).  ``decisions`` (the EKF's) is required for ``"ekf"``; with fusion its
    anchor also provides the anchor's initial value and step.
    """

    def __init__(
        self,
        log: MeasurementLog,
        options: GraphOptions | None = None,
        decisions: AssociationDecisions | None = None,
        association: tuple[np.ndarray, np.ndarray] | None = None,
        steps: int | None = None,
    ) -> None:
        self.log = log
        self.options = opts = options or GraphOptions()
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
        self.pairings: list[tuple[int, int]] = []
        """(landmark index, known row) of every tie factor added."""
        self._next_step = 0
        self._gate = {d: chi2_gate(opts.data_association.gate_prob, d) for d in (2, 3)}
        self._label: dict[int, int] = {}
        self._planned: dict[int, tuple[FeatureKind, int, int]] = {}
        self._planned_known: dict[int, int] = {}
        self._fit_count = 0

        if association is not None:
            lm, kn = _check_assoc_arrays(log, association, self._known_row)
            self._mode = "fixed"
            self._plan(lm, kn)
        elif opts.association == "ekf":
            if decisions is None:
                raise ValueError(
                    "association 'ekf' needs decisions (the EKF's AssociationDecisions on this log)"
                )
            lm, kn = _check_assoc_arrays(log, decisions.arrays, self._known_row)
            self._mode = "fixed"
            self._plan(lm, kn)
        elif opts.association == "truth":
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
            opts.fusion
            and len(self.known) > 0
            and decisions is not None
            and decisions.anchor is not None
            and self._mode == "fixed"
        ):
            a = np.asarray(decisions.anchor.x_Wknown_Wglobal, dtype=float)
            self.anchor_init = inverse(a)
            self.anchor_step = min(int(decisions.anchor.accepted_at_step), self.n_steps - 1)
            self.anchor_step = max(self.anchor_step, 0)
            self.anchor_source = "ekf"
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
        if opts.fusion and np.any(self.known.kinds == int(FeatureKind.CIRCLE)):
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

    # ------------------------------------------------------------------ planning

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
            if kid >= 0 and self.options.fusion:
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

    # ------------------------------------------------------------------ stepping

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

    # ------------------------------------------------------------------ fusion

    def _fusion_step(self, k: int, est: Estimate, out: StepGraph) -> None:
        opts = self.options
        if not opts.fusion or len(self.known) == 0:
            return
        if self.anchor_init is None and self._mode == "fixed" and self.anchor_source != "ekf":
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
        if not res.accepted or not self._anchor_ok(res.x_A_B, res.cov):
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

    # ------------------------------------------------------------------ own association

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
                d2 = self._obs_d2(k, kind, z, x, Px, i, vals[n], log.feat_cov[j], est)
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

    # ------------------------------------------------------------------ summary

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


# --------------------------------------------------------------------------- helpers


class _WithStep:
    """An estimate extended with the values created during the current step."""

    def __init__(self, est: Estimate, k: int, new: gtsam.Values) -> None:
        self._est, self._k, self._new = est, k, new

    def pose(self, k: int) -> FloatArray:
        if k == self._k:
            p = self._new.atPose2(pose_key(k))
            return np.array([p.x(), p.y(), p.theta()])
        return self._est.pose(k)

    def vector(self, key: int) -> FloatArray:
        if self._new.exists(key):
            return np.asarray(self._new.atVector(key), dtype=float)
        return self._est.vector(key)

    def anchor(self) -> FloatArray:
        return self._est.anchor()

    def pose_cov(self, k: int) -> FloatArray | None:
        return None if k == self._k else self._est.pose_cov(k)

    def cov(self, key: int) -> FloatArray | None:
        return None if self._new.exists(key) else self._est.cov(key)


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


def _pd_rows(covs: FloatArray) -> np.ndarray:
    """(n,) bool: which of the stacked covariances (n, d, d) are positive definite."""
    if covs.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    finite = np.all(np.isfinite(covs), axis=(1, 2))
    safe = np.where(finite[:, None, None], covs, 0.0)
    w = np.linalg.eigvalsh(0.5 * (safe + np.swapaxes(safe, 1, 2)))
    out: np.ndarray = finite & (w[:, 0] > 0.0) & (w[:, 0] > 1e-14 * np.maximum(w[:, -1], 1e-300))
    return out


@dataclass(frozen=True)
class _LogNoise:
    """Noise covariances of every factor of the log, computed (and checked) once."""

    odometry: FloatArray
    """(N, 3, 3) covariance of each Between error (row 0 unused)."""
    observation: list[FloatArray]
    """Per observation, its residual covariance (2×2 lines, 3×3 circles)."""


def _validate_log(log: MeasurementLog, steps: int) -> _LogNoise:
    """Checks beyond :class:`MeasurementLog`'s own: what GTSAM needs to be safe.

    Returns the noise covariances it had to compute for the checks, so that building
    the factors does not compute them again.
    """
    kinds = np.asarray(log.feat_kind)
    bad = np.nonzero(~np.isin(kinds, [int(FeatureKind.LINE), int(FeatureKind.CIRCLE)]))[0]
    if bad.size:
        j = int(bad[0])
        raise ValueError(f"observation {j} has unknown feature kind {int(kinds[j])}")
    for name in ("odometry", "feat_params", "feat_cov", "odometry_cov"):
        a = np.asarray(getattr(log, name))
        if not np.all(np.isfinite(a)):
            where = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise ValueError(f"log '{name}' has a non-finite value at {where}")
    odo = np.zeros((log.n_steps, 3, 3))
    for k in range(1, steps):
        odo[k] = odometry_noise_cov(log.odometry[k], log.odometry_cov[k])
    ok = _pd_rows(odo[1:steps])
    if not np.all(ok):
        raise ValueError(
            f"odometry covariance of step {int(np.nonzero(~ok)[0][0]) + 1} is not positive definite"
        )
    m = int(np.searchsorted(log.feat_step, steps, side="left"))
    circles = np.nonzero(kinds[:m] == int(FeatureKind.CIRCLE))[0]
    small = circles[~(log.feat_params[circles, 2] > 0.0)]
    if small.size:
        j = int(small[0])
        raise ValueError(f"observation {j} is a circle with radius {log.feat_params[j, 2]}")
    obs = [
        residual_noise_cov(FeatureKind(int(kinds[j])), log.feat_params[j], log.feat_cov[j])
        for j in range(m)
    ]
    for d in (2, 3):
        idx = [j for j in range(m) if obs[j].shape[0] == d]
        if idx:
            ok_obs = _pd_rows(np.stack([obs[j] for j in idx]))
            if not np.all(ok_obs):
                raise ValueError(
                    f"observation {idx[int(np.nonzero(~ok_obs)[0][0])]}: its covariance projected "
                    "on the residual is not positive definite"
                )
    km = log.known_map
    for r in range(len(km)):
        kind = int(km.kinds[r])
        if kind not in (int(FeatureKind.LINE), int(FeatureKind.CIRCLE)):
            raise ValueError(f"known feature {int(km.ids[r])} has unknown kind {kind}")
        if not np.all(np.isfinite(km.params[r])) or not np.all(np.isfinite(km.covs[r])):
            raise ValueError(f"known feature {int(km.ids[r])} has non-finite parameters")
        _, P = _known_prior(FeatureKind(kind), km.params[r], km.covs[r])
        if not _is_pd(P):
            raise ValueError(
                f"known feature {int(km.ids[r])}: covariance is not positive definite "
                "(a prior needs a σ on every degree of freedom)"
            )
    return _LogNoise(odo, obs)


def _check_assoc_arrays(
    log: MeasurementLog, association: tuple[Any, Any], known_row: dict[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    if not (isinstance(association, tuple | list) and len(association) == 2):
        raise ValueError("association arrays must be a pair (obs_landmark, obs_known_id)")
    out = []
    for name, a in zip(("obs_landmark", "obs_known_id"), association, strict=True):
        arr = np.asarray(a)
        if arr.shape != (log.n_features,):
            raise ValueError(
                f"{name} has shape {arr.shape}, the log has {log.n_features} observations"
            )
        if arr.dtype.kind not in "iu":
            if arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
                arr = arr.astype(np.int64)
            else:
                raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
        out.append(arr.astype(np.int64))
    lm, kn = out
    if np.any(lm < -1) or np.any(kn < -1):
        raise ValueError("association ids must be >= -1 (-1 = none)")
    missing = sorted({int(i) for i in kn[kn >= 0]} - set(known_row))
    if missing:
        raise ValueError(f"obs_known_id refers to known features missing from the map: {missing}")
    orphan = np.nonzero((kn >= 0) & (lm < 0))[0]
    if orphan.size:
        raise ValueError(
            f"observation {int(orphan[0])} is merged with a known feature but has no landmark"
        )
    return lm, kn
