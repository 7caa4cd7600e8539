"""The measurement log: the single input both backends consume.

A log holds, per step ``k = 0 … N−1``: the true pose (simulation), the odometry
increment from step ``k−1`` to ``k`` with its covariance (row 0 is zero: the first
step has no motion), and the features extracted from the scan taken at step ``k``
(kind, parameters and covariance in the sensor frame, true world id or −1).  It also
carries the known map exactly as the run uses it (with its noise realisation) and
the true world, so that every backend and every metric sees identical inputs.

On disk it is a versioned ``.npz`` of plain arrays (no pickled objects), written
with fixed zip timestamps so that the same seed gives a bit-identical file.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog.known_map import KnownMapArrays

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MeasurementLog",
    "MeasurementLogError",
    "load_log",
    "save_log",
]

FORMAT_NAME = "mapfuse.measurement_log"
FORMAT_VERSION = 1

IntArray = np.ndarray


class MeasurementLogError(ValueError):
    """A measurement log is malformed, damaged or of another format version."""


@dataclass(frozen=True)
class MeasurementLog:
    """Everything a run consumes, step by step.  Arrays are read-only views."""

    scenario: str
    """Scenario name (``loop600``, a TOML path, a dataset name)."""
    seed: int
    """Seed the log was simulated with (−1 for real data)."""
    timestamps: FloatArray
    """(N,) time of each step in seconds."""
    odometry: FloatArray
    """(N, 3) odometry increment ``x^{R_{k−1}}_{R_k}`` ordered ``(x, y, θ)``; row 0 zero."""
    odometry_cov: FloatArray
    """(N, 3, 3) covariance of each increment; row 0 zero."""
    feat_step: IntArray
    """(M,) int64 step at which each feature was extracted, non-decreasing."""
    feat_kind: IntArray
    """(M,) int8 :class:`FeatureKind` of each feature."""
    feat_params: FloatArray
    """(M, 3) feature parameters in the sensor frame at its step."""
    feat_cov: FloatArray
    """(M, 3, 3) covariance of :attr:`feat_params` (lines: along-line is a pseudo-variance)."""
    feat_true_id: IntArray
    """(M,) int64 world id the feature came from, −1 if unknown (real data) or mixed."""
    feat_n_points: IntArray
    """(M,) int64 number of laser points the feature was fitted to."""
    feat_extent: FloatArray
    """(M, 2) along-line coordinates of the segment ends (lines), NaN for circles."""
    known_map: KnownMapArrays
    """The a-priori known map, in ``Wknown``, exactly as this run uses it."""
    world: KnownMapArrays | None = None
    """The true world features in ``W`` (simulation), for evaluation only."""
    true_poses: FloatArray | None = None
    """(N, 3) true vehicle pose at each step in ``W`` (simulation), or ``None``."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Extraction rejections over the whole run: reason → count."""
    gps_times: FloatArray | None = None
    """(G,) times of GPS fixes (real data), on the clock of :attr:`timestamps`."""
    gps_xy: FloatArray | None = None
    """(G, 2) GPS positions (East, North) in metres, the frame of the surveyed known map."""
    metadata: dict[str, str] = field(default_factory=dict)
    """Facts about how the log was made, name → text (e.g. ``odometry: simulated from
    reference``, counts of skipped messages); empty when there is nothing to say."""
    known_frame: FloatArray | None = None
    """(3,) ``x^W_Wknown``, the pose of the known map's frame in the world (simulation),
    for evaluation only; ``None`` (real data, logs written without it) means the
    identity."""
    scan_bearings: FloatArray | None = None
    """(B,) bearing of each beam of the raw scans in the sensor frame (rad), increasing;
    ``None`` when the log keeps no raw scans."""
    scan_ranges: np.ndarray | None = None
    """(N, B) float32 range each beam of step ``k``'s scan measured (m), ``inf`` where it
    returned nothing; given with :attr:`scan_bearings`.  The features are extracted from
    these; change detection reads them for where the laser saw through a mapped feature
    (``docs/change-detection.md``)."""
    feat_gate_cov: FloatArray | None = None
    """(M, 3, 3) covariance of each feature's error taken alone, which the tests of
    compatibility (association gates) use; ``None``: :attr:`feat_cov`.  It differs from
    :attr:`feat_cov` where that is inflated so that consecutive observations sharing
    one error count once (the line model error estimated with its autocorrelation,
    :func:`~mapfuse_core.data.datasets.line_noise.estimate_line_model_error`): that
    inflation is right for the information an observation carries, not for how far
    one observation strays (:attr:`gate_covs`)."""
    _offsets: IntArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _validate(self)
        object.__setattr__(
            self,
            "_offsets",
            np.searchsorted(self.feat_step, np.arange(self.n_steps + 1), side="left"),
        )

    @property
    def n_steps(self) -> int:
        """Number of steps ``N``."""
        return int(self.timestamps.shape[0])

    @property
    def n_features(self) -> int:
        """Total number of extracted features ``M``."""
        return int(self.feat_step.shape[0])

    @property
    def gate_covs(self) -> FloatArray:
        """(M, 3, 3) covariances the compatibility tests use: :attr:`feat_gate_cov`
        where the log gives one, else :attr:`feat_cov`."""
        return self.feat_cov if self.feat_gate_cov is None else self.feat_gate_cov

    @property
    def gps(self) -> tuple[FloatArray, FloatArray] | None:
        """``(gps_times, gps_xy)`` when the log carries GPS fixes, else ``None``."""
        if self.gps_times is None or self.gps_xy is None:
            return None
        return self.gps_times, self.gps_xy

    def head(self, n_steps: int) -> MeasurementLog:
        """The first ``n_steps`` steps of this log (all of it if it is shorter).

        For quick experiments on a long run; GPS fixes are kept whole (the metrics use
        only those inside the run).
        """
        if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
            raise ValueError(f"n_steps must be an int >= 1, got {n_steps!r}")
        n = min(n_steps, self.n_steps)
        m = int(self._offsets[n])
        return replace(
            self,
            timestamps=self.timestamps[:n],
            odometry=self.odometry[:n],
            odometry_cov=self.odometry_cov[:n],
            feat_step=self.feat_step[:m],
            feat_kind=self.feat_kind[:m],
            feat_params=self.feat_params[:m],
            feat_cov=self.feat_cov[:m],
            feat_gate_cov=None if self.feat_gate_cov is None else self.feat_gate_cov[:m],
            feat_true_id=self.feat_true_id[:m],
            feat_n_points=self.feat_n_points[:m],
            feat_extent=self.feat_extent[:m],
            true_poses=None if self.true_poses is None else self.true_poses[:n],
            scan_ranges=None if self.scan_ranges is None else self.scan_ranges[:n],
        )

    def feature_slice(self, k: int) -> slice:
        """Index range of the features extracted at step ``k``."""
        if not 0 <= k < self.n_steps:
            raise IndexError(f"step {k} outside the log's 0..{self.n_steps - 1}")
        return slice(int(self._offsets[k]), int(self._offsets[k + 1]))


