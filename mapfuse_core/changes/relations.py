"""How a landmark's observations relate to one known feature: the measurements the
classification rules (:mod:`mapfuse_core.changes.rules`) decide on.

* :func:`move_test`: the χ² test of the landmark's observation-only evidence against
  the known feature (:func:`passes_move_test`: the landmark is that feature, unmoved);
* :func:`move_size`: how far the known feature must move to become the landmark, or
  ``inf`` beyond the move limits;
* for walls, where the landmark lies along the known line (:func:`overlaps_wall`,
  :func:`on_the_wall_itself`, :func:`longer_than_the_wall`);
* for trees, whether the landmark stands beyond the reach of a beam read at the
  surveyed place (:func:`beyond_reach`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapfuse_core.changes.evidence import ObservationSet, fuse_against
from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.residual import feature_residual, residual_dof
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays

__all__ = [
    "MoveTest",
    "along_known_line",
    "beyond_reach",
    "longer_than_the_wall",
    "move_size",
    "move_test",
    "on_the_wall_itself",
    "overlaps_wall",
    "passes_move_test",
    "position_sigmas",
    "surveyed_extent",
]


@dataclass(frozen=True, eq=False)
class MoveTest:
    """The χ² test of a landmark's evidence against a known feature."""

    residual: FloatArray
    """The fused residual of the observations from the known feature (line: lateral
    offset (m), angle (rad); circle: dx, dy, dr (m))."""
    cov: FloatArray
    """Its covariance ``S``: the evidence's plus the known feature's through the
    residual's Jacobian."""
    statistic: float
    """``rᵀS⁻¹r``."""
    displacement: FloatArray
    """(3,) the residual as a move: ``(dx, dy, dθ)`` of a line's reference point across
    the line and its turn, ``(dx, dy, dr)`` of a circle."""
    spread_factor: float
    """Factor the evidence's measurement covariance was scaled by
    (:func:`~mapfuse_core.changes.evidence.spread_factor`)."""


def move_test(obs: ObservationSet, known: FloatArray, known_cov: FloatArray) -> MoveTest:
    """Test landmark ``obs`` against the known feature ``known`` (covariance
    ``known_cov``): ``r = residual(known, evidence)``, ``S = cov(evidence) + J P Jᵀ``."""
    evidence = fuse_against(obs, known)
    _, J_known, _ = feature_residual(obs.kind, known, known)
    S = evidence.cov + J_known @ known_cov @ J_known.T
    r = evidence.residual
    statistic = float(r @ np.linalg.solve(S, r))
    if obs.kind == FeatureKind.LINE:
        normal = np.array([-math.sin(known[2]), math.cos(known[2])])
        displacement = np.array([*(r[0] * normal), r[1]])
    else:
        displacement = r.copy()
    return MoveTest(
        residual=r,
        cov=S,
        statistic=statistic,
        displacement=displacement,
        spread_factor=evidence.spread_factor,
    )


def passes_move_test(
    obs: ObservationSet, known: KnownMapArrays, row: int, params: ChangeParams
) -> bool:
    """Whether landmark ``obs`` passes the move test of known feature ``row`` at
    ``params.level``: its evidence is that feature where the map has it."""
    statistic = move_test(obs, known.params[row], known.covs[row]).statistic
    return statistic <= params.threshold(residual_dof(obs.kind))


def move_size(
    obs: ObservationSet,
    known: FloatArray,
    known_cov: FloatArray,
    extent: FloatArray | None,
    params: ChangeParams,
) -> float:
    """Size of the move that takes ``known`` onto ``obs`` (m), ``inf`` beyond the limits.

    The limits are ``max_move_m`` and ``max_turn_rad`` widened by three of the known
    feature's own σ (its position, or its angle for a line): the surveyed value itself
    is that far from where the feature stood, so a feature turned by the largest turn
    looked for, in a map whose angles have σθ = 0.05 rad, can appear turned by 0.15 rad
    more.  A line must also overlap the known wall along its length (its surveyed
    extent widened by ``max_move_m``; without one, within ``max_move_m`` of its
    reference point).  A circle's size is the distance of the centres, a line's its
    lateral offset.
    """
    sigma_xy = math.sqrt(max(0.0, 0.5 * float(known_cov[0, 0] + known_cov[1, 1])))
    max_move = params.max_move_m + 3.0 * sigma_xy
    mean = obs.features.mean(axis=0)
    if obs.kind == FeatureKind.CIRCLE:
        distance = float(np.hypot(*(mean[:2] - known[:2])))
        return distance if distance <= max_move else math.inf
    max_turn = params.max_turn_rad + 3.0 * math.sqrt(max(0.0, float(known_cov[2, 2])))
    mean_residual = np.array([feature_residual(obs.kind, known, f)[0] for f in obs.features]).mean(
        axis=0
    )
    if abs(mean_residual[1]) > max_turn or abs(mean_residual[0]) > max_move:
        return math.inf
    if not overlaps_wall(obs, known, extent, params.max_move_m):
        return math.inf
    return float(abs(mean_residual[0]))


