"""Real datasets as measurement logs: the ACFR car park, Victoria Park, CARMEN logs.

The files are read from a directory the caller gives (the project never ships them);
``docs/real-data.md`` describes both datasets, their provenance and their conventions.

Frames of a log built here (checked against the data in
``tests/test_datasets_carpark.py`` and ``tests/test_datasets_victoria.py``):

* The log's frame ``R`` of every step is the **laser** frame: odometry increments are
  those of the laser point and features are given in it.  With bearing β
  counter-clockwise from the laser's forward axis, a return at range ρ is at
  ``ρ (cos β, sin β)``.
* GPS fixes and the car park's surveyed beacons are (East, North) metres in one frame;
  ``gps_times`` are on the clock of ``timestamps``.

One responsibility per module: :mod:`~mapfuse_core.data.datasets.odometry` (car model,
odometry integration and its noise), :mod:`~mapfuse_core.data.datasets.poles` (the car
park's pole detector), :mod:`~mapfuse_core.data.datasets.gps` (GPS reference labels),
:mod:`~mapfuse_core.data.datasets.carpark` and :mod:`~mapfuse_core.data.datasets.victoria_park`
(the two loaders and their options), :mod:`~mapfuse_core.data.datasets.carmen_format` and
:mod:`~mapfuse_core.data.datasets.carmen` (CARMEN indoor laser logs, ``docs/real-data.md``),
:mod:`~mapfuse_core.data.datasets.floorplan` (a wall map from scans at reference poses),
:mod:`~mapfuse_core.data.datasets.line_noise` (a log's line model error, from its scans),
:mod:`~mapfuse_core.data.datasets.files` (checked file reading) and
:mod:`~mapfuse_core.data.datasets.common` (error type, log builder).

Every missing or malformed input raises :class:`DatasetError` naming the file and the
problem.
"""

from mapfuse_core.data.datasets.carmen import (
    CarmenOptions,
    IncrementNoise,
    carmen_association,
    detect_odometry_kind,
    load_carmen,
    redraw_odometry,
)
from mapfuse_core.data.datasets.carmen_format import read_carmen
from mapfuse_core.data.datasets.carpark import CARPARK_NAME, load_carpark
from mapfuse_core.data.datasets.carpark_options import CARPARK_ODOMETRY_NOISE, CarparkOptions
from mapfuse_core.data.datasets.common import DatasetError
from mapfuse_core.data.datasets.floorplan import (
    FloorPlan,
    FloorPlanParams,
    build_floor_plan,
    label_with_plan,
    line_nees,
    reference_labels,
    same_wall,
    wall_d2,
)
from mapfuse_core.data.datasets.gps import gps_reference_labels
from mapfuse_core.data.datasets.line_noise import (
    LineModelError,
    LineModelShape,
    LineTerms,
    estimate_line_model_error,
    with_line_model_error,
)
from mapfuse_core.data.datasets.odometry import (
    CarGeometry,
    OdometryNoise,
    dead_reckoning,
    integrate_odometry,
    rear_axle_speed,
)
from mapfuse_core.data.datasets.poles import detect_reflector_poles
from mapfuse_core.data.datasets.victoria_park import (
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
    "CarmenOptions",
    "CarparkOptions",
    "DatasetError",
    "FloorPlan",
    "FloorPlanParams",
    "IncrementNoise",
    "LineModelError",
    "LineModelShape",
    "LineTerms",
    "OdometryNoise",
    "VictoriaParkOptions",
    "build_floor_plan",
    "carmen_association",
    "dead_reckoning",
    "detect_odometry_kind",
    "detect_reflector_poles",
    "estimate_line_model_error",
    "gps_reference_labels",
    "integrate_odometry",
    "label_with_plan",
    "line_nees",
    "load_carmen",
    "load_carpark",
    "load_victoria_park",
    "read_carmen",
    "rear_axle_speed",
    "redraw_odometry",
    "reference_labels",
    "same_wall",
    "wall_d2",
    "with_line_model_error",
]
