"""The map matchings a run made and how each ended: :class:`MatchAttempts`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["MatchAttempts"]


@dataclass(frozen=True)
class MatchAttempts:
    """The map matchings (CCDA calls) a run made and how each ended."""

    attempts: int
    """CCDA calls."""
    reasons: Mapping[str, int]
    """Calls per outcome: a :data:`mapfuse_core.matching.ccda.REASONS` entry
    (``"accepted"``, ``"ambiguous"``, ``"search_limit"``, ...), or the estimator's own
    verdict on a match CCDA accepted: refused before fusion (the EKF's
    ``"jointly inconsistent"``, ``"a pairing inconsistent with the others"``,
    ``"compatible with an undone anchor"``; the graph's ``"anchor refused"``), or fused
    and undone later (the EKF's ``"anchor contradicted"``).  Each call has one
    outcome."""

    @property
    def search_limit(self) -> int:
        """Calls that ended at CCDA's search budget (``"search_limit"``)."""
        return int(self.reasons.get("search_limit", 0))
