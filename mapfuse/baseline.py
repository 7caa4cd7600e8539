"""Regression baselines: record a run's metrics, later check a new run is no worse.

A *baseline file* is JSON::

    {"format": "mapfuse.baseline", "version": 1,
     "entries": [{"metrics": {...metrics.json...}, "note": "...", "mapfuse_version": "..."}]}

Each entry keeps the whole ``metrics.json`` object of one run (scenario, seed,
backend, fusion, …), so any metric can be checked later.  :func:`check_baseline`
compares a new ``metrics.json`` object with the entry of the same backend and
fusion setting, metric by metric, each with a direction and a tolerance:

======================================  =========  ==================================
metric (dotted path in metrics.json)    better     default: the new value may be …
======================================  =========  ==================================
``position_error_m.rmse``               lower      ≤ baseline × (1 + 10 %) + 0.01 m
``position_error_m.max``                lower      ≤ baseline × (1 + 10 %) + 0.02 m
``heading_error_rad.rmse``              lower      ≤ baseline × (1 + 10 %) + 0.001 rad
``nees.fraction_within_chi2_95``        higher     ≥ baseline − 0.05
``nees.mean``                           target 3   ``|new − 3| ≤ |baseline − 3| × (1 + 25 %) + 0.5``
``anchor.position_error_m``             lower      ≤ baseline × (1 + 10 %) + 0.01 m
``anchor.heading_error_rad``            lower      ≤ baseline × (1 + 10 %) + 0.001 rad
======================================  =========  ==================================

These seven are :data:`DEFAULT_METRICS`.  More are known to :data:`METRICS` (e.g.
``position_error_m.final``, iSAM2's ``nees_filtered.*``, and ``runtime_s.*``, which is
machine dependent and therefore never checked unless asked for).  The additive
part of each tolerance keeps near-zero baselines from failing on noise; the
relative part lets large values move with them.  ``nees.mean`` has a target, the
3 degrees of freedom of the pose: a filter may not get *farther* from consistency
in either direction (over- or under-confident).

A metric the baseline has (e.g. an anchor) but the new run lacks fails; one the
baseline lacks (``anchor`` of a run without fusion, errors of a log without truth)
is skipped.  A new run of another scenario, seed, length, backend or fusion
setting than its baseline fails with a message saying so.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

from mapfuse_core.estimate import RunMetrics
from mapfuse_core.measlog import MeasurementLog

__all__ = [
    "BASELINE_FORMAT",
    "BASELINE_VERSION",
    "DEFAULT_METRICS",
    "METRICS",
    "BaselineEntry",
    "BaselineError",
    "BaselineReport",
    "MetricCheck",
    "MetricSpec",
    "Tolerance",
    "check_baseline",
    "check_log_against_baseline",
    "load_baseline",
    "record_baseline",
    "record_baselines",
    "save_baseline",
]

BASELINE_FORMAT = "mapfuse.baseline"
BASELINE_VERSION = 1

Better = Literal["lower", "higher", "target"]

# What identifies a run (RunMetrics fields, JSON names in messages): a baseline only
# applies to a run with the same values.
_KEY_FIELDS = {
    "scenario": "scenario",
    "seed": "seed",
    "steps": "steps",
    "estimator": "backend",
    "fusion": "fusion",
    "association": "association",
    "estimate": "estimate",
}
# Fields that select the entry of a multi-run baseline file.
_SELECT_FIELDS = ("estimator", "fusion", "association", "estimate")


class BaselineError(ValueError):
    """A baseline file or object is malformed, or a requested metric is unknown."""


@dataclass(frozen=True)
class BaselineEntry:
    """One recorded run: its metrics, a note, and the mapfuse that made it."""

    metrics: RunMetrics
    """The run's metrics."""
    note: str = ""
    """Free text (why it was recorded)."""
    mapfuse_version: str = "unknown"
    """Version of mapfuse that recorded it."""

    def to_json(self) -> dict[str, Any]:
        """The entry as stored in a baseline file."""
        return {
            "metrics": self.metrics.to_json(),
            "note": self.note,
            "mapfuse_version": self.mapfuse_version,
        }


