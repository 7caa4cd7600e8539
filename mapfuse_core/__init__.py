"""mapfuse_core: geometry, features, scenarios, sensing, matching and evaluation.

numpy, scipy and networkx only (plots live in the harness, :mod:`mapfuse.plotting`).
Poses are ``(x, y, θ)`` everywhere.
"""

from mapfuse_core.ccda import CCDAParams, CCDAResult, ccda_match, estimate_transform
from mapfuse_core.extraction import (
    ExtractedFeature,
    ExtractionParams,
    ExtractionResult,
    extract_features,
)
from mapfuse_core.features import (
    FeatureKind,
    canonical_line,
    circle_pairing,
    express_in,
    line_from_normal,
    line_pairing,
    line_to_normal,
    normal_to_line,
    observe,
    pairing_residual,
    transform_feature,
)
from mapfuse_core.laser import LaserParams, Scan, cast_rays, simulate_scan
from mapfuse_core.measlog import (
    KnownMapArrays,
    MeasurementLog,
    MeasurementLogError,
    load_log,
    save_log,
)
from mapfuse_core.scenario import (
    Scenario,
    ScenarioError,
    build_known_map,
    list_builtin_scenarios,
    load_scenario,
)
from mapfuse_core.se2 import compose, compose_jacobians, inverse, inverse_jacobian, relative
from mapfuse_core.simulate import SimulationResult, simulate
from mapfuse_core.vehicle import MotionResult, VehicleParams, car_increment, simulate_motion
from mapfuse_core.world import CircleObstacle, WallSegment, World

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
