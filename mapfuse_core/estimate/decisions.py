"""Association decisions of a run, as data another estimator can consume.

An estimator that associates observations itself (the EKF reference) hands its final
decisions to one that consumes them (the graph backends, which take them as their
``"given"`` association) through :class:`AssociationDecisions`, so neither imports the
other.  They are also
saved beside a run's outputs (``associations.npz``) and loaded back by
:func:`load_associations`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = [
    "ASSOCIATIONS_FORMAT",
    "AnchorDecision",
    "AssociationDecisions",
    "KnownMapGating",
    "load_associations",
]

#: ``format_name`` stored in an associations file.
ASSOCIATIONS_FORMAT = "mapfuse.associations"


@dataclass(frozen=True)
class AnchorDecision:
    """The map match a run accepted: where ``Wglobal`` lies in the known map, and when."""

    x_Wknown_Wglobal: FloatArray
    """(3,) pose of ``Wglobal`` (the vehicle at step 0) in ``Wknown``."""
    accepted_at_step: int
    """Step at which the match was accepted."""

    def __post_init__(self) -> None:
        a = np.asarray(self.x_Wknown_Wglobal, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"anchor x_Wknown_Wglobal must be a finite (3,) pose, got {a!r}")
        if self.accepted_at_step < 0:
            raise ValueError(f"anchor accepted_at_step must be >= 0, got {self.accepted_at_step}")


@dataclass(frozen=True, eq=False)
class KnownMapGating:
    """What the known-map gate of a run refused: every rejection counted, and the known
    features it stopped fusing (a consumer adds no tie for those)."""

    level: float
    """χ² level of the gate's consistency tests."""
    rejected: dict[int, int]
    """Known-map id → steps at which a pairing with it was refused: nothing was paired
    with it, and an observation or a landmark inside its pre-gate was not (it failed
    its individual χ² test, or fitted an estimated landmark better)."""
    accepted: dict[int, int]
    """Known-map id → pairings with it the gate let through."""
    unfused: dict[int, int]
    """Known-map id → step from which it is no longer fused (treated as unknown)."""
    anchor_pairings_unfused: int = 0
    """How many of the accepted match's pairings have a known feature later un-fused."""
    anchor_pairings: int = 0
    """Pairings of the accepted match (0 without one)."""

    @property
    def anchor_refuted(self) -> bool:
        """More than half of the match's pairings were later found inconsistent: the
        match itself is in doubt (reported, the anchor is kept)."""
        return self.anchor_pairings > 0 and 2 * self.anchor_pairings_unfused > self.anchor_pairings

    def as_dict(self) -> dict[str, object]:
        """The ``known_map_rejections`` block of ``metrics.json``."""
        return {
            "level": self.level,
            "known_rejected": int(sum(self.rejected.values())),
            "known_unfused": len(self.unfused),
            "known_accepted": int(sum(self.accepted.values())),
            "anchor_pairings": self.anchor_pairings,
            "anchor_pairings_unfused": self.anchor_pairings_unfused,
            "anchor_refuted": self.anchor_refuted,
            "per_feature": {
                str(k): {
                    "rejected": self.rejected.get(k, 0),
                    "accepted": self.accepted.get(k, 0),
                    "unfused_at_step": self.unfused.get(k, -1),
                }
                for k in sorted({*self.rejected, *self.accepted, *self.unfused})
            },
        }


@dataclass(frozen=True, eq=False)
class AssociationDecisions:
    """Which landmark, and which known feature, every logged observation belongs to."""

    obs_landmark: np.ndarray
    """(M,) int64 landmark (track) id of every logged observation, −1 if not associated."""
    obs_known_id: np.ndarray
    """(M,) int64 known-map id the observation's landmark is merged with, −1 otherwise."""
    anchor: AnchorDecision | None = None
    """The accepted map match, or ``None`` (no fusion, or no match accepted)."""
    known_gating: KnownMapGating | None = None
    """The known-map gate's rejections and un-fused features, or ``None`` (no gate)."""

    @property
    def unfused_known_ids(self) -> frozenset[int]:
        """Known-map ids the run stopped fusing: no tie is added for them."""
        return frozenset() if self.known_gating is None else frozenset(self.known_gating.unfused)

    def __post_init__(self) -> None:
        lm, kn = np.asarray(self.obs_landmark), np.asarray(self.obs_known_id)
        if lm.ndim != 1 or kn.shape != lm.shape:
            raise ValueError(
                f"obs_landmark and obs_known_id must be (M,) arrays of one length, got "
                f"shapes {lm.shape} and {kn.shape}"
            )
        for name, a in (("obs_landmark", lm), ("obs_known_id", kn)):
            if a.size and not np.issubdtype(a.dtype, np.integer):
                raise ValueError(f"{name} must hold integers, got dtype {a.dtype}")

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(obs_landmark, obs_known_id)`` as int64 arrays."""
        return (
            np.asarray(self.obs_landmark, dtype=np.int64),
            np.asarray(self.obs_known_id, dtype=np.int64),
        )

    def save(self, path: str | Path) -> Path:
        """Write the decisions (and the anchor, if any) to ``path`` (``.npz``)."""
        path = Path(path)
        lm, kn = self.arrays
        arrays: dict[str, np.ndarray] = {
            "format_name": np.array(ASSOCIATIONS_FORMAT),
            "format_version": np.array(1),
            "obs_landmark": lm,
            "obs_known_id": kn,
        }
        if self.anchor is not None:
            arrays["anchor_x_Wknown_Wglobal"] = np.asarray(self.anchor.x_Wknown_Wglobal, float)
            arrays["anchor_accepted_at_step"] = np.array(self.anchor.accepted_at_step)
        if self.known_gating is not None:
            kg = self.known_gating
            arrays["unfused_known_ids"] = np.array(sorted(kg.unfused), dtype=np.int64)
            arrays["unfused_at_step"] = np.array(
                [kg.unfused[k] for k in sorted(kg.unfused)], dtype=np.int64
            )
        np.savez(path, allow_pickle=False, **arrays)
        return path


def load_associations(path: str | Path, n_obs: int) -> AssociationDecisions:
    """Decisions saved by :meth:`AssociationDecisions.save`, checked to fit a log of
    ``n_obs`` observations."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as z:
        if str(z.get("format_name", "")) != ASSOCIATIONS_FORMAT:
            raise ValueError(f"{path}: not a mapfuse associations file")
        lm, kn = z["obs_landmark"], z["obs_known_id"]
        anchor = None
        if "anchor_x_Wknown_Wglobal" in z:
            anchor = AnchorDecision(
                np.asarray(z["anchor_x_Wknown_Wglobal"], dtype=float),
                int(z["anchor_accepted_at_step"]),
            )
        gating = None
        if "unfused_known_ids" in z:
            # Only the un-fuse decisions travel with the associations; the counts stay
            # in the run's metrics.json.
            ids, at = z["unfused_known_ids"], z["unfused_at_step"]
            gating = KnownMapGating(
                level=float("nan"),
                rejected={},
                accepted={},
                unfused={int(i): int(s) for i, s in zip(ids, at, strict=True)},
            )
    if lm.shape != (n_obs,) or kn.shape != (n_obs,):
        raise ValueError(f"{path}: holds {lm.shape[0]} decisions, the log has {n_obs} observations")
    return AssociationDecisions(lm.astype(np.int64), kn.astype(np.int64), anchor, gating)
