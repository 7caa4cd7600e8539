"""The paper's EKF pipeline: robotcentric multi-map SLAM with known-map fusion.

Depends on :mod:`mapfuse_core` only; never imports gtsam.
"""

from ekf_reference.config import EKFConfig
from ekf_reference.loops import LoopClosureParams
from ekf_reference.pipeline import run_ekf
from ekf_reference.result import EKFDetails, LoopClosure

__all__ = [
    "EKFConfig",
    "EKFDetails",
    "LoopClosure",
    "LoopClosureParams",
    "run_ekf",
]
