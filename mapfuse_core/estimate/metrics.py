"""A run's metrics as types: :class:`RunMetrics` and its parts.

One :class:`RunMetrics` per run, computed from its
:class:`~mapfuse_core.estimate.EstimatorResult` and log alone (the harness's
:func:`mapfuse.metrics.run_metrics`).  :meth:`RunMetrics.to_json` gives the
``metrics.json`` object, whose keys are those of the README's table;
:meth:`RunMetrics.from_json` reads one back (a baseline, a comparison).  Field names
are Python's; the JSON key of a field that differs is in its ``metadata["json"]``.
"""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any, Literal

__all__ = [
    "METRICS_SCHEMA_VERSION",
    "AnchorMetrics",
    "ErrorStats",
    "HeadingError",
    "MapMetrics",
    "MatchingMetrics",
    "NeesMeanInterval",
    "NeesSummary",
    "PositionError",
    "RunMetrics",
    "RuntimeMetrics",
]

#: Version of the ``metrics.json`` schema (its ``schema_version`` key; a file without
#: the key is version 1); a new key or a changed meaning raises it.  Version 2 names
#: ``nees.mean_interval.acceptance_95`` (version 1: ``interval_95``, still read).
METRICS_SCHEMA_VERSION = 2

#: Field metadata of an optional block, left out of the JSON when ``None``.
_OMIT: Mapping[str, Any] = {"omit_none": True}