# --------------------------------------------------------------------------- validation


#: Largest magnitude of a coordinate, length or angle in a log (poses, odometry, feature
#: and map parameters, extents, GPS positions): 1e9 m, as in a scenario file, so that
#: products and squares stay finite in the estimators.  Times are not bounded.
MAX_MAGNITUDE = 1e9
#: Largest magnitude of a covariance entry: the square of :data:`MAX_MAGNITUDE`.
MAX_VARIANCE = MAX_MAGNITUDE**2


def _check_array(
    name: str,
    a: Any,
    shape: tuple[int | None, ...],
    finite: bool = True,
    kinds: str = "fiu",
    limit: float | None = MAX_MAGNITUDE,
) -> None:
    """A numpy array of the given shape (``None``: any length) whose dtype kind is one of
    ``kinds`` (an empty array may be of any numeric kind), finite unless ``finite=False``
    (NaN allowed then), and of magnitude at most ``limit`` when given."""
    if not isinstance(a, np.ndarray):
        raise MeasurementLogError(f"'{name}' must be a numpy array, got {type(a).__name__}")
    if a.dtype.kind not in (kinds if a.size else "fiu"):
        what = "integer" if kinds == "iu" else "numeric"
        raise MeasurementLogError(f"'{name}' must be {what}, got dtype {a.dtype}")
    mismatch = a.ndim != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, a.shape, strict=True)
    )
    if mismatch:
        want = "×".join("N" if s is None else str(s) for s in shape)
        raise MeasurementLogError(f"'{name}' has shape {a.shape}, expected {want}")
    if finite and a.dtype.kind == "f" and a.size and not np.all(np.isfinite(a)):
        idx = np.argwhere(~np.isfinite(a))[0]
        raise MeasurementLogError(
            f"'{name}' has a non-finite value ({a[tuple(idx)]}) "
            f"at index {tuple(int(i) for i in idx)}"
        )
    if limit is not None and a.dtype.kind == "f" and a.size:
        mag = np.abs(np.where(np.isnan(a), 0.0, a))
        worst = int(np.argmax(mag))
        if mag.flat[worst] > limit:
            idx = tuple(int(i) for i in np.unravel_index(worst, a.shape))
            raise MeasurementLogError(
                f"'{name}' has a value beyond ±{limit:g} ({a[idx]:g}) at index {idx}"
            )


