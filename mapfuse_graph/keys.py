"""GTSAM keys of the mapfuse factor graph: one symbol character per variable type.

The ``*_key`` functions make the keys; :func:`key_map` names every variable of a
``Values``, e.g. ``"x12"`` → ``"vehicle pose x^Wglobal_R of step 12 (Pose2)"``, so a
user of :attr:`mapfuse_graph.results.GraphDetails.graph` knows what the keys of its
factors are.
"""

from __future__ import annotations

import gtsam

from mapfuse_core.geometry.features import FeatureKind

__all__ = [
    "KEY_KINDS",
    "anchor_key",
    "describe_key",
    "key_map",
    "known_key",
    "landmark_key",
    "pose_key",
    "radius_key",
    "symbol_name",
]


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


#: What the variables of each symbol character are (``{i}``: the symbol's index).
KEY_KINDS: dict[str, str] = {
    "x": "vehicle pose x^Wglobal_R of step {i} (Pose2)",
    "l": "line landmark {i} in Wglobal, (ρ, α) (Vector2)",
    "c": "circle landmark {i} in Wglobal, (x, y, r) (Vector3; its centre (x, y) alone "
    "with split circles)",
    "r": "radius of circle landmark {i} with split circles (Vector1)",
    "k": "known line {i} (row of the known map) in Wknown, (ρ, α) (Vector2)",
    "q": "known circle {i} (row of the known map) in Wknown, (x, y, r) (Vector3)",
    "a": "anchor A = x^Wglobal_Wknown, the known map's frame in Wglobal (Pose2)",
}


def symbol_name(key: int) -> str:
    """``"x12"`` for the key ``gtsam.symbol("x", 12)``."""
    s = gtsam.Symbol(int(key))
    return f"{chr(s.chr())}{s.index()}"


def describe_key(key: int) -> str:
    """What the variable of ``key`` is; :class:`ValueError` for a key mapfuse never makes."""
    s = gtsam.Symbol(int(key))
    ch = chr(s.chr())
    if ch not in KEY_KINDS:
        raise ValueError(f"key {symbol_name(key)} is not a mapfuse graph variable")
    return KEY_KINDS[ch].format(i=s.index())


def key_map(values: gtsam.Values) -> dict[str, str]:
    """``{symbol name: what it is}`` for every variable of ``values``, poses first."""
    # Bound to a name first: gtsam's key containers must outlive their iteration.
    held = values.keys()  # a gtsam.Values is not iterable itself
    keys = sorted((int(k) for k in held), key=lambda k: (symbol_name(k)[0] != "x", k))
    return {symbol_name(k): describe_key(k) for k in keys}
