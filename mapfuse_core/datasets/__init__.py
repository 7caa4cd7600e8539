"""Real datasets as measurement logs: the ACFR car park and Victoria Park.

The files are read from a directory the caller gives (the project never ships them);
``docs/datasets.md`` describes both datasets, their provenance and their conventions.

Frames of a log built here (checked against the data in ``tests/test_datasets.py``):

* The log's frame ``R`` of every step is the **laser** frame: odometry increments are
  those of the laser point and features are given in it.  With bearing β
  counter-clockwise from the laser's forward axis, a return at range ρ is at
  ``ρ (cos β, sin β)``.
* GPS fixes and the car park's surveyed beacons are (East, North) metres in one frame;
  ``gps_times`` are on the clock of ``timestamps``.

One responsibility per module: :mod:`~mapfuse_core.datasets.odometry` (car model,
odometry integration and its noise), :mod:`~mapfuse_core.datasets.poles` (the car
park's pole detector), :mod:`~mapfuse_core.datasets.gps` (GPS reference labels),
:mod:`~mapfuse_core.datasets.carpark` and :mod:`~mapfuse_core.datasets.victoria_park`
(the two loaders and their options), :mod:`~mapfuse_core.datasets.files` (checked file
reading) and :mod:`~mapfuse_core.datasets.common` (error type, log builder).

Every missing or malformed input raises :class:`DatasetError` naming the file and the
problem.
"""

from mapfuse_core.datasets.carpark import (
    CARPARK_NAME,
    CARPARK_ODOMETRY_NOISE,
    CarparkOptions,
    load_carpark,
)
from mapfuse_core.datasets.common import DatasetError
from mapfuse_core.datasets.gps import gps_reference_labels
from mapfuse_core.datasets.odometry import (
    CarGeometry,
    OdometryNoise,
    dead_reckoning,
    integrate_odometry,
    rear_axle_speed,
)
from mapfuse_core.datasets.poles import detect_reflector_poles
from mapfuse_core.datasets.victoria_park import (
    VICTORIA_PARK_NAME,
    VICTORIA_PARK_ODOMETRY_NOISE,
    VictoriaParkOptions,
    load_victoria_park,
)

__all__ = [
    "CARPARK_NAME",
    "CARPARK_ODOMETRY_NOISE",
    "VICTORIA_PARK_NAME",
    "VICTORIA_PARK_ODOMETRY_NOISE",
    "CarGeometry",
    "CarparkOptions",
    "DatasetError",
    "OdometryNoise",
    "VictoriaParkOptions",
    "dead_reckoning",
    "detect_reflector_poles",
    "gps_reference_labels",
    "integrate_odometry",
    "load_carpark",
    "load_victoria_park",
    "rear_axle_speed",
]