#: Relative tolerance of the covariance checks: symmetry to this fraction of the largest
#: entry, and eigenvalues of the correlation matrix ``D^-½ C D^-½`` (``D`` the diagonal)
#: down to ``-PSD_TOLERANCE`` count as zero.  Rounding in ``J Σ Jᵀ`` leaves errors of
#: about 1e-15 there; a wrong sign or a bad correlation gives far more.
PSD_TOLERANCE = 1e-9
#: Smallest eigenvalue of the correlation matrix of a covariance that must be positive
#: definite (odometry): three orders above rounding, so an exact zero or a rank-deficient
#: ``J Σ Jᵀ`` is refused while strongly correlated noise is not.
PD_THRESHOLD = 1e-12


def _correlation_eigenvalues(covs: FloatArray) -> FloatArray:
    """(M, 3) ascending eigenvalues of each covariance scaled to unit diagonal (a zero
    variance is scaled by the matrix's largest standard deviation instead)."""
    d = np.sqrt(np.maximum(np.diagonal(covs, axis1=1, axis2=2), 0.0))
    top = d.max(axis=1, keepdims=True)
    d = np.where(d > 0.0, d, np.where(top > 0.0, top, 1.0))
    corr = covs / (d[:, :, None] * d[:, None, :])
    return np.asarray(np.linalg.eigvalsh(0.5 * (corr + np.swapaxes(corr, 1, 2))))


