"""Whether a CARMEN log's poses are corrected ones or raw odometry, from what the log
holds (``docs/real-data.md``, "Odometry").

A corrected log (a SLAM benchmark's) has every pose rewritten by a SLAM or scan-matching
run: its poses are a reference trajectory.  A raw log has the robot's own odometry.  The
file name says nothing; four kinds of evidence in the file do, each of which holds for
every message variant (``FLASER``/``RLASER``/``ROBOTLASER1``/``ROBOTLASER2``, with or
without time fields, laser-offset ``PARAM`` lines, ``ODOM`` lines or velocities):

* **pose fields**: every laser message has a laser pose and an odometry pose.  On a robot
  they are one trajectory, a rigid laser offset apart in the robot frame.  When that
  relation changes along the log (beyond the printed digits), the odometry fields hold
  another trajectory than the laser poses: raw odometry.
* **laser offset**: CARMEN's robot module writes the laser pose as the odometry pose
  composed with the ``PARAM`` laser offset.  A log that states a non-zero offset while
  its laser and odometry poses are not that offset apart (whichever way it is applied)
  had its poses written by something else: corrected.
* **velocities**: a robot base reports the velocities it drives at (``ODOM`` ``tv rv``,
  ``ROBOTLASER1`` ``tv rv``).  Poses that move while every velocity is exactly 0 were
  written without them: corrected.  A non-zero velocity says raw.
* **revisits**: a corrected trajectory closes its loops: two scans taken at the same
  place (within 2 m and 45°) after 10 m or more of travel coincide to a few
  centimetres.  Raw odometry drifts by decimetres over that distance, so its scans of
  one place do not coincide.

The log's kind is the one every piece of evidence that speaks names.  When none speaks,
or two disagree, the kind is undecided and the caller must state it
(:class:`UndecidedOdometryError`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from mapfuse_core.data.datasets.carmen_format import CarmenRecords, LaserMessage
from mapfuse_core.data.datasets.common import DatasetError
from mapfuse_core.geometry.se2 import FloatArray, compose, relative, wrap_scalar

__all__ = [
    "Evidence",
    "LogKind",
    "OdometryVerdict",
    "UndecidedOdometryError",
    "judge_odometry",
    "laser_offset",
    "laser_poses_on_odometry",
]

LogKind = Literal["raw", "corrected"]
EvidenceName = Literal["pose fields", "laser offset", "velocities", "revisits"]

REVISIT_MIN_PATH_M = 10.0
"""Travel between two scans of one place for them to count as a revisit (m): raw
wheel odometry drifts by 1–5 % of the distance and a few degrees over it."""
REVISIT_MAX_GAP_M = 2.0
"""Largest distance between the two poses of a revisit (m): the scans then see mostly
the same walls, and the distance to the other scan's outline (not to its returns) does
not grow with the change of viewpoint."""
REVISIT_MAX_TURN_RAD = math.radians(45.0)
"""Largest heading difference between the two poses of a revisit (rad)."""
REVISIT_MAX_RANGE_M = 8.0
"""Returns used to compare two scans (m): nearer ones, where consecutive returns of a
wall are close enough (≤ 14 cm at 1°) to stand for the wall."""
REVISIT_LINK_M = 0.3
"""Two consecutive returns closer than this (m) are joined by a segment (the wall
between them); farther apart, they are separate points."""
REVISIT_MIN_PAIRS = 3
"""Revisits needed for the evidence to speak."""
REVISIT_CONSISTENT_M = 0.10
"""Median distance (m) of one scan's returns to the other's outline at or below which
revisits coincide: a trajectory good to a few centimetres, with rough walls and a
beam's footprint."""
REVISIT_INCONSISTENT_M = 0.25
"""Median distance (m) at or above which revisits do not coincide: the decimetres of
raw odometry's drift.  Between the two the evidence is silent."""
_MIN_RETURNS = 20
"""Returns a scan needs within :data:`REVISIT_MAX_RANGE_M` to be compared."""


@dataclass(frozen=True)
class Evidence:
    """What one kind of evidence in a log says."""

    name: EvidenceName
    """Which evidence."""
    says: LogKind | None
    """The kind it points to; ``None``: it does not speak."""
    detail: str
    """What was found, in words."""


