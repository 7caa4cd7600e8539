"""A CARMEN laser log as a measurement log of wall lines (``docs/real-data.md``).

One step per laser scan (``FLASER``, ``ROBOTLASER1``, or the rear laser's ``RLASER``,
``ROBOTLASER2`` in a log without front laser messages).  The log's frame ``R`` of a
step is the **laser** frame (as for the other datasets): odometry increments are those
of the laser pose, features are extracted in it.  Two kinds of log, stated in
:attr:`CarmenOptions.odometry` or decided from the log's evidence
(:mod:`~mapfuse_core.data.datasets.carmen_kind`):

* **raw**: the odometry fields are the robot's own odometry; increments come from
  them, with the covariance of :class:`IncrementNoise`; no reference trajectory.
* **corrected** (the SLAM benchmark's logs): the laser poses are corrected ones.  They
  become the log's ``true_poses`` (the reference trajectory) and the odometry is
  simulated from the reference increments with :class:`IncrementNoise` and a seed;
  ``metadata["odometry"]`` says ``simulated from reference``.

The laser's beam geometry and maximum range come from the log (``ROBOTLASER1``
fields, ``PARAM robot_front_laser_max``, CARMEN's beam-count convention for
``FLASER`` and ``RLASER``); its noise (σρ, σβ) from :class:`CarmenOptions`, stated defaults for a
SICK LMS, never from the file name.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from mapfuse_core.data.datasets.carmen_format import CarmenRecords, LaserMessage, read_carmen
from mapfuse_core.data.datasets.carmen_kind import (
    LogKind,
    OdometryVerdict,
    UndecidedOdometryError,
    judge_odometry,
    laser_poses_on_odometry,
)
from mapfuse_core.data.datasets.common import (
    DatasetError,
    check_choice,
    check_finite,
    empty_map,
)
from mapfuse_core.data.datasets.line_noise import (
    LineModelShape,
    LineTerms,
    estimate_line_model_error,
    with_line_model_error,
)
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, relative, wrap_scalar
from mapfuse_core.matching import AssociationConfig
from mapfuse_core.matching.ccda import CCDAParams
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.perception.extraction import ExtractionParams, extract_features
from mapfuse_core.sensor import LaserParams, Scan

__all__ = [
    "CarmenOptions",
    "IncrementNoise",
    "carmen_association",
    "carmen_scans",
    "carmen_view_laser",
    "detect_odometry_kind",
    "load_carmen",
    "redraw_odometry",
]

OdometryKind = Literal["auto", "raw", "corrected"]

LineModelErrorSource = Literal["correlated", "independent", "profile"]
"""Where a CARMEN log's line model-error terms come from
(:attr:`CarmenOptions.line_model_error`)."""

LineModelGate = Literal["weight", "alone"]
"""Which line terms the association gates take (:attr:`CarmenOptions.line_model_gate`)."""

_DEFAULT_MAX_RANGE_M = 80.0
"""Maximum range when the log states none (m): the SICK LMS 2xx's 80 m.  Its
no-return codes are written just above it (81.83 m, 81.91 m)."""


@dataclass(frozen=True)
class IncrementNoise:
    """Covariance of an odometry increment ``(dx, dy, dθ)`` of a wheeled indoor robot.

    Independent errors with ``σx = σy = trans_frac · d + trans_floor_m`` and
    ``σθ = rot_frac · |dθ| + rot_per_m · d + rot_floor_rad`` (``d`` the distance
    travelled).  The defaults (5 % of the distance, 5 % of the turn, 0.6°/m of drift)
    are those of a differential-drive base on office floors (``docs/real-data.md``).
    """

    trans_frac: float = 0.05
    """σ of each position component per metre travelled."""
    trans_floor_m: float = 0.005
    """σ (m) of each position component of any increment (wheel quantisation, slip)."""
    rot_frac: float = 0.05
    """σ of the heading change per radian turned."""
    rot_per_m: float = math.radians(0.6)
    """σ (rad) of the heading change per metre travelled (wheel-base uncertainty)."""
    rot_floor_rad: float = math.radians(0.2)
    """σ (rad) of the heading change of any increment."""

    def __post_init__(self) -> None:
        for name in ("trans_frac", "rot_frac", "rot_per_m"):
            check_finite("IncrementNoise", name, getattr(self, name), positive=False)
        for name in ("trans_floor_m", "rot_floor_rad"):
            check_finite("IncrementNoise", name, getattr(self, name), positive=True)

    def cov(self, inc: FloatArray) -> FloatArray:
        """(3, 3) covariance of the increment ``inc``."""
        d = math.hypot(float(inc[0]), float(inc[1]))
        s_xy = self.trans_frac * d + self.trans_floor_m
        s_th = self.rot_frac * abs(float(inc[2])) + self.rot_per_m * d + self.rot_floor_rad
        return np.diag([s_xy * s_xy, s_xy * s_xy, s_th * s_th])


@dataclass(frozen=True)
class CarmenOptions:
    """How :func:`load_carmen` turns a CARMEN log into a measurement log."""

    odometry: OdometryKind = "auto"
    """``"raw"``: increments from the log's odometry fields.  ``"corrected"``: the log's
    laser poses are the reference trajectory, odometry is simulated from it.
    ``"auto"``: decided from the log's evidence (:func:`detect_odometry_kind`), an
    :class:`~mapfuse_core.data.datasets.carmen_kind.UndecidedOdometryError` error when it
    does not decide."""
    seed: int = 0
    """Seed of the simulated odometry noise (unused for raw odometry)."""
    odometry_noise: IncrementNoise = field(default_factory=IncrementNoise)
    """Odometry error model: the covariance of every increment, and with simulated
    odometry also the distribution the noise is drawn from."""
    sigma_range_m: float = 0.01
    """σρ of one range (m): a SICK LMS 2xx's statistical error (5 mm at indoor ranges)
    plus the 1 cm resolution of the logged ranges, rounded up."""
    sigma_bearing_rad: float = math.radians(0.05)
    """σβ of a beam's pointing (rad); small against the 0.5°–1° beam spacing."""
    max_range_m: float | None = None
    """Maximum range (m); ``None``: the message's own (``ROBOTLASER1``/``2``), else
    ``PARAM robot_front_laser_max`` (``robot_rear_laser_max`` for the rear laser), else
    80 m.  Readings at or above it, or ≤ 0, are no return."""
    extraction: ExtractionParams = field(default_factory=ExtractionParams.indoor_sick)
    """Extraction thresholds (:meth:`ExtractionParams.indoor_sick`)."""
    line_model_error: LineModelErrorSource = "profile"
    """Where the line model-error terms come from.  ``"profile"``: :attr:`extraction`'s
    terms on every log.  ``"correlated"`` and
    ``"independent"``: a log with a reference trajectory gets terms estimated from its
    own scans against its floor plan
    (:func:`~mapfuse_core.data.datasets.line_noise.estimate_line_model_error`), in place
    of :attr:`extraction`'s ``line_model_sigma_m`` / ``line_model_sigma_rad``;
    ``"correlated"`` counts the correlation of consecutive scans (each observation worth
    ``1/τ``), ``"independent"`` whitens each observation to 1.  A log without a
    reference (raw odometry), or with too few observations on its plan, keeps
    :attr:`extraction`'s.  The estimates are not the default: with them and the plan
    every estimator's ANEES is at most 6 on four of the seven logs (two with the
    profile's terms), but FHW's larger angle term breaks its runs
    (``docs/results/carmen.md``).  The log's metadata
    (``line_model_error``) says which were used."""
    line_model_gate: LineModelGate = "weight"
    """Which line terms the association gates take with ``line_model_error="correlated"``:
    ``"weight"`` those the updates weigh each observation with, ``"alone"`` those of
    each observation's error alone.  ``"weight"``: each observation worth ``1/τ``.
    ``"alone"``: the terms that whiten each observation to 1
    (:attr:`~mapfuse_core.data.datasets.line_noise.LineModelError.gate_sigma_m`), how
    far one observation strays from its wall, as the log's gate covariances
    (:attr:`~mapfuse_core.measlog.MeasurementLog.feat_gate_cov`).  Not the default:
    with the match's joint test it mends FHW and worsens Seattle, where the narrower
    gates start duplicate landmarks of walls already mapped and two runs of eight never
    anchor (``docs/results/carmen.md``).  A log that keeps the profile's terms (too few
    observations on its plan) has no gate covariances of its own."""
    line_model_shape: LineModelShape = "constant"
    """How the estimated σ on a line's ``ρ`` varies with ``line_model_error``
    ``"correlated"`` or ``"independent"``: ``"constant"`` one σ for every line,
    ``"length"`` a constant part plus one falling as ``1/L`` with the segment's length
    (:class:`~mapfuse_core.data.datasets.line_noise.LineTerms`), split by maximum
    likelihood on the log's residuals (no ``1/L`` part where they give too little
    evidence for one: Acapulco, Freiburg and Intel).  Short pieces of wall stray from the plan
    several times farther than long ones on six logs of seven.  Not the default: with
    ``line_model_gate="alone"`` and the match's joint test every estimator's ANEES is
    at most 6 with the plan on five logs of seven (Seattle and FHW both, which one σ
    does not give), but one CSAIL run of eight pairs a short unlabelled segment with
    a landmark of another and ends far off (``docs/results/carmen.md``)."""
    extraction_max_range_m: float = 20.0
    """Returns farther than this (m) are not used for features: beyond it a 1° beam
    footprint is over 35 cm and indoor walls are seen through doors and glass."""
    keep_scans: bool = True
    """Keep the raw scans in the log (``scan_bearings``/``scan_ranges``, every return
    up to the maximum range), for the free-space evidence of change detection.  Kept
    only when every laser message has the same beams; the log's metadata says why
    not otherwise."""

    def __post_init__(self) -> None:
        check_choice("CarmenOptions", "odometry", self.odometry, get_args(OdometryKind))
        _check_seed("CarmenOptions.seed", self.seed)
        for name in ("sigma_range_m", "sigma_bearing_rad", "extraction_max_range_m"):
            check_finite("CarmenOptions", name, getattr(self, name), positive=True)
        if self.max_range_m is not None:
            check_finite("CarmenOptions", "max_range_m", self.max_range_m, positive=True)
        if not isinstance(self.odometry_noise, IncrementNoise):
            raise ValueError("CarmenOptions.odometry_noise must be an IncrementNoise")
        if not isinstance(self.extraction, ExtractionParams):
            raise ValueError("CarmenOptions.extraction must be an ExtractionParams")
        if not isinstance(self.keep_scans, bool):
            raise ValueError(f"CarmenOptions.keep_scans must be a bool, got {self.keep_scans!r}")
        for name, kind in (
            ("line_model_error", LineModelErrorSource),
            ("line_model_gate", LineModelGate),
            ("line_model_shape", LineModelShape),
        ):
            check_choice("CarmenOptions", name, getattr(self, name), get_args(kind))
        if self.line_model_gate == "alone" and self.line_model_error != "correlated":
            raise ValueError(
                "CarmenOptions.line_model_gate='alone' needs line_model_error='correlated' "
                f"(with {self.line_model_error!r} the gates and the updates take the same terms)"
            )
        if self.line_model_shape == "length" and self.line_model_error == "profile":
            raise ValueError(
                "CarmenOptions.line_model_shape='length' needs line_model_error "
                "'correlated' or 'independent' (the profile's terms are one σ for every line)"
            )


