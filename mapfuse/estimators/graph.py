"""The GTSAM mirror (:mod:`mapfuse_graph`) as harness estimators: batch, iSAM2 and the
fixed-lag smoother."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal, cast

from mapfuse.estimator import Capabilities, Progress
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.graph import GraphOptions, centre_radius_correlated
from mapfuse_graph.solvers import Backend, FixedLagOptions, ISAM2Options, LMOptions, run_graph

__all__ = ["BatchEstimator", "FixedLagEstimator", "GraphRunOptions", "ISAM2Estimator"]

#: Where a graph run's data association comes from: ``"ekf"`` the decisions of the run
#: it consumes (its ``upstream``, the EKF's), ``"truth"`` the simulator's ids,
#: ``"own"`` decided by the graph itself.
GraphAssociation = Literal["ekf", "truth", "own"]

GRAPH_ASSOCIATIONS: tuple[GraphAssociation, ...] = ("ekf", "truth", "own")


@dataclass(frozen=True)
class GraphRunOptions:
    """Settings of a graph backend run (the log, the fusion setting and the upstream
    result are the run's inputs, not settings)."""

    association: GraphAssociation = "ekf"
    """Where the data association comes from (:data:`GraphAssociation`).  With ``"ekf"``
    and ``"truth"`` the anchor's initial value and step come from the upstream run."""
    graph: GraphOptions = field(default_factory=GraphOptions)
    """What shapes the graph, its robust kernel included
    (:class:`~mapfuse_graph.options.GraphOptions`)."""
    isam2: ISAM2Options = field(default_factory=ISAM2Options)
    """iSAM2 settings (also batch's iSAM2 pass with ``association="own"``, and the
    fixed-lag smoother's iSAM2)."""
    fixedlag: FixedLagOptions = field(default_factory=FixedLagOptions)
    """Fixed-lag smoother: the lag (``lag_s``) and what happens to landmarks."""
    lm: LMOptions | None = None
    """Batch: Levenberg–Marquardt settings (``None``: the defaults)."""
    split_circles_where_exact: bool = False
    """Turn :attr:`GraphOptions.split_circles` on where it is the same model: a fixed
    association, no robust kernel and no centre–radius correlation in the log."""
    joint_stride: int | None = None
    """Batch: also keep the joint covariance of every ``joint_stride``-th pose
    (``result.details.joint_pose_cov``)."""

    def __post_init__(self) -> None:
        if self.association not in GRAPH_ASSOCIATIONS:
            raise ValueError(
                f"unknown association {self.association!r}; choose one of "
                f"{', '.join(GRAPH_ASSOCIATIONS)}"
            )


class _GraphEstimator:
    """One graph backend; options: :class:`GraphRunOptions`."""

    name: str
    options_type = GraphRunOptions
    capabilities: Capabilities

    def run(
        self,
        log: MeasurementLog,
        options: GraphRunOptions,
        *,
        fusion: bool,
        upstream: EstimatorResult | None = None,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Build and solve the graph of ``log``: with ``association="ekf"`` on
        ``upstream``'s decisions and anchor, with ``"truth"`` on the simulator's ids and
        ``upstream``'s anchor; batch starts from ``upstream``'s poses with either.  With
        ``"own"`` the graph decides everything itself and ignores ``upstream``."""
        if not isinstance(options, GraphRunOptions):
            raise TypeError(
                f"the {self.name} estimator takes GraphRunOptions, got {type(options).__name__}"
            )
        if options.association == "ekf" and upstream is None:
            raise ValueError(
                f"the {self.name} estimator with association 'ekf' needs the upstream run "
                f"whose decisions it takes ({self.capabilities.consumes}'s)"
            )
        graph = options.graph
        if (
            options.split_circles_where_exact
            and options.association != "own"
            and graph.robust is None
            and centre_radius_correlated(log) is None
        ):
            graph = dataclasses.replace(graph, split_circles=True)
        # "own" decides everything itself: the upstream run is neither its decisions
        # nor its starting point.
        given = None if options.association == "own" else upstream
        decisions = None if given is None else given.decisions
        result = run_graph(
            log,
            cast(Backend, self.name),
            fusion=fusion,
            association="given" if options.association == "ekf" else options.association,
            decisions=decisions,
            options=graph,
            lm=options.lm,
            isam2=options.isam2,
            fixedlag=options.fixedlag,
            init_poses=None if given is None else given.poses,
            progress=progress,
            joint_stride=options.joint_stride,
        )
        label = upstream.estimator if options.association == "ekf" and upstream else None
        return dataclasses.replace(result, association=label or options.association, upstream=given)


_SMOOTHER = Capabilities(
    tracks=frozenset({"smoothed"}),
    consumes="ekf",
    smooths_before_anchor=True,
    exports_graph=True,
)


class BatchEstimator(_GraphEstimator):
    """Batch Levenberg–Marquardt over the whole log (smoothed estimates)."""

    name = "batch"
    capabilities = _SMOOTHER


class ISAM2Estimator(_GraphEstimator):
    """iSAM2, one update per step (filtered and smoothed estimates)."""

    name = "isam2"
    capabilities = dataclasses.replace(_SMOOTHER, tracks=frozenset({"filtered", "smoothed"}))


class FixedLagEstimator(_GraphEstimator):
    """GTSAM's incremental fixed-lag smoother over the iSAM2 graph (filtered estimates,
    and each pose as final when it leaves the window; :mod:`mapfuse_graph.fixedlag`)."""

    name = "fixedlag"
    capabilities = Capabilities(
        tracks=frozenset({"filtered", "smoothed"}), consumes="ekf", exports_graph=False
    )
