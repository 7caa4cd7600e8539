"""Map-to-map pairings at a join: the ambiguity rule (``AssociationConfig.map_ambiguity``:
a map feature compatible with two walls that cannot be one wall is not paired) and the
joint search (``AssociationConfig.map_method``: a local map's features pair as a
jointly compatible set).

Constructed joins: a global map with walls, and a local feature (a query element)
whose uncertainty relative to them makes it compatible with more than one.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ekf_reference.association import Query, choose, predict_all_targets, targets_distinct
from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from ekf_reference.result import EKFDetails
from ekf_reference.state import Element, ElementKind, GaussianMap, Role, bind_line_cov
from mapfuse_core.geometry.features import FeatureKind, canonical_line
from mapfuse_core.matching import AssociationConfig, ScoredPair, drop_ambiguous
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

REFUSE = AssociationConfig(map_ambiguity="refuse")
NEAREST = AssociationConfig(map_ambiguity="nearest")


def _line(y: float, theta: float = 0.0, x: float = 0.0) -> np.ndarray:
    """A wall through ``(x, y)`` with direction ``theta``."""
    return np.array([x, y, theta])


def _cov(lat: float, ang: float, line: np.ndarray) -> np.ndarray:
    """A bound line covariance: ``lat`` (m) across the line, ``ang`` (rad)."""
    c, s = math.cos(line[2]), math.sin(line[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return bind_line_cov(line, R @ np.diag([0.0, lat**2, ang**2]) @ R.T)


def _join(
    walls: list[tuple[np.ndarray, float]], local: np.ndarray, local_sigma: float
) -> tuple[GaussianMap, int]:
    """Global walls ``(line, lateral σ)`` (not in the local map) and one local feature
    (``in_local``) at ``local`` with lateral σ ``local_sigma``; returns the map and
    the local feature's index."""
    m = GaussianMap()
    for k, (line, sig) in enumerate(walls):
        m.add(
            Element(ElementKind.LINE, Role.FEATURE, moving=False, track=k, extent=(-3.0, 3.0)),
            line,
            _cov(sig, 0.01, line),
        )
    i = m.add(
        Element(
            ElementKind.LINE,
            Role.FEATURE,
            moving=False,
            track=len(walls),
            extent=(-2.0, 2.0),
            in_local=True,
        ),
        local,
        _cov(local_sigma, 0.01, local),
    )
    return m, i


def _pair(m: GaussianMap, i: int, config: AssociationConfig) -> int | None:
    """The global wall local feature ``i`` is paired with, ``None`` for none."""
    e = m.elements[i]
    q = Query(e.kind, m.mean[i], np.zeros((3, 3)), e.extent, element=i)
    targets = predict_all_targets(m, lambda el: not el.in_local)
    (c,) = choose(m, [q], targets, config)
    return None if c is None else c.target


def test_a_feature_between_two_parallel_walls_a_corridor_apart_is_not_merged() -> None:
    # Walls at y = 0 and y = 1.2 m (a corridor), each known to 5 cm; the local feature
    # at y = 0.5 m with a lateral σ of 0.4 m (the drift since the walls were mapped)
    # is compatible with both: which one it is cannot be told.
    m, i = _join([(_line(0.0), 0.05), (_line(1.2), 0.05)], _line(0.5), 0.4)
    assert targets_distinct(m, 0, 1, REFUSE.gate_prob)
    assert _pair(m, i, NEAREST) == 0
    assert _pair(m, i, REFUSE) is None
    # Once its drift is small, only the right wall is in the gate: it is merged.
    m, i = _join([(_line(0.0), 0.05), (_line(1.2), 0.05)], _line(0.05), 0.05)
    assert _pair(m, i, REFUSE) == 0


def test_two_landmarks_of_one_wall_are_not_an_ambiguity() -> None:
    # Two global landmarks of one wall (compatible with each other, a duplicate the
    # association made earlier): the local feature goes to the nearer.
    m, i = _join([(_line(0.0), 0.05), (_line(0.03), 0.05)], _line(0.2), 0.3)
    assert not targets_distinct(m, 0, 1, REFUSE.gate_prob)
    assert _pair(m, i, REFUSE) == 1
    # Collinear walls a doorway apart are one line to a line landmark: not ambiguous.
    m, i = _join([(_line(0.0), 0.05), (_line(0.0, x=7.0), 0.05)], _line(0.2, x=3.5), 0.3)
    assert not targets_distinct(m, 0, 1, REFUSE.gate_prob)
    assert _pair(m, i, REFUSE) is not None


