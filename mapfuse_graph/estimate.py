"""What the graph builder reads from a solver (:class:`Estimate`) and hands back per step
(:class:`StepGraph`), and its per-landmark bookkeeping."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_graph.keys import pose_key

__all__ = ["Estimate", "StepGraph"]


class Estimate(Protocol):
    """What the builder needs from a solver's current estimate."""

    def pose(self, k: int) -> FloatArray:
        """``(x, y, θ)`` of ``X_k``."""
        ...

    def vector(self, key: int) -> FloatArray:
        """Value of a vector variable (landmark or known feature)."""
        ...

    def anchor(self) -> FloatArray:
        """``(x, y, θ)`` of the anchor."""
        ...

    def pose_cov(self, k: int) -> FloatArray | None:
        """Absolute ``(x, y, θ)`` covariance of ``X_k``, or ``None`` if unavailable."""
        ...

    def cov(self, key: int) -> FloatArray | None:
        """Marginal covariance of a vector variable, or ``None`` if unavailable."""
        ...


@dataclass
class StepGraph:
    """The new factors and variables of one step."""

    factors: gtsam.NonlinearFactorGraph
    """Factors added at this step."""
    values: gtsam.Values
    """Initial values of the variables created at this step."""
    new_landmarks: list[int] = field(default_factory=list)
    """Dense indices of landmarks created at this step."""
    anchor_added: bool = False
    """Whether the anchor and the known features were added at this step."""


@dataclass
class _Landmark:
    kind: FeatureKind
    first_step: int
    first_obs: int
    n_obs: int = 0
    known: int = -1
    """Row of the known map this landmark is tied to, −1 if none."""
    tied: bool = False
    created: bool = False
    """Whether its variable has been handed to the solver."""
    extent: tuple[float, float] = (math.nan, math.nan)
    """``own``: along-line interval (on the landmark's ``(ρ, α)`` line) it was seen on."""
    cov: FloatArray | None = None
    cov_step: int = -1


class _WithStep:
    """An estimate extended with the values created during the current step."""

    def __init__(self, est: Estimate, k: int, new: gtsam.Values) -> None:
        self._est, self._k, self._new = est, k, new

    def pose(self, k: int) -> FloatArray:
        if k == self._k:
            p = self._new.atPose2(pose_key(k))
            return np.array([p.x(), p.y(), p.theta()])
        return self._est.pose(k)

    def vector(self, key: int) -> FloatArray:
        if self._new.exists(key):
            return np.asarray(self._new.atVector(key), dtype=float)
        return self._est.vector(key)

    def anchor(self) -> FloatArray:
        return self._est.anchor()

    def pose_cov(self, k: int) -> FloatArray | None:
        return None if k == self._k else self._est.pose_cov(k)

    def cov(self, key: int) -> FloatArray | None:
        return None if self._new.exists(key) else self._est.cov(key)