def detect_odometry_kind(rec: CarmenRecords) -> LogKind:
    """``"corrected"`` or ``"raw"`` as the log's evidence decides
    (:func:`~mapfuse_core.data.datasets.carmen_kind.judge_odometry`); an
    :class:`~mapfuse_core.data.datasets.carmen_kind.UndecidedOdometryError` error naming the
    evidence when it does not decide."""
    verdict = judge_odometry(rec)
    if verdict.kind is None:
        raise UndecidedOdometryError(rec.path, verdict)
    return verdict.kind


def _kind(rec: CarmenRecords, stated: OdometryKind) -> tuple[LogKind, OdometryVerdict, str]:
    """The kind to load ``rec`` as, the verdict of its evidence, and how the kind was
    chosen (for the metadata)."""
    verdict = judge_odometry(rec)
    if stated != "auto":
        found = verdict.kind or "undecided"
        return stated, verdict, f"{stated}: stated (the evidence says {found})"
    if verdict.kind is None:
        raise UndecidedOdometryError(rec.path, verdict)
    return verdict.kind, verdict, f"{verdict.kind}: detected"


def _max_range(rec: CarmenRecords, msg: LaserMessage, opts: CarmenOptions) -> float:
    if opts.max_range_m is not None:
        return opts.max_range_m
    name = "robot_rear_laser_max" if msg.rear else "robot_front_laser_max"
    if name in rec.params and not math.isfinite(msg.max_range):
        try:
            v = float(rec.params[name])
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and v > 0.0):
            raise DatasetError(f"{rec.path}: PARAM {name} is not a range > 0: {rec.params[name]!r}")
        return v
    if math.isfinite(msg.max_range):
        return msg.max_range
    return _DEFAULT_MAX_RANGE_M


