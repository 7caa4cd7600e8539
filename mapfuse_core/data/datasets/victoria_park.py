"""The Victoria Park run as a measurement log (``docs/real-data.md``).

One step per scan with at least one tree detection; features are the trunks as
circles; the known map is empty; GPS is a rough reference.  The calibration of
:class:`VictoriaParkOptions` and :data:`VICTORIA_PARK_ODOMETRY_NOISE` is explained in
``docs/results/victoria-park-calibration.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapfuse_core.data.datasets.common import (
    BEAM_SPACING_RAD,
    DatasetError,
    Features,
    check_finite,
    empty_map,
    make_log,
)
from mapfuse_core.data.datasets.files import check_increasing, load_mat, mat_vector, read_table
from mapfuse_core.data.datasets.odometry import CarGeometry, OdometryNoise, integrate_odometry
from mapfuse_core.measlog import MeasurementLog

VICTORIA_PARK_NAME = "victoria_park"
"""Scenario name of the Victoria Park log (also its sub-directory of the data directory)."""


VICTORIA_PARK_ODOMETRY_NOISE = OdometryNoise(sigma_slip_m_per_sqrt_m=0.04)
"""Odometry errors of Victoria Park: the default ones plus sideways slip, 4 cm per √m.

Without slip the kinematic model holds the laser's lateral motion within millimetres
per scan, and the EKF can then meet a lateral disagreement with the trees only by
turning.  The value is the one at which the EKF's loop closures stop turning one way
(no GPS used); ``docs/results/victoria-park-calibration.md`` gives the sweep.  The car park
needs none: its odometry against the surveyed-beacon pose fits is consistent across the
direction of travel without it (``tests/test_datasets_victoria.py``)."""


@dataclass(frozen=True)
class VictoriaParkOptions:
    """How :func:`load_victoria_park` turns the tree detections into a measurement log.

    A detection's range and diameter come from the edges of the trunk in a scan with
    0.5° beam spacing, so their errors grow with range (an edge is only known to within
    a beam): each edge is uniform over ``±Δβ/2``, which gives the centre's bearing a
    variance ``Δβ²/24`` and the diameter ``ρ²Δβ²/6``.  Trunks are not circles either: a
    shape error independent of range is added to the centre and the radius.
    """

    geometry: CarGeometry = field(default_factory=CarGeometry)
    """Car geometry (``info.txt``: a = 0.95 m from the front axle = 3.78 m from the rear)."""
    odometry_noise: OdometryNoise = field(default_factory=lambda: VICTORIA_PARK_ODOMETRY_NOISE)
    """Errors of the dead-reckoning sensors (:data:`VICTORIA_PARK_ODOMETRY_NOISE`)."""
    sigma_range_m: float = 0.05
    """σ of the range to the trunk's centre beside the radius error (m): laser range
    noise and the detector's centre estimate."""
    sigma_bearing_rad: float = math.radians(0.25)
    """σ of the bearing to the centre beside the edge quantisation (rad)."""
    sigma_shape_m: float = 0.05
    """Trunk irregularity (m): added, isotropic, to the centre and to the radius."""
    beam_spacing_rad: float = BEAM_SPACING_RAD
    """Angular spacing of the beams the detector worked on (rad)."""
    max_range_m: float = math.inf
    """Detections farther than this are dropped (``range_too_far``); none by default."""
    min_diameter_m: float = 0.0
    """Detections with a smaller diameter are dropped (``diameter_too_small``); none by
    default (the file's smallest is 1.7 cm)."""
    gps_clock_offset_s: float = 20.967
    """``aa3_gpsx.mat`` times are ``(t + offset)·1000`` ms for a detections-clock time ``t``
    (``docs/real-data.md``); used to put the GPS on the clock of the log."""
    bearing_offset_rad: float = 0.0
    """Added to every detection's bearing: a yaw misalignment of the laser.  0, the
    file's bearings: with the odometry's sideways slip the EKF's loop closures do not
    turn one way at 0, and a negative yaw makes them turn clockwise
    (``docs/results/victoria-park-calibration.md``)."""
    steering_offset_rad: float = 0.0039
    """Added to every steering reading: the steering sensor's zero (+0.22°, fitted)."""
    speed_scale: float = 1.0216
    """Multiplies every encoder speed (wheel radius; +2.2 %, fitted on the trees).  GPS
    and 2 s windows registered on tracked trees disagree; the value is kept pending a
    fit of all parameters together (``docs/results/victoria-park-calibration.md``)."""
    detection_time_offset_s: float = -0.028
    """Added to the detections' times: the scanner's latency relative to the dead
    reckoning (−28 ms, fitted; the car park's beacons suggest −30 ms on the same car)."""

    def __post_init__(self) -> None:
        for name in ("sigma_range_m", "sigma_bearing_rad", "sigma_shape_m", "beam_spacing_rad"):
            check_finite("VictoriaParkOptions", name, getattr(self, name), positive=True)
        check_finite("VictoriaParkOptions", "speed_scale", self.speed_scale, positive=True)
        for name in ("bearing_offset_rad", "steering_offset_rad", "detection_time_offset_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"VictoriaParkOptions.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"VictoriaParkOptions.{name} must be finite, got {value}")
        if not (isinstance(self.max_range_m, int | float) and self.max_range_m > 0.0):
            raise ValueError(f"VictoriaParkOptions.max_range_m must be > 0, got {self.max_range_m}")
        check_finite("VictoriaParkOptions", "min_diameter_m", self.min_diameter_m, positive=False)
        if isinstance(self.gps_clock_offset_s, bool) or not isinstance(
            self.gps_clock_offset_s, int | float
        ):
            raise ValueError("VictoriaParkOptions.gps_clock_offset_s must be a number")


