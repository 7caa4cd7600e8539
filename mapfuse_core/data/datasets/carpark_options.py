"""How the ACFR car-park run becomes a measurement log: :class:`CarparkOptions`, and the
odometry errors of its car (:data:`CARPARK_ODOMETRY_NOISE`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mapfuse_core.data.datasets.common import check_finite
from mapfuse_core.data.datasets.odometry import CarGeometry, OdometryNoise

__all__ = ["CARPARK_ODOMETRY_NOISE", "CarparkOptions"]


CARPARK_ODOMETRY_NOISE = OdometryNoise(
    steer_saturation_rad=0.59, sigma_steer_saturated_rad=math.radians(5.0)
)
"""Odometry errors of the car park: the default ones plus a steering end stop.

The car-park steering readings pile up at 0.597–0.624 rad while the car drives tighter
circles than they imply: the sensor is at its stop, and a step holding such a reading
gets a wider steering error.  ``docs/results/carpark.md`` gives the effect of the value.
"""


@dataclass(frozen=True)
class CarparkOptions:
    """How :func:`load_carpark` turns the raw car-park data into a measurement log."""

    geometry: CarGeometry = field(default_factory=CarGeometry)
    """Car geometry (``docs/real-data.md``)."""
    odometry_noise: OdometryNoise = field(default_factory=lambda: CARPARK_ODOMETRY_NOISE)
    """Errors of the dead-reckoning sensors (:data:`CARPARK_ODOMETRY_NOISE`)."""
    pole_radius_m: float = 0.03
    """Radius of a beacon pole (about 6 cm diameter, ``docs/real-data.md``).  With 1 to 6
    returns on a pole the radius cannot be fitted, so every pole, observed or surveyed,
    gets this."""
    pole_radius_sigma_m: float = 0.005
    """σ of the pole radius (m): "about 6 cm" read as 6 ± 1 cm of diameter."""
    sigma_range_m: float = 0.02
    """σρ of a SICK LMS range (m): the sensor's ±15 mm systematic error at the car park's
    1–16 m (1 cm resolution in this file); slightly conservative against the scatter of
    poses fitted to the surveyed beacons alone (``docs/results/carpark.md``)."""
    sigma_bearing_rad: float = math.radians(0.35)
    """σβ of the direction to a pole's centre (rad), beside the beam quantisation (added
    separately, ``Δβ²/24``): pointing and beam-footprint asymmetry.  Slightly
    conservative against the same pose fits (``docs/results/carpark.md``), which the single
    poles seen at 1–2 returns deserve."""
    max_range_m: float = 30.0
    """Reflective returns farther than this are ignored and counted per return as
    ``beyond_max_range`` (the ACFR example code's cut); no pole is seen beyond 16 m here."""
    cluster_max_beam_gap: int = 2
    """Two reflective returns belong to one pole only if their beam indices differ by at
    most this (one missing beam tolerated: the tape does not always flag)."""
    cluster_max_gap_m: float = 0.3
    """… and if they are at most this far apart (m); poles are metres apart."""
    max_cluster_width_m: float = 0.3
    """A cluster wider than this (first to last return, m) is not a 6 cm pole; rejected
    as ``cluster_too_wide``."""
    reference_labels: bool = True
    """Give every pole the id of its surveyed beacon as located through GPS
    (:func:`gps_reference_labels`) in ``feat_true_id``: what lets ``correct_pairings`` and
    ``--association truth`` work on this real run.  A GPS-based label, not ground truth."""
    laser_time_offset_s: float = 0.0
    """Added to ``TimeLaser`` before use.  The raw clock is kept by default; the beacon
    projections fit best with −0.03 s (range residuals of the GPS-aligned dead reckoning
    are unbiased there), which suggests a 30 ms scanner latency."""
    bearing_offset_rad: float = 0.0
    """Added to every bearing (laser yaw misalignment).  Kept 0; the surveyed beacons
    appear about 0.5–0.7° clockwise of their measured bearing from the GPS-aligned dead
    reckoning, which this parameter can absorb."""

    def __post_init__(self) -> None:
        for name in (
            "pole_radius_m",
            "pole_radius_sigma_m",
            "sigma_range_m",
            "sigma_bearing_rad",
            "max_range_m",
            "cluster_max_gap_m",
            "max_cluster_width_m",
        ):
            check_finite("CarparkOptions", name, getattr(self, name), positive=True)
        for name in ("laser_time_offset_s", "bearing_offset_rad"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"CarparkOptions.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"CarparkOptions.{name} must be finite, got {value}")
        gap = self.cluster_max_beam_gap
        if isinstance(gap, bool) or not isinstance(gap, int) or gap < 1:
            raise ValueError(
                f"CarparkOptions.cluster_max_beam_gap must be an int >= 1, got {gap!r}"
            )