def _returns(rec: CarmenRecords, msg: LaserMessage, opts: CarmenOptions) -> FloatArray:
    """``msg``'s ranges with every no-return reading (at or beyond the maximum range,
    not positive, not finite) as ``inf``."""
    r = msg.ranges
    max_r = _max_range(rec, msg, opts)
    out: FloatArray = np.where((r <= 0.0) | (r >= max_r) | ~np.isfinite(r), np.inf, r)
    return out


def _bearings(msg: LaserMessage) -> FloatArray:
    n = msg.ranges.shape[0]
    out: FloatArray = msg.start_angle + msg.angular_resolution * np.arange(n, dtype=np.float64)
    return out


def _laser(n: int, span_rad: float, max_range_m: float, opts: CarmenOptions) -> LaserParams:
    return LaserParams(
        fov_rad=min(abs(span_rad), 2.0 * math.pi),
        max_range_m=max_range_m,
        n_beams=n,
        sigma_range_m=opts.sigma_range_m,
        sigma_bearing_rad=opts.sigma_bearing_rad,
    )


def carmen_scans(rec: CarmenRecords, opts: CarmenOptions) -> list[tuple[Scan, LaserParams]]:
    """Every laser message as a :class:`Scan` (no return: ``inf``) and its laser model."""
    out: list[tuple[Scan, LaserParams]] = []
    for msg in rec.lasers:
        n = msg.ranges.shape[0]
        r = _returns(rec, msg, opts)
        ranges = np.where(r > opts.extraction_max_range_m, np.inf, r)
        laser = _laser(n, msg.angular_resolution * (n - 1), _max_range(rec, msg, opts), opts)
        out.append((Scan(_bearings(msg), ranges, np.full(n, -1, dtype=np.int64)), laser))
    return out


