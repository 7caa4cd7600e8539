"""GTSAM keys of the mapfuse factor graph, one symbol character per variable type."""

from __future__ import annotations

import gtsam

from mapfuse_core.features import FeatureKind

__all__ = ["anchor_key", "known_key", "landmark_key", "pose_key", "radius_key"]


def pose_key(k: int) -> int:
    """Key of the vehicle pose at step ``k``."""
    return int(gtsam.symbol("x", k))


def landmark_key(i: int, kind: FeatureKind) -> int:
    """Key of landmark ``i`` (dense index, in ``Wglobal``): ``l`` lines, ``c`` circles.

    Separate symbols per kind let iSAM2 take a relinearisation threshold per
    variable type (its threshold map is keyed by symbol character and dimension).
    """
    return int(gtsam.symbol("l" if kind == FeatureKind.LINE else "c", i))


def radius_key(i: int) -> int:
    """Key of circle landmark ``i``'s radius with :attr:`GraphOptions.split_circles`
    (its centre keeps :func:`landmark_key`)."""
    return int(gtsam.symbol("r", i))


def known_key(j: int, kind: FeatureKind) -> int:
    """Key of known feature ``j`` (row of the known map, ``Wknown``): ``k`` lines, ``q`` circles."""
    return int(gtsam.symbol("k" if kind == FeatureKind.LINE else "q", j))


def anchor_key() -> int:
    """Key of the anchor ``A = x^Wglobal_Wknown``."""
    return int(gtsam.symbol("a", 0))
