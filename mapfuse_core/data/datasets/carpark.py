"""The ACFR car-park run as a measurement log (``docs/real-data.md``).

One step per laser scan; features are the reflective beacon poles of each scan
(:func:`~mapfuse_core.data.datasets.poles.detect_reflector_poles`); the known map is the
surveyed beacons; GPS fixes and beacons are (East, North) metres in one frame, on the
clock of the dead reckoning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapfuse_core.data.datasets.carpark_options import CarparkOptions
from mapfuse_core.data.datasets.common import DatasetError, Features, check_finite, make_log
from mapfuse_core.data.datasets.files import (
    check_increasing,
    load_mat,
    mat_matrix,
    mat_vector,
)
from mapfuse_core.data.datasets.gps import gps_reference_labels
from mapfuse_core.data.datasets.odometry import integrate_odometry
from mapfuse_core.data.datasets.poles import detect_reflector_poles
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

CARPARK_NAME = "acfr_carpark"
"""Scenario name of the car-park log (also its sub-directory of the data directory)."""

_N_BEAMS = 361
"""Beams per car-park scan (−90° to +90° in 0.5° steps)."""


def load_carpark(
    data_dir: str | Path,
    *,
    known_sigma_m: float = 0.02,
    options: CarparkOptions | None = None,
) -> MeasurementLog:
    """The ACFR car-park run from ``data_dir/acfr_carpark/`` as a measurement log.

    One step per laser scan (586 at about 4.7 Hz), timestamped ``TimeLaser`` (plus
    ``options.laser_time_offset_s``).  Odometry integrates the 40 Hz dead reckoning
    (``Time_VS``, ``Velocity``, ``Steering``); features are the reflective beacon poles
    of each scan (:func:`detect_reflector_poles`).  The known map is the 15 surveyed
    beacons of ``beac_juan3.mat`` (ids 0–14, East/North, radius ``pole_radius_m``),
    with σ ``known_sigma_m`` on each coordinate (the kinematic-GPS survey, about 2 cm)
    and ``pole_radius_sigma_m`` on the radius.  GPS: ``TimeGPS``, (``GPSLon`` = East,
    ``GPSLat`` = North), same frame as the beacons and same clock as the dead reckoning.
    ``feat_true_id`` holds GPS-based reference beacon labels (``options.reference_labels``).
    """
    opts = CarparkOptions() if options is None else options
    check_finite("load_carpark", "known_sigma_m", known_sigma_m, positive=True)
    folder = Path(data_dir) / CARPARK_NAME
    data_path = folder / "data_set.mat"
    beac_path = folder / "beac_juan3.mat"
    mat = load_mat(data_path)
    beac = load_mat(beac_path)

    t_laser = mat_vector(mat, data_path, "TimeLaser")
    n = t_laser.shape[0]
    laser = mat_matrix(mat, data_path, "Laser", (n, _N_BEAMS))
    intensity = mat_matrix(mat, data_path, "Intensity", (n, _N_BEAMS))
    t_vs = mat_vector(mat, data_path, "Time_VS")
    velocity = mat_vector(mat, data_path, "Velocity", length=t_vs.shape[0])
    steering = mat_vector(mat, data_path, "Steering", length=t_vs.shape[0])
    t_gps = mat_vector(mat, data_path, "TimeGPS")
    east = mat_vector(mat, data_path, "GPSLon", length=t_gps.shape[0])
    north = mat_vector(mat, data_path, "GPSLat", length=t_gps.shape[0])
    beacons = mat_matrix(beac, beac_path, "estbeac", (None, 2))
    if beacons.shape[0] == 0:
        raise DatasetError(f"{beac_path}: 'estbeac' holds no beacon")
    check_increasing(t_laser, data_path, "TimeLaser", strict=True)
    check_increasing(t_vs, data_path, "Time_VS", strict=True)
    check_increasing(t_gps, data_path, "TimeGPS", strict=False)
    if np.any(laser <= 0.0):
        raise DatasetError(f"{data_path}: 'Laser' has a range <= 0")

    timestamps = t_laser + opts.laser_time_offset_s
    try:
        odometry, odometry_cov = integrate_odometry(
            t_vs, velocity, steering, timestamps, opts.geometry, opts.odometry_noise
        )
    except ValueError as exc:
        raise DatasetError(f"{data_path}: dead reckoning unusable ({exc})") from exc

    steps: list[int] = []
    params: list[FloatArray] = []
    covs: list[FloatArray] = []
    npts: list[int] = []
    rejected: dict[str, int] = {}
    for k in range(n):
        poles, rej = detect_reflector_poles(laser[k], intensity[k], opts)
        for key, count in rej.items():
            rejected[key] = rejected.get(key, 0) + count
        for circle, cov, n_points in poles:
            steps.append(k)
            params.append(circle)
            covs.append(cov)
            npts.append(n_points)

    nb = beacons.shape[0]
    var_xy = known_sigma_m**2
    known = KnownMapArrays(
        ids=np.arange(nb, dtype=np.int64),
        kinds=np.full(nb, int(FeatureKind.CIRCLE), dtype=np.int8),
        params=np.column_stack((beacons, np.full(nb, opts.pole_radius_m))),
        covs=np.tile(np.diag([var_xy, var_xy, opts.pole_radius_sigma_m**2]), (nb, 1, 1)),
        extents=np.full((nb, 2), np.nan),
    )
    feats = Features.of(steps, params, covs, npts)
    gps_xy = np.column_stack((east, north))
    labels = None
    if opts.reference_labels:
        labels = gps_reference_labels(
            timestamps, odometry, feats.step, feats.params[:, :2], t_gps, gps_xy, beacons
        )
    return make_log(
        CARPARK_NAME,
        timestamps,
        odometry,
        odometry_cov,
        feats,
        known,
        rejected,
        t_gps,
        gps_xy,
        labels,
    )
