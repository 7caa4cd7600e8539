"""Which runs to make, in which order, and making them: :func:`plan_runs` and
:func:`execute`.

Every command that runs several estimators on one log (``compare``, ``montecarlo``,
``spectrum``, ``baseline``, and :func:`mapfuse.run` itself) plans through here, so
one rule holds everywhere: an estimator that consumes another's result
(:attr:`~mapfuse.estimator.Capabilities.consumes`) gets that estimator's run of the
same log and fusion setting, made once, before it (and made even when it was not
asked for, then not reported); an estimator that cannot fuse runs once, without
fusion; a log without a known map runs everything without fusion.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from mapfuse.execution import estimate
from mapfuse.registry import resolve
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog

__all__ = [
    "PlannedRun",
    "RunRequest",
    "RunResult",
    "execute",
    "plan_runs",
]

#: ``progress(label, k, n)``: run ``label`` has done ``k`` of ``n`` steps.
LabelledProgress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class RunRequest:
    """One run asked for: an estimator, a fusion setting, option overrides."""

    estimator: str
    """Registered estimator name."""
    fusion: bool
    """Whether to fuse the known map (adjusted by :func:`plan_runs` where nothing can
    be fused)."""
    overrides: Mapping[str, Any] = field(default_factory=dict)
    """Fields of the estimator's options to change (:func:`mapfuse.options.make_options`)."""
    label: str | None = None
    """Name of the run in progress and reports (default ``"NAME with/without fusion"``)."""


@dataclass(frozen=True)
class PlannedRun:
    """One run of the plan."""

    estimator: str
    """Registered estimator name."""
    fusion: bool
    """Whether it fuses the known map."""
    overrides: Mapping[str, Any]
    """Fields of its options to change."""
    label: str
    """Its name in progress and reports."""
    upstream: int | None
    """Index in the plan of the run whose result it consumes, or ``None``."""
    reported: bool
    """``False`` for a run made only because another consumes it."""


def _label(name: str, fusion: bool) -> str:
    return f"{name} {'with' if fusion else 'without'} fusion"


def plan_runs(requests: Sequence[RunRequest], log_has_known_map: bool) -> tuple[PlannedRun, ...]:
    """The runs that make ``requests``, in an order where each consumed run comes
    before its consumers.

    Fusion is on only where the log has a known map and the estimator
    :attr:`~mapfuse.estimator.Capabilities.fuses`; requests that then coincide (same
    estimator, fusion and overrides) run once.  A consumer's upstream is the plan's run
    of the consumed estimator with the same fusion and no overrides, added (not
    reported) when it was not requested.  Requests otherwise keep their order.
    """
    planned: list[PlannedRun] = []
    index: dict[tuple[str, bool, str], int] = {}

    def key(name: str, fusion: bool, overrides: Mapping[str, Any]) -> tuple[str, bool, str]:
        return (name, fusion, repr(sorted(overrides.items())))

    def add(req: RunRequest, reported: bool, chain: tuple[str, ...]) -> int:
        est = resolve(req.estimator)
        if est.name in chain:
            raise ValueError(f"estimators consume each other in a loop: {' -> '.join(chain)}")
        fusion = bool(req.fusion) and log_has_known_map and est.capabilities.fuses
        k = key(est.name, fusion, req.overrides)
        if k in index:
            i = index[k]
            if reported and not planned[i].reported:
                planned[i] = PlannedRun(**{**planned[i].__dict__, "reported": True})
            return i
        upstream = None
        consumed = est.capabilities.consumes
        if consumed is not None:
            upstream = add(RunRequest(consumed, fusion), False, (*chain, est.name))
        planned.append(
            PlannedRun(
                estimator=est.name,
                fusion=fusion,
                overrides=dict(req.overrides),
                label=req.label or _label(est.name, fusion),
                upstream=upstream,
                reported=reported,
            )
        )
        index[k] = len(planned) - 1
        return index[k]

    for req in requests:
        add(req, True, ())
    return tuple(planned)


@dataclass(frozen=True)
class RunResult:
    """What one planned run gave: its result, or the error that stopped it."""

    planned: PlannedRun
    """The run."""
    result: EstimatorResult | None
    """Its result, ``None`` if it failed."""
    error: str | None = None
    """``None``, or the error (message and the end of its traceback); a run whose
    upstream failed fails with a message naming it."""


def _error_text(exc: BaseException) -> str:
    tb = traceback.format_exception(type(exc), exc, exc.__traceback__)
    return f"{type(exc).__name__}: {exc}\n{''.join(tb[-3:])}".strip()


def execute(
    plan: Sequence[PlannedRun],
    log: MeasurementLog,
    *,
    progress: LabelledProgress | None = None,
    errors: Literal["raise", "record"] = "raise",
    given: Mapping[int, EstimatorResult] | None = None,
) -> tuple[RunResult, ...]:
    """Make the runs of ``plan`` on ``log``, in order, each consumer getting its
    upstream's result.

    ``errors="raise"`` lets the first error through; ``"record"`` records it and goes
    on (its consumers then fail too, naming it).  ``given``: results already made, by
    plan index (they are not run again).
    """
    out: list[RunResult] = []
    for i, p in enumerate(plan):
        if given is not None and i in given:
            out.append(RunResult(p, given[i]))
            continue
        up = None if p.upstream is None else out[p.upstream]
        if up is not None and up.result is None:
            out.append(RunResult(p, None, f"its upstream {up.planned.label} failed: {up.error}"))
            continue
        report = None
        if progress is not None:
            label, cb = p.label, progress

            def report(k: int, n: int, label: str = label, cb: LabelledProgress = cb) -> None:
                cb(label, k, n)

        try:
            result = estimate(
                log,
                p.estimator,
                fusion=p.fusion,
                upstream=None if up is None else up.result,
                progress=report,
                **p.overrides,
            )
        except Exception as exc:
            if errors == "raise":
                raise
            out.append(RunResult(p, None, _error_text(exc)))
            continue
        out.append(RunResult(p, result))
    return tuple(out)