def _check_covs(name: str, covs: FloatArray, definite_from: int | None = None) -> None:
    """Symmetric, non-negative variances, positive semi-definite; positive definite from
    index ``definite_from`` on when given (odometry: row 0 is the zero of no motion)."""
    if covs.size == 0:
        return
    asym = np.abs(covs - np.swapaxes(covs, 1, 2)).max(axis=(1, 2))
    scale = np.maximum(np.abs(covs).max(axis=(1, 2)), 1e-300)
    bad = np.nonzero(asym > PSD_TOLERANCE * scale)[0]
    if bad.size:
        raise MeasurementLogError(f"'{name}'[{int(bad[0])}] is not symmetric")
    diag = np.diagonal(covs, axis1=1, axis2=2)
    neg = np.argwhere(diag < 0.0)
    if neg.size:
        raise MeasurementLogError(f"'{name}'[{int(neg[0][0])}] has a negative variance")
    low = _correlation_eigenvalues(covs)[:, 0]
    bad = np.nonzero(low < -PSD_TOLERANCE)[0]
    if bad.size:
        i = int(bad[0])
        raise MeasurementLogError(
            f"'{name}'[{i}] is not positive semi-definite "
            f"(min eigenvalue {_min_eigenvalue(covs[i]):.3g})"
        )
    if definite_from is not None:
        weak = (low <= PD_THRESHOLD) | np.any(diag <= 0.0, axis=1)
        bad = np.nonzero(weak[definite_from:])[0]
        if bad.size:
            i = int(bad[0]) + definite_from
            raise MeasurementLogError(
                f"'{name}'[{i}] is not positive definite "
                f"(min eigenvalue {_min_eigenvalue(covs[i]):.3g}): every increment needs "
                "some uncertainty in x, y and θ"
            )


def _min_eigenvalue(cov: FloatArray) -> float:
    return float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[0])


def _check_map(prefix: str, m: KnownMapArrays) -> None:
    _check_array(f"{prefix}_ids", m.ids, (None,), kinds="iu")
    n = len(m)
    _check_array(f"{prefix}_kinds", m.kinds, (n,), kinds="iu")
    _check_array(f"{prefix}_params", m.params, (n, 3))
    _check_array(f"{prefix}_covs", m.covs, (n, 3, 3), limit=MAX_VARIANCE)
    _check_kinds(f"{prefix}_kinds", m.kinds)
    _check_covs(f"{prefix}_covs", m.covs)
    if m.extents is not None:
        _check_array(f"{prefix}_extents", m.extents, (n, 2), finite=False)
    if len(np.unique(m.ids)) != n:
        raise MeasurementLogError(f"'{prefix}_ids' has duplicate ids")


def _check_kinds(name: str, kinds: IntArray) -> None:
    valid = {int(k) for k in FeatureKind}
    bad = np.nonzero(~np.isin(kinds, list(valid)))[0]
    if bad.size:
        raise MeasurementLogError(
            f"'{name}'[{int(bad[0])}] = {int(kinds[bad[0]])} is not a feature kind "
            f"(0 = line, 1 = circle)"
        )