@dataclass(frozen=True)
class Tolerance:
    """How much worse than its baseline a metric may get: ``rel × |baseline| + abs``."""

    rel: float = 0.10
    """Relative part, a fraction of the baseline value (0.10 = 10 %)."""
    abs: float = 0.0
    """Absolute part, in the metric's unit."""

    def __post_init__(self) -> None:
        for name in ("rel", "abs"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"Tolerance.{name} must be finite and >= 0, got {v}")

    def describe(self, better: Better, unit: str, target: float | None = None) -> str:
        """The rule in words, e.g. ``"≤ baseline × (1 + 10 %) + 0.01 m"``."""
        u = f" {unit}" if unit else ""
        if better == "lower":
            return f"≤ baseline × (1 + {100 * self.rel:g} %) + {self.abs:g}{u}"
        if better == "higher":
            return f"≥ baseline × (1 − {100 * self.rel:g} %) − {self.abs:g}{u}"
        return (
            f"|value − {target:g}| ≤ |baseline − {target:g}| × (1 + {100 * self.rel:g} %)"
            f" + {self.abs:g}{u}"
        )


@dataclass(frozen=True)
class MetricSpec:
    """A checkable metric: which way is better, its unit and its default tolerance."""

    better: Better
    """``"lower"`` (errors, time), ``"higher"`` (fractions) or ``"target"`` (closer is better)."""
    unit: str
    """Unit for messages (``""`` when dimensionless)."""
    tolerance: Tolerance
    """Default tolerance."""
    target: float | None = None
    """The ideal value when :attr:`better` is ``"target"``."""


#: Every metric :func:`check_baseline` knows, by dotted path into ``metrics.json``.
METRICS: Mapping[str, MetricSpec] = {
    "position_error_m.rmse": MetricSpec("lower", "m", Tolerance(0.10, 0.01)),
    "position_error_m.mean": MetricSpec("lower", "m", Tolerance(0.10, 0.01)),
    "position_error_m.median": MetricSpec("lower", "m", Tolerance(0.10, 0.01)),
    "position_error_m.max": MetricSpec("lower", "m", Tolerance(0.10, 0.02)),
    "position_error_m.final": MetricSpec("lower", "m", Tolerance(0.25, 0.02)),
    "heading_error_rad.rmse": MetricSpec("lower", "rad", Tolerance(0.10, 0.001)),
    "heading_error_rad.max": MetricSpec("lower", "rad", Tolerance(0.10, 0.002)),
    "nees.fraction_within_chi2_95": MetricSpec("higher", "", Tolerance(0.0, 0.05)),
    "nees.mean": MetricSpec("target", "", Tolerance(0.25, 0.5), target=3.0),
    "anchor.position_error_m": MetricSpec("lower", "m", Tolerance(0.10, 0.01)),
    "anchor.heading_error_rad": MetricSpec("lower", "rad", Tolerance(0.10, 0.001)),
    "anchor.correct_pairings": MetricSpec("higher", "", Tolerance(0.25, 0.0)),
    "map.matched_known": MetricSpec("higher", "", Tolerance(0.10, 1.0)),
    "position_error_filtered_m.rmse": MetricSpec("lower", "m", Tolerance(0.10, 0.01)),
    "position_error_filtered_m.max": MetricSpec("lower", "m", Tolerance(0.10, 0.02)),
    "nees_filtered.fraction_within_chi2_95": MetricSpec("higher", "", Tolerance(0.0, 0.05)),
    "nees_filtered.mean": MetricSpec("target", "", Tolerance(0.25, 0.5), target=3.0),
    "runtime_s.total": MetricSpec("lower", "s", Tolerance(1.0, 1.0)),
    "runtime_s.per_step_p50": MetricSpec("lower", "s", Tolerance(1.0, 0.005)),
    "runtime_s.per_step_p99": MetricSpec("lower", "s", Tolerance(1.0, 0.02)),
}

