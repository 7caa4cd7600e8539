"""Which estimators exist: the ``mapfuse.estimators`` entry points and :func:`register`.

Built-in ``ekf``, ``batch`` and ``isam2`` are entry points of this package
(``pyproject.toml``), like any plugin's.  Entry points are loaded only when their
estimator is asked for, so ``mapfuse run --backend ekf`` never imports gtsam.  An
entry point names an :class:`~mapfuse.estimator.Estimator` instance or a class (or
any callable) that makes one without arguments.  :func:`register` adds one in a
running process (a notebook, a test).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from importlib import metadata
from typing import Any

from mapfuse.estimator import Estimator

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "available",
    "get",
    "load_plugin",
    "register",
    "register_plugin",
    "registered_plugins",
    "resolve",
    "unregister",
]

ENTRY_POINT_GROUP = "mapfuse.estimators"

#: The built-in estimators, in report order, and their entry-point targets.  Used as
#: well when the installed package metadata does not declare them (a source tree put
#: on ``PYTHONPATH`` over another install).
BUILTIN: dict[str, str] = {
    "ekf": "mapfuse.estimators.ekf:EKFEstimator",
    "batch": "mapfuse.estimators.graph:BatchEstimator",
    "isam2": "mapfuse.estimators.graph:ISAM2Estimator",
}

_registered: dict[str, Estimator] = {}
_loaded: dict[str, Estimator] = {}


def _entry_points() -> dict[str, metadata.EntryPoint]:
    out: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep)
    return out


def available() -> tuple[str, ...]:
    """Every estimator name, without loading any: built-ins first, then the others."""
    names = dict.fromkeys([*BUILTIN, *_entry_points(), *_registered])
    return tuple(names)


def _check(est: Any, where: str) -> Estimator:
    if not isinstance(est, Estimator):
        raise TypeError(
            f"{where} is not a mapfuse estimator (needs name, options_type, capabilities "
            f"and run()), got {type(est).__name__}"
        )
    return est


def _make(target: Any, where: str) -> Estimator:
    if isinstance(target, type) or (not isinstance(target, Estimator) and callable(target)):
        target = target()
    return _check(target, where)


def _load_target(spec: str) -> Any:
    module, _, attr = spec.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def load_plugin(spec: str) -> Any:
    """The object named by a ``module:attribute`` plug-in spec (an estimator, its
    class, or a callable that makes one), imported; :class:`ValueError` naming the
    spec when it is malformed or cannot be loaded.  The one parser of ``--plugin``."""
    module, _, attr = str(spec).partition(":")
    if not module or not attr:
        raise ValueError(f"a plugin must look like module:attribute, got {spec!r}")
    try:
        return _load_target(spec)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"plugin {spec!r} cannot be loaded: {e}") from None


def register_plugin(spec: str, *, replace: bool = False) -> Estimator:
    """Load the ``module:attribute`` plug-in (:func:`load_plugin`) and register it."""
    return register(load_plugin(spec), replace=replace)


@contextmanager
def registered_plugins(specs: Sequence[str]) -> Iterator[tuple[Estimator, ...]]:
    """The ``module:attribute`` plug-ins (:func:`load_plugin`) registered for the
    duration of the block (``--plugin``; a plug-in named like an available estimator
    replaces it there); what the block registered is removed again, so the registry is
    left as it was found (a serial campaign, a command run inside a test)."""
    before = dict(_registered)
    try:
        yield tuple(register(load_plugin(spec), replace=True) for spec in specs)
    finally:
        _registered.clear()
        _registered.update(before)


def get(name: str) -> Estimator:
    """The estimator registered as ``name``; :class:`ValueError` naming the known ones."""
    if name in _registered:
        return _registered[name]
    if name in _loaded:
        return _loaded[name]
    eps = _entry_points()
    if name in eps:
        est = _make(eps[name].load(), f"entry point {name!r} ({eps[name].value})")
    elif name in BUILTIN:
        est = _make(_load_target(BUILTIN[name]), f"built-in estimator {name!r}")
    else:
        raise ValueError(f"unknown estimator {name!r}; choose one of {', '.join(available())}")
    if est.name != name:
        raise ValueError(f"estimator registered as {name!r} calls itself {est.name!r}")
    _loaded[name] = est
    return est


def resolve(estimator: str | Estimator) -> Estimator:
    """An estimator by registered name (:func:`get`), or the estimator itself."""
    return get(estimator) if isinstance(estimator, str) else estimator


def register(estimator: Estimator | Callable[[], Estimator], *, replace: bool = False) -> Estimator:
    """Make ``estimator`` (or what the callable returns) available under its name.

    A name already registered or provided by an entry point needs ``replace=True``.
    Returns the registered estimator.
    """
    est = _make(estimator, "register()'s argument")
    if not replace and (est.name in _registered or est.name in available()):
        raise ValueError(
            f"an estimator named {est.name!r} exists already; pass replace=True to replace it"
        )
    _registered[est.name] = est
    return est


def unregister(name: str) -> None:
    """Remove an estimator added by :func:`register` (entry points stay)."""
    if name not in _registered:
        raise ValueError(f"no estimator {name!r} was added by register()")
    del _registered[name]