def test_a_feature_between_a_wall_and_the_next_one_beyond_a_turn_is_not_merged() -> None:
    # A wall along y = 0 and, beyond a 10° turn at its end, the next wall: a local
    # feature midway in angle, drifted by 0.3 m and 0.1 rad (σ), fits both, and they
    # are not one wall.
    a = _line(0.0)
    b = _line(0.0, math.radians(10.0), x=4.0)
    m, i = _join([(a, 0.05), (b, 0.05)], _line(0.0, math.radians(5.0), x=2.0), 0.3)
    m.cov[3 * i + 2, 3 * i + 2] = 0.1**2
    assert targets_distinct(m, 0, 1, REFUSE.gate_prob)
    assert _pair(m, i, NEAREST) is not None
    assert _pair(m, i, REFUSE) is None


def test_measurements_always_take_the_nearest() -> None:
    # The same corridor, seen by a measurement: it is paired, with the nearest wall.
    m, _ = _join([(_line(0.0), 0.05), (_line(1.2), 0.05)], _line(0.5), 0.4)
    z = _line(0.5)
    q = Query(ElementKind.LINE, z, _cov(0.4, 0.01, z), (-1.0, 1.0))
    targets = predict_all_targets(m, lambda el: not el.in_local)
    (c,) = choose(m, [q], targets, REFUSE)
    assert c is not None
    assert c.target == 0


def test_two_known_walls_are_compared_in_the_known_frame() -> None:
    # An anchor far from the identity: two known walls 1.2 m apart are distinct, and
    # one known wall against itself shifted by 1 cm is not.
    m = GaussianMap()
    m.add(
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
        np.array([30.0, -12.0, 2.0]),
        np.diag([0.3**2, 0.3**2, 0.05**2]),
    )
    for k, y in enumerate((0.0, 1.2, 0.01)):
        w = _line(y)
        m.add(Element(ElementKind.LINE, Role.KNOWN, moving=False, track=k), w, _cov(0.02, 0.002, w))
    assert targets_distinct(m, 1, 2, 0.999)
    assert not targets_distinct(m, 1, 3, 0.999)


def test_drop_ambiguous_keeps_queries_whose_candidates_name_one_feature() -> None:
    cands = [
        [ScoredPair(0, 1.0), ScoredPair(1, 2.0)],
        [ScoredPair(2, 0.5), ScoredPair(3, 4.0)],
        [ScoredPair(4, 0.1)],
        [],
    ]
    # 0 and 1 are two walls, 2 and 3 one wall seen twice.
    out = drop_ambiguous(cands, lambda a, b: {a, b} == {0, 1})
    assert out == [[], cands[1], cands[2], []]


def test_an_unknown_ambiguity_rule_is_refused() -> None:
    with pytest.raises(ValueError, match="map_ambiguity"):
        dataclasses.replace(REFUSE, map_ambiguity="guess")  # type: ignore[arg-type]


def _drifted_local_map(drift: float, common_sigma: float) -> tuple[GaussianMap, list[int]]:
    """Global walls along y = 0, 1 and 3 m (lateral σ 2 cm) and a local map that saw the
    walls at y = 0 and 3 m with a common lateral drift ``drift`` (m): two local features,
    each known to 3 cm relative to the other, both to ``common_sigma`` relative to the
    global map (the local map's pose in it)."""
    m = GaussianMap()
    for k, y in enumerate((0.0, 1.0, 3.0)):
        w = _line(y)
        m.add(
            Element(ElementKind.LINE, Role.FEATURE, moving=False, track=k, extent=(-3.0, 3.0)),
            w,
            _cov(0.02, 0.002, w),
        )
    local = []
    for k, y in enumerate((0.0, 3.0)):
        w = _line(y + drift)
        local.append(
            m.add(
                Element(
                    ElementKind.LINE,
                    Role.FEATURE,
                    moving=False,
                    track=10 + k,
                    extent=(-2.0, 2.0),
                    in_local=True,
                ),
                w,
                _cov(0.03, 0.002, w),
            )
        )
    ya, yb = (3 * i + 1 for i in local)
    for a in (ya, yb):
        for b in (ya, yb):
            m.cov[a, b] += common_sigma**2
    return m, local


def _pair_all(m: GaussianMap, local: list[int], config: AssociationConfig) -> list[int | None]:
    queries = [
        Query(m.elements[i].kind, m.mean[i], np.zeros((3, 3)), m.elements[i].extent, element=i)
        for i in local
    ]
    targets = predict_all_targets(m, lambda el: not el.in_local)
    return [None if c is None else c.target for c in choose(m, queries, targets, config)]


