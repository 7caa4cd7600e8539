"""A dead-reckoning estimator defined outside the packages: the plugin tests' toy.

It integrates the logged odometry and its covariance and keeps no map, so it never
fuses.  ``docs/plugins.md`` shows the same estimator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapfuse.estimator import Capabilities
from mapfuse_core.estimate import EstimatorResult, MapEstimate, PoseTrack
from mapfuse_core.geometry.se2 import compose_jacobians
from mapfuse_core.measlog import MeasurementLog


@dataclass(frozen=True)
class DeadReckoningOptions:
    """Options of the toy estimator."""

    noise_scale: float = 1.0
    """Factor on the odometry covariance (a stand-in for a real tuning knob)."""


class DeadReckoning:
    """Composes the odometry increments from the origin of ``Wglobal``."""

    name = "toy"
    options_type = DeadReckoningOptions
    capabilities = Capabilities(tracks=frozenset({"filtered"}), fuses=False)

    def run(
        self,
        log: MeasurementLog,
        options: DeadReckoningOptions,
        *,
        fusion: bool,
        upstream: EstimatorResult | None = None,
        progress: Any = None,
    ) -> EstimatorResult:
        n = log.n_steps
        poses, covs, times = np.zeros((n, 3)), np.zeros((n, 3, 3)), np.zeros(n)
        for k in range(1, n):
            t0 = time.perf_counter()
            poses[k], Ja, Ju = compose_jacobians(poses[k - 1], log.odometry[k])
            Q = options.noise_scale * log.odometry_cov[k]
            covs[k] = Ja @ covs[k - 1] @ Ja.T + Ju @ Q @ Ju.T
            times[k] = time.perf_counter() - t0
            if progress is not None:
                progress(k + 1, n)
        return EstimatorResult(
            estimator=self.name,
            scenario=log.scenario,
            seed=log.seed,
            fusion=False,  # it never uses the known map
            timestamps=log.timestamps,
            step_time_s=times,
            map=MapEstimate.empty(),
            filtered=PoseTrack(poses, covs),
        )