@dataclass(frozen=True)
class OdometryVerdict:
    """The kind of a CARMEN log as decided from its evidence."""

    kind: LogKind | None
    """``"corrected"`` or ``"raw"``; ``None`` when undecided."""
    evidence: tuple[Evidence, ...]
    """Every piece of evidence, in a fixed order."""
    mounting: FloatArray | None
    """(3,) the laser pose in the robot frame shared by every laser message, when the
    pose fields are one rigid trajectory; ``None`` when their relation changes."""

    def summary(self) -> str:
        """The evidence in one line: ``name: detail`` items separated by ``; ``."""
        return "; ".join(f"{e.name}: {e.detail}" for e in self.evidence)


class UndecidedOdometryError(DatasetError):
    """The log's evidence does not decide between corrected and raw.  Attributes:
    ``path`` (the log), ``verdict`` (its evidence), ``reason`` (why, in words)."""

    def __init__(self, path: object, verdict: OdometryVerdict) -> None:
        self.path = path
        self.verdict = verdict
        speaking = [e for e in verdict.evidence if e.says is not None]
        self.reason = (
            "its evidence disagrees"
            if speaking
            else "no evidence in it tells a corrected log from raw odometry"
        )
        super().__init__(f"{self.question()}; state it: odometry raw or corrected")

    def question(self) -> str:
        """The problem without the remedy: the log, why, and its evidence."""
        return (
            f"{self.path}: cannot tell whether the poses are corrected or raw odometry: "
            f"{self.reason} ({self.verdict.summary()})"
        )


def laser_offset(rec: CarmenRecords, *, rear: bool = False) -> FloatArray | None:
    """The laser pose on the robot stated by the ``PARAM`` messages
    (``robot_frontlaser_offset``, ``…_side_offset``, ``…_angular_offset``, or the
    ``rearlaser`` ones), ``None`` when none is stated."""
    which = "rearlaser" if rear else "frontlaser"
    names = (f"robot_{which}_offset", f"robot_{which}_side_offset", f"robot_{which}_angular_offset")
    if not any(n in rec.params for n in names):
        return None
    out = np.zeros(3)
    for i, name in enumerate(names):
        if name in rec.params:
            try:
                out[i] = float(rec.params[name])
            except ValueError:
                raise DatasetError(
                    f"{rec.path}: PARAM {name} is not a number: {rec.params[name]!r}"
                ) from None
            if not math.isfinite(out[i]):
                raise DatasetError(f"{rec.path}: PARAM {name} is not finite")
    return out


def _tolerance(msg: LaserMessage, mounting: FloatArray) -> tuple[float, float]:
    """How far (m, rad) the relation of ``msg``'s two printed poses may be from
    ``mounting`` through printing alone: each printed coordinate is off by up to half
    its last digit, a float32 value by a few parts in 10⁷."""
    scale = float(np.max(np.abs(np.concatenate([msg.laser_pose[:2], msg.robot_pose[:2]]))))
    res = msg.pose_resolution + 1e-6 * scale + 1e-9
    lever = math.hypot(float(mounting[0]), float(mounting[1]))
    return 3.0 * res + lever * res, 2.0 * msg.pose_resolution + 1e-7


def _relation(msg: LaserMessage) -> FloatArray:
    """The laser pose in the frame of the message's odometry pose."""
    out: FloatArray = relative(msg.robot_pose, msg.laser_pose)[0]
    return out


def _off(rel: FloatArray, mounting: FloatArray, msg: LaserMessage) -> bool:
    tol_xy, tol_th = _tolerance(msg, mounting)
    d = rel - mounting
    return math.hypot(float(d[0]), float(d[1])) > tol_xy or abs(wrap_scalar(float(d[2]))) > tol_th


