"""Run one estimator on one measurement log: :func:`prepare_log` and :func:`run`.

The library side of ``mapfuse run``: a log in, a :class:`Run` (the estimator's
:class:`~mapfuse.result.EstimatorResult`, the log and its ``metrics.json`` object) out.
:mod:`mapfuse.outputs` writes the run's files.  The rule that a log without a known
map has nothing to fuse is applied here, once (:func:`fusion_for`), for every run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from mapfuse import registry
from mapfuse.carmen_input import is_carmen, load_carmen_input
from mapfuse.estimator import Estimator, Progress
from mapfuse.metrics import run_metrics
from mapfuse.profiles import default_options
from mapfuse.result import EstimatorResult
from mapfuse_core.data.measlog import MeasurementLog, load_log
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

__all__ = [
    "DATASETS",
    "Run",
    "consumer_options",
    "fusion_for",
    "labelled",
    "make_options",
    "override_options",
    "prepare_log",
    "resolve",
    "run",
]

#: Real datasets :func:`prepare_log` loads by name (they need a data directory).
DATASETS = ("carpark", "victoria-park")


@dataclass(frozen=True)
class Run:
    """One estimator's run on one log, with its metrics."""

    result: EstimatorResult
    """What the estimator returned."""
    log: MeasurementLog
    """The log the run consumed."""
    metrics: dict[str, Any]
    """The ``metrics.json`` object (:func:`mapfuse.metrics.run_metrics`)."""

    @property
    def estimator(self) -> str:
        """Name of the estimator."""
        return self.result.estimator

    @property
    def fusion(self) -> bool:
        """Whether the known map was fused."""
        return self.result.fusion

    @property
    def timestamps(self) -> FloatArray:
        """(N,) step times (s)."""
        return self.result.timestamps

    @property
    def poses(self) -> FloatArray:
        """(N, 3) the main pose estimate in ``Wglobal``."""
        return self.result.poses

    @property
    def covs(self) -> FloatArray:
        """(N, 3, 3) its covariance."""
        return self.result.covs


def fusion_for(log: MeasurementLog, fusion: bool) -> bool:
    """Whether a run of ``log`` asked for ``fusion`` fuses anything: never without a
    known map (Victoria Park), whatever it asked.  Runs are made, and reported, so."""
    return bool(fusion) and len(log.known_map) > 0


def prepare_log(
    source: str,
    seed: int | None = None,
    progress: Progress | None = None,
    data_dir: str | None = None,
    known_map: str | None = None,
    workers: int | None = None,
) -> MeasurementLog:
    """A log from a ``.npz`` file, a real dataset (``carpark``, ``victoria-park``, needs
    ``data_dir``), a CARMEN log (``carmen:PATH``; ``seed`` of its simulated odometry,
    ``known_map`` ``"floorplan"`` or ``"none"``, :mod:`mapfuse.carmen_input`), or by
    simulating a scenario (built-in name or TOML) with ``workers`` extraction processes
    (:func:`~mapfuse_core.sim.simulate.extraction_workers`: by default none in a script).

    ``seed`` applies to a simulation and to a CARMEN log's simulated odometry only:
    given with a saved log or a dataset it is an error (it would change nothing), as
    is ``data_dir`` for anything but a dataset.
    """
    if data_dir is not None and source not in DATASETS:
        raise ValueError(f"a data directory applies to {', '.join(DATASETS)} only, not {source!r}")
    if is_carmen(source):
        return load_carmen_input(source, seed=seed, known_map=known_map)
    if known_map is not None:
        raise ValueError(f"a known-map choice applies to CARMEN logs only, not {source!r}")
    if seed is not None and (source.endswith(".npz") or source in DATASETS):
        what = "a saved log" if source.endswith(".npz") else "the real dataset"
        raise ValueError(f"seed does not apply to {what} {source!r}: only a simulation has one")
    if source.endswith(".npz"):
        return load_log(source)
    if source in DATASETS:
        if data_dir is None:
            raise ValueError(f"dataset {source!r} needs a data directory (--data DIR)")
        from mapfuse_core.data.datasets import load_carpark, load_victoria_park

        loader = load_carpark if source == "carpark" else load_victoria_park
        return loader(data_dir)
    return simulate(load_scenario(source), seed=seed, progress=progress, workers=workers).log


def resolve(estimator: str | Estimator) -> Estimator:
    """An estimator by registered name, or the estimator itself."""
    return registry.get(estimator) if isinstance(estimator, str) else estimator


def make_options(estimator: str | Estimator, log: MeasurementLog, **overrides: Any) -> Any:
    """``estimator``'s options for ``log`` (:func:`mapfuse.profiles.default_options`)
    with ``overrides`` of their fields (:func:`override_options`)."""
    est = resolve(estimator)
    return override_options(default_options(est, log), est.name, **overrides)