def carmen_view_laser(scan_bearings: FloatArray, opts: CarmenOptions | None = None) -> LaserParams:
    """The laser model that predicts what the extractor sees in a CARMEN log kept with
    its raw scans: the scans' beams, up to ``extraction_max_range_m`` (no feature is
    taken from farther returns)."""
    opts = opts or CarmenOptions()
    b = np.asarray(scan_bearings, dtype=float)
    if b.ndim != 1 or b.shape[0] < 2:
        raise ValueError(f"the scan bearings must be (B,) with B >= 2, got shape {b.shape}")
    return _laser(int(b.shape[0]), float(b[-1] - b[0]), opts.extraction_max_range_m, opts)


def raw_scans(rec: CarmenRecords, opts: CarmenOptions) -> tuple[FloatArray, np.ndarray] | str:
    """Every laser message's ranges as one (N, B) float32 array (no return: ``inf``;
    returns beyond ``extraction_max_range_m`` kept) with their (B,) increasing
    bearings, or why that cannot be: the messages' beams differ, or a bearing is
    outside ±π."""
    if not rec.lasers:
        return "the log has no laser message"
    first = rec.lasers[0]
    n = first.ranges.shape[0]
    for k, msg in enumerate(rec.lasers):
        if msg.ranges.shape[0] != n or not (
            math.isclose(msg.start_angle, first.start_angle, abs_tol=1e-9)
            and math.isclose(msg.angular_resolution, first.angular_resolution, abs_tol=1e-12)
        ):
            return f"laser message {k} has other beams than the first"
    flip = n > 1 and first.angular_resolution < 0.0
    bearings = _bearings(first)[::-1].copy() if flip else _bearings(first)
    if np.any(np.abs(bearings) > math.pi) or np.any(np.diff(bearings) <= 0.0):
        return "the beams' bearings are not increasing within ±π"
    ranges = np.empty((len(rec.lasers), n), dtype=np.float32)
    for k, msg in enumerate(rec.lasers):
        r = _returns(rec, msg, opts)
        ranges[k] = r[::-1] if flip else r
    return bearings, ranges


