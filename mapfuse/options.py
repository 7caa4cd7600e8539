"""An estimator's options for a log: its dataset defaults (:mod:`mapfuse.profiles`) with
the fields a caller changes (:func:`make_options`, :func:`override_options`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from mapfuse.estimator import Estimator
from mapfuse.profiles import default_options
from mapfuse.registry import resolve
from mapfuse_core.measlog import MeasurementLog

__all__ = ["make_options", "override_options"]


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