def override_options(options: Any, name: str, **overrides: Any) -> Any:
    """``options`` with ``overrides`` of their fields; ``name`` names the estimator in
    errors and warnings.

    A mapping given for a dataclass-valued field changes only the fields it names, at
    any depth: ``graph={"data_association": {"line_gap_m": 2.0}}`` keeps every other
    setting the dataset's profile made.  A dataclass given for such a field replaces it
    whole; where that drops a value the profile set (a field that differs both from the
    type's default and from the value given), a :class:`UserWarning` names it, because
    the run then silently loses a dataset setting.  A field the options do not have
    is an error.
    """
    if not overrides:
        return options
    if not dataclasses.is_dataclass(options) or isinstance(options, type):
        raise ValueError(f"the {name} estimator takes no options (given {', '.join(overrides)})")
    return _merge(options, overrides, name)


def _merge(options: Any, overrides: Mapping[str, Any], where: str) -> Any:
    names = {f.name for f in dataclasses.fields(options)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        owner = (
            f"the {where} options have no field"
            if "." in where
            else (f"the {where} estimator has no option")
        )
        raise ValueError(
            f"{owner} {', '.join(unknown)} (its options: {', '.join(sorted(names)) or 'none'})"
        )
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        current = getattr(options, key)
        nested = dataclasses.is_dataclass(current) and not isinstance(current, type)
        if nested and isinstance(value, Mapping):
            changes[key] = _merge(current, value, f"{where}.{key}")
            continue
        if nested and type(value) is type(current):
            _warn_dropped(current, value, f"{where}.{key}")
        changes[key] = value
    return dataclasses.replace(options, **changes)


def _warn_dropped(current: Any, given: Any, where: str) -> None:
    """Warn when ``given`` replaces values of ``current`` that are not the defaults."""
    import warnings

    try:
        default = type(current)()
    except TypeError:  # no defaults to compare with
        return
    dropped = [
        f.name
        for f in dataclasses.fields(current)
        if getattr(current, f.name) != getattr(default, f.name)
        and getattr(given, f.name) != getattr(current, f.name)
    ]
    if dropped:
        warnings.warn(
            f"{where}: the value given replaces the dataset profile's "
            f"{', '.join(dropped)}; pass a mapping of the fields to change "
            f"({where.rsplit('.', 1)[-1]}={{...}}) to keep them",
            UserWarning,
            stacklevel=4,
        )


def run(
    log: MeasurementLog,
    estimator: str | Estimator,
    *,
    fusion: bool = True,
    options: Any = None,
    progress: Progress | None = None,
    **overrides: Any,
) -> Run:
    """Run ``estimator`` (a registered name or an estimator) on ``log``.

    ``options``: the estimator's options (default :func:`make_options` of the log,
    with ``overrides`` of their fields, e.g. ``association="truth"`` for a graph
    backend, ``upstream=`` a finished EKF run's result).  On a log without a known map
    the run is made without fusion, whatever ``fusion`` asks.
    """
    est = resolve(estimator)
    if options is None:
        options = make_options(est, log, **overrides)
    elif overrides:
        options = override_options(options, est.name, **overrides)
    if options is not None and not isinstance(options, est.options_type):
        raise TypeError(
            f"the {est.name} estimator takes {est.options_type.__name__} options, "
            f"got {type(options).__name__}"
        )
    result = est.run(log, options, fusion=fusion_for(log, fusion), progress=progress)
    if not isinstance(result, EstimatorResult):
        raise TypeError(
            f"the {est.name} estimator returned {type(result).__name__}, not an EstimatorResult"
        )
    return Run(result=result, log=log, metrics=run_metrics(result, log))


def labelled(progress: Callable[[str, int, int], None] | None, label: str) -> Progress | None:
    """``progress(k, n)`` from a labelled ``progress(label, k, n)``."""
    if progress is None:
        return None

    def report(k: int, n: int) -> None:
        progress(label, k, n)

    return report


def consumer_options(
    estimator: Estimator,
    log: MeasurementLog,
    upstream: Mapping[str, EstimatorResult],
    **overrides: Any,
) -> Any:
    """Options of ``estimator`` for ``log`` with ``upstream`` set to the result it
    consumes (its ``consumes`` attribute) when that result is in ``upstream``."""
    name = getattr(estimator, "consumes", None)
    if name is not None and name in upstream and "upstream" not in overrides:
        overrides = {**overrides, "upstream": upstream[name]}
    return make_options(estimator, log, **overrides)
