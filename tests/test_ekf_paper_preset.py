"""``EKFConfig.paper()``: the paper's method as a preset, and where the default differs."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from scipy.stats import chi2

from ekf_reference import EKFConfig, run_ekf
from ekf_reference.config import PAPER_FIELDS
from mapfuse_core.evaluation import anchor_truth, nees_series, pose_errors, truth_in_global
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario
from tests.scripts import load_benchmark


def _leaves(obj: object, prefix: str = "") -> dict[str, object]:
    """Every setting of a nested frozen dataclass: dotted name → value."""
    out: dict[str, object] = {}
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            out.update(_leaves(v, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = v
    return out


def _at(obj: object, path: str) -> object:
    """The setting at dotted ``path`` of ``obj`` (a whole settings object, or None)."""
    for name in path.split("."):
        obj = getattr(obj, name)
    return obj


def _covering(leaf: str) -> list[str]:
    """The names in PAPER_FIELDS that classify ``leaf``: itself or a settings object
    holding it."""
    return [k for k in PAPER_FIELDS if leaf == k or leaf.startswith(k + ".")]


def test_every_setting_is_classified_once() -> None:
    """A new setting fails here until PAPER_FIELDS says whether it is the paper's, a
    choice or an extension (and so whether paper() must switch it)."""
    leaves = _leaves(EKFConfig())
    assert [leaf for leaf in leaves if len(_covering(leaf)) != 1] == []
    used = {k for leaf in leaves for k in _covering(leaf)}
    assert used == set(PAPER_FIELDS), "names in PAPER_FIELDS that are no setting"


def test_default_differs_from_paper_exactly_in_the_extensions() -> None:
    default, paper = EKFConfig(), EKFConfig.paper()
    # Compared at the classified names: a settings object the paper turns off is None.
    differ = {k for k in PAPER_FIELDS if _at(default, k) != _at(paper, k)}
    assert differ == set(EKFConfig.extensions())
    assert set(EKFConfig.extensions()) == {
        k for k, f in PAPER_FIELDS.items() if f.role == "extension"
    }


def test_paper_values() -> None:
    p = EKFConfig.paper()
    a = p.data_association
    # The paper's values (docs/method.md §4–5): extensions off.
    assert p.known_map_gating is False
    assert (a.match_joint_test, a.match_pairing_test, a.match_exclusions) == (False, False, 0)
    assert a.min_obs_for_matching == 1
    assert a.ccda.min_pairings == 4  # "more than three"
    assert a.ccda.redundant_pairings is False
    assert a.ccda.ambiguity_margin == 0
    assert (p.tentative_min_sightings, p.min_obs_to_join, p.carry_seen_steps) == (1, 1, 0)
    assert p.loop_closure is None
    assert p.join_circle_sigma_m == 0.0
    assert p.anchor_watch is None
    # The paper's three forms (eqs. 12–16, 14 and 17–24, 5 and 20).
    assert p.anchor_entry == "ccda_estimate"
    assert p.known_map_in_local_maps == "copied"
    assert p.line_tie_residual_at == "target"
    d0 = EKFConfig()
    assert (d0.anchor_entry, d0.known_map_in_local_maps, d0.line_tie_residual_at) == (
        "pairings",
        "shared",
        "observed",
    )
    # Choices stay the default.
    d = EKFConfig()
    assert (p.local_map_steps, a.gate_prob, a.method) == (
        d.local_map_steps,
        d.data_association.gate_prob,
        d.data_association.method,
    )
    assert p == EKFConfig.paper()


def test_docstring_names_every_choice_and_extension() -> None:
    doc = EKFConfig.paper.__doc__ or ""
    missing = [
        k
        for k, f in PAPER_FIELDS.items()
        if f.role != "paper" and f"{k.rsplit('.')[-1]}``" not in doc
    ]
    assert missing == []
    assert doc.count("*(choice)*") >= 10


def test_every_note_is_one_line() -> None:
    assert all(f.why and "\n" not in f.why for f in PAPER_FIELDS.values())


@functools.cache
def _loop600_start() -> MeasurementLog:
    """loop600, seed 0, its first 300 steps (the first match is at the first join)."""
    sc = dataclasses.replace(load_scenario("loop600"), steps=300)
    return simulate(sc, seed=0, workers=1).log


def _anchor_nees(x: np.ndarray, cov: np.ndarray, log: MeasurementLog) -> float:
    """NEES of an estimate ``x`` (covariance ``cov``) of ``x^Wknown_Wglobal``."""
    assert log.true_poses is not None
    d = pose_errors(x[None], anchor_truth(log.true_poses)[None])
    return float(nees_series(d.dx, cov[None])[0])


def test_paper_preset_runs_and_fuses_on_loop600() -> None:
    log = _loop600_start()
    res = run_ekf(log, EKFConfig.paper())
    assert res.decisions is not None
    assert res.decisions.known_gating is None
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 39  # the first join: 9 pairings, all right
    assert len(res.anchor.pairings) >= 4
    assert all(t == k for t, k in res.anchor.pairings)
    # Consistent anchor: its NEES below χ²₃(0.999).
    assert _anchor_nees(res.anchor.x_Wknown_Wglobal, res.anchor.cov, log) < chi2.ppf(0.999, 3)
    assert log.true_poses is not None
    d = pose_errors(res.poses, truth_in_global(log.true_poses)).dx
    # The paper's figure: the fused position error stays under 0.15 m.
    assert float(np.hypot(d[:, 0], d[:, 1]).max()) < 0.15
    known = res.decisions.obs_known_id
    fused = (known >= 0) & (log.feat_true_id >= 0)
    assert fused.sum() > 0
    assert np.array_equal(known[fused], log.feat_true_id[fused])


def test_without_fusion_the_preset_is_the_default_filter_but_for_ties_and_linearisation() -> None:
    """Every extension but ``line_tie_residual_at`` and ``odometry_linearisation`` acts
    on the fusion only: without it the two filters are one when they measure the join's
    line ties alike (eq. 5) and linearise the odometry alike, and differ when they do
    not."""
    log = _loop600_start()
    paper = run_ekf(log, EKFConfig.paper(), fusion=False)
    assert not np.array_equal(paper.poses, run_ekf(log, EKFConfig(), fusion=False).poses)
    for changed in ({"line_tie_residual_at": "observed"}, {"odometry_linearisation": "iterated"}):
        one = run_ekf(log, dataclasses.replace(EKFConfig.paper(), **changed), fusion=False)
        assert not np.array_equal(one.poses, run_ekf(log, EKFConfig(), fusion=False).poses)
    paper = run_ekf(
        log,
        dataclasses.replace(
            EKFConfig.paper(), line_tie_residual_at="observed", odometry_linearisation="iterated"
        ),
        fusion=False,
    )
    default = run_ekf(log, EKFConfig(), fusion=False)
    np.testing.assert_array_equal(paper.poses, default.poses)
    np.testing.assert_array_equal(paper.covs, default.covs)
    assert paper.decisions is not None
    assert default.decisions is not None
    np.testing.assert_array_equal(paper.decisions.obs_landmark, default.decisions.obs_landmark)


@pytest.mark.parametrize("config", ["paper", "default"])
def test_a_match_of_four_pairings(config: str) -> None:
    """A generated world whose first 120 steps see four known features twice: the
    paper's "more than three" accepts them, the default's 8 pairings does not."""
    params = WorldParams(
        seed=2, shape="figure8", laser_range_m=40.0, walls=22, trees=50, loop_length_m=400.0
    )
    sc = dataclasses.replace(generate_scenario(params, base=load_scenario("loop600")), steps=120)
    log = simulate(sc, seed=2, workers=1).log
    res = run_ekf(log, EKFConfig.paper() if config == "paper" else EKFConfig())
    if config == "default":
        assert res.anchor is None
        return
    assert res.anchor is not None
    assert len(res.anchor.pairings) == 4
    assert all(t == k for t, k in res.anchor.pairings)
    assert _anchor_nees(res.anchor.x_Wknown_Wglobal, res.anchor.cov, log) < chi2.ppf(0.999, 3)


def test_benchmark_ablations_cover_the_extensions_one_group_each() -> None:
    """``benchmarks/ekf_paper_vs_default.py --ablation``: each of its configurations is
    the default with exactly its group of extensions at the paper's values."""
    bench = load_benchmark("ekf_paper_vs_default")
    bench._check_ablations()
    default, paper = EKFConfig(), EKFConfig.paper()
    for name, paths in bench.ABLATIONS.items():
        cfg = bench.config_of(f"default-no-{name}")
        assert {k for k in PAPER_FIELDS if _at(cfg, k) != _at(default, k)} == set(paths)
        assert all(_at(cfg, p) == _at(paper, p) for p in paths)