def _validate(log: MeasurementLog) -> None:
    if not isinstance(log.scenario, str):
        raise MeasurementLogError(f"'scenario' must be text, got {type(log.scenario).__name__}")
    seed = log.seed
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise MeasurementLogError(f"'seed' must be an integer, got {type(seed).__name__}")
    if not -1 <= int(seed) <= _INT64.max:
        raise MeasurementLogError(f"'seed' must be in -1 … 2**63 - 1, got {int(seed)}")
    _check_array("timestamps", log.timestamps, (None,), limit=None)
    n = log.timestamps.shape[0]
    if n < 1:
        raise MeasurementLogError("the log has no steps")
    _check_array("odometry", log.odometry, (n, 3))
    _check_array("odometry_cov", log.odometry_cov, (n, 3, 3), limit=MAX_VARIANCE)
    _check_covs("odometry_cov", log.odometry_cov, definite_from=1)
    if np.any(np.diff(log.timestamps) < 0):
        raise MeasurementLogError("'timestamps' decrease")
    _check_array("feat_step", log.feat_step, (None,), kinds="iu")
    m = log.feat_step.shape[0]
    _check_array("feat_kind", log.feat_kind, (m,), kinds="iu")
    _check_array("feat_params", log.feat_params, (m, 3))
    _check_array("feat_true_id", log.feat_true_id, (m,), kinds="iu")
    _check_array("feat_n_points", log.feat_n_points, (m,), kinds="iu")
    _check_array("feat_extent", log.feat_extent, (m, 2), finite=False)
    _check_kinds("feat_kind", log.feat_kind)
    covs = {"feat_cov": log.feat_cov}
    if log.feat_gate_cov is not None:
        covs["feat_gate_cov"] = log.feat_gate_cov
    for name, c in covs.items():
        _check_array(name, c, (m, 3, 3), limit=MAX_VARIANCE)
        _check_covs(name, c)
    if m and (log.feat_step.min() < 0 or log.feat_step.max() >= n):
        raise MeasurementLogError(f"'feat_step' refers to a step outside 0..{n - 1}")
    if m and np.any(np.diff(log.feat_step) < 0):
        raise MeasurementLogError("'feat_step' must be non-decreasing")
    circles = log.feat_kind == FeatureKind.CIRCLE
    if np.any(log.feat_params[circles, 2] <= 0.0):
        i = int(np.nonzero(circles & (log.feat_params[:, 2] <= 0.0))[0][0])
        raise MeasurementLogError(f"'feat_params'[{i}] is a circle with radius <= 0")
    _check_map("known", log.known_map)
    if log.world is not None:
        _check_map("world", log.world)
    if log.true_poses is not None:
        _check_array("true_poses", log.true_poses, (n, 3))
    if log.known_frame is not None:
        _check_array("known_frame", log.known_frame, (3,))
    if (log.gps_times is None) != (log.gps_xy is None):
        raise MeasurementLogError("'gps_times' and 'gps_xy' must be given together")
    if log.gps_times is not None and log.gps_xy is not None:
        _check_array("gps_times", log.gps_times, (None,), limit=None)
        _check_array("gps_xy", log.gps_xy, (log.gps_times.shape[0], 2))
    _check_scans(log, n)
    for k, v in log.rejected.items():
        if not isinstance(k, str) or not isinstance(v, int) or v < 0:
            raise MeasurementLogError(f"'rejected' entry {k!r}: {v!r} is not a count")
    for key, text in log.metadata.items():
        if not isinstance(key, str) or not isinstance(text, str):
            raise MeasurementLogError(f"'metadata' entry {key!r}: {text!r} is not text")


def _check_scans(log: MeasurementLog, n: int) -> None:
    """Raw scans: bearings and ranges together, one row of ranges per step; bearings
    finite, increasing and within ±π; ranges non-negative, ``inf`` for no return."""
    if (log.scan_bearings is None) != (log.scan_ranges is None):
        raise MeasurementLogError("'scan_bearings' and 'scan_ranges' must be given together")
    if log.scan_bearings is None or log.scan_ranges is None:
        return
    b = log.scan_bearings
    _check_array("scan_bearings", b, (None,), kinds="f")
    if b.shape[0] < 1:
        raise MeasurementLogError("'scan_bearings' is empty")
    if np.any(np.abs(b) > np.pi + 1e-9) or np.any(np.diff(b) <= 0.0):
        raise MeasurementLogError("'scan_bearings' must increase strictly within ±π")
    r = log.scan_ranges
    _check_array("scan_ranges", r, (n, b.shape[0]), finite=False, kinds="f", limit=None)
    if r.dtype != np.float32:
        raise MeasurementLogError(f"'scan_ranges' must be float32, got {r.dtype}")
    bad = np.argwhere(np.isnan(r) | (r < 0.0))
    if bad.size:
        k, j = (int(i) for i in bad[0])
        raise MeasurementLogError(
            f"'scan_ranges'[{k}, {j}] = {r[k, j]} is not a range (a range is >= 0, "
            "inf for no return)"
        )


# --------------------------------------------------------------------------- disk format