def test_a_join_pairs_the_local_features_as_a_jointly_compatible_set() -> None:
    # The local map drifted 0.6 m: its wall at y = 0.6 m is nearer the global wall at
    # 1 m than the one at 0 m it is, while the other local wall (3.6 m) has only the
    # wall at 3 m in its gate.  Alone, each fits its nearest; together, both must
    # share one drift, which only (0 m, 3 m) does.
    m, local = _drifted_local_map(0.6, 0.4)
    jcbb = AssociationConfig(map_method="jcbb", map_ambiguity="nearest")
    nn = AssociationConfig(map_method="nn", map_ambiguity="nearest")
    assert _pair_all(m, local, nn) == [1, 2]
    assert _pair_all(m, local, jcbb) == [0, 2]
    # Refusing ambiguous features (the CARMEN profile) leaves the first unpaired (two
    # walls fit it) and pairs the second.
    assert _pair_all(m, local, REFUSE) == [None, 2]
    assert _pair_all(m, local, AssociationConfig(map_method="jcbb", map_ambiguity="refuse")) == [
        None,
        2,
    ]


def test_an_unknown_map_method_is_refused() -> None:
    with pytest.raises(ValueError, match="map_method"):
        dataclasses.replace(REFUSE, map_method="guess")  # type: ignore[arg-type]


# --------------------------------------------------------------------- measurements


def _measure(walls: list[float], z: float, config: AssociationConfig) -> int | None:
    """A measured segment at ``y = z`` (lateral σ 2 cm) against walls along x at the
    given ``y``, in the vehicle frame: each known to 5 cm relative to the others and all
    together 0.4 m across (a drifted pose); returns the wall it is paired with, ``None``
    for none."""
    m = GaussianMap()
    for k, y in enumerate(walls):
        m.add(
            Element(ElementKind.LINE, Role.FEATURE, moving=True, track=k, extent=(-3.0, 3.0)),
            _line(y),
            np.zeros((3, 3)),
        )
    n = len(walls)
    lateral = 3 * np.arange(n) + 1
    m.cov[np.ix_(lateral, lateral)] = 0.4**2
    m.cov[lateral, lateral] += 0.05**2
    m.cov[3 * np.arange(n) + 2, 3 * np.arange(n) + 2] = 0.01**2
    q = Query(ElementKind.LINE, _line(z), _cov(0.02, 0.005, _line(z)), (-0.3, 0.3))
    (c,) = choose(m, [q], predict_all_targets(m, lambda el: True), config)
    return None if c is None else c.target


def test_a_measurement_between_two_walls_is_refused_or_takes_the_nearest() -> None:
    """Walls at y = 0 and y = 1.2 m: a segment at y = 0.5 m fits both, which are not
    one wall.  ``ambiguity="refuse"`` leaves it unpaired (a feature of its own);
    ``"nearest"`` takes the wall at 0.5 m."""
    assert _measure([0.0, 1.2], 0.5, AssociationConfig(ambiguity="refuse")) is None
    assert _measure([0.0, 1.2], 0.5, AssociationConfig(ambiguity="nearest")) == 0
    # The map rule does not reach measurements.
    assert _measure([0.0, 1.2], 0.5, REFUSE) == 0


def test_a_measurement_that_fits_one_wall_is_paired_under_refuse() -> None:
    """The second wall out of the gate (at 5 m): nothing to refuse."""
    assert _measure([0.0, 5.0], 0.3, AssociationConfig(ambiguity="refuse")) == 0


def test_unknown_measurement_ambiguity_rule_is_refused() -> None:
    with pytest.raises(ValueError, match="ambiguity must be one of"):
        AssociationConfig(ambiguity="guess")  # type: ignore[arg-type]


def _measure_known(walls: list[float], z: float, config: AssociationConfig) -> int | None:
    """As :func:`_measure`, the walls known-map features seen through an anchor at the
    vehicle frame that is uncertain by 0.4 m across them."""
    m = GaussianMap()
    m.add(
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
        np.zeros(3),
        np.diag([1e-4, 0.4**2, 1e-6]),
    )
    for k, y in enumerate(walls):
        m.add(
            Element(ElementKind.LINE, Role.KNOWN, moving=False, track=k, extent=(-3.0, 3.0)),
            _line(y),
            _cov(0.05, 0.01, _line(y)),
        )
    q = Query(ElementKind.LINE, _line(z), _cov(0.02, 0.005, _line(z)), (-0.3, 0.3))
    (c,) = choose(m, [q], predict_all_targets(m, lambda el: False), config)
    return None if c is None else c.target