#: Metrics checked when none are named: accuracy, consistency and the anchor.
DEFAULT_METRICS: tuple[str, ...] = (
    "position_error_m.rmse",
    "position_error_m.max",
    "heading_error_rad.rmse",
    "nees.fraction_within_chi2_95",
    "nees.mean",
    "anchor.position_error_m",
    "anchor.heading_error_rad",
)


@dataclass(frozen=True)
class MetricCheck:
    """The outcome of one metric against its baseline."""

    metric: str
    """Dotted path of the metric in ``metrics.json``."""
    status: Literal["pass", "fail", "skipped"]
    """``"skipped"`` when the baseline has no value for it."""
    baseline: float | None
    """Baseline value (``None`` if absent)."""
    value: float | None
    """New value (``None`` if absent)."""
    limit: float | None
    """Worst acceptable value (``target`` metrics: the worst distance from the target)."""
    tolerance: Tolerance
    """Tolerance applied."""
    spec: MetricSpec
    """Direction and unit of the metric."""
    message: str
    """One line: metric, baseline value, new value and the rule."""

    @property
    def passed(self) -> bool:
        """True unless the check failed (skipped checks pass)."""
        return self.status != "fail"


@dataclass(frozen=True)
class BaselineReport:
    """All checks of one run against its baseline entry."""

    run: str
    """What was checked, e.g. ``"ekf with fusion on loop600 seed 0 (2400 steps)"``."""
    checks: tuple[MetricCheck, ...]
    """One per metric checked."""
    problems: tuple[str, ...] = field(default=())
    """Failures not tied to a metric: a run of another scenario, seed, backend, … than
    the baseline, or no matching baseline entry."""

    @property
    def passed(self) -> bool:
        """True when no check failed and there is no problem."""
        return not self.problems and all(c.passed for c in self.checks)

    @property
    def failures(self) -> tuple[MetricCheck, ...]:
        """The failed checks."""
        return tuple(c for c in self.checks if not c.passed)

    def failure_message(self) -> str:
        """Problems and failed checks, one per line (empty when passed)."""
        return "\n".join([*self.problems, *(c.message for c in self.failures)])

    def summary(self) -> str:
        """Every check, one per line, under a PASS/FAIL header."""
        head = f"{'PASS' if self.passed else 'FAIL'}: {self.run}"
        body = [f"  problem: {p}" for p in self.problems]
        body += [f"  {c.status:7s} {c.message}" for c in self.checks]
        return "\n".join([head, *body])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "run": self.run,
            "passed": self.passed,
            "problems": list(self.problems),
            "checks": [
                {
                    "metric": c.metric,
                    "status": c.status,
                    "baseline": c.baseline,
                    "value": c.value,
                    "limit": c.limit,
                    "better": c.spec.better,
                    "tolerance": {"rel": c.tolerance.rel, "abs": c.tolerance.abs},
                    "message": c.message,
                }
                for c in self.checks
            ],
        }


# --------------------------------------------------------------------------- recording


def _version() -> str:
    try:
        return metadata.version("mapfuse")
    except metadata.PackageNotFoundError:
        return "unknown"


def _metrics_of(metrics: RunMetrics | Mapping[str, Any]) -> RunMetrics:
    if isinstance(metrics, RunMetrics):
        return metrics
    try:
        return RunMetrics.from_json(metrics)
    except (ValueError, TypeError) as exc:
        raise BaselineError(f"not a metrics.json object: {exc}") from None


