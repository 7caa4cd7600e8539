"""Measurement models, one per feature type (numpy only; docs/method.md).

Each model is the residual of an observed feature ``Z`` against a target ``T`` of the
same type, estimated or known, with its Jacobians and its noise, plus the observation
form through a sensor pose.  The EKF (:mod:`ekf_reference.association`) and the factor
graph (:mod:`mapfuse_graph.factors`) both linearise these functions.
"""

from mapfuse_core.models.circle import (
    circle_observation,
    circle_observation_cov,
    circle_residual,
    circle_residual_cov,
)
from mapfuse_core.models.dispatch import (
    circle_pairing,
    line_pairing,
    observe,
    pairing_cov,
    pairing_residual,
)
from mapfuse_core.models.line import (
    B_LINE,
    bind_line_cov,
    line_observation,
    line_observation_cov,
    line_residual,
    line_residual_cov,
)

__all__ = [
    "B_LINE",
    "bind_line_cov",
    "circle_observation",
    "circle_observation_cov",
    "circle_pairing",
    "circle_residual",
    "circle_residual_cov",
    "line_observation",
    "line_observation_cov",
    "line_pairing",
    "line_residual",
    "line_residual_cov",
    "observe",
    "pairing_cov",
    "pairing_residual",
]
