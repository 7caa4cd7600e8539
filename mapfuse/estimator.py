"""The :class:`Estimator` protocol: what the harness needs from an estimator, and the
:class:`Capabilities` each declares.

An estimator has a registered :attr:`~Estimator.name`, an options type whose
no-argument instance holds its defaults (per-dataset defaults come from
:mod:`mapfuse.profiles`), its :attr:`~Estimator.capabilities`, and a
:meth:`~Estimator.run` that turns a measurement log into an
:class:`~mapfuse_core.estimate.EstimatorResult`.  Register one with
:func:`mapfuse.registry.register` or the ``mapfuse.estimators`` entry-point group
(``docs/plugins.md``).  The harness reads what an estimator can do from its
capabilities, never from its name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog

__all__ = ["Capabilities", "Estimator", "Progress", "Track"]

#: ``progress(k, n)``: ``k`` of ``n`` steps done.
Progress = Callable[[int, int], None]

#: A pose track a result can carry: each step from the steps up to it (``filtered``),
#: or from the whole log (``smoothed``).
Track = Literal["filtered", "smoothed"]


@dataclass(frozen=True)
class Capabilities:
    """What an estimator declares of itself; the harness plans, reports and checks
    options from these alone."""

    tracks: frozenset[Track] = frozenset({"filtered"})
    """The pose tracks its results carry (:attr:`EstimatorResult.filtered`,
    :attr:`EstimatorResult.smoothed`); metrics evaluate the smoothed one when there
    is one."""
    consumes: str | None = None
    """Registered name of the estimator whose result (of the same log and fusion
    setting) this one takes as its run's ``upstream``: its association decisions and
    anchor, e.g. the graph backends consume the EKF's.  The harness runs that estimator
    first, once per fusion setting, and hands its result to every consumer."""
    fuses: bool = True
    """Whether it can fuse a known map; one that cannot runs once, without fusion,
    whatever a comparison asks."""
    smooths_before_anchor: bool = False
    """Whether its poses from before the map match are re-estimated with the match (a
    smoother over the whole run), so that they lie in the known map through the anchor
    with the anchor's uncertainty already counted.  A filter's, or a fixed-lag
    smoother's whose window left them before the match, are not."""
    exports_graph: bool = False
    """Whether its results hold a GTSAM factor graph (``result.details``) that
    ``mapfuse run --export-graph`` can write."""

    def __post_init__(self) -> None:
        tracks = frozenset(self.tracks)
        if not tracks or not tracks <= {"filtered", "smoothed"}:
            raise ValueError(
                f"capabilities.tracks must hold 'filtered' and/or 'smoothed', got {self.tracks!r}"
            )
        object.__setattr__(self, "tracks", tracks)


@runtime_checkable
class Estimator(Protocol):
    """An estimator the harness can run, compare and baseline."""

    name: str
    """Registered name (``--estimator NAME``, ``metrics.json``'s ``backend``)."""
    options_type: type[Any]
    """Type of :meth:`run`'s ``options``; ``options_type()`` holds the defaults."""
    capabilities: Capabilities
    """What it can do (:class:`Capabilities`)."""

    def run(
        self,
        log: MeasurementLog,
        options: Any,
        *,
        fusion: bool,
        upstream: EstimatorResult | None = None,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Estimate ``log``.

        ``fusion``: whether to fuse the log's known map; the harness passes ``True``
        only for a log that has one and an estimator that :attr:`~Capabilities.fuses`.
        ``upstream``: the result of the estimator named by
        :attr:`~Capabilities.consumes` on the same log and fusion setting (given only
        to an estimator that declares one).  ``progress(k, n)`` may be called after
        each step.
        """
        ...
