"""mapfuse_core: the estimator-independent core, numpy and scipy only.

Subpackages mirror the method (``docs/method.md``): :mod:`~mapfuse_core.geometry`
(SE(2) and features), :mod:`~mapfuse_core.sim` (worlds, sensors, scenarios,
simulation), :mod:`~mapfuse_core.perception` (feature extraction),
:mod:`~mapfuse_core.matching` (CCDA), :mod:`~mapfuse_core.data` (measurement logs and
real datasets) and :mod:`~mapfuse_core.evaluation` (metrics and NEES statistics).
Poses are ``(x, y, θ)`` everywhere (``docs/conventions.md``).
"""

from mapfuse_core.geometry.features import (
    FeatureKind,
    canonical_line,
    express_in,
    line_from_normal,
    line_to_normal,
    normal_to_line,
    transform_feature,
)
from mapfuse_core.geometry.se2 import (
    compose,
    compose_jacobians,
    inverse,
    inverse_jacobian,
    relative,
)
from mapfuse_core.matching.ccda import CCDAParams, CCDAResult, ccda_match, estimate_transform
from mapfuse_core.measlog import (
    KnownMapArrays,
    MeasurementLog,
    MeasurementLogError,
    load_log,
    save_log,
)
from mapfuse_core.models import circle_pairing, line_pairing, observe, pairing_residual
from mapfuse_core.perception.extraction import (
    ExtractedFeature,
    ExtractionParams,
    ExtractionResult,
    extract_features,
)
from mapfuse_core.sensor import LaserParams, Scan
from mapfuse_core.sim.laser import cast_rays, simulate_scan
from mapfuse_core.sim.scenario import (
    Scenario,
    ScenarioError,
    build_known_map,
    list_builtin_scenarios,
    load_scenario,
)
from mapfuse_core.sim.simulate import SimulationResult, simulate
from mapfuse_core.sim.vehicle import MotionResult, VehicleParams, car_increment, simulate_motion
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

__all__ = [
    "CCDAParams",
    "CCDAResult",
    "CircleObstacle",
    "ExtractedFeature",
    "ExtractionParams",
    "ExtractionResult",
    "FeatureKind",
    "KnownMapArrays",
    "LaserParams",
    "MeasurementLog",
    "MeasurementLogError",
    "MotionResult",
    "Scan",
    "Scenario",
    "ScenarioError",
    "SimulationResult",
    "VehicleParams",
    "WallSegment",
    "World",
    "build_known_map",
    "canonical_line",
    "car_increment",
    "cast_rays",
    "ccda_match",
    "circle_pairing",
    "compose",
    "compose_jacobians",
    "estimate_transform",
    "express_in",
    "extract_features",
    "inverse",
    "inverse_jacobian",
    "line_from_normal",
    "line_pairing",
    "line_to_normal",
    "list_builtin_scenarios",
    "load_log",
    "load_scenario",
    "normal_to_line",
    "observe",
    "pairing_residual",
    "relative",
    "save_log",
    "simulate",
    "simulate_motion",
    "simulate_scan",
    "transform_feature",
]
