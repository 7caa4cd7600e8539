"""Scenarios: TOML files describing a world, a drive, the sensors and a known map.

A scenario is validated completely when it is loaded: any problem raises
:class:`ScenarioError` naming the file, the dotted key (``world.circles[3].radius``)
and the reason, so a typo never silently falls back to a default.

File layout (every section rejects keys it does not know)::

    [scenario]    name?, description?, seed
    [trajectory]  start = [x, y, θ], and either
                  steps, waypoints = [[x, y], …]             (pure pursuit, constant speed)
                  or controls = [[v, φ, n], …], steps?       (n steps at speed v, steering φ)
    [vehicle]     optional overrides of VehicleParams fields
    [laser]       optional overrides of LaserParams fields
    [world]       segments = [{id, p1, p2}, …], circles = [{id, centre, radius}, …]
    [known_map]   ids = [...] | "all", sigma_xy_m, sigma_r_m, sigma_theta_rad,
                  frame?, moved?, added?, [known_map.removed] segments?, circles?

Angles may be written as numbers or as multiples of π in a string (``"pi/3"``,
``"-pi/2"``, ``"2*pi"``), which keeps values such as Table 1's σβ = π/720 exact and
readable.  Feature ids are non-negative integers (−1 means "no feature" in logs).

The visibility of the features along the trajectory needs the driven path, so it is
checked by :func:`check_visibility` (called by the simulator), not on load.
"""

from mapfuse_core.sim.scenario.drive import (
    check_visibility,
    control_table,
    features_in_view,
    simulate_drive,
)
from mapfuse_core.sim.scenario.known_map import build_known_map
from mapfuse_core.sim.scenario.parse import (
    list_builtin_scenarios,
    load_scenario,
    scenario_from_toml,
)
from mapfuse_core.sim.scenario.types import (
    ControlSegment,
    FeatureMove,
    KnownMap,
    KnownMapSpec,
    Scenario,
    ScenarioError,
)

__all__ = [
    "ControlSegment",
    "FeatureMove",
    "KnownMap",
    "KnownMapSpec",
    "Scenario",
    "ScenarioError",
    "build_known_map",
    "check_visibility",
    "control_table",
    "features_in_view",
    "list_builtin_scenarios",
    "load_scenario",
    "scenario_from_toml",
    "simulate_drive",
]
