"""What the dataset readers share: the error type, parameter checks, the log builder.

Every missing or malformed input raises :class:`DatasetError` naming the file and the
problem; :func:`make_log` assembles a :class:`~mapfuse_core.measlog.MeasurementLog` of
circle features from the parallel arrays a reader produces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

BEAM_SPACING_RAD = math.radians(0.5)
"""Angular spacing of the SICK beams of both datasets (rad)."""


class DatasetError(ValueError):
    """A dataset file is missing or malformed; the message names the file and the problem."""


def check_finite(owner: str, name: str, value: object, *, positive: bool) -> None:
    """Raise ``ValueError`` naming ``owner.name`` unless ``value`` is a finite number,
    ``> 0`` when ``positive`` and ``>= 0`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{owner}.{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{owner}.{name} must be finite, got {value}")
    if positive and value <= 0.0:
        raise ValueError(f"{owner}.{name} must be > 0, got {value}")
    if not positive and value < 0.0:
        raise ValueError(f"{owner}.{name} must be >= 0, got {value}")


def check_choice(owner: str, name: str, value: object, choices: tuple[object, ...]) -> None:
    """Raise ``ValueError`` naming ``owner.name`` and every choice unless ``value`` is one
    of ``choices`` (a ``Literal``'s ``get_args``)."""
    if value not in choices:
        named = ", ".join(repr(c) for c in choices[:-1]) + f" or {choices[-1]!r}"
        raise ValueError(f"{owner}.{name} must be {named}, got {value!r}")


@dataclass(frozen=True)
class Features:
    """Features of a whole run as the parallel arrays of a measurement log."""

    step: np.ndarray
    """(M,) int64 step of each feature."""
    params: FloatArray
    """(M, 3) circles ``(x, y, r)`` in the laser frame."""
    cov: FloatArray
    """(M, 3, 3) covariances."""
    n_points: np.ndarray
    """(M,) int64 returns per feature (0 when unknown)."""

    @staticmethod
    def of(
        step: list[int], params: list[FloatArray], cov: list[FloatArray], n_points: list[int]
    ) -> Features:
        m = len(step)
        return Features(
            step=np.asarray(step, dtype=np.int64).reshape(m),
            params=np.asarray(params, dtype=np.float64).reshape(m, 3),
            cov=np.asarray(cov, dtype=np.float64).reshape(m, 3, 3),
            n_points=np.asarray(n_points, dtype=np.int64).reshape(m),
        )


def make_log(
    scenario: str,
    timestamps: FloatArray,
    odometry: FloatArray,
    odometry_cov: FloatArray,
    feats: Features,
    known_map: KnownMapArrays,
    rejected: dict[str, int],
    gps_times: FloatArray,
    gps_xy: FloatArray,
    true_ids: np.ndarray | None = None,
) -> MeasurementLog:
    """A measurement log of circle features (``seed = −1``: a real run, not a simulation)."""
    m = feats.step.shape[0]
    return MeasurementLog(
        scenario=scenario,
        seed=-1,
        timestamps=timestamps,
        odometry=odometry,
        odometry_cov=odometry_cov,
        feat_step=feats.step,
        feat_kind=np.full(m, int(FeatureKind.CIRCLE), dtype=np.int8),
        feat_params=feats.params,
        feat_cov=feats.cov,
        feat_true_id=np.full(m, -1, dtype=np.int64) if true_ids is None else true_ids,
        feat_n_points=feats.n_points,
        feat_extent=np.full((m, 2), np.nan),
        known_map=known_map,
        rejected=dict(sorted(rejected.items())),
        gps_times=gps_times,
        gps_xy=gps_xy,
    )


def empty_map() -> KnownMapArrays:
    """A known map with no feature."""
    return KnownMapArrays(
        ids=np.zeros(0, dtype=np.int64),
        kinds=np.zeros(0, dtype=np.int8),
        params=np.zeros((0, 3)),
        covs=np.zeros((0, 3, 3)),
        extents=np.zeros((0, 2)),
    )
