"""Tentative features: a new local feature joins the map only once it is seen again.

*(choice, beyond the paper)* The paper makes every unassociated observation a new,
permanent feature, so a spurious detection (clutter) stays in the map for the whole
run.  With ``EKFConfig.tentative_min_sightings = k > 1`` a new feature is tentative:

- it enters the local map as usual (initialised from its observation, so it carries
  no information about the vehicle yet) and observations are associated with it as
  with any feature, but it is not paired with the known map while it is tentative
  in its local map;
- it is promoted (an ordinary feature from then on) at the step it has been seen on
  ``k`` distinct steps within ``tentative_window_steps`` steps of its birth;
- otherwise it is dropped at the end of its window: removed from the state, which
  marginalises it out (exact for a Gaussian), and its observations become
  unassociated (−1);
- at a join, an undecided tentative seen on every step since its birth (it had no
  chance to fail yet) joins the global map with the others, and is decided at the
  next join, after the merges: kept if its merged feature has ``k`` observations,
  otherwise removed from the global map (marginalised out); the other undecided
  tentatives are dropped, and at the last step all of them.

Dropping a feature seen once changes nothing else in the estimate, since a feature
initialised from one observation has not constrained anything; one seen on fewer
than ``k`` steps gives back the vehicle information those few sightings carried.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ekf_reference.state import GaussianMap, Role

__all__ = ["Tentatives"]


class Tentatives:
    """The tentative features of the current local map, by track id, and the counts."""

    def __init__(self, min_sightings: int, window_steps: int) -> None:
        self.min_sightings = int(min_sightings)
        self.window_steps = int(window_steps)
        self.birth: dict[int, int] = {}
        """Birth step of every undecided tentative feature, by track."""
        self.sightings: dict[int, int] = {}
        """Distinct steps on which each undecided tentative feature was seen."""
        self.joined: set[int] = set()
        """Tracks of the tentatives that joined the global map at the last join,
        decided at the next one (:meth:`settle`)."""
        self.promoted = 0
        """Tentative features promoted so far."""
        self.dropped = 0
        """Tentative features dropped so far."""

    @property
    def pending(self) -> set[int]:
        """Tracks of the undecided tentative features."""
        return set(self.birth)

    def review(
        self, k: int, loc: GaussianMap, born: list[int], obs_track: np.ndarray, seen: np.ndarray
    ) -> None:
        """After step ``k``'s observations: register the features ``born`` (indices into
        ``loc``), count a sighting for every tentative whose track is in ``seen`` (the
        step's observation tracks), promote and drop."""
        if self.min_sightings <= 1:
            return
        tracks = {int(t) for t in seen.tolist() if t >= 0}
        new = {loc.elements[i].track for i in born}
        for t in tracks & self.pending - new:
            self.sightings[t] += 1
        for t in new:
            self.birth[t], self.sightings[t] = k, 1
        drop = []
        for t in list(self.birth):
            if self.sightings[t] >= self.min_sightings:
                del self.birth[t], self.sightings[t]
                self.promoted += 1
            elif k - self.birth[t] + 1 >= self.window_steps:
                drop.append(t)
        self._drop(loc, drop, obs_track)

    def flush(self, k: int, loc: GaussianMap, obs_track: np.ndarray, last: bool) -> list[int]:
        """Before the join at step ``k``: drop the undecided tentatives, except (unless
        ``last``) those seen on every step since their birth, which join the global map
        and are returned (to :meth:`settle` at the next join)."""
        on_track = [
            t for t in self.birth if not last and self.sightings[t] == k - self.birth[t] + 1
        ]
        self._drop(loc, [t for t in self.birth if t not in on_track], obs_track)
        for t in on_track:
            del self.birth[t], self.sightings[t]
        return on_track

    def settle(
        self,
        joint: GaussianMap,
        obs_track: np.ndarray,
        root: Callable[[int], int],
        joined_now: list[int],
    ) -> None:
        """After a join's merges: keep the tentatives of the previous join whose merged
        feature has ``min_sightings`` observations, remove the others from ``joint``;
        ``joined_now`` (from :meth:`flush`) wait for the next join."""
        prev, self.joined = self.joined, set(joined_now)
        if not prev:
            return
        idx, gone = [], []
        for i, e in enumerate(joint.elements):
            if e.role != Role.FEATURE or e.track not in prev:
                continue
            if e.n_obs >= self.min_sightings:
                self.promoted += 1
            else:
                idx.append(i)
                gone.append(root(e.track))
        if not idx:
            return
        joint.remove(idx)
        roots = np.array([root(int(t)) if t >= 0 else -1 for t in obs_track.tolist()])
        obs_track[np.isin(roots, np.array(gone, dtype=np.int64))] = -1
        self.dropped += len(idx)

    def _drop(self, loc: GaussianMap, tracks: list[int], obs_track: np.ndarray) -> None:
        if not tracks:
            return
        gone = set(tracks)
        idx = [
            i
            for i, e in enumerate(loc.elements)
            if e.role == Role.FEATURE and e.in_local and e.track in gone
        ]
        loc.remove(idx)
        obs_track[np.isin(obs_track, np.array(tracks, dtype=np.int64))] = -1
        for t in tracks:
            del self.birth[t], self.sightings[t]
        self.dropped += len(tracks)
