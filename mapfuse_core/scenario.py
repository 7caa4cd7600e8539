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

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapfuse_core.features import FeatureKind, express_in
from mapfuse_core.laser import LaserParams, cast_rays
from mapfuse_core.se2 import FloatArray, wrap_angle
from mapfuse_core.vehicle import MotionResult, VehicleParams, simulate_controls, simulate_motion
from mapfuse_core.world import CircleObstacle, WallSegment, World

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

IntArray = NDArray[np.int64]


class ScenarioError(ValueError):
    """A scenario file is invalid: names the file, the dotted key and the reason."""

    def __init__(self, file: str, key: str, reason: str) -> None:
        self.file = file
        """The scenario file (or the name that was looked up)."""
        self.key = key
        """Dotted path of the offending key, e.g. ``world.circles[3].radius`` ("" for the file)."""
        self.reason = reason
        """What is wrong, in words."""
        where = f"{file}: {key}" if key else file
        super().__init__(f"{where}: {reason}")


# --------------------------------------------------------------------------- data model


@dataclass(frozen=True)
class FeatureMove:
    """A deliberate error of the known map: it holds feature ``id`` at a displaced place.

    Offsets are in the world frame; a line is rotated about its midpoint.
    """

    id: int
    """Feature id (must be held by the known map)."""
    dx: float
    """Displacement of the line midpoint or circle centre along x (m)."""
    dy: float
    """Displacement along y (m)."""
    dtheta: float
    """Rotation of a line about its midpoint (rad); 0 for circles."""
    dr: float
    """Change of a circle's radius (m); 0 for lines."""