def test_refuse_known_refuses_between_known_walls_only() -> None:
    """``ambiguity="refuse_known"``: a segment between two plan walls is refused, one
    between two estimated walls takes the nearest."""
    rk = AssociationConfig(ambiguity="refuse_known")
    assert _measure_known([0.0, 1.2], 0.5, rk) is None
    assert _measure_known([0.0, 1.2], 0.5, AssociationConfig()) == 1
    assert _measure([0.0, 1.2], 0.5, rk) == 0


def test_skip_leaves_an_ambiguous_measurement_unpaired_and_reports_it() -> None:
    """``ambiguity="skip"``: the segment between two walls is unpaired and named in
    ``skipped``; ``"refuse"`` leaves it unpaired too but not skipped (it starts a
    feature); a segment that fits no wall is not skipped either (it is new)."""
    skip = AssociationConfig(ambiguity="skip")
    skipped: list[int] = []
    m = GaussianMap()
    for k, y in enumerate((0.0, 1.2)):
        m.add(
            Element(ElementKind.LINE, Role.FEATURE, moving=True, track=k, extent=(-3.0, 3.0)),
            _line(y),
            np.zeros((3, 3)),
        )
    m.cov[np.ix_([1, 4], [1, 4])] = 0.4**2
    m.cov[[1, 4], [1, 4]] += 0.05**2
    m.cov[[2, 5], [2, 5]] = 0.01**2
    targets = predict_all_targets(m, lambda el: True)
    queries = [
        Query(ElementKind.LINE, _line(z), _cov(0.02, 0.005, _line(z)), (-0.3, 0.3))
        for z in (0.5, 6.0)
    ]
    chosen = choose(m, queries, targets, skip, skipped)
    assert chosen == [None, None]
    assert skipped == [0]
    refused: list[int] = []
    chosen = choose(m, queries, targets, AssociationConfig(ambiguity="refuse"), refused)
    assert chosen[0] is None
    assert refused == []


def _corridor_log() -> MeasurementLog:
    """Two steps: the walls of a corridor 1.2 m wide (y = 0 and 1.2 m, each 6 m long),
    then a move of unknown sideways offset (σ 0.4 m) and a short segment at y = 0.5 m,
    which fits both walls."""
    walls = [canonical_line(_line(0.0)), canonical_line(_line(1.2))]
    seen = [*walls, canonical_line(_line(0.5))]
    covs = [_line_cov(w) for w in seen]
    return MeasurementLog(
        scenario="corridor",
        seed=0,
        timestamps=np.array([0.0, 0.1]),
        odometry=np.zeros((2, 3)),
        odometry_cov=np.array([np.zeros((3, 3)), np.diag([1e-4, 0.4**2, 1e-6])]),
        feat_step=np.array([0, 0, 1], dtype=np.int64),
        feat_kind=np.full(3, int(FeatureKind.LINE), dtype=np.int8),
        feat_params=np.array(seen),
        feat_cov=np.array(covs),
        feat_true_id=np.array([0, 1, 0], dtype=np.int64),
        feat_n_points=np.full(3, 20, dtype=np.int64),
        feat_extent=np.array([[-3.0, 3.0], [-3.0, 3.0], [-0.3, 0.3]]),
        known_map=KnownMapArrays(
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=np.int8),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros((0, 2)),
        ),
    )


def _line_cov(line: np.ndarray) -> np.ndarray:
    """A measured line's covariance: 2 cm across, 5 mrad in angle, 2 m along."""
    c, s = math.cos(line[2]), math.sin(line[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ np.diag([4.0, 0.02**2, 0.005**2]) @ R.T


@pytest.mark.parametrize(
    ("rule", "paired", "new_feature", "skipped"),
    [("nearest", True, False, 0), ("refuse", False, True, 0), ("skip", False, False, 1)],
)
def test_the_ekf_skips_an_ambiguous_measurement_without_starting_a_feature(
    rule: str, paired: bool, new_feature: bool, skipped: int
) -> None:
    """Through the EKF: ``"nearest"`` pairs the segment with a wall, ``"refuse"`` makes
    it a third feature, ``"skip"`` leaves it out (track −1) and counts it."""
    config = EKFConfig(data_association=AssociationConfig(ambiguity=rule))  # type: ignore[arg-type]
    res = run_ekf(_corridor_log(), config, fusion=False)
    details = res.details
    assert isinstance(details, EKFDetails)
    track = details.obs_local_track
    assert track is not None
    assert track[0] != track[1]
    assert (track[2] in (track[0], track[1])) == paired
    assert (track[2] >= 0 and track[2] not in (track[0], track[1])) == new_feature
    assert (track[2] == -1) == (skipped == 1)
    assert details.ambiguous_skipped == skipped
