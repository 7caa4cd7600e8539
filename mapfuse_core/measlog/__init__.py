"""The measurement log, the single input every estimator consumes, and the known map
it carries (``docs/conventions.md``).  Bottom-layer types: simulation, datasets,
matching and evaluation all read or build them."""

from mapfuse_core.measlog.known_map import KnownMapArrays
from mapfuse_core.measlog.log import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MeasurementLog,
    MeasurementLogError,
    load_log,
    save_log,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "KnownMapArrays",
    "MeasurementLog",
    "MeasurementLogError",
    "load_log",
    "save_log",
]
