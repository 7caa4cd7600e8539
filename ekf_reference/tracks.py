"""Which observations are one landmark: :class:`Tracks`."""

from __future__ import annotations

import numpy as np

__all__ = ["Tracks"]


class Tracks:
    """Union-find over feature tracks, so every observation ends with one landmark.

    A track is born with each new local feature and each known feature the map fuses;
    pairings (a local map's duplicates, joins, loop closures, a CCDA match) merge the
    tracks of what turns out to be one feature, and the known id of a track paired with
    a known feature survives later merges."""

    def __init__(self) -> None:
        self.parent: list[int] = []
        self.known: dict[int, int] = {}

    def new(self) -> int:
        """A new track's index."""
        self.parent.append(len(self.parent))
        return len(self.parent) - 1

    def root(self, t: int) -> int:
        """The track ``t`` belongs to now (path halving)."""
        while self.parent[t] != t:
            self.parent[t] = self.parent[self.parent[t]]
            t = self.parent[t]
        return t

    def merge(self, child: int, into: int) -> None:
        """Make ``child``'s track part of ``into``'s; a known id moves with it."""
        a, b = self.root(child), self.root(into)
        if a != b:
            self.parent[a] = b
            if a in self.known and b not in self.known:
                self.known[b] = self.known[a]

    def mark_known(self, t: int, known_id: int) -> None:
        """Record that track ``t`` is known feature ``known_id``."""
        self.known[self.root(t)] = known_id

    def roots(self, obs_track: np.ndarray) -> np.ndarray:
        """(M,) int64 track every observation of ``obs_track`` belongs to now (−1 stays)."""
        return np.array(
            [self.root(int(t)) if t >= 0 else -1 for t in obs_track.tolist()], dtype=np.int64
        )