def _increments(poses: FloatArray) -> FloatArray:
    inc = np.zeros_like(poses)
    for k in range(1, poses.shape[0]):
        inc[k] = relative(poses[k - 1], poses[k])[0]
    return inc


def _check_seed(name: str, seed: object) -> None:
    """A :class:`ValueError` naming ``name`` unless ``seed`` is an int ≥ 0 (a seed of
    :func:`numpy.random.default_rng`)."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"{name} must be an int, got {seed!r}")
    if seed < 0:
        raise ValueError(f"{name} must be >= 0, got {seed}")


_SIMULATED = "simulated from reference"
"""``metadata["odometry"]`` of a log whose odometry is drawn from its reference."""


def _simulated_odometry(
    true_poses: FloatArray, noise: IncrementNoise, seed: int
) -> tuple[FloatArray, FloatArray]:
    """Odometry increments drawn around the reference increments of ``true_poses`` with
    ``noise``'s covariance, and that covariance; row 0 (no increment) is zero."""
    n = true_poses.shape[0]
    ref_inc = _increments(true_poses)
    rng = np.random.default_rng(seed)
    odometry = np.zeros((n, 3))
    odometry_cov = np.zeros((n, 3, 3))
    for k in range(1, n):
        odometry_cov[k] = noise.cov(ref_inc[k])
        drawn = rng.standard_normal(3) * np.sqrt(np.diag(odometry_cov[k]))
        odometry[k] = ref_inc[k] + drawn
        odometry[k, 2] = wrap_scalar(float(odometry[k, 2]))
    return odometry, odometry_cov


def redraw_odometry(
    log: MeasurementLog, seed: int, noise: IncrementNoise | None = None
) -> MeasurementLog:
    """``log`` (a corrected CARMEN log as :func:`load_carmen` reads it) with its
    simulated odometry drawn again with ``seed`` and ``noise``: equal to loading the
    file again with that seed and noise, without reading the file or extracting its
    lines again.  ``noise`` defaults to :class:`IncrementNoise`'s defaults: the log does
    not record the model it was drawn with, so a log loaded with another one needs it
    given here.

    Everything but the odometry, its covariance, ``seed`` and
    ``metadata["odometry_seed"]`` is ``log``'s own (its known map and labels included).
    A log whose odometry is not simulated from its reference is a :class:`ValueError`.
    """
    _check_seed("redraw_odometry: seed", seed)
    if log.true_poses is None or log.metadata.get("odometry") != _SIMULATED:
        said = log.metadata.get("odometry", "not stated")
        raise ValueError(
            f"redraw_odometry needs a log whose odometry is simulated from its reference "
            f"trajectory; {log.scenario!r} has odometry {said!r}"
        )
    odometry, odometry_cov = _simulated_odometry(
        log.true_poses, IncrementNoise() if noise is None else noise, seed
    )
    return replace(
        log,
        seed=seed,
        odometry=odometry,
        odometry_cov=odometry_cov,
        metadata={**log.metadata, "odometry_seed": str(seed)},
    )


