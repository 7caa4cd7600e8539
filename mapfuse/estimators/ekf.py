"""The EKF reference (:mod:`ekf_reference`) as a harness estimator."""

from __future__ import annotations

from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from mapfuse.estimator import Capabilities, Progress
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog

__all__ = ["EKFEstimator"]


class EKFEstimator:
    """Chanier et al.'s multi-map EKF with known-map fusion; options: :class:`EKFConfig`."""

    name = "ekf"
    options_type = EKFConfig
    capabilities = Capabilities(tracks=frozenset({"filtered"}))

    def run(
        self,
        log: MeasurementLog,
        options: EKFConfig,
        *,
        fusion: bool,
        upstream: EstimatorResult | None = None,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Run the EKF with ``options``."""
        if not isinstance(options, EKFConfig):
            raise TypeError(f"the ekf estimator takes an EKFConfig, got {type(options).__name__}")
        return run_ekf(log, options, fusion=fusion, progress=progress)