def _to_json(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        out: dict[str, Any] = {}
        for f in fields(value):
            v = getattr(value, f.name)
            if v is None and f.metadata.get("omit_none"):
                continue
            out[f.metadata.get("json") or f.name] = _to_json(v)
        return out
    if isinstance(value, tuple | list):
        return [_to_json(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _to_json(v) for k, v in value.items()}
    return value


def _from_json(tp: Any, value: Any, where: str) -> Any:
    """``value`` (parsed JSON) as type ``tp``; :class:`ValueError` naming ``where``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _from_json(inner[0], value, where)
    if isinstance(tp, type) and is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ValueError(f"metrics: {where} must be an object, got {type(value).__name__}")
        hints = typing.get_type_hints(tp)
        kwargs: dict[str, Any] = {}
        for f in fields(tp):
            key = f.metadata.get("json") or f.name
            # A key of an older schema version names the same field.
            found = [k for k in (key, *f.metadata.get("json_old", ())) if k in value]
            if found:
                kwargs[f.name] = _from_json(hints[f.name], value[found[0]], f"{where}.{key}")
            elif f.default is MISSING and f.default_factory is MISSING:
                raise ValueError(f"metrics: {where} has no {key!r}")
        return tp(**kwargs)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ValueError(f"metrics: {where} must be a list, got {type(value).__name__}")
        item = typing.get_args(tp)[0]
        return tuple(_from_json(item, v, f"{where}[{i}]") for i, v in enumerate(value))
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ValueError(
                f"metrics: {where} must be one of {typing.get_args(tp)}, got {value!r}"
            )
        return value
    if tp is float:
        if value is None:
            return math.nan
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"metrics: {where} must be a number, got {value!r}")
        return float(value)
    if tp is int or tp is bool or tp is str:
        if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
            raise ValueError(f"metrics: {where} must be of type {tp.__name__}, got {value!r}")
        return value
    return value  # Mapping[str, Any] blocks are kept as parsed


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a non-negative error series."""

    rmse: float
    """Root mean square."""
    mean: float
    """Mean."""
    median: float
    """Median."""
    max: float
    """Largest value."""
    final: float
    """Value at the last step."""


@dataclass(frozen=True)
class PositionError(ErrorStats):
    """Vehicle position error (m): against truth in ``Wglobal`` (simulation), or against
    GPS at its fixes (real data, the fields below then set)."""

    reference: Literal["gps"] | None = field(default=None, metadata=_OMIT)
    """``"gps"`` when measured against GPS fixes; ``None`` against truth."""
    alignment: Literal["anchor", "best_fit"] | None = field(
        default=None, metadata={"omit_none": True}
    )
    """How the estimate was put in the GPS frame: through the run's anchor, or the rigid
    best fit of the whole trajectory to GPS (which favours the run)."""
    fixes: int | None = field(default=None, metadata=_OMIT)
    """GPS fixes inside the run."""
    x_gps_Wglobal: tuple[float, ...] | None = field(default=None, metadata=_OMIT)
    """(3,) pose of ``Wglobal`` in the GPS frame used."""


@dataclass(frozen=True)
class HeadingError:
    """Vehicle heading error (rad)."""

    rmse: float
    """Root mean square."""
    max: float
    """Largest absolute value."""


@dataclass(frozen=True)
class NeesMeanInterval:
    """Where a consistent estimator's mean NEES lies, allowing for the autocorrelation
    of the NEES series (:func:`mapfuse_core.evaluation.nees_mean_interval`)."""

    autocorrelation_steps: float
    """Integrated autocorrelation time τ of the NEES series (steps)."""
    effective_samples: float
    """``N / τ``: independent samples the mean is worth."""
    acceptance_95: tuple[float, ...] = field(metadata={"json_old": ("interval_95",)})
    """``(low, high)``: the two-sided 95 % acceptance region of a consistent
    estimator's mean NEES, around the 3 degrees of freedom: a run whose mean NEES lies
    outside it is inconsistent at the 5 % level.  Not a confidence interval of this
    run's mean (JSON ``acceptance_95``; schema version 1 called it ``interval_95``)."""

    @property
    def interval_95(self) -> tuple[float, ...]:
        """:attr:`acceptance_95` under its schema-1 name (kept for old callers)."""
        return self.acceptance_95


@dataclass(frozen=True)
class NeesSummary:
    """The 3-dof vehicle NEES over a run."""

    mean: float
    """Mean over the steps with a finite NEES (NaN when none)."""
    fraction_within_chi2_95: float
    """Fraction of those steps with NEES ≤ :attr:`bound`."""
    bound: float
    """χ²(3, 0.95) = 7.815."""
    steps: int
    """Steps with a finite NEES."""
    mean_interval: NeesMeanInterval | None
    """Acceptance region of the mean (``None`` without steps)."""


@dataclass(frozen=True)
class AnchorMetrics:
    """The anchor ``x^Wknown_Wglobal``: the run's estimate against truth."""

    estimate: tuple[float, ...]
    """(3,) estimated pose of ``Wglobal`` in ``Wknown``."""
    truth: tuple[float, ...] | None
    """(3,) the true one (simulation), else ``None``."""
    position_error_m: float | None
    """Distance of the estimate from the truth (m), ``None`` without truth."""
    heading_error_rad: float | None
    """Absolute heading difference (rad), ``None`` without truth."""
    accepted_at_step: int
    """Step at which the match was accepted."""
    pairings: int
    """Pairings of the match (or ties, for a graph backend)."""
    correct_pairings: int
    """Those whose estimated feature carries the known feature's true id."""
    nees: float | None = None
    """NEES of the estimate against the truth under the anchor's covariance (3 dof),
    ``None`` without truth or covariance."""


@dataclass(frozen=True)
class MapMetrics:
    """Size of the final map."""

    features: int
    """Features in the final map (the EKF's include the known map it carries)."""
    matched_known: int
    """Known features paired with at least one observation."""
    seen_once: int
    """Estimated features built from one observation (clutter)."""
    tentative_dropped: int
    """New features dropped before entering the map (EKF ``tentative_min_sightings``)."""


@dataclass(frozen=True)
class MatchingMetrics:
    """Whether fusion was asked for and achieved, and the map matchings behind it."""

    requested: bool
    """Fusion was requested on a log with a known map."""
    achieved: bool
    """An anchor was accepted."""
    ccda_by: str | None
    """The estimator whose CCDA calls made the anchor (its own, or the one it consumed)."""
    ccda_attempts: int | None
    """CCDA calls."""
    ccda_reasons: Mapping[str, int] | None
    """Calls per outcome."""
    search_limit: int | None
    """Calls that ended at CCDA's search budget."""


@dataclass(frozen=True)
class RuntimeMetrics:
    """Run time of the estimator (s)."""

    total: float
    """Sum of the step times."""
    per_step_p50: float
    """Median step time."""
    per_step_p99: float
    """99th percentile of the step time."""


@dataclass(frozen=True)
class RunMetrics:
    """Everything ``metrics.json`` says of one run (README, *metrics.json*)."""

    scenario: str = field()
    """Scenario name of the log."""
    seed: int = field()
    """Seed of the log."""
    estimator: str = field(metadata={"json": "backend"})
    """Registered name of the estimator (JSON ``backend``)."""
    fusion: bool = field()
    """Whether the known map was fused."""
    steps: int = field()
    """Estimated steps."""
    position_error: PositionError | None = field(metadata={"json": "position_error_m"})
    """Position error of the evaluated track; ``None`` without truth or GPS."""
    heading_error: HeadingError | None = field(metadata={"json": "heading_error_rad"})
    """Heading error; ``None`` without truth."""
    nees: NeesSummary | None = field()
    """Vehicle NEES; ``None`` without truth."""
    anchor: AnchorMetrics | None = field()
    """The anchor, ``None`` without one."""
    map: MapMetrics = field()
    """Size of the final map."""
    runtime: RuntimeMetrics = field(metadata={"json": "runtime_s"})
    """Run time."""
    matching: MatchingMetrics = field()
    """Map matching."""
    log: Mapping[str, Any] | None = field(default=None, metadata=_OMIT)
    """How the log was made (its metadata), when it says."""
    association: str | None = field(default=None, metadata=_OMIT)
    """Where the decisions came from, for an estimator that takes them as an input."""
    known_map_rejections: Mapping[str, Any] | None = field(
        default=None, metadata={"omit_none": True}
    )
    """The known-map gate's report (:meth:`~mapfuse_core.estimate.KnownMapGating.as_dict`)."""
    estimate: Literal["filtered", "smoothed"] | None = field(
        default=None, metadata={"omit_none": True}
    )
    """Which track was evaluated, for an estimator with a smoothed one."""
    nees_filtered: NeesSummary | None = field(default=None, metadata=_OMIT)
    """NEES of the filtered track, for an estimator with both tracks."""
    position_error_filtered: PositionError | None = field(
        default=None, metadata={"json": "position_error_filtered_m", "omit_none": True}
    )
    """Position error of the filtered track, for an estimator with both tracks."""
    warnings: tuple[str, ...] = field(default=(), metadata={"json": "warnings"})
    """What the numbers do not say (``docs/warnings.md``)."""

    def to_json(self) -> dict[str, Any]:
        """The ``metrics.json`` object, its ``schema_version`` first."""
        out: dict[str, Any] = {"schema_version": METRICS_SCHEMA_VERSION, **_to_json(self)}
        return out

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> RunMetrics:
        """A ``metrics.json`` object read back, of this schema version or an older one
        (no ``schema_version`` key: version 1); :class:`ValueError` naming a missing or
        mistyped key, or a newer schema."""
        if not isinstance(obj, Mapping):
            raise ValueError(f"metrics must be an object, got {type(obj).__name__}")
        version = obj.get("schema_version", 1)
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise ValueError(f"metrics: schema_version must be an integer >= 1, got {version!r}")
        if version > METRICS_SCHEMA_VERSION:
            raise ValueError(
                f"metrics: schema version {version} is newer than this mapfuse reads "
                f"({METRICS_SCHEMA_VERSION}); upgrade mapfuse"
            )
        out: RunMetrics = _from_json(cls, obj, "metrics")
        return out

    def scalars(self) -> dict[str, float]:
        """Every finite number of the metrics by dotted JSON path (e.g.
        ``position_error_m.rmse``, ``nees.mean``), for tables and baselines."""
        out: dict[str, float] = {}

        def walk(prefix: str, value: Any) -> None:
            if isinstance(value, Mapping):
                for k, v in value.items():
                    walk(f"{prefix}.{k}" if prefix else str(k), v)
            elif (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
            ):
                out[prefix] = float(value)

        walk("", _to_json(self))
        return out