def load_carmen(
    path: str | Path,
    *,
    options: CarmenOptions | None = None,
    known_map: KnownMapArrays | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> MeasurementLog:
    """The CARMEN log at ``path`` (plain or gzipped) as a measurement log of lines.

    ``known_map`` (e.g. :func:`~mapfuse_core.data.datasets.floorplan.build_floor_plan`'s,
    in the reference frame) becomes the log's known map; none by default.
    ``progress(k, n)`` is called after the features of each of the ``n`` scans are
    extracted (the slow part).
    """
    opts = CarmenOptions() if options is None else options
    rec = read_carmen(path)
    kind, verdict, chosen = _kind(rec, opts.odometry)
    n = len(rec.lasers)

    raw_t = np.array([m.timestamp for m in rec.lasers])
    t = np.maximum.accumulate(raw_t - raw_t[0])
    metadata = {
        "source": str(Path(path).name),
        "format": "CARMEN",
        "laser_messages": ", ".join(
            f"{k}: {c}" for k, c in sorted(Counter(m.kind for m in rec.lasers).items())
        ),
        "skipped_messages": ", ".join(f"{k}: {v}" for k, v in rec.skipped.items()) or "none",
        "timestamps_held": str(int(np.count_nonzero(np.diff(raw_t) < 0))),
        "log_kind": chosen,
        "log_kind_evidence": verdict.summary(),
    }
    true_poses: FloatArray | None
    if kind == "corrected":
        true_poses = np.array([m.laser_pose for m in rec.lasers])
        odometry, odometry_cov = _simulated_odometry(true_poses, opts.odometry_noise, opts.seed)
        metadata["odometry"] = _SIMULATED
        metadata["odometry_seed"] = str(opts.seed)
    else:
        true_poses = None
        odometry = _increments(laser_poses_on_odometry(rec, verdict))
        odometry_cov = np.zeros((n, 3, 3))
        for k in range(1, n):
            odometry_cov[k] = opts.odometry_noise.cov(odometry[k])
        metadata["odometry"] = "raw"

    estimate = opts.line_model_error != "profile" and kind == "corrected"
    extraction = opts.extraction
    if estimate:
        # Fitted covariances alone: the terms are estimated on them, then added.
        extraction = replace(extraction, line_model_sigma_m=0.0, line_model_sigma_rad=0.0)
    steps: list[int] = []
    params: list[FloatArray] = []
    covs: list[FloatArray] = []
    npts: list[int] = []
    extents: list[tuple[float, float]] = []
    rejected: dict[str, int] = {}
    for k, (scan, laser) in enumerate(carmen_scans(rec, opts)):
        res = extract_features(scan, laser, extraction)
        if progress is not None:
            progress(k + 1, n)
        for key, c in res.rejected.items():
            rejected[key] = rejected.get(key, 0) + c
        for f in res.features:
            steps.append(k)
            params.append(f.params)
            covs.append(f.cov)
            npts.append(f.n_points)
            extents.append(f.extent)
    m = len(steps)
    kinds = np.full(m, int(FeatureKind.LINE), dtype=np.int8)
    scans = raw_scans(rec, opts) if opts.keep_scans else "not asked for (keep_scans)"
    if isinstance(scans, str):
        metadata["raw_scans"] = f"not kept: {scans}"
        scan_bearings, scan_ranges = None, None
    else:
        metadata["raw_scans"] = f"{scans[1].shape[0]} x {scans[1].shape[1]} beams"
        scan_bearings, scan_ranges = scans
    log = MeasurementLog(
        scenario=f"carmen:{Path(path).name}",
        seed=opts.seed if kind == "corrected" else -1,
        timestamps=t,
        odometry=odometry,
        odometry_cov=odometry_cov,
        feat_step=np.asarray(steps, dtype=np.int64).reshape(m),
        feat_kind=kinds,
        feat_params=np.asarray(params, dtype=np.float64).reshape(m, 3),
        feat_cov=np.asarray(covs, dtype=np.float64).reshape(m, 3, 3),
        feat_true_id=np.full(m, -1, dtype=np.int64),
        feat_n_points=np.asarray(npts, dtype=np.int64).reshape(m),
        feat_extent=np.asarray(extents, dtype=np.float64).reshape(m, 2),
        known_map=empty_map() if known_map is None else known_map,
        true_poses=true_poses,
        rejected=dict(sorted(rejected.items())),
        metadata=metadata,
        scan_bearings=scan_bearings,
        scan_ranges=scan_ranges,
    )
    if not estimate:
        return _profile_terms(log, opts)
    return _estimated_terms(log, opts)


def _profile_terms(log: MeasurementLog, opts: CarmenOptions) -> MeasurementLog:
    """``log`` (extracted with ``opts.extraction``'s terms) with the metadata saying so."""
    why = "as asked" if opts.line_model_error == "profile" else "the log has no reference"
    return _noted(log, opts.extraction, why)


def _noted(log: MeasurementLog, e: ExtractionParams, why: str) -> MeasurementLog:
    """``log`` with ``metadata["line_model_error"]`` naming ``e``'s terms and ``why``."""
    text = (
        f"extraction profile's ({why}): {e.line_model_sigma_m:.3f} m, "
        f"{math.degrees(e.line_model_sigma_rad):.2f} deg"
    )
    return replace(log, metadata={**log.metadata, "line_model_error": text})


def _estimated_terms(log: MeasurementLog, opts: CarmenOptions) -> MeasurementLog:
    """``log`` (lines without model-error terms) with the terms estimated on it
    (:attr:`CarmenOptions.line_model_error`, :attr:`CarmenOptions.line_model_gate`), or
    the profile's where it has too few observations on its floor plan."""
    profile = opts.extraction
    try:
        err = estimate_line_model_error(
            log,
            correlated=opts.line_model_error == "correlated",
            shape=opts.line_model_shape,
        )
    except ValueError as exc:
        terms = LineTerms(profile.line_model_sigma_m, profile.line_model_sigma_rad)
        return _noted(with_line_model_error(log, terms), profile, str(exc))
    gate = err.gate_terms if opts.line_model_gate == "alone" else None
    out = with_line_model_error(log, err.terms, gate)
    return replace(
        out, metadata={**out.metadata, "line_model_error": err.summary(gate is not None)}
    )


def carmen_association() -> AssociationConfig:
    """Association settings for runs of a CARMEN log against its floor plan.

    The defaults but for six settings (``docs/real-data.md``):

    * CCDA's ``min_pairings``: 12 instead of 8.  Office walls come in parallel families
      a door width or a corridor apart, and a match of 8 walls seen in the first local
      maps can slide by one family.
    * No joint test of the match (``match_joint_test``).  The test trusts the EKF's
      joint covariance, and on these logs the EKF is overconfident (its pose NEES is
      far above 3: walls that are not flat, correlated from scan to scan), so the test
      refuses matches whose pairings are all correct.
    * ``line_gap_m``: 1 m instead of 4 m.  Indoors, two collinear pieces of one wall are
      a doorway apart (about 1 m); pieces farther apart along the line are as often an
      alcove, a cupboard front or the next room's wall a few decimetres off the line.
      Bridging them merges two walls into one landmark, which then pairs with either
      wall of the plan.
    * ``map_method``: ``"jcbb"`` and ``map_ambiguity``: ``"refuse"``.  After a few
      metres of drift a local map's wall fits the parallel wall a corridor or a recess
      away as well as its own; a join then pairs the local map's walls only as a
      jointly compatible set, and leaves a wall that fits two walls unpaired.  On the
      seven logs this cuts the re-observations a join sends to another wall by more
      than half (``docs/results/association.md``).
    * ``ambiguity``: ``"refuse_known"``.  Once the pose has drifted a few decimetres a
      short segment far off fits the plan wall beside its own as well as its own; a
      measurement that fits two plan walls which are not one wall is left unpaired.
      Refused against estimated features too, its duplicate landmarks let CCDA accept
      wrong pairings before the match (Intel, Seattle); between plan walls it acts
      after the match alone (``docs/results/carmen.md``).
    """
    return AssociationConfig(
        ccda=CCDAParams(min_pairings=12),
        match_joint_test=False,
        line_gap_m=1.0,
        map_method="jcbb",
        map_ambiguity="refuse",
        ambiguity="refuse_known",
    )


def with_known_map(log: MeasurementLog, known_map: KnownMapArrays) -> MeasurementLog:
    """``log`` with ``known_map`` as its known map."""
    return replace(log, known_map=known_map)
