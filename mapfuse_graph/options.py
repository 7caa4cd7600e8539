"""Options that shape the factor graph (:class:`GraphOptions`) and the association sources."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mapfuse_core.matching import (
    AssociationConfig,
)
from mapfuse_graph.factors import (
    make_noise,
)

__all__ = ["ASSOCIATIONS", "AssociationName", "GraphOptions"]


AssociationName = Literal["given", "truth", "own"]
"""Where a graph's data association comes from (:mod:`mapfuse_graph.builder`)."""

ASSOCIATIONS: tuple[AssociationName, ...] = ("given", "truth", "own")


@dataclass(frozen=True)
class GraphOptions:
    """Everything that shapes the graph (not the solver)."""

    robust: str | None = None
    """Robust kernel of the observation factors: ``None``, ``"huber[:k]"``, ``"cauchy[:k]"``."""
    first_pose_sigma: tuple[float, float, float] = (1e-6, 1e-6, 1e-6)
    """σ (m, m, rad) of the prior holding ``X_0`` at the origin of ``Wglobal``.  Tight
    but not a hard constraint, which the Cholesky of iSAM2 cannot take."""
    tie_sigma: tuple[float, float] = (1e-3, 1e-4)
    """σ (m, rad) of the tie factors.  The EKF applies the pairing as a hard constraint;
    1 mm / 0.1 mrad is two orders below the known map's σ, so the answer is that of a
    hard constraint to < 1e-4 relative, while the system stays well conditioned."""
    data_association: AssociationConfig = field(default_factory=AssociationConfig)
    """Settings shared with the EKF (:class:`~mapfuse_core.matching.AssociationConfig`):
    the anchor's loose prior (every fused run) and, for ``own``, the gates, the
    one-to-one rules, the CCDA match and which landmarks it takes.  ``own`` searches
    by nearest neighbour only (``method`` must be ``"nn"``)."""
    ccda_every: int = 40
    """``own``: steps between CCDA attempts (the EKF's local-map length), and between
    attempts to pair the remaining landmarks with known features once matched."""
    cov_refresh_steps: int = 100
    """``own``: a landmark marginal used for gating is re-read from the solver after
    this many steps (reading iSAM2 marginals costs more than an update)."""
    min_anchor_pairings: int = 4
    """``truth``: paired landmarks needed before the anchor is initialised."""
    max_anchor_std: tuple[float, float] = (1.0, 0.05)
    """``truth``/``own``: largest σ (m, rad) of the fitted anchor for it to be used."""
    split_circles: bool = False
    """*(speed option)* Each circle landmark as two variables, its centre (``c``, 2-vector)
    and its radius (``r``, 1-vector): an observation gives a centre factor
    (:func:`~mapfuse_graph.factors.circle_centre_factor`) and a ``PriorFactorVector`` on
    the radius.  Allowed only when that is the same model: every circle observation's
    residual covariance has no centre–radius correlation (true of Victoria Park's
    detections; then the radius is independent of everything else and the estimates,
    and the zero centre–radius covariance, are those of the 3-vector form), no robust
    kernel (it would weigh the two parts apart), a fixed association and no known
    circles.  iSAM2 then eliminates 2- instead of 3-dimensional landmark blocks, for less
    CPU (``docs/results/victoria-park.md``)."""

    def __post_init__(self) -> None:
        if not isinstance(self.data_association, AssociationConfig):
            raise ValueError(
                "data_association must be an AssociationConfig, got "
                f"{type(self.data_association).__name__}"
            )
        for name in ("first_pose_sigma", "tie_sigma", "max_anchor_std"):
            v = getattr(self, name)
            if not all(math.isfinite(s) and s > 0 for s in v):
                raise ValueError(f"{name} must hold positive finite values, got {v}")
        if self.ccda_every < 1 or self.cov_refresh_steps < 1:
            raise ValueError("ccda_every and cov_refresh_steps must be >= 1")
        if self.min_anchor_pairings < 2:
            raise ValueError(f"min_anchor_pairings must be >= 2, got {self.min_anchor_pairings}")
        if self.robust is not None:
            make_noise(np.eye(2), self.robust)  # raises ValueError on a bad spec