def record_baseline(
    source: MeasurementLog | RunMetrics | Mapping[str, Any],
    estimator: str | None = None,
    fusion: bool = True,
    association: str = "ekf",
    note: str = "",
    progress: Callable[[str, int, int], None] | None = None,
) -> BaselineEntry:
    """A baseline entry from a run's metrics, or by running ``estimator`` on a log.

    With a log, ``estimator`` (a registered name) is required and the run is
    :func:`mapfuse.runner.run` of it with ``fusion`` (and ``association`` for an
    estimator whose options have that field), reporting ``progress(label, k, n)``.
    With metrics (a :class:`~mapfuse_core.estimate.RunMetrics` or a ``metrics.json``
    object), ``estimator`` (if given) must match them and ``fusion``/``association``
    are ignored.
    """
    if isinstance(source, MeasurementLog):
        if estimator is None:
            raise ValueError("record_baseline on a log needs an estimator ('ekf', 'batch', ...)")
        import dataclasses

        from mapfuse.execution import fusion_for
        from mapfuse.registry import resolve
        from mapfuse.runner import labelled, run

        est = resolve(estimator)
        fusion = fusion_for(source, fusion)
        label = f"{est.name} {'with' if fusion else 'without'} fusion"
        takes = {f.name for f in dataclasses.fields(est.options_type)}
        overrides = {"association": association} if "association" in takes else {}
        from mapfuse.options import make_options

        options = make_options(est, source, **overrides)
        r = run(source, est, fusion=fusion, options=options, progress=labelled(progress, label))
        return BaselineEntry(r.metrics, note, _version())
    metrics = _metrics_of(source)
    if estimator is not None and metrics.estimator != estimator:
        raise ValueError(f"metrics are of estimator {metrics.estimator!r}, not {estimator!r}")
    return BaselineEntry(metrics, note, _version())


def record_baselines(
    log: MeasurementLog,
    estimators: Sequence[str] | None = None,
    fusions: Sequence[bool] = (True, False),
    note: str = "",
    progress: Callable[[str, int, int], None] | None = None,
) -> list[BaselineEntry]:
    """Entries for ``estimators`` × ``fusions`` on ``log`` (as
    :func:`mapfuse.comparison.compare`, whose defaults ``None`` takes).

    ``progress(label, k, n)`` as in :func:`mapfuse.comparison.compare`.
    """
    from mapfuse.comparison import compare

    comparison = compare(log, progress=progress, estimators=estimators, fusions=fusions)
    return [BaselineEntry(m, note, _version()) for m in comparison.metrics]


def save_baseline(baseline: BaselineEntry | Sequence[BaselineEntry], path: str | Path) -> Path:
    """Write one entry or a list of entries to ``path`` as a baseline file."""
    entries = [baseline] if isinstance(baseline, BaselineEntry) else list(baseline)
    if not entries:
        raise BaselineError("a baseline needs at least one entry")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "format": BASELINE_FORMAT,
        "version": BASELINE_VERSION,
        "entries": [e.to_json() for e in entries],
    }
    path.write_text(json.dumps(doc, indent=2, sort_keys=False) + "\n")
    return path