@dataclass(frozen=True)
class ControlSegment:
    """A stretch of the drive at constant true controls (a ``trajectory.controls`` row)."""

    speed_mps: float
    """Speed ``v`` of the rear axle (m/s); negative reverses, 0 stands still."""
    steer_rad: float
    """Steering angle ``φ`` (rad), ``|φ| ≤ VehicleParams.max_steer_rad``; positive turns left."""
    steps: int
    """Number of steps ``n ≥ 1`` driven with these controls."""


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class KnownMapSpec:
    """What the a-priori known map holds and how uncertain it is (paper eq. 11).

    The map is block-diagonal: every feature has an independent diagonal covariance,
    ``diag(σxy², σxy², σθ²)`` for lines and ``diag(σxy², σxy², σr²)`` for circles.
    """

    world_ids: tuple[int, ...]
    """World feature ids the map holds (after ``ids = "all"`` and ``added`` are applied)."""
    sigma_xy_m: float
    """Standard deviation of feature coordinates (m): line midpoints and circle centres."""
    sigma_r_m: float
    """Standard deviation of circle radii (m)."""
    sigma_theta_rad: float
    """Standard deviation of line angles (rad)."""
    frame: FloatArray
    """``x^W_Wknown``: pose of the map's frame in the world (usually zero)."""
    moved: tuple[FeatureMove, ...]
    """Features the map holds at a displaced place."""
    removed: tuple[WallSegment | CircleObstacle, ...]
    """Features the map holds that the world no longer has (ids not in the world)."""
    added: tuple[int, ...]
    """World ids that are new since the map was made: never in the map."""

    @property
    def ids(self) -> tuple[int, ...]:
        """All ids the map holds, sorted: held world features and removed ones."""
        return tuple(sorted((*self.world_ids, *(f.id for f in self.removed))))


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario.  Arrays are read-only."""

    name: str
    """Scenario name (``[scenario].name``, else the file stem)."""
    description: str
    """Free text from the file."""
    source: str
    """Path of the TOML file it was loaded from."""
    seed: int
    """Default random seed of the simulation (≥ 0)."""
    world: World
    """The ground-truth world."""
    start: FloatArray
    """(3,) true start pose ``(x, y, θ)`` in ``W``."""
    steps: int
    """Number of poses to simulate (≥ 2), the start included; with :attr:`controls`, at
    most one more than the steps they drive (fewer shortens the drive)."""
    waypoints: FloatArray
    """(K, 2) path the pure-pursuit driver follows, K ≥ 2; (0, 2) when the drive is given
    by :attr:`controls` instead."""
    controls: tuple[ControlSegment, ...]
    """The true controls the car is driven with, stretch by stretch; empty when it
    follows :attr:`waypoints`."""
    vehicle: VehicleParams
    """Vehicle model, odometry noise and driver."""
    laser: LaserParams
    """Laser scanner geometry and noise."""
    known_map: KnownMapSpec
    """What the a-priori map holds."""


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class KnownMap:
    """A realisation of the known map: one noisy draw from its stated σ.

    ``true_params`` are the features as the map *should* hold them (the world's,
    or the removed ones, with the deliberate ``moved`` changes applied), expressed in
    the map frame.  ``params = true_params + n`` with ``n ~ N(0, covs)`` drawn once
    per map, so the map's covariance is honest: the estimator is told the σ the error
    really has.  Lines are SPmap frames at the wall midpoint, x axis from ``p1`` to
    ``p2``; circles are ``(x, y, r)``.  A noisy radius ≤ 0 (possible for thin poles
    with σr comparable to r) is redrawn, which truncates that one variable's tail.
    """

    ids: IntArray
    """(M,) int64 feature ids, sorted."""
    kinds: NDArray[np.int8]
    """(M,) int8 :class:`FeatureKind` codes."""
    params: FloatArray
    """(M, 3) noisy parameters in the map frame."""
    covs: FloatArray
    """(M, 3, 3) diagonal covariances of :attr:`params` in the map frame."""
    true_params: FloatArray
    """(M, 3) noise-free, change-applied parameters in the map frame."""
    frame: FloatArray
    """(3,) ``x^W_Wknown`` the map is expressed in."""

    def __len__(self) -> int:
        return int(self.ids.shape[0])


# --------------------------------------------------------------------------- loading


def list_builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``mapfuse_core/scenarios``."""
    folder = resources.files("mapfuse_core") / "scenarios"
    return sorted(
        p.name[: -len(".toml")]
        for p in folder.iterdir()
        if p.name.endswith(".toml") and p.is_file()
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a built-in scenario by name (``"loop600"``) or a TOML file by path.

    A string is a built-in name unless it ends in ``.toml`` or contains a path
    separator.  Raises :class:`ScenarioError` for every problem.
    """
    is_path = isinstance(name_or_path, Path) or (
        name_or_path.endswith(".toml") or "/" in name_or_path or "\\" in name_or_path
    )
    if is_path:
        path = Path(name_or_path)
        source = str(path)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise ScenarioError(source, "", "file not found") from None
        except OSError as e:
            raise ScenarioError(source, "", f"cannot read the file: {e}") from None
        stem = path.stem
    else:
        name = str(name_or_path)
        builtins = list_builtin_scenarios()
        if name not in builtins:
            raise ScenarioError(
                name,
                "",
                f"no built-in scenario of that name (built-ins: {', '.join(builtins)}); "
                "give a path to a .toml file instead",
            )
        res = resources.files("mapfuse_core") / "scenarios" / f"{name}.toml"
        source = str(res)
        raw = res.read_bytes()
        stem = name
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScenarioError(source, "", f"not UTF-8 text: {e}") from None
    return scenario_from_toml(text, source, stem)


def scenario_from_toml(text: str, source: str = "<string>", stem: str = "scenario") -> Scenario:
    """Parse and validate a scenario from TOML text, as :func:`load_scenario` does a
    file (``source`` names it in errors; ``stem`` is the name when it gives none)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(source, "", f"invalid TOML: {e}") from None
    return _parse(doc, source, stem)


# --------------------------------------------------------------------------- validation


class _Reader:
    """Typed access to a parsed TOML document, raising ScenarioError with dotted keys."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, reason: str) -> ScenarioError:
        return ScenarioError(self.source, key, reason)

    def table(
        self,
        value: object,
        key: str,
        required: Sequence[str] = (),
        optional: Sequence[str] = (),
    ) -> dict[str, Any]:
        """A table with exactly the allowed keys and at least the required ones."""
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a table, got {_tname(value)}")
        allowed = set(required) | set(optional)
        for k in value:
            if k not in allowed:
                hint = f"; allowed: {', '.join(sorted(allowed))}" if allowed else ""
                raise self.fail(_join(key, k), f"unknown key{hint}")
        for k in required:
            if k not in value:
                raise self.fail(_join(key, k), "missing required key")
        return value

    def number(
        self,
        value: object,
        key: str,
        *,
        positive: bool = False,
        nonneg: bool = False,
        angle: bool = False,
    ) -> float:
        """A finite float (ints accepted); angles may be ``"k*pi/n"`` strings."""
        if angle and isinstance(value, str):
            x = _parse_pi(value)
            if x is None:
                raise self.fail(
                    key, f"cannot read angle {value!r}: write a number or e.g. 'pi/3', '-2*pi/5'"
                )
        elif isinstance(value, bool) or not isinstance(value, int | float):
            what = "a number or a 'k*pi/n' string" if angle else "a number"
            raise self.fail(key, f"must be {what}, got {_tname(value)}")
        else:
            x = float(value)
        if not math.isfinite(x):
            raise self.fail(key, f"must be finite, got {x}")
        if positive and x <= 0.0:
            raise self.fail(key, f"must be > 0, got {x}")
        if nonneg and x < 0.0:
            raise self.fail(key, f"must be >= 0, got {x}")
        return x

    def integer(self, value: object, key: str, *, minimum: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"must be an integer, got {_tname(value)}")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {value}")
        return value

    def string(self, value: object, key: str) -> str:
        if not isinstance(value, str):
            raise self.fail(key, f"must be a string, got {_tname(value)}")
        return value

    def array(self, value: object, key: str) -> list[Any]:
        if not isinstance(value, list):
            raise self.fail(key, f"must be an array, got {_tname(value)}")
        return value

    def vector(self, value: object, key: str, n: int, angle_last: bool = False) -> list[float]:
        items = self.array(value, key)
        if len(items) != n:
            raise self.fail(key, f"must have {n} entries, got {len(items)}")
        return [
            self.number(v, f"{key}[{i}]", angle=angle_last and i == n - 1)
            for i, v in enumerate(items)
        ]

    def feature_id(self, value: object, key: str) -> int:
        return self.integer(value, key, minimum=0)


_PI_RE = re.compile(
    r"^\s*(?P<sign>[+-]?)\s*(?:(?P<k>\d+(?:\.\d*)?|\.\d+)\s*\*\s*)?pi"
    r"\s*(?:/\s*(?P<n>\d+(?:\.\d*)?|\.\d+))?\s*$"
)


def _parse_pi(text: str) -> float | None:
    """``[±][k*]pi[/n]`` → float, else ``None``."""
    m = _PI_RE.match(text)
    if m is None:
        return None
    k = float(m["k"]) if m["k"] else 1.0
    n = float(m["n"]) if m["n"] else 1.0
    if n == 0.0:
        return None
    x = k * math.pi / n
    return -x if m["sign"] == "-" else x


def _tname(value: object) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return f"{type(value).__name__} {value!r}"


def _join(key: str, sub: str) -> str:
    return f"{key}.{sub}" if key else sub


_SEGMENT_KEYS = ("id", "p1", "p2")
_CIRCLE_KEYS = ("id", "centre", "radius")


def _segments(r: _Reader, value: object, key: str) -> Iterator[tuple[str, WallSegment]]:
    for i, item in enumerate(r.array(value, key)):
        k = f"{key}[{i}]"
        t = r.table(item, k, required=_SEGMENT_KEYS)
        fid = r.feature_id(t["id"], f"{k}.id")
        p1 = r.vector(t["p1"], f"{k}.p1", 2)
        p2 = r.vector(t["p2"], f"{k}.p2", 2)
        if math.hypot(p2[0] - p1[0], p2[1] - p1[1]) <= 1e-6:
            raise r.fail(f"{k}.p2", "zero-length segment: p2 equals p1")
        yield f"{k}.id", WallSegment(id=fid, p1=(p1[0], p1[1]), p2=(p2[0], p2[1]))


def _circles(r: _Reader, value: object, key: str) -> Iterator[tuple[str, CircleObstacle]]:
    for i, item in enumerate(r.array(value, key)):
        k = f"{key}[{i}]"
        t = r.table(item, k, required=_CIRCLE_KEYS)
        fid = r.feature_id(t["id"], f"{k}.id")
        c = r.vector(t["centre"], f"{k}.centre", 2)
        radius = r.number(t["radius"], f"{k}.radius", positive=True)
        yield f"{k}.id", CircleObstacle(id=fid, centre=(c[0], c[1]), radius=radius)


def _features(
    r: _Reader, t: dict[str, Any], key: str
) -> tuple[list[WallSegment], list[CircleObstacle], dict[int, str]]:
    """Segments and circles of a ``{segments, circles}`` table; ids unique within it."""
    seen: dict[int, str] = {}
    segs: list[WallSegment] = []
    circs: list[CircleObstacle] = []

    def note(id_key: str, fid: int) -> None:
        if fid in seen:
            raise r.fail(id_key, f"duplicate id {fid} (also {seen[fid]})")
        seen[fid] = id_key

    for id_key, s in _segments(r, t.get("segments", []), _join(key, "segments")):
        note(id_key, s.id)
        segs.append(s)
    for id_key, c in _circles(r, t.get("circles", []), _join(key, "circles")):
        note(id_key, c.id)
        circs.append(c)
    return segs, circs, seen


def _params_from(
    r: _Reader, value: object, key: str, cls: type[VehicleParams] | type[LaserParams]
) -> Any:
    """Build ``cls`` from a table of overrides of its fields (defaults for the rest).

    Every value is type-checked here and then tried alone in ``cls`` so that the
    class's own validation is reported against the right key.
    """
    defaults = cls()
    t = r.table(value, key, optional=list(cls.__dataclass_fields__))
    kwargs: dict[str, Any] = {}
    for name, raw in t.items():
        k = _join(key, name)
        default = getattr(defaults, name)
        angle = name.endswith("_rad") or name == "sigma_phi"
        if isinstance(default, int) and not isinstance(default, bool):
            v: Any = r.integer(raw, k)
        elif isinstance(default, tuple):
            v = tuple(r.vector(raw, k, len(default), angle_last=True))
            for j, x in enumerate(v):
                if x <= 0.0:
                    raise r.fail(f"{k}[{j}]", f"must be > 0, got {x}")
        else:
            v = r.number(raw, k, positive=True, angle=angle)
        try:
            cls(**{name: v})
        except ValueError as e:
            raise r.fail(k, str(e)) from None
        kwargs[name] = v
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise r.fail(key, str(e)) from None


def _parse(doc: dict[str, Any], source: str, stem: str) -> Scenario:
    r = _Reader(source)
    top = r.table(
        doc,
        "",
        required=("scenario", "trajectory", "world", "known_map"),
        optional=("vehicle", "laser"),
    )

    meta = r.table(
        top["scenario"], "scenario", required=("seed",), optional=("name", "description")
    )
    name = r.string(meta["name"], "scenario.name") if "name" in meta else stem
    if not name.strip():
        raise r.fail("scenario.name", "must not be empty")
    description = (
        r.string(meta["description"], "scenario.description") if "description" in meta else ""
    )
    seed = r.integer(meta["seed"], "scenario.seed", minimum=0)

    start, steps, waypoints, controls = _parse_trajectory(r, top["trajectory"])
    vehicle: VehicleParams = _params_from(r, top.get("vehicle", {}), "vehicle", VehicleParams)
    laser: LaserParams = _params_from(r, top.get("laser", {}), "laser", LaserParams)
    for i, c in enumerate(controls):
        if abs(c.steer_rad) > vehicle.max_steer_rad:
            raise r.fail(
                f"trajectory.controls[{i}][1]",
                f"steering {c.steer_rad:.6g} rad is beyond the vehicle's steering limit "
                f"vehicle.max_steer_rad = {vehicle.max_steer_rad:.6g}",
            )

    wt = r.table(top["world"], "world", optional=("segments", "circles"))
    segs, circs, world_keys = _features(r, wt, "world")
    if not segs and not circs:
        raise r.fail("world", "the world is empty: give at least one segment or circle")
    try:
        world = World(segments=tuple(segs), circles=tuple(circs))
    except ValueError as e:  # pragma: no cover - every World check is done above
        raise r.fail("world", str(e)) from None
    known = _parse_known_map(r, top["known_map"], world, world_keys)
    return Scenario(
        name=name,
        description=description,
        source=source,
        seed=seed,
        world=world,
        start=start,
        steps=steps,
        waypoints=waypoints,
        controls=controls,
        vehicle=vehicle,
        laser=laser,
        known_map=known,
    )


def _parse_trajectory(
    r: _Reader, value: object
) -> tuple[FloatArray, int, FloatArray, tuple[ControlSegment, ...]]:
    """Start, number of poses, waypoints and controls of ``[trajectory]`` (one of the two
    given, the other empty); the steering limit is checked once the vehicle is known."""
    key = "trajectory"
    traj = r.table(value, key, required=("start",), optional=("steps", "waypoints", "controls"))
    start = np.array(r.vector(traj["start"], f"{key}.start", 3, angle_last=True))
    start[2] = float(wrap_angle(start[2]))
    start.setflags(write=False)
    if "waypoints" in traj and "controls" in traj:
        raise r.fail(f"{key}.controls", "give either waypoints or controls, not both")
    if "controls" not in traj:
        if "waypoints" not in traj:
            raise r.fail(
                key,
                "no drive: give waypoints = [[x, y], ...] (with steps) "
                "or controls = [[v, phi, n], ...]",
            )
        if "steps" not in traj:
            raise r.fail(f"{key}.steps", "missing required key")
        steps = r.integer(traj["steps"], f"{key}.steps", minimum=2)
        wp_items = r.array(traj["waypoints"], f"{key}.waypoints")
        if len(wp_items) < 2:
            raise r.fail(f"{key}.waypoints", f"needs at least 2 waypoints, got {len(wp_items)}")
        waypoints = np.array(
            [r.vector(w, f"{key}.waypoints[{i}]", 2) for i, w in enumerate(wp_items)]
        )
        for i in range(1, waypoints.shape[0]):
            if np.hypot(*(waypoints[i] - waypoints[i - 1])) <= 1e-6:
                raise r.fail(f"{key}.waypoints[{i}]", "repeats the previous waypoint")
        waypoints.setflags(write=False)
        return start, steps, waypoints, ()

    rows = r.array(traj["controls"], f"{key}.controls")
    if not rows:
        raise r.fail(f"{key}.controls", "needs at least one control [v, phi, n]")
    controls: list[ControlSegment] = []
    for i, row in enumerate(rows):
        k = f"{key}.controls[{i}]"
        items = r.array(row, k)
        if len(items) != 3:
            raise r.fail(k, f"must be [v, phi, n] (3 entries), got {len(items)} entries")
        controls.append(
            ControlSegment(
                speed_mps=r.number(items[0], f"{k}[0]"),
                steer_rad=r.number(items[1], f"{k}[1]", angle=True),
                steps=r.integer(items[2], f"{k}[2]", minimum=1),
            )
        )
    driven = sum(c.steps for c in controls)
    steps = driven + 1
    if "steps" in traj:
        given = r.integer(traj["steps"], f"{key}.steps", minimum=2)
        if given != steps:
            raise r.fail(
                f"{key}.steps",
                f"is {given} but the controls drive {driven} steps, i.e. {steps} poses with "
                "the start (leave steps out to take it from the controls)",
            )
    waypoints = np.zeros((0, 2))
    waypoints.setflags(write=False)
    return start, steps, waypoints, tuple(controls)


def _parse_known_map(
    r: _Reader,
    value: object,
    world: World,
    world_keys: Mapping[int, str],
) -> KnownMapSpec:
    key = "known_map"
    t = r.table(
        value,
        key,
        required=("ids", "sigma_xy_m", "sigma_r_m", "sigma_theta_rad"),
        optional=("frame", "moved", "removed", "added"),
    )
    sigma_xy = r.number(t["sigma_xy_m"], f"{key}.sigma_xy_m", positive=True)
    sigma_r = r.number(t["sigma_r_m"], f"{key}.sigma_r_m", positive=True)
    sigma_th = r.number(t["sigma_theta_rad"], f"{key}.sigma_theta_rad", positive=True, angle=True)
    frame = np.array(r.vector(t.get("frame", [0.0, 0.0, 0.0]), f"{key}.frame", 3, True))
    frame[2] = float(wrap_angle(frame[2]))
    frame.setflags(write=False)

    added: list[int] = []
    for i, v in enumerate(r.array(t.get("added", []), f"{key}.added")):
        k = f"{key}.added[{i}]"
        fid = r.feature_id(v, k)
        if fid not in world_keys:
            raise r.fail(k, f"id {fid} is not in the world (added features are world features)")
        if fid in added:
            raise r.fail(k, f"duplicate id {fid}")
        added.append(fid)

    ids_value = t["ids"]
    if isinstance(ids_value, str):
        if ids_value != "all":
            raise r.fail(f"{key}.ids", f'must be an array of ids or "all", got {ids_value!r}')
        held = [fid for fid in world_keys if fid not in added]
    else:
        held = []
        for i, v in enumerate(r.array(ids_value, f"{key}.ids")):
            k = f"{key}.ids[{i}]"
            fid = r.feature_id(v, k)
            if fid not in world_keys:
                raise r.fail(k, f"id {fid} is not in the world")
            if fid in held:
                raise r.fail(k, f"duplicate id {fid}")
            if fid in added:
                raise r.fail(k, f"id {fid} is also listed in {key}.added (new since the map)")
            held.append(fid)

    removed: list[WallSegment | CircleObstacle] = []
    kinds = {fid: world.feature(fid)[0] for fid in held}
    if "removed" in t:
        rt = r.table(t["removed"], f"{key}.removed", optional=("segments", "circles"))
        segs, circs, rkeys = _features(r, rt, f"{key}.removed")
        for fid, k in rkeys.items():
            if fid in world_keys:
                raise r.fail(
                    k,
                    f"id {fid} is in the world ({world_keys[fid]}); removed features are "
                    "gone from the world and need ids of their own",
                )
        removed = [*segs, *circs]
        kinds |= {s.id: FeatureKind.LINE for s in segs}
        kinds |= {c.id: FeatureKind.CIRCLE for c in circs}
    if not kinds:
        raise r.fail(f"{key}.ids", "the known map holds no feature")

    radii = {c.id: c.radius for c in (*world.circles, *removed) if isinstance(c, CircleObstacle)}
    moves: list[FeatureMove] = []
    moved_ids: set[int] = set()
    for i, item in enumerate(r.array(t.get("moved", []), f"{key}.moved")):
        k = f"{key}.moved[{i}]"
        mt = r.table(item, k, required=("id",), optional=("dx", "dy", "dtheta", "dr"))
        fid = r.feature_id(mt["id"], f"{k}.id")
        if fid not in kinds:
            raise r.fail(f"{k}.id", f"id {fid} is not in the known map")
        if fid in moved_ids:
            raise r.fail(f"{k}.id", f"id {fid} is moved twice")
        moved_ids.add(fid)
        kind = kinds[fid]
        if kind == FeatureKind.LINE and "dr" in mt:
            raise r.fail(f"{k}.dr", f"feature {fid} is a line: it has no radius")
        if kind == FeatureKind.CIRCLE and "dtheta" in mt:
            raise r.fail(f"{k}.dtheta", f"feature {fid} is a circle: it has no angle")
        move = FeatureMove(
            id=fid,
            dx=r.number(mt.get("dx", 0.0), f"{k}.dx"),
            dy=r.number(mt.get("dy", 0.0), f"{k}.dy"),
            dtheta=r.number(mt.get("dtheta", 0.0), f"{k}.dtheta", angle=True),
            dr=r.number(mt.get("dr", 0.0), f"{k}.dr"),
        )
        if kind == FeatureKind.CIRCLE:
            radius = radii[fid]
            if radius + move.dr <= 0.0:
                raise r.fail(
                    f"{k}.dr", f"moves the radius {radius:g} m to {radius + move.dr:.6g} m <= 0"
                )
        moves.append(move)

    return KnownMapSpec(
        world_ids=tuple(sorted(held)),
        sigma_xy_m=sigma_xy,
        sigma_r_m=sigma_r,
        sigma_theta_rad=sigma_th,
        frame=frame,
        moved=tuple(moves),
        removed=tuple(removed),
        added=tuple(sorted(added)),
    )


# --------------------------------------------------------------------------- known map


def _true_map_feature(spec: KnownMapSpec, world: World, fid: int) -> tuple[FeatureKind, FloatArray]:
    """Kind and world-frame parameters of map feature ``fid``, with its move applied."""
    removed = {f.id: f for f in spec.removed}
    if fid in removed:
        f = removed[fid]
        kind, p = (
            (FeatureKind.LINE, f.spmap())
            if isinstance(f, WallSegment)
            else (FeatureKind.CIRCLE, f.params())
        )
    else:
        kind, p = world.feature(fid)
    p = p.copy()
    for m in spec.moved:
        if m.id == fid:
            p[0] += m.dx
            p[1] += m.dy
            if kind == FeatureKind.LINE:
                p[2] = float(wrap_angle(p[2] + m.dtheta))
            else:
                p[2] += m.dr
    return kind, p


def build_known_map(scenario: Scenario, rng: np.random.Generator) -> KnownMap:
    """Realise the scenario's known map with one seeded draw of its noise.

    For every held id (sorted): take the world feature (or the removed one), apply the
    deliberate ``moved`` change, express it in the map frame (``⊖frame ⊕ f``); those are
    ``true_params``.  Then add ``N(0, diag σ²)`` drawn from ``rng`` (one ``(M, 3)`` draw,
    so the map depends on the seed only).  See :class:`KnownMap`.
    """
    spec = scenario.known_map
    ids = np.array(spec.ids, dtype=np.int64)
    m = ids.shape[0]
    kinds = np.zeros(m, dtype=np.int8)
    true_params = np.zeros((m, 3))
    sig = np.zeros((m, 3))
    for i, fid in enumerate(spec.ids):
        kind, p_W = _true_map_feature(spec, scenario.world, fid)
        true_params[i] = express_in(kind, spec.frame, p_W)[0]
        kinds[i] = int(kind)
        third = spec.sigma_theta_rad if kind == FeatureKind.LINE else spec.sigma_r_m
        sig[i] = (spec.sigma_xy_m, spec.sigma_xy_m, third)
    params = true_params + sig * rng.normal(size=(m, 3))
    lines = kinds == int(FeatureKind.LINE)
    params[lines, 2] = wrap_angle(params[lines, 2])
    # Redraw non-positive radii (truncated normal): a circle must keep r > 0.
    while True:
        bad = np.nonzero(~lines & (params[:, 2] <= 0.0))[0]
        if bad.size == 0:
            break
        params[bad, 2] = true_params[bad, 2] + sig[bad, 2] * rng.normal(size=bad.size)
    covs = np.zeros((m, 3, 3))
    covs[:, [0, 1, 2], [0, 1, 2]] = sig**2
    for a in (ids, kinds, params, covs, true_params):
        a.setflags(write=False)
    return KnownMap(
        ids=ids,
        kinds=kinds,
        params=params,
        covs=covs,
        true_params=true_params,
        frame=np.array(spec.frame),
    )


# --------------------------------------------------------------------------- drive


def control_table(controls: Sequence[ControlSegment]) -> FloatArray:
    """(Σ n, 2) true controls ``(v, φ)`` step by step: each segment repeated ``steps`` times."""
    if not controls:
        return np.zeros((0, 2))
    vphi = np.array([(c.speed_mps, c.steer_rad) for c in controls], dtype=np.float64)
    return np.repeat(vphi, [c.steps for c in controls], axis=0)


def simulate_drive(scenario: Scenario, rng: np.random.Generator) -> MotionResult:
    """The scenario's true drive and odometry over ``scenario.steps`` poses.

    Pure pursuit through :attr:`Scenario.waypoints`
    (:func:`~mapfuse_core.vehicle.simulate_motion`), or the first ``steps − 1`` rows of
    the :attr:`Scenario.controls` table (:func:`~mapfuse_core.vehicle.simulate_controls`);
    the noise is drawn from ``rng`` the same way for both.
    """
    if not scenario.controls:
        return simulate_motion(
            scenario.start, scenario.waypoints, scenario.steps, scenario.vehicle, rng
        )
    table = control_table(scenario.controls)
    if not 2 <= scenario.steps <= table.shape[0] + 1:
        raise ValueError(
            f"steps must be in [2, {table.shape[0] + 1}] for these controls, got {scenario.steps}"
        )
    return simulate_controls(scenario.start, table[: scenario.steps - 1], scenario.vehicle, rng)


# --------------------------------------------------------------------------- visibility


def features_in_view(world: World, poses: FloatArray, laser: LaserParams) -> IntArray:
    """Number of distinct features hit by the noise-free beams of ``laser`` from each pose.

    ``poses`` is (P, 3), the sensor at each pose; returns (P,) int64 counts.
    """
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    bearings = laser.bearings()
    out = np.zeros(P.shape[0], dtype=np.int64)
    for k in range(P.shape[0]):
        _, ids = cast_rays(world, P[k], P[k, 2] + bearings, laser.max_range_m)
        out[k] = np.unique(ids[ids >= 0]).size
    return out


def check_visibility(scenario: Scenario, motion: MotionResult, stride: int = 8) -> IntArray:
    """Check that the drive sees the world; return the feature counts at the sampled steps.

    Every ``stride``-th true pose (and the last) is checked with noise-free rays.
    Raises :class:`ScenarioError` (key ``trajectory``) when no sampled pose sees any
    feature: such a scenario cannot exercise anything.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    n = motion.true_poses.shape[0]
    steps = np.unique(np.append(np.arange(0, n, stride), n - 1))
    counts = features_in_view(scenario.world, motion.true_poses[steps], scenario.laser)
    if counts.max(initial=0) == 0:
        raise ScenarioError(
            scenario.source,
            "trajectory",
            f"no feature is within {scenario.laser.max_range_m} m in the field of view at any "
            f"of {steps.size} sampled poses: the trajectory never sees the world",
        )
    return counts
