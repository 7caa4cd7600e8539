"""A Gaussian over a list of 3-parameter elements: the storage of every EKF map.

Each element is a pose (a frame such as ``Wlocal`` or ``Wknown``), an SPmap line or a
circle, always 3 parameters ordered as in :mod:`mapfuse_core.geometry.features`.  An element
is *moving* when it is expressed in the vehicle frame ``R`` (robotcentric maps: it
changes with every odometry step) and *static* otherwise (known-map features, which
live in ``Wknown``).

Lines carry no along-line information (SPmap binding): after every operation that
could put uncertainty on the along-line coordinate, :meth:`GaussianMap.bind_lines`
projects it out.  This is a gauge choice (the reference point on the line is
arbitrary), not a loss of information, and it keeps the along-line pseudo-variance
from leaking into lateral residuals when angles differ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle
from mapfuse_core.models.line import bind_line_cov

__all__ = ["Element", "ElementKind", "GaussianMap", "Role", "bind_line_cov"]


class ElementKind(IntEnum):
    """What the 3 parameters of an element mean."""

    POSE = 0
    """A frame ``(x, y, θ)``."""
    LINE = 1
    """An SPmap line ``(x, y, θ)``."""
    CIRCLE = 2
    """A circle ``(x, y, r)``."""

    @staticmethod
    def of_feature(kind: FeatureKind | int) -> ElementKind:
        """Element kind of a :class:`FeatureKind`."""
        return ElementKind.LINE if int(kind) == int(FeatureKind.LINE) else ElementKind.CIRCLE

    def feature_kind(self) -> FeatureKind:
        """:class:`FeatureKind` of a line or circle element (poses transform like lines)."""
        return FeatureKind.CIRCLE if self == ElementKind.CIRCLE else FeatureKind.LINE


class Role(IntEnum):
    """Why an element is in a map."""

    BASE = 0
    """The base frame of the map (``x^R_Wlocal`` in a local map, ``x^Wlocal_Wglobal``)."""
    ANCHOR = 1
    """The known-map frame ``Wknown`` (the paper's translation vector)."""
    FEATURE = 2
    """An estimated feature."""
    KNOWN = 3
    """A known-map feature (static, in ``Wknown``)."""


@dataclass
class Element:
    """Bookkeeping of one element (its mean and covariance live in the map arrays)."""

    kind: ElementKind
    """Meaning of the parameters."""
    role: Role
    """Why it is in the map."""
    moving: bool
    """Expressed in the vehicle frame (moves with odometry)."""
    track: int
    """Feature track id (estimated features), known-map id (known features), −1 otherwise."""
    extent: tuple[float, float] = (math.nan, math.nan)
    """Along-line interval of the observed points relative to the reference point (lines)."""
    extent_sd: float = 0.0
    """σ (m) of where the extent's ends lie along the line: a known wall's survey (its
    position σ in the wall's direction); an estimated line's, the largest of its
    segments' (:attr:`~ekf_reference.association.Query.end_sd`)."""
    true_id: int = -1
    """World id of the observations (simulation, evaluation only: never used to associate)."""
    n_obs: int = 0
    """How many observations were fused into it."""
    in_local: bool = False
    """Created in the current local map (join pairs these against the global ones)."""


class GaussianMap:
    """Mean ``(n, 3)`` and covariance ``(3n, 3n)`` over a list of :class:`Element`."""

    def __init__(self) -> None:
        self.mean: FloatArray = np.zeros((0, 3))
        self.cov: FloatArray = np.zeros((0, 0))
        self.elements: list[Element] = []
        self._kr: tuple[list[Element], int, np.ndarray, np.ndarray] | None = None

    def kinds_roles(self) -> tuple[np.ndarray, np.ndarray]:
        """(n,) int arrays of the elements' kinds and roles (read-only, cached).

        Asked for several times a step; an element's kind and role never change, and
        the element list only grows or is replaced, so the cache is keyed on the list
        object (held, so its identity cannot be reused) and its length.
        """
        kr = self._kr
        if kr is None or kr[0] is not self.elements or kr[1] != len(self.elements):
            n = len(self.elements)
            kinds = np.fromiter((e.kind for e in self.elements), dtype=np.int64, count=n)
            roles = np.fromiter((e.role for e in self.elements), dtype=np.int64, count=n)
            kinds.setflags(write=False)
            roles.setflags(write=False)
            kr = self._kr = (self.elements, n, kinds, roles)
        return kr[2], kr[3]

    # ------------------------------------------------------------------ structure

    def __len__(self) -> int:
        return len(self.elements)

    def copy(self) -> GaussianMap:
        """Deep copy."""
        out = GaussianMap()
        out.mean = self.mean.copy()
        out.cov = self.cov.copy()
        out.elements = [Element(**vars(e)) for e in self.elements]
        return out

    def add(
        self, element: Element, mean: FloatArray, cov: FloatArray, cross: FloatArray | None = None
    ) -> int:
        """Append an element; ``cross`` is its (3, 3n) covariance with the existing ones."""
        n = len(self)
        mean = np.asarray(mean, dtype=float).reshape(3)
        if not np.all(np.isfinite(mean)) or not np.all(np.isfinite(cov)):
            raise ValueError(f"non-finite mean or covariance for a new {element.kind.name}")
        new = np.zeros((3 * n + 3, 3 * n + 3))
        new[: 3 * n, : 3 * n] = self.cov
        new[3 * n :, 3 * n :] = 0.5 * (cov + cov.T)
        if cross is not None:
            new[3 * n :, : 3 * n] = cross
            new[: 3 * n, 3 * n :] = cross.T
        self.cov = new
        self.mean = np.vstack([self.mean, mean[None, :]])
        self.elements.append(element)
        return n

    def remove(self, indices: list[int]) -> None:
        """Drop elements (marginalisation: just delete their rows and columns)."""
        if not indices:
            return
        keep = [i for i in range(len(self)) if i not in set(indices)]
        self.keep(keep)

    def keep(self, order: list[int]) -> None:
        """Keep only the elements in ``order``, in that order."""
        idx = self.dofs(order)
        self.cov = self.cov[np.ix_(idx, idx)]
        self.mean = self.mean[order]
        self.elements = [self.elements[i] for i in order]

    @staticmethod
    def dofs(indices: list[int] | range) -> np.ndarray:
        """Covariance row indices of the given elements."""
        return (3 * np.asarray(list(indices), dtype=np.int64)[:, None] + np.arange(3)).reshape(-1)

    def block(self, i: int, j: int | None = None) -> FloatArray:
        """Covariance block ``(i, j)`` (default: the marginal of ``i``)."""
        j = i if j is None else j
        return self.cov[3 * i : 3 * i + 3, 3 * j : 3 * j + 3]

    def marginal(self, indices: list[int]) -> FloatArray:
        """Joint covariance of the given elements."""
        idx = self.dofs(indices)
        out: FloatArray = self.cov[np.ix_(idx, idx)]
        return out

    def find(self, role: Role) -> int:
        """Index of the (single) element with ``role``; raises if absent."""
        hits = np.flatnonzero(self.kinds_roles()[1] == int(role))
        if hits.size == 0:
            raise KeyError(f"no {role.name} element in the map")
        return int(hits[0])

    def has(self, role: Role) -> bool:
        """Whether an element with ``role`` exists."""
        return bool((self.kinds_roles()[1] == int(role)).any())

    def indices(self, role: Role) -> list[int]:
        """Indices of the elements with ``role``."""
        out: list[int] = np.flatnonzero(self.kinds_roles()[1] == int(role)).tolist()
        return out

    # ------------------------------------------------------------------ operations

    def wrap(self) -> None:
        """Wrap the angles of poses and lines to ``(−π, π]``."""
        ang = self.kinds_roles()[0] != int(ElementKind.CIRCLE)
        if ang.any():
            self.mean[ang, 2] = wrap_angle(self.mean[ang, 2])

    def symmetrise(self) -> None:
        """Remove round-off asymmetry of the covariance."""
        # In place (numpy buffers the overlapping transpose): this runs twice a step.
        self.cov += self.cov.T
        self.cov *= 0.5

    def apply_linear(self, blocks: FloatArray, mask: np.ndarray) -> None:
        """``P ← F P Fᵀ`` for block-diagonal ``F`` with ``blocks[i]`` where ``mask[i]``, else I."""
        n = len(self)
        if n == 0 or not mask.any():
            return
        P4 = self.cov.reshape(n, 3, n, 3)
        sel = np.nonzero(mask)[0]
        B = blocks[sel]
        P4[sel] = np.einsum("iab,ibjc->iajc", B, P4[sel])
        P4[:, :, sel] = np.einsum("iajc,jdc->iajd", P4[:, :, sel], B)
        self.cov = P4.reshape(3 * n, 3 * n)

    def bind_lines(self) -> None:
        """Project the along-line degree of freedom of every line out of the covariance."""
        lines = self.kinds_roles()[0] == int(ElementKind.LINE)
        if not lines.any():
            return
        th = self.mean[:, 2]
        c, s = np.cos(th), np.sin(th)
        # Π = I − u uᵀ on (x, y), u the line direction: removes the along-line component.
        blocks = np.zeros((len(self), 3, 3))
        blocks[:, 0, 0] = 1.0 - c * c
        blocks[:, 0, 1] = -c * s
        blocks[:, 1, 0] = -c * s
        blocks[:, 1, 1] = 1.0 - s * s
        blocks[:, 2, 2] = 1.0
        self.apply_linear(blocks, lines)

    def _innovation(
        self, indices: list[int], H: FloatArray, R: FloatArray, jitter: float
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``P Hᵀ`` (3n × m), ``S = H P Hᵀ + R`` and its Cholesky factor."""
        idx = self.dofs(indices)
        PHt = self.cov[:, idx] @ H.T
        S = H @ PHt[idx] + R
        S = 0.5 * (S + S.T) + jitter * np.eye(S.shape[0])
        try:
            L = np.linalg.cholesky(S)
        except np.linalg.LinAlgError as exc:
            raise np.linalg.LinAlgError(
                f"innovation covariance not positive definite for elements {indices}"
            ) from exc
        return PHt, S, L

    def update(
        self,
        indices: list[int],
        residual: FloatArray,
        H: FloatArray,
        R: FloatArray,
        jitter: float = 1e-12,
    ) -> float:
        """EKF update with residual ``r(x)`` (to be driven to zero) of the given elements.

        ``H`` is ``∂r/∂x`` over the blocks of ``indices`` (m × 3k), ``R`` the covariance of
        ``r`` due to measurement noise (m × m; zero for a hard constraint).  Returns the
        Mahalanobis distance ``rᵀ S⁻¹ r`` of the residual before the update.
        """
        PHt, S, L = self._innovation(indices, H, R, jitter)
        # K = P Hᵀ S⁻¹ via the Cholesky factor (better conditioned than inv(S)).
        Linv_PHt = np.linalg.solve(L, PHt.T)
        K = np.linalg.solve(L.T, Linv_PHt).T
        d2 = float(residual @ np.linalg.solve(S, residual))
        self.mean = self.mean - (K @ residual).reshape(-1, 3)
        self.cov = self.cov - Linv_PHt.T @ Linv_PHt
        self.symmetrise()
        self.wrap()
        return d2

    def updated_mean(
        self,
        indices: list[int],
        residual: FloatArray,
        H: FloatArray,
        R: FloatArray,
        jitter: float = 1e-12,
    ) -> tuple[FloatArray, float]:
        """The mean :meth:`update` would leave (angles wrapped) and ``rᵀ S⁻¹ r``, the
        covariance untouched: ``O(n·m)`` instead of the update's ``O(n²·m)``."""
        PHt, _, L = self._innovation(indices, H, R, jitter)
        w = np.linalg.solve(L.T, np.linalg.solve(L, residual))
        mean = self.mean - (PHt @ w).reshape(-1, 3)
        ang = self.kinds_roles()[0] != int(ElementKind.CIRCLE)
        mean[ang, 2] = wrap_angle(mean[ang, 2])
        return mean, float(residual @ w)