def along_known_line(obs: ObservationSet, known: FloatArray) -> list[float]:
    """Where the ends of ``obs``'s observed segments fall along the known line (m from
    its reference point; a segment without a finite extent gives its reference point)."""
    u_known = np.array([math.cos(known[2]), math.sin(known[2])])
    along = []
    for f, e in zip(obs.features, obs.extents, strict=True):
        u = np.array([math.cos(f[2]), math.sin(f[2])])
        ends = [0.0] if not np.all(np.isfinite(e)) else [float(e[0]), float(e[1])]
        along += [float((f[:2] + t * u - known[:2]) @ u_known) for t in ends]
    return along


def overlaps_wall(
    obs: ObservationSet, known: FloatArray, extent: FloatArray | None, margin: float
) -> bool:
    """Whether ``obs`` overlaps the known wall along its length, its surveyed extent
    widened by ``margin`` on each side (without an extent: within ``margin`` of its
    reference point)."""
    along = along_known_line(obs, known)
    lo, hi = (0.0, 0.0) if extent is None or not np.all(np.isfinite(extent)) else extent
    return not (max(along) < lo - margin or min(along) > hi + margin)


def surveyed_extent(known: KnownMapArrays, row: int) -> FloatArray | None:
    """The along-line extent of known feature ``row`` (``None`` for a map without
    extents)."""
    return None if known.extents is None else np.asarray(known.extents[row], dtype=float)


def position_sigmas(obs: ObservationSet, known: KnownMapArrays, row: int) -> float:
    """Known feature ``row``'s position σ plus the landmark's mean pose position σ (m)."""
    known_cov = known.covs[row]
    sigma_known = math.sqrt(max(0.0, 0.5 * float(known_cov[0, 0] + known_cov[1, 1])))
    pose_covs = obs.pose_covs
    sigma_pose = math.sqrt(max(0.0, 0.5 * float(np.mean(pose_covs[:, 0, 0] + pose_covs[:, 1, 1]))))
    return sigma_known + sigma_pose


def on_the_wall_itself(obs: ObservationSet, known: KnownMapArrays, row: int) -> bool:
    """Whether line landmark ``obs`` overlaps known wall ``row`` itself, not just its
    line: the surveyed extent widened by three of the wall's position σ and of the
    landmark's pose σ.  A wall consistent with another only as a line but beyond its
    ends is a collinear piece of another wall (the next stretch of a corridor past a
    door)."""
    margin = 3.0 * position_sigmas(obs, known, row)
    return overlaps_wall(obs, known.params[row], surveyed_extent(known, row), margin)


def longer_than_the_wall(obs: ObservationSet, known: KnownMapArrays, row: int) -> bool:
    """Whether line landmark ``obs`` spans more of the known wall's line than wall
    ``row`` is long, by more than six of the wall's and the landmark's position σ (the
    margin of three at each end that :func:`on_the_wall_itself` allows); ``False`` for
    a wall without a finite extent."""
    extent = surveyed_extent(known, row)
    if extent is None or not np.all(np.isfinite(extent)):
        return False
    along = along_known_line(obs, known.params[row])
    excess = (max(along) - min(along)) - float(extent[1] - extent[0])
    return excess > 6.0 * position_sigmas(obs, known, row)


def beyond_reach(obs: ObservationSet, known: FloatArray, reach: float) -> bool:
    """Whether circle landmark ``obs`` stands too far from the known circle's centre for
    a beam it returns to have been read as a hit there: such a beam is aimed within the
    mapped radius of the centre (across the beam) and returns within ``reach`` of the
    centre's range (along it)."""
    centre = np.mean(obs.features[:, :2], axis=0)
    radius = max(float(np.median(obs.features[:, 2])), 0.0)
    window = math.hypot(reach, float(known[2]))
    return float(np.hypot(*(centre - known[:2]))) > window + radius