_MAP_FIELDS = ("ids", "kinds", "params", "covs")
_LOG_ARRAYS = tuple(
    f.name
    for f in fields(MeasurementLog)
    if f.name
    not in {
        "scenario",
        "seed",
        "known_map",
        "world",
        "true_poses",
        "feat_gate_cov",
        "rejected",
        "gps_times",
        "gps_xy",
        "metadata",
        "known_frame",
        "scan_bearings",
        "scan_ranges",
    }
    and not f.name.startswith("_")
)
_DTYPES: dict[str, type[np.signedinteger[Any]]] = {
    "feat_step": np.int64,
    "feat_kind": np.int8,
    "feat_true_id": np.int64,
    "feat_n_points": np.int64,
    "ids": np.int64,
    "kinds": np.int8,
}


def _arrays_of(log: MeasurementLog) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {
        "format_name": np.array(FORMAT_NAME),
        "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
        "scenario": np.array(log.scenario),
        "seed": np.array(log.seed, dtype=np.int64),
        "rejected_reasons": np.array(sorted(log.rejected), dtype=np.str_).reshape(-1),
        "rejected_counts": np.array(
            [log.rejected[k] for k in sorted(log.rejected)], dtype=np.int64
        ).reshape(-1),
    }
    if log.metadata:
        out["metadata_keys"] = np.array(sorted(log.metadata), dtype=np.str_).reshape(-1)
        out["metadata_values"] = np.array(
            [log.metadata[k] for k in sorted(log.metadata)], dtype=np.str_
        ).reshape(-1)
    for name in _LOG_ARRAYS:
        out[name] = np.asarray(getattr(log, name))
    for prefix, m in (("known", log.known_map), ("world", log.world)):
        if m is not None:
            for f in _MAP_FIELDS:
                out[f"{prefix}_{f}"] = np.asarray(getattr(m, f))
            if m.extents is not None:
                out[f"{prefix}_extents"] = np.asarray(m.extents)
    for name in (
        "feat_gate_cov",
        "true_poses",
        "gps_times",
        "gps_xy",
        "known_frame",
        "scan_bearings",
        "scan_ranges",
    ):
        value = getattr(log, name)
        if value is not None:
            out[name] = np.asarray(value)
    return out


