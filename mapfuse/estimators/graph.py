"""The GTSAM mirror (:mod:`mapfuse_graph`) as harness estimators: batch, iSAM2 and the
fixed-lag smoother."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from mapfuse import registry
from mapfuse.estimator import Progress
from mapfuse.profiles import default_options
from mapfuse.result import Anchor, EstimatorResult, MapEstimate, MatchAttempts, PoseTrack
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.graph import ASSOCIATIONS, GraphOptions, centre_radius_correlated
from mapfuse_graph.solvers import (
    FixedLagOptions,
    GraphResult,
    ISAM2Options,
    LMOptions,
    run_graph,
)

__all__ = [
    "BatchEstimator",
    "FixedLagEstimator",
    "GraphRunOptions",
    "ISAM2Estimator",
    "to_result",
]


@dataclass(frozen=True)
class GraphRunOptions:
    """Options of a graph backend run."""

    association: str = "ekf"
    """``"ekf"`` (the decisions of :attr:`upstream`, the EKF's), ``"truth"`` or ``"own"``."""
    robust: str | None = None
    """Robust kernel of the observation factors: ``None``, ``"huber[:k]"``, ``"cauchy[:k]"``."""
    graph: GraphOptions = field(default_factory=GraphOptions)
    """Graph options (``fusion``, ``association`` and ``robust`` are set from the run)."""
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
    upstream: EstimatorResult | None = None
    """A finished run of the same log and fusion setting whose association decisions
    and anchor this run consumes (batch also starts from its poses); with
    ``association="ekf"`` and none given, the EKF runs first with its defaults for the log."""
    joint_stride: int | None = None
    """Batch: also keep the joint covariance of every ``joint_stride``-th pose
    (``extras["graph"].joint_pose_cov``)."""


def to_result(
    g: GraphResult, log: MeasurementLog, upstream: EstimatorResult | None = None
) -> EstimatorResult:
    """A :class:`GraphResult` of ``log`` as an :class:`EstimatorResult`."""
    lm = g.landmarks
    anchor = None
    if g.anchor is not None:
        a = g.anchor
        anchor = Anchor(a.x_Wknown_Wglobal, a.cov, int(a.accepted_at_step), a.pairings)
    filtered = None
    if g.filtered_poses is not None and g.filtered_covs is not None:
        filtered = PoseTrack(g.filtered_poses, g.filtered_covs)
    return EstimatorResult(
        estimator=g.backend,
        scenario=log.scenario,
        seed=log.seed,
        fusion=bool(g.fusion),
        timestamps=np.asarray(log.timestamps[: g.poses.shape[0]], dtype=float),
        step_time_s=g.step_time_s,
        map=MapEstimate(lm.kinds, lm.params, lm.covs, lm.known_ids, lm.true_ids, lm.n_obs),
        filtered=filtered,
        smoothed=PoseTrack(g.poses, g.covs),
        anchor=anchor,
        decisions=g.decisions,
        association=g.association,
        upstream=upstream,
        matching=None
        if g.ccda_reasons is None or not g.fusion
        else MatchAttempts(sum(g.ccda_reasons.values()), dict(g.ccda_reasons)),
        extras={"graph": g},
    )


class _GraphEstimator:
    """One graph backend; options: :class:`GraphRunOptions`."""

    name = ""
    options_type = GraphRunOptions
    consumes = "ekf"

    def run(
        self,
        log: MeasurementLog,
        options: GraphRunOptions,
        *,
        fusion: bool,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Build and solve the graph of ``log``."""
        if not isinstance(options, GraphRunOptions):
            raise TypeError(
                f"the {self.name} estimator takes GraphRunOptions, got {type(options).__name__}"
            )
        if options.association not in ASSOCIATIONS:
            raise ValueError(
                f"unknown association {options.association!r}; choose one of "
                f"{', '.join(ASSOCIATIONS)}"
            )
        upstream = options.upstream
        if options.association == "ekf" and upstream is None:
            ekf = registry.get("ekf")
            upstream = ekf.run(log, default_options(ekf, log), fusion=fusion)
        graph = options.graph
        if (
            options.split_circles_where_exact
            and options.association != "own"
            and options.robust is None
            and centre_radius_correlated(log) is None
        ):
            graph = dataclasses.replace(graph, split_circles=True)
        g = run_graph(
            log,
            backend=self.name,
            fusion=fusion,
            association=options.association,
            decisions=None if upstream is None else upstream.decisions,
            robust=options.robust,
            options=graph,
            lm=options.lm,
            isam2=options.isam2,
            fixedlag=options.fixedlag if self.name == "fixedlag" else None,
            init_poses=None if upstream is None else upstream.poses,
            progress=progress,
            joint_stride=options.joint_stride,
        )
        return to_result(g, log, upstream)


class BatchEstimator(_GraphEstimator):
    """Batch Levenberg–Marquardt over the whole log (smoothed estimates)."""

    name = "batch"


class ISAM2Estimator(_GraphEstimator):
    """iSAM2, one update per step (filtered and smoothed estimates)."""

    name = "isam2"


class FixedLagEstimator(_GraphEstimator):
    """GTSAM's incremental fixed-lag smoother over the iSAM2 graph (filtered estimates,
    and each pose as final when it leaves the window; :mod:`mapfuse_graph.fixedlag`)."""

    name = "fixedlag"
