"""Validation of a measurement log and of association arrays before any factor is built.

An exception inside an iSAM2 update leaves it corrupt, so malformed input must never
reach GTSAM: :func:`_validate_log` checks what GTSAM needs and returns the noise
covariances it computed on the way, so that the builder does not compute them again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.factors import (
    line_to_rho_alpha,
    residual_noise_cov,
)

__all__ = ["centre_radius_correlated", "odometry_noise_cov"]


def centre_radius_correlated(log: MeasurementLog) -> int | None:
    """First circle observation of ``log`` whose covariance correlates its centre and
    radius (then :attr:`GraphOptions.split_circles` would change the model), else ``None``."""
    circles = np.nonzero(log.feat_kind == int(FeatureKind.CIRCLE))[0]
    bad = circles[np.any(log.feat_cov[circles][:, :2, 2] != 0.0, axis=1)]
    return int(bad[0]) if bad.size else None


def odometry_noise_cov(u: FloatArray, Q: FloatArray) -> FloatArray:
    """Raw-increment covariance ``Q`` → covariance of GTSAM's Between error, ``Gᵀ Q G``."""
    c, s = math.cos(u[2]), math.sin(u[2])
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = G.T @ Q @ G
    return 0.5 * (out + out.T)


def _is_pd(cov: FloatArray) -> bool:
    if not np.all(np.isfinite(cov)):
        return False
    w = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    return bool(w.min() > 1e-14 * max(w.max(), 1e-300) and w.min() > 0.0)


def _known_prior(
    kind: FeatureKind, f: FloatArray, cov: FloatArray
) -> tuple[FloatArray, FloatArray]:
    if kind == FeatureKind.CIRCLE:
        return f.copy(), cov.copy()
    v, J = line_to_rho_alpha(f)
    return v, J @ cov @ J.T


def _pd_rows(covs: FloatArray) -> np.ndarray:
    """(n,) bool: which of the stacked covariances (n, d, d) are positive definite."""
    if covs.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    finite = np.all(np.isfinite(covs), axis=(1, 2))
    safe = np.where(finite[:, None, None], covs, 0.0)
    w = np.linalg.eigvalsh(0.5 * (safe + np.swapaxes(safe, 1, 2)))
    out: np.ndarray = finite & (w[:, 0] > 0.0) & (w[:, 0] > 1e-14 * np.maximum(w[:, -1], 1e-300))
    return out


@dataclass(frozen=True)
class _LogNoise:
    """Noise covariances of every factor of the log, computed (and checked) once."""

    odometry: FloatArray
    """(N, 3, 3) covariance of each Between error (row 0 unused)."""
    observation: list[FloatArray]
    """Per observation, its residual covariance (2×2 lines, 3×3 circles)."""


def _validate_log(log: MeasurementLog, steps: int) -> _LogNoise:
    """Checks beyond :class:`MeasurementLog`'s own: what GTSAM needs to be safe.

    Returns the noise covariances it had to compute for the checks, so that building
    the factors does not compute them again.
    """
    kinds = np.asarray(log.feat_kind)
    bad = np.nonzero(~np.isin(kinds, [int(FeatureKind.LINE), int(FeatureKind.CIRCLE)]))[0]
    if bad.size:
        j = int(bad[0])
        raise ValueError(f"observation {j} has unknown feature kind {int(kinds[j])}")
    for name in ("odometry", "feat_params", "feat_cov", "odometry_cov"):
        a = np.asarray(getattr(log, name))
        if not np.all(np.isfinite(a)):
            where = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise ValueError(f"log '{name}' has a non-finite value at {where}")
    odo = np.zeros((log.n_steps, 3, 3))
    for k in range(1, steps):
        odo[k] = odometry_noise_cov(log.odometry[k], log.odometry_cov[k])
    ok = _pd_rows(odo[1:steps])
    if not np.all(ok):
        raise ValueError(
            f"odometry covariance of step {int(np.nonzero(~ok)[0][0]) + 1} is not positive definite"
        )
    m = int(np.searchsorted(log.feat_step, steps, side="left"))
    circles = np.nonzero(kinds[:m] == int(FeatureKind.CIRCLE))[0]
    small = circles[~(log.feat_params[circles, 2] > 0.0)]
    if small.size:
        j = int(small[0])
        raise ValueError(f"observation {j} is a circle with radius {log.feat_params[j, 2]}")
    obs = _projected(log, kinds, log.feat_cov[:m], "covariance")
    if log.feat_gate_cov is not None:
        _projected(log, kinds, log.feat_gate_cov[:m], "gate covariance")
    km = log.known_map
    for r in range(len(km)):
        kind = int(km.kinds[r])
        if kind not in (int(FeatureKind.LINE), int(FeatureKind.CIRCLE)):
            raise ValueError(f"known feature {int(km.ids[r])} has unknown kind {kind}")
        if not np.all(np.isfinite(km.params[r])) or not np.all(np.isfinite(km.covs[r])):
            raise ValueError(f"known feature {int(km.ids[r])} has non-finite parameters")
        _, P = _known_prior(FeatureKind(kind), km.params[r], km.covs[r])
        if not _is_pd(P):
            raise ValueError(
                f"known feature {int(km.ids[r])}: covariance is not positive definite "
                "(a prior needs a σ on every degree of freedom)"
            )
    return _LogNoise(odo, obs)


def _check_assoc_arrays(
    log: MeasurementLog, association: tuple[Any, Any], known_row: dict[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    if not (isinstance(association, tuple | list) and len(association) == 2):
        raise ValueError("association arrays must be a pair (obs_landmark, obs_known_id)")
    out = []
    for name, a in zip(("obs_landmark", "obs_known_id"), association, strict=True):
        arr = np.asarray(a)
        if arr.shape != (log.n_features,):
            raise ValueError(
                f"{name} has shape {arr.shape}, the log has {log.n_features} observations"
            )
        if arr.dtype.kind not in "iu":
            if arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
                arr = arr.astype(np.int64)
            else:
                raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
        out.append(arr.astype(np.int64))
    lm, kn = out
    if np.any(lm < -1) or np.any(kn < -1):
        raise ValueError("association ids must be >= -1 (-1 = none)")
    missing = sorted({int(i) for i in kn[kn >= 0]} - set(known_row))
    if missing:
        raise ValueError(f"obs_known_id refers to known features missing from the map: {missing}")
    orphan = np.nonzero((kn >= 0) & (lm < 0))[0]
    if orphan.size:
        raise ValueError(
            f"observation {int(orphan[0])} is merged with a known feature but has no landmark"
        )
    return lm, kn


def _projected(
    log: MeasurementLog, kinds: np.ndarray, covs: np.ndarray, what: str
) -> list[FloatArray]:
    """Each observation's ``what`` (its rows ``covs``) projected on its residual,
    checked positive definite: a gate or a factor divides by it."""
    obs = [
        residual_noise_cov(FeatureKind(int(kinds[j])), log.feat_params[j], covs[j])
        for j in range(len(covs))
    ]
    for d in (2, 3):
        idx = [j for j in range(len(obs)) if obs[j].shape[0] == d]
        if idx:
            ok_obs = _pd_rows(np.stack([obs[j] for j in idx]))
            if not np.all(ok_obs):
                raise ValueError(
                    f"observation {idx[int(np.nonzero(~ok_obs)[0][0])]}: its {what} projected "
                    "on the residual is not positive definite"
                )
    return obs