def _pose_fields(rec: CarmenRecords) -> tuple[Evidence, FloatArray | None]:
    rels = np.array([_relation(m) for m in rec.lasers])
    mounting = np.median(rels, axis=0)
    # The median heading about the first one's, so that headings near ±π (a rear
    # laser looking backwards) do not average to 0.
    turn = np.array([wrap_scalar(float(a)) for a in rels[:, 2] - rels[0, 2]])
    mounting[2] = wrap_scalar(float(rels[0, 2] + np.median(turn)))
    off = sum(_off(r, mounting, m) for r, m in zip(rels, rec.lasers, strict=True))
    n = len(rec.lasers)
    where = f"({mounting[0]:+.3f} m, {mounting[1]:+.3f} m, {math.degrees(mounting[2]):+.2f}°)"
    if off == 0:
        return Evidence("pose fields", None, f"one trajectory, the laser at {where}"), mounting
    if 2 * off > n:
        detail = f"odometry drifts from the laser pose in {off} of {n} laser messages"
        return Evidence("pose fields", "raw", detail), None
    detail = f"odometry off the laser pose in {off} of {n} laser messages only"
    return Evidence("pose fields", None, detail), None


def _applied(mounting: FloatArray, stated: FloatArray, msg: LaserMessage) -> bool:
    """Whether the pose fields' relation is the stated offset, whichever way it is
    applied: the same lever length, and the stated angular offset either way round
    (turned by a half turn for a rear laser, which looks backwards)."""
    tol_xy, tol_th = _tolerance(msg, stated)
    lever = math.hypot(float(mounting[0]), float(mounting[1]))
    if abs(lever - math.hypot(float(stated[0]), float(stated[1]))) > tol_xy:
        return False
    turns = (0.0, math.pi) if msg.rear else (0.0,)
    return any(
        abs(wrap_scalar(float(mounting[2]) - sign * float(stated[2]) - turn)) <= tol_th
        for sign in (1.0, -1.0)
        for turn in turns
    )


def _stated_offset(rec: CarmenRecords, mounting: FloatArray | None) -> Evidence:
    stated = laser_offset(rec, rear=rec.lasers[0].rear)
    if stated is None:
        return Evidence("laser offset", None, "none stated")
    text = f"PARAM offset ({stated[0]:+g} m, {stated[1]:+g} m, {stated[2]:+g} rad)"
    if mounting is None:
        return Evidence("laser offset", None, f"{text}; the pose fields are not rigid")
    if not np.any(stated):
        return Evidence("laser offset", None, f"{text}: zero")
    if _applied(mounting, stated, rec.lasers[0]):
        return Evidence("laser offset", None, f"{text}, applied between the pose fields")
    return Evidence("laser offset", "corrected", f"{text}, not applied between the pose fields")


def _moves(rec: CarmenRecords) -> bool:
    poses = np.array([m.robot_pose for m in rec.lasers])
    res = max(m.pose_resolution for m in rec.lasers)
    span = np.ptp(poses[:, :2], axis=0)
    return bool(np.hypot(span[0], span[1]) > 10.0 * res + 1e-6)


def _velocities(rec: CarmenRecords) -> Evidence:
    v = [(o.tv, o.rv) for o in rec.odometry]
    v += [(m.tv, m.rv) for m in rec.lasers if math.isfinite(m.tv)]
    if not v:
        return Evidence("velocities", None, "no message carries velocities")
    nonzero = sum(tv != 0.0 or rv != 0.0 for tv, rv in v)
    if nonzero:
        return Evidence("velocities", "raw", f"{nonzero} of {len(v)} messages report a velocity")
    if not _moves(rec):
        return Evidence("velocities", None, "all 0, and the robot does not move")
    return Evidence("velocities", "corrected", f"all {len(v)} are 0 while the poses move")


