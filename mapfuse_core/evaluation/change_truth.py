"""The true changes of a simulated known map, and how a report scores against them.

The log keeps the true world (in ``W``) and the noisy known map (in ``Wknown``) but
not the scenario's ``moved``/``removed``/``added`` lists nor the map frame, so the
truth comes from the :class:`~mapfuse_core.sim.scenario.Scenario` the log was simulated
from (:func:`change_truth`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.report import ChangeReport, ChangeStatus
from mapfuse_core.changes.visibility import scans_in_view, world_as_map
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import FeatureMove, Scenario
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

__all__ = ["ChangeScore", "ChangeTruth", "change_truth", "score_changes"]


@dataclass(frozen=True)
class ChangeTruth:
    """What really changed between the known map and the world."""

    moved: dict[int, tuple[float, float, float, float]]
    """Known id → its move ``(dx, dy, dθ, dr)`` (world frame, as the scenario gives it)."""
    lateral: dict[int, float]
    """Known id of a moved line → its displacement across the line at its reference
    point (m); a move along a wall is no change of the wall."""
    removed: tuple[int, ...]
    """Known ids no longer in the world."""
    removed_in_view: tuple[int, ...]
    """Removed ids the true drive would have seen (at least ``min_scans`` scans)."""
    added: tuple[int, ...]
    """World ids the known map does not hold."""
    added_observed: tuple[int, ...]
    """Added ids observed at least ``min_obs`` times in the log."""
    observed: tuple[int, ...]
    """Known ids of world features observed at least ``min_obs`` times."""
    moved_surveyed_in_view: tuple[int, ...] = ()
    """Moved ids the true drive would have seen at their surveyed place (the known
    map's, at least ``min_scans`` scans, with a copy of the feature put there beside
    the feature where it is).  A move whose surveyed place never came into view
    cannot be told from a feature removed out of sight plus one added: nothing shows
    the surveyed place empty."""

    def significant_move(self, kid: int, min_move_m: float, min_turn_rad: float) -> bool:
        """Whether known feature ``kid`` moved by at least ``min_move_m`` (circle centre
        or radius, line across itself) or turned by at least ``min_turn_rad`` (line)."""
        if kid not in self.moved:
            return False
        dx, dy, dth, dr = self.moved[kid]
        if kid in self.lateral:
            return abs(self.lateral[kid]) >= min_move_m or abs(dth) >= min_turn_rad
        return math.hypot(dx, dy) >= min_move_m or abs(dr) >= min_move_m


def change_truth(
    scenario: Scenario, log: MeasurementLog, params: ChangeParams | None = None
) -> ChangeTruth:
    """True changes of ``scenario``'s known map, and which of them ``log`` could show:
    a removed feature counts as in view when the true drive, in the true world with
    it put back, sees it as :func:`~mapfuse_core.changes.visibility.scans_in_view`
    would; a feature counts as observed with ``params.min_obs`` observations."""
    params = params or ChangeParams()
    min_obs, min_scans = params.min_obs, params.min_scans
    spec = scenario.known_map
    ids, counts = np.unique(log.feat_true_id[log.feat_true_id >= 0], return_counts=True)
    seen = {int(i) for i, c in zip(ids.tolist(), counts.tolist(), strict=True) if c >= min_obs}
    moved = {m.id: (m.dx, m.dy, m.dtheta, m.dr) for m in spec.moved}
    lateral = {}
    for m in spec.moved:
        kind, p = _original(scenario, m.id)
        if kind == FeatureKind.LINE:
            lateral[m.id] = -math.sin(p[2]) * m.dx + math.cos(p[2]) * m.dy
    removed = tuple(f.id for f in spec.removed)
    in_view = []
    surveyed_in_view = []
    if log.true_poses is not None:
        world = scenario.world
        for f in spec.removed:
            if f.id in world.ids:
                continue
            if _scans_with(world, f, log.true_poses, params) >= min_scans:
                in_view.append(f.id)
        spare = max(world.ids, default=0) + 1
        for m in spec.moved:
            if m.id not in world.ids:
                continue
            # The copy stands beside the feature where it really is, which hides what
            # lies behind it, as it would hide the surveyed place from the drive.
            surveyed = _surveyed(world, m, spare)
            if _scans_with(world, surveyed, log.true_poses, params) >= min_scans:
                surveyed_in_view.append(m.id)
    known_ids = set(spec.ids)
    added = tuple(sorted(i for i in scenario.world.ids if i not in known_ids))
    return ChangeTruth(
        moved=moved,
        lateral=lateral,
        removed=removed,
        removed_in_view=tuple(in_view),
        moved_surveyed_in_view=tuple(surveyed_in_view),
        added=added,
        added_observed=tuple(i for i in added if i in seen),
        observed=tuple(sorted(i for i in spec.world_ids if i in seen)),
    )


def _scans_with(
    world: World, f: WallSegment | CircleObstacle, poses: np.ndarray, params: ChangeParams
) -> int:
    """Scans of ``poses`` in which ``f``, added to ``world``, is in view."""
    w = World(
        segments=world.segments + ((f,) if isinstance(f, WallSegment) else ()),
        circles=world.circles + ((f,) if isinstance(f, CircleObstacle) else ()),
    )
    return scans_in_view(world_as_map(w), poses, params)[f.id]


def _surveyed(world: World, m: FeatureMove, new_id: int) -> WallSegment | CircleObstacle:
    """A copy, with id ``new_id``, of world feature ``m.id`` where the known map holds
    it: a wall moved by ``(dx, dy)`` and turned by ``dθ`` about its midpoint, a circle
    moved and its radius changed."""
    for s in world.segments:
        if s.id == m.id:
            mid = 0.5 * (np.asarray(s.p1) + np.asarray(s.p2))
            R = np.array(
                [
                    [math.cos(m.dtheta), -math.sin(m.dtheta)],
                    [math.sin(m.dtheta), math.cos(m.dtheta)],
                ]
            )
            p1, p2 = (mid + (m.dx, m.dy) + R @ (np.asarray(p) - mid) for p in (s.p1, s.p2))
            return WallSegment(
                id=new_id, p1=(float(p1[0]), float(p1[1])), p2=(float(p2[0]), float(p2[1]))
            )
    for ci in world.circles:
        if ci.id == m.id:
            centre = (ci.centre[0] + m.dx, ci.centre[1] + m.dy)
            return CircleObstacle(id=new_id, centre=centre, radius=max(ci.radius + m.dr, 1e-3))
    raise KeyError(f"no feature with id {m.id} in the world")


def _original(scenario: Scenario, fid: int) -> tuple[FeatureKind, np.ndarray]:
    """Kind and world parameters of map feature ``fid`` before its move."""
    for f in scenario.known_map.removed:
        if f.id == fid:
            if isinstance(f, WallSegment):
                return FeatureKind.LINE, f.spmap()
            return FeatureKind.CIRCLE, f.params()
    return scenario.world.feature(fid)


@dataclass(frozen=True)
class ChangeScore:
    """Precision and recall of a report against the truth, per change type."""

    moved_tp: int
    """Significant moves (observed) classified moved."""
    moved_fn: int
    """Significant moves (observed) not classified moved."""
    moved_fp: int
    """Unmoved features classified moved."""
    removed_tp: int
    """Removed features in view classified missing."""
    removed_fn: int
    """Removed features in view not classified missing."""
    removed_fp: int
    """Features still in the world classified missing."""
    added_tp: int
    """Added features observed and reported new."""
    added_fn: int
    """Added features observed and not reported new."""
    added_fp: int
    """New features that are not added world features."""
    moved_seen_tp: int = 0
    """Of :attr:`moved_tp`, the moves whose surveyed place came into view
    (:attr:`ChangeTruth.moved_surveyed_in_view`)."""
    moved_seen_fn: int = 0
    """Of :attr:`moved_fn`, the moves whose surveyed place came into view."""
    removed_beyond_view_tp: int = 0
    """Removed features not in view (:attr:`ChangeTruth.removed_in_view`) classified
    missing: right, but outside the recall's population (the raw scans saw through
    a place the extractor's rule does not predict in view)."""

    @staticmethod
    def _pr(tp: int, fp: int, fn: int) -> tuple[float, float]:
        p = tp / (tp + fp) if tp + fp else math.nan
        r = tp / (tp + fn) if tp + fn else math.nan
        return p, r

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form with precision and recall (NaN → None when undefined)."""
        out: dict[str, Any] = {}
        for name in ("moved", "removed", "added"):
            tp, fp, fn = (getattr(self, f"{name}_{s}") for s in ("tp", "fp", "fn"))
            right = tp + (self.removed_beyond_view_tp if name == "removed" else 0)
            p = self._pr(right, fp, 0)[0]
            r = self._pr(tp, 0, fn)[1]
            out[name] = {
                "tp": tp,
                "fp": fp,
                "fn": fn,
                "precision": None if math.isnan(p) else p,
                "recall": None if math.isnan(r) else r,
            }
        out["removed"]["beyond_view_tp"] = self.removed_beyond_view_tp
        tp, fn = self.moved_seen_tp, self.moved_seen_fn
        out["moved_surveyed_in_view"] = {
            "tp": tp,
            "fn": fn,
            "recall": tp / (tp + fn) if tp + fn else None,
        }
        return out


def score_changes(
    report: ChangeReport,
    truth: ChangeTruth,
    min_move_m: float = 0.5,
    min_turn_rad: float = 0.1,
) -> ChangeScore:
    """Score ``report``: moves at least ``min_move_m``/``min_turn_rad`` must be found; a
    smaller true move classified moved counts neither way, and so does a moved feature
    never observed where it went that is classified missing (its surveyed place is
    empty; no observation shows where it went)."""
    mtp = mfn = mfp = rtp = rfn = rfp = rbv = stp = sfn = 0
    removed = set(truth.removed)
    for c in report.known:
        sig = truth.significant_move(c.known_id, min_move_m, min_turn_rad)
        small = c.known_id in truth.moved and not sig
        observed = c.known_id in truth.observed
        seen = c.known_id in truth.moved_surveyed_in_view
        if c.status == ChangeStatus.MOVED:
            if sig:
                mtp += 1
                stp += seen
            elif not small and c.known_id not in removed:
                mfp += 1
        elif sig and observed:
            mfn += 1
            sfn += seen
        if c.status == ChangeStatus.MISSING:
            if c.known_id in truth.removed_in_view:
                rtp += 1
            elif c.known_id in removed:
                rbv += 1
            elif c.known_id not in truth.moved or observed:
                # A feature that moved and was never observed where it went is gone from
                # where the map has it, and missing is what the classes call that.
                rfp += 1
        elif c.known_id in truth.removed_in_view:
            rfn += 1
    new_true = {n.true_id for n in report.new}
    atp = sum(1 for i in truth.added_observed if i in new_true)
    added = set(truth.added)
    afp = sum(1 for n in report.new if n.true_id not in added)
    return ChangeScore(
        moved_tp=mtp,
        moved_fn=mfn,
        moved_fp=mfp,
        removed_tp=rtp,
        removed_fn=rfn,
        removed_fp=rfp,
        added_tp=atp,
        added_fn=len(truth.added_observed) - atp,
        added_fp=afp,
        moved_seen_tp=stp,
        moved_seen_fn=sfn,
        removed_beyond_view_tp=rbv,
    )