def load_baseline(path: str | Path) -> list[BaselineEntry]:
    """The entries of a baseline file; :class:`BaselineError` naming the file otherwise."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise BaselineError(f"{path}: no such baseline file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BaselineError(f"{path}: not a readable JSON baseline ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != BASELINE_FORMAT:
        raise BaselineError(f"{path}: not a mapfuse baseline file (format {BASELINE_FORMAT!r})")
    if doc.get("version") != BASELINE_VERSION:
        raise BaselineError(
            f"{path}: baseline format version {doc.get('version')}, this mapfuse reads "
            f"version {BASELINE_VERSION}; record the baseline again"
        )
    try:
        return _entries_of(doc.get("entries"))
    except BaselineError as exc:
        raise BaselineError(f"{path}: {exc}") from None


def _entries_of(baseline: object) -> list[BaselineEntry]:
    """Entries from one entry, a list of entries, or their stored (JSON) form."""
    if isinstance(baseline, BaselineEntry):
        return [baseline]
    items = [baseline] if isinstance(baseline, Mapping) else baseline
    if not isinstance(items, Sequence) or isinstance(items, str) or not items:
        raise BaselineError("a baseline must be an entry or a non-empty list of entries")
    out = []
    for i, e in enumerate(items):
        if isinstance(e, BaselineEntry):
            out.append(e)
            continue
        if not isinstance(e, Mapping) or not isinstance(e.get("metrics"), Mapping):
            raise BaselineError(f"entry {i} has no 'metrics' object")
        try:
            metrics = RunMetrics.from_json(e["metrics"])
        except (ValueError, TypeError) as exc:
            raise BaselineError(f"entry {i}: {exc}") from None
        out.append(
            BaselineEntry(metrics, str(e.get("note", "")), str(e.get("mapfuse_version", "unknown")))
        )
    return out


# --------------------------------------------------------------------------- checking


def _describe_run(m: RunMetrics) -> str:
    est = f", {m.estimate} estimate" if m.estimate else ""
    return (
        f"{m.estimator} {'with' if m.fusion else 'without'} fusion{est} on "
        f"{m.scenario} seed {m.seed} ({m.steps} steps)"
    )


def _fmt(v: float | None, unit: str) -> str:
    if v is None:
        return "missing"
    return f"{v:.6g}{' ' + unit if unit else ''}"


def _check_one(
    metric: str, spec: MetricSpec, tol: Tolerance, base: float | None, new: float | None
) -> MetricCheck:
    rule = tol.describe(spec.better, spec.unit, spec.target)
    u = spec.unit

    def out(
        status: Literal["pass", "fail", "skipped"], limit: float | None, msg: str
    ) -> MetricCheck:
        return MetricCheck(metric, status, base, new, limit, tol, spec, msg)

    if base is None:
        return out("skipped", None, f"{metric}: not in the baseline (new value {_fmt(new, u)})")
    if spec.better == "lower":
        limit = base * (1.0 + tol.rel) + tol.abs
        ok = new is not None and new <= limit
        verdict = "within tolerance of" if ok else "worse than"
        msg = (
            f"{metric} = {_fmt(new, u)} is {verdict} the baseline {_fmt(base, u)} "
            f"(lower is better; tolerance {rule} = {_fmt(limit, u)})"
        )
    elif spec.better == "higher":
        limit = base * (1.0 - tol.rel) - tol.abs
        ok = new is not None and new >= limit
        verdict = "within tolerance of" if ok else "worse than"
        msg = (
            f"{metric} = {_fmt(new, u)} is {verdict} the baseline {_fmt(base, u)} "
            f"(higher is better; tolerance {rule} = {_fmt(limit, u)})"
        )
    else:
        target = 0.0 if spec.target is None else spec.target
        limit = abs(base - target) * (1.0 + tol.rel) + tol.abs
        ok = new is not None and abs(new - target) <= limit
        verdict = "within tolerance of" if ok else "farther from the target than"
        msg = (
            f"{metric} = {_fmt(new, u)} is {verdict} the baseline {_fmt(base, u)} "
            f"(target {target:g}; tolerance {rule} = {_fmt(limit, u)})"
        )
    if new is None:
        msg = f"{metric} is missing from the new run; the baseline has {_fmt(base, u)} ({rule})"
    return out("pass" if ok else "fail", limit, msg)


def _select(metrics: RunMetrics, entries: list[BaselineEntry]) -> tuple[BaselineEntry | None, str]:
    if len(entries) == 1:
        return entries[0], ""
    same = [
        e
        for e in entries
        if all(getattr(e.metrics, k) == getattr(metrics, k) for k in _SELECT_FIELDS)
    ]
    if len(same) == 1:
        return same[0], ""
    have = "; ".join(_describe_run(e.metrics) for e in entries)
    if not same:
        return None, f"no baseline entry for {_describe_run(metrics)} (the baseline has: {have})"
    return None, f"{len(same)} baseline entries match {_describe_run(metrics)}: ambiguous"


def _tolerance_for(
    metric: str, spec: MetricSpec, tolerances: Tolerance | Mapping[str, Tolerance] | None
) -> Tolerance:
    if tolerances is None:
        return spec.tolerance
    if isinstance(tolerances, Tolerance):
        return tolerances
    return tolerances.get(metric, spec.tolerance)


Baseline = BaselineEntry | Sequence[BaselineEntry] | Mapping[str, Any] | str | Path
"""A baseline: an entry, a list of entries, their stored form, or a baseline file."""


def check_baseline(
    metrics: RunMetrics | Mapping[str, Any],
    baseline: Baseline,
    tolerances: Tolerance | Mapping[str, Tolerance] | None = None,
    which: Sequence[str] | None = None,
) -> BaselineReport:
    """Check a run's metrics (a :class:`~mapfuse_core.estimate.RunMetrics` or a
    ``metrics.json`` object) against its baseline entry.

    ``baseline``: an entry (:func:`record_baseline`), a list of entries, or a baseline
    file path; from several entries the one of the same estimator, fusion, association
    and estimate is used.  ``which``: metrics to check (default
    :data:`DEFAULT_METRICS`; any key of :data:`METRICS`).  ``tolerances``: one
    :class:`Tolerance` for all of them, or per metric (the others keep their default).
    Raises :class:`BaselineError` for an unknown metric or a malformed baseline.
    """
    names = tuple(DEFAULT_METRICS if which is None else which)
    unknown = [n for n in names if n not in METRICS]
    if unknown:
        raise BaselineError(
            f"unknown metric(s) {', '.join(unknown)}; known: {', '.join(sorted(METRICS))}"
        )
    if isinstance(tolerances, Mapping):
        extra = [n for n in tolerances if n not in METRICS]
        if extra:
            raise BaselineError(f"tolerance for unknown metric(s) {', '.join(extra)}")
    new = _metrics_of(metrics)
    entries = load_baseline(baseline) if isinstance(baseline, str | Path) else _entries_of(baseline)
    run = _describe_run(new)
    entry, problem = _select(new, entries)
    if entry is None:
        return BaselineReport(run=run, checks=(), problems=(problem,))
    base = entry.metrics
    problems = []
    for attr, key in _KEY_FIELDS.items():
        b, v = getattr(base, attr), getattr(new, attr)
        if b is not None and b != v:
            problems.append(f"{key}: the baseline is of {key} {b!r}, the new run of {v!r}")
    base_values, new_values = base.scalars(), new.scalars()
    checks = tuple(
        _check_one(
            n,
            METRICS[n],
            _tolerance_for(n, METRICS[n], tolerances),
            base_values.get(n),
            new_values.get(n),
        )
        for n in names
    )
    return BaselineReport(run=run, checks=checks, problems=tuple(problems))


def check_log_against_baseline(
    log: MeasurementLog,
    baseline: Baseline,
    tolerances: Tolerance | Mapping[str, Tolerance] | None = None,
    which: Sequence[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[BaselineReport]:
    """Re-run every entry's estimator/fusion/association on ``log`` and check each.

    The runs are planned together (:mod:`mapfuse.plan`): an estimator's result that
    others consume (the EKF's, for graph entries) is made once per fusion setting and
    reused.  ``progress(label, k, n)`` as in :func:`mapfuse.comparison.compare`.
    """
    from mapfuse.metrics import run_metrics
    from mapfuse.plan import RunRequest, execute, plan_runs

    entries = load_baseline(baseline) if isinstance(baseline, str | Path) else _entries_of(baseline)
    requests = [
        RunRequest(
            e.metrics.estimator,
            e.metrics.fusion,
            {} if e.metrics.association is None else {"association": e.metrics.association},
        )
        for e in entries
    ]
    plan = plan_runs(requests, len(log.known_map) > 0)
    done = execute(plan, log, progress=progress)
    by_request = {
        (d.planned.estimator, d.planned.fusion, repr(sorted(d.planned.overrides.items()))): d
        for d in done
    }
    reports = []
    for e, req in zip(entries, requests, strict=True):
        fusion = req.fusion and len(log.known_map) > 0
        d = by_request.get((req.estimator, fusion, repr(sorted(req.overrides.items()))))
        if d is None or d.result is None:
            # The estimator cannot fuse: its one run is the one without fusion.
            d = by_request[(req.estimator, False, repr(sorted(req.overrides.items())))]
        assert d.result is not None  # errors raise
        which_track: Literal["filtered", "smoothed"] | None = (
            "filtered" if e.metrics.estimate == "filtered" else None
        )
        new = run_metrics(d.result, log, which=which_track)
        reports.append(check_baseline(new, [e], tolerances, which))
    return reports