class _Outline:
    """One scan in the world frame: its near returns, and segments between consecutive
    returns of one surface."""

    def __init__(self, msg: LaserMessage, pose: FloatArray) -> None:
        r = msg.ranges
        b = msg.start_angle + msg.angular_resolution * np.arange(r.shape[0])
        ok = (r > 0.0) & (r < REVISIT_MAX_RANGE_M)
        local = np.c_[r * np.cos(b), r * np.sin(b)]
        c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
        self.points = pose[:2] + local @ np.array([[c, s], [-s, c]])
        self.index = np.flatnonzero(ok)
        gaps = np.hypot(*(self.points[1:] - self.points[:-1]).T)
        self.joined = ok[:-1] & ok[1:] & (gaps < REVISIT_LINK_M)
        self.tree = cKDTree(self.points[self.index]) if self.index.size >= _MIN_RETURNS else None

    def distance(self, q: FloatArray) -> FloatArray:
        """Distance of every point of ``q`` to this outline (nearest return, or the
        segment on either side of it)."""
        assert self.tree is not None
        _, j = self.tree.query(q)
        i = self.index[j]
        best: FloatArray = np.hypot(*(q - self.points[i]).T)
        last = self.points.shape[0] - 1
        for a in (np.maximum(i - 1, 0), i):
            b = np.minimum(a + 1, last)
            valid = self.joined[np.minimum(a, last - 1)] & (b > a)
            pa, pb = self.points[a], self.points[b]
            ab = pb - pa
            t = np.clip(np.sum((q - pa) * ab, axis=1) / (np.sum(ab * ab, axis=1) + 1e-12), 0, 1)
            d = np.hypot(*(q - pa - t[:, None] * ab).T)
            best = np.where(valid, np.minimum(best, d), best)
        return best


def _revisit_pairs(poses: FloatArray) -> list[tuple[int, int]]:
    """``(k, j)``: for every scan ``k``, the nearest earlier scan ``j`` at the same place
    and heading with at least :data:`REVISIT_MIN_PATH_M` travelled between them."""
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    tree = cKDTree(poses[:, :2])
    pairs: list[tuple[int, int]] = []
    for k in range(poses.shape[0]):
        near = [
            j
            for j in tree.query_ball_point(poses[k, :2], REVISIT_MAX_GAP_M)
            if path[k] - path[j] >= REVISIT_MIN_PATH_M
            and abs(wrap_scalar(float(poses[k, 2] - poses[j, 2]))) <= REVISIT_MAX_TURN_RAD
        ]
        if near:
            pairs.append(
                (k, min(near, key=lambda j: float(np.hypot(*(poses[k, :2] - poses[j, :2])))))
            )
    return pairs


def _revisits(rec: CarmenRecords) -> Evidence:
    poses = np.array([m.laser_pose for m in rec.lasers])
    outlines: dict[int, _Outline] = {}

    def outline(i: int) -> _Outline:
        if i not in outlines:
            outlines[i] = _Outline(rec.lasers[i], poses[i])
        return outlines[i]

    residuals = []
    for k, j in _revisit_pairs(poses):
        a, b = outline(k), outline(j)
        if a.tree is not None and b.tree is not None:
            residuals.append(float(np.median(b.distance(a.points[a.index]))))
    n = len(residuals)
    if n < REVISIT_MIN_PAIRS:
        return Evidence("revisits", None, f"{n} revisited places, too few to judge")
    med = float(np.median(residuals))
    detail = f"scans of {n} revisited places {{}} (median {100.0 * med:.1f} cm)"
    if med <= REVISIT_CONSISTENT_M:
        return Evidence("revisits", "corrected", detail.format("coincide"))
    if med >= REVISIT_INCONSISTENT_M:
        return Evidence("revisits", "raw", detail.format("do not coincide"))
    return Evidence("revisits", None, detail.format("neither coincide nor clearly differ"))


def judge_odometry(rec: CarmenRecords) -> OdometryVerdict:
    """The kind of ``rec``'s poses, from its evidence (module docstring)."""
    fields, mounting = _pose_fields(rec)
    evidence = (fields, _stated_offset(rec, mounting), _velocities(rec), _revisits(rec))
    said = {e.says for e in evidence if e.says is not None}
    kind: LogKind | None = said.pop() if len(said) == 1 else None
    return OdometryVerdict(kind=kind, evidence=evidence, mounting=mounting)


def laser_poses_on_odometry(rec: CarmenRecords, verdict: OdometryVerdict) -> FloatArray:
    """(N, 3) the laser poses the odometry fields give: the written laser poses when the
    pose fields are one rigid trajectory, else every odometry pose composed with the
    stated laser offset (zero when none is stated)."""
    if verdict.mounting is not None:
        return np.array([m.laser_pose for m in rec.lasers])
    stated = laser_offset(rec, rear=rec.lasers[0].rear)
    offset = np.zeros(3) if stated is None else stated
    return np.array([compose(m.robot_pose, offset) for m in rec.lasers])