def save_log(log: MeasurementLog, path: str | Path) -> Path:
    """Write ``log`` to ``path`` (``.npz``); the bytes depend only on the log's content."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in sorted(_arrays_of(log).items()):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arr, order="C"), allow_pickle=False)
            # A fixed timestamp keeps the file bit-identical across runs of one seed.
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    return path


#: Arrays of text, each 0-d (one string) or 1-D (a list).
_TEXT = {
    "format_name": 0,
    "scenario": 0,
    "rejected_reasons": 1,
    "metadata_keys": 1,
    "metadata_values": 1,
}
#: Integer scalars and lists besides the int arrays of :data:`_DTYPES`.
_INTS = {"format_version": 0, "seed": 0, "rejected_counts": 1}
_INT64 = np.iinfo(np.int64)


def _get(arrays: dict[str, np.ndarray], path: Path, name: str) -> np.ndarray:
    """Array ``name`` with its dtype checked: text, int64/int8, or float64 (ints and
    floats of any width are converted)."""
    if name not in arrays:
        raise MeasurementLogError(f"{path}: missing array '{name}'")
    arr = arrays[name]
    if name in _TEXT:
        ndim = _TEXT[name]
        if arr.dtype.kind != "U" or arr.ndim != ndim:
            want = "a text scalar" if ndim == 0 else "a 1-D array of text"
            raise MeasurementLogError(
                f"{path}: '{name}' must be {want}, got {arr.dtype} of shape {arr.shape}"
            )
        return arr
    base = name.split("_", 1)[1] if name.startswith(("known_", "world_")) else name
    dtype = _DTYPES.get(base, np.int64 if name in _INTS else None)
    if dtype is not None:
        if arr.dtype.kind not in "iu":
            raise MeasurementLogError(f"{path}: '{name}' must be integer, got {arr.dtype}")
        if name in _INTS and arr.ndim != _INTS[name]:
            what = "a scalar" if _INTS[name] == 0 else "1-D"
            raise MeasurementLogError(f"{path}: '{name}' must be {what}, got shape {arr.shape}")
        limits = np.iinfo(dtype)
        if arr.size and (arr.min() < limits.min or arr.max() > limits.max):
            raise MeasurementLogError(
                f"{path}: '{name}' has a value outside {np.dtype(dtype).name} "
                f"({limits.min} … {limits.max})"
            )
        return arr.astype(dtype)
    if arr.dtype.kind not in "fiu":
        raise MeasurementLogError(f"{path}: '{name}' must be numeric, got {arr.dtype}")
    return arr.astype(np.float32 if name == "scan_ranges" else np.float64)


def load_log(path: str | Path) -> MeasurementLog:
    """Read and validate a log written by :func:`save_log`.

    Raises :class:`MeasurementLogError` naming the file and the problem for a missing,
    damaged or foreign file, another format version, or inconsistent arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise MeasurementLogError(f"{path}: no such measurement log")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise MeasurementLogError(f"{path}: not a readable .npz measurement log ({exc})") from exc
    name = str(arrays["format_name"]) if "format_name" in arrays else ""
    if name != FORMAT_NAME:
        raise MeasurementLogError(f"{path}: not a mapfuse measurement log (format_name={name!r})")
    version = int(_get(arrays, path, "format_version")) if "format_version" in arrays else -1
    if version != FORMAT_VERSION:
        raise MeasurementLogError(
            f"{path}: measurement log format version {version}, this mapfuse reads version "
            f"{FORMAT_VERSION}; re-create the log with this version"
        )

    def map_of(prefix: str) -> KnownMapArrays:
        ext = f"{prefix}_extents"
        ids, kinds, params, covs = (_get(arrays, path, f"{prefix}_{f}") for f in _MAP_FIELDS)
        extents = _get(arrays, path, ext) if ext in arrays else None
        return KnownMapArrays(ids, kinds, params, covs, extents)

    reasons = _get(arrays, path, "rejected_reasons")
    counts = _get(arrays, path, "rejected_counts")
    if reasons.shape != counts.shape:
        raise MeasurementLogError(f"{path}: 'rejected_reasons' and 'rejected_counts' differ")
    metadata: dict[str, str] = {}
    if "metadata_keys" in arrays or "metadata_values" in arrays:
        keys = _get(arrays, path, "metadata_keys")
        values = _get(arrays, path, "metadata_values")
        if keys.shape != values.shape:
            raise MeasurementLogError(f"{path}: 'metadata_keys' and 'metadata_values' differ")
        metadata = {str(k): str(v) for k, v in zip(keys, values, strict=True)}
    try:
        return MeasurementLog(
            scenario=str(_get(arrays, path, "scenario")),
            seed=int(_get(arrays, path, "seed")),
            known_map=map_of("known"),
            world=map_of("world") if "world_ids" in arrays else None,
            true_poses=_get(arrays, path, "true_poses") if "true_poses" in arrays else None,
            feat_gate_cov=(
                _get(arrays, path, "feat_gate_cov") if "feat_gate_cov" in arrays else None
            ),
            gps_times=_get(arrays, path, "gps_times") if "gps_times" in arrays else None,
            gps_xy=_get(arrays, path, "gps_xy") if "gps_xy" in arrays else None,
            known_frame=_get(arrays, path, "known_frame") if "known_frame" in arrays else None,
            **{s: _get(arrays, path, s) for s in ("scan_bearings", "scan_ranges") if s in arrays},
            rejected={str(r): int(c) for r, c in zip(reasons, counts, strict=True)},
            metadata=metadata,
            **{n: _get(arrays, path, n) for n in _LOG_ARRAYS},
        )
    except MeasurementLogError as exc:
        msg = str(exc)
        if not msg.startswith(f"{path}: "):
            msg = f"{path}: {msg}"
        raise MeasurementLogError(msg) from None