def load_victoria_park(
    data_dir: str | Path, *, options: VictoriaParkOptions | None = None
) -> MeasurementLog:
    """The Victoria Park run from ``data_dir/victoria_park/`` as a measurement log.

    One step per scan with at least one tree detection (the raw scans are not in the
    data; 7,230 of them), timestamped on the detections' clock.  Detections come from
    ``detections/measurements.dat`` (``t range bearing diameter``; range to the trunk's
    centre, bearing 0..π with π/2 ahead, hence ``β = bearing − π/2`` in the laser frame)
    as circles of radius ``diameter/2``.  Odometry integrates ``detections/inputs.dat``
    (``t speed steering``, the rear-left encoder, same clock).  The known map is empty.

    GPS is ``aa3_gpsx.mat`` (``Lo_m`` = East, ``La_m`` = North, original frame; the
    shifted and rotated copy ``detections/gps.dat`` is not used), its ``timeGps``
    milliseconds converted to the detections' clock as ``ms/1000 − 20.967`` s.  It has
    jumps and gaps: a rough reference only.

    The data are corrected by the calibration of :class:`VictoriaParkOptions` (steering
    and time offsets and speed scale; a bearing offset, 0 by default; see
    ``docs/results/victoria-park-calibration.md``): ``timestamps`` are the detections' times
    plus ``detection_time_offset_s``, on the clock of the dead reckoning and the GPS.
    Setting the four to 0, 0, 1 and 0 gives the raw data.  The odometry covariance holds
    the sideways slip of :data:`VICTORIA_PARK_ODOMETRY_NOISE` unless ``odometry_noise``
    says otherwise.
    """
    opts = VictoriaParkOptions() if options is None else options
    folder = Path(data_dir) / VICTORIA_PARK_NAME
    meas_path = folder / "detections" / "measurements.dat"
    inp_path = folder / "detections" / "inputs.dat"
    gps_path = folder / "aa3_gpsx.mat"
    meas = read_table(meas_path, 4, "t range bearing diameter")
    inputs = read_table(inp_path, 3, "t speed steering")
    gps = load_mat(gps_path)
    t_gps_ms = mat_vector(gps, gps_path, "timeGps")
    east = mat_vector(gps, gps_path, "Lo_m", length=t_gps_ms.shape[0])
    north = mat_vector(gps, gps_path, "La_m", length=t_gps_ms.shape[0])
    check_increasing(t_gps_ms, gps_path, "timeGps", strict=False)

    t_meas, rng_, bearing, diameter = meas.T
    check_increasing(t_meas, meas_path, "t", strict=False)
    check_increasing(inputs[:, 0], inp_path, "t", strict=True)
    if np.any(rng_ <= 0.0):
        raise DatasetError(f"{meas_path}: a range is <= 0 (row {int(np.argmax(rng_ <= 0)) + 1})")
    if np.any(diameter <= 0.0):
        bad = int(np.argmax(diameter <= 0.0)) + 1
        raise DatasetError(f"{meas_path}: a diameter is <= 0 (row {bad})")
    if np.any((bearing < -1e-9) | (bearing > math.pi + 1e-9)):
        bad = int(np.argmax((bearing < -1e-9) | (bearing > math.pi + 1e-9))) + 1
        raise DatasetError(f"{meas_path}: a bearing is outside 0..π (row {bad})")

    timestamps, step_of_row = np.unique(t_meas, return_inverse=True)
    timestamps = timestamps + opts.detection_time_offset_s
    try:
        odometry, odometry_cov = integrate_odometry(
            inputs[:, 0],
            inputs[:, 1] * opts.speed_scale,
            inputs[:, 2] + opts.steering_offset_rad,
            timestamps,
            opts.geometry,
            opts.odometry_noise,
        )
    except ValueError as exc:
        raise DatasetError(f"{inp_path}: dead reckoning unusable ({exc})") from exc

    keep = np.ones(t_meas.shape[0], dtype=bool)
    rejected: dict[str, int] = {}
    for reason, bad in (
        ("range_too_far", rng_ > opts.max_range_m),
        ("diameter_too_small", diameter < opts.min_diameter_m),
    ):
        bad = bad & keep
        if np.any(bad):
            rejected[reason] = int(bad.sum())
            keep &= ~bad
    rho, radius = rng_[keep], diameter[keep] / 2.0
    beta = bearing[keep] - math.pi / 2.0 + opts.bearing_offset_rad
    dbeta2 = opts.beam_spacing_rad**2
    shape2 = opts.sigma_shape_m**2
    # Edge quantisation: diameter ρΔβ·√(2/12) → radius variance ρ²Δβ²/24.
    var_r = shape2 + rho**2 * dbeta2 / 24.0
    # The centre is a radius behind the trunk's front: the radius error moves it radially.
    var_radial = opts.sigma_range_m**2 + var_r
    var_tang = rho**2 * (opts.sigma_bearing_rad**2 + dbeta2 / 24.0) + shape2
    c, s = np.cos(beta), np.sin(beta)
    cov = np.zeros((rho.shape[0], 3, 3))
    cov[:, 0, 0] = c * c * var_radial + s * s * var_tang
    cov[:, 1, 1] = s * s * var_radial + c * c * var_tang
    cov[:, 0, 1] = cov[:, 1, 0] = c * s * (var_radial - var_tang)
    cov[:, 2, 2] = var_r
    feats = Features(
        step=np.asarray(step_of_row[keep], dtype=np.int64).reshape(-1),
        params=np.column_stack((rho * c, rho * s, radius)),
        cov=cov,
        n_points=np.zeros(rho.shape[0], dtype=np.int64),
    )
    return make_log(
        VICTORIA_PARK_NAME,
        timestamps,
        odometry,
        odometry_cov,
        feats,
        empty_map(),
        rejected,
        t_gps_ms / 1000.0 - opts.gps_clock_offset_s,
        np.column_stack((east, north)),
    )
