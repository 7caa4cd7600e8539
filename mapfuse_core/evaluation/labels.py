"""Which true feature an estimated landmark stands for: :func:`landmark_labels`."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np

__all__ = ["landmark_labels"]


def landmark_labels(
    obs_landmark: np.ndarray, labels: np.ndarray, landmarks: Sequence[int]
) -> list[int]:
    """For each id in ``landmarks``, the label most of its labelled observations carry
    (−1 if none has one).

    ``obs_landmark[i]`` is the landmark observation ``i`` was given (−1: none) and
    ``labels[i]`` its true or reference id (−1: none).  A landmark is the fusion of all
    its observations, so the wall or tree most of them saw is the one it stands for;
    its first observation may be a stray one (a door frame, the end of the next wall,
    a clutter segment the association later grew into a wall).  Ties go to the label
    seen first.  How a known-map pairing of a landmark is judged.
    """
    obs_landmark = np.asarray(obs_landmark)
    labels = np.asarray(labels)
    if obs_landmark.shape != labels.shape:
        raise ValueError(
            f"obs_landmark has shape {obs_landmark.shape}, labels {labels.shape}: "
            "give one landmark and one label per observation"
        )
    counts: dict[int, Counter[int]] = {}
    for lm, lab in zip(obs_landmark.tolist(), labels.tolist(), strict=True):
        if lm >= 0 and lab >= 0:
            counts.setdefault(int(lm), Counter())[int(lab)] += 1
    out = []
    for lm in landmarks:
        c = counts.get(int(lm))
        out.append(c.most_common(1)[0][0] if c else -1)
    return out
