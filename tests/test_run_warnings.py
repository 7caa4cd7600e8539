"""What a run's numbers alone do not say: ``metrics.json``'s ``matching`` block and
``warnings`` list, the one meaning of ``matched_known``, and options that do not
apply being errors (``docs/warnings.md``)."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from mapfuse.cli import main
from mapfuse.comparison import compare
from mapfuse.metrics import run_metrics
from mapfuse.runner import Run, prepare_log, run
from mapfuse_core.estimate import MatchAttempts, PoseTrack
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog, save_log
from tests.synthetic import synthetic_log, with_known

STEPS = 60  # the synthetic vehicle drives the whole ring in any number of steps


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(STEPS, 0)


@pytest.fixture(scope="module")
def ekf_run(log: MeasurementLog) -> Run:
    return run(log, "ekf")


def _with_far_known_circle(log: MeasurementLog) -> MeasurementLog:
    """``log`` whose known map also holds a tree 500 m away, which nothing observes."""
    k = log.known_map
    assert k.extents is not None
    known = KnownMapArrays(
        ids=np.append(k.ids, 999),
        kinds=np.append(k.kinds, np.int8(FeatureKind.CIRCLE)),
        params=np.vstack([k.params, [500.0, 500.0, 0.5]]),
        covs=np.vstack([k.covs, 0.01 * np.eye(3)[None]]),
        extents=np.vstack([k.extents, [np.nan, np.nan]]),
    )
    return dataclasses.replace(log, known_map=known)


def _distinct_known(r: Run) -> int:
    assert r.result.decisions is not None
    kn = np.asarray(r.result.decisions.obs_known_id)
    return int(np.unique(kn[kn >= 0]).size)


def test_a_clean_fused_run_has_no_warning_and_reports_its_match(ekf_run: Run) -> None:
    m = ekf_run.metrics
    assert m.warnings == ()
    match = m.matching
    assert (match.requested, match.achieved, match.ccda_by) == (True, True, "ekf")
    assert match.ccda_reasons["accepted"] == 1
    assert sum(match.ccda_reasons.values()) == match.ccda_attempts
    assert match.search_limit == 0


def test_matched_known_counts_known_features_paired_with_observations_in_both(
    log: MeasurementLog,
) -> None:
    # The EKF inserts every known feature when it fuses, the far tree too; the graph
    # only ties landmarks.  Both count the known features observations are paired with.
    far = _with_far_known_circle(log)
    ekf = run(far, "ekf")
    batch = run(far, "batch", upstream=ekf.result)
    own = run(far, "isam2", association="own")
    assert ekf.result.anchor is not None
    assert own.result.anchor is not None
    ekf_map = ekf.result.map
    assert 999 in ekf_map.known_ids.tolist()  # carried, never observed
    assert int(ekf_map.n_obs[ekf_map.known_ids == 999][0]) == 0
    for r in (ekf, batch, own):
        assert r.metrics.map.matched_known == _distinct_known(r), r.estimator
        assert r.metrics.map.matched_known < len(far.known_map)
    # Same decisions, same count.
    assert ekf.metrics.map.matched_known == batch.metrics.map.matched_known
    # The EKF's known features count the observations paired with them.
    assert ekf.result.decisions is not None
    kn = np.asarray(ekf.result.decisions.obs_known_id)
    for kid, n in zip(ekf_map.known_ids.tolist(), ekf_map.n_obs.tolist(), strict=True):
        if kid >= 0:
            assert n == int(np.sum(kn == kid))


def test_fusion_without_a_match_is_reported_as_such(log: MeasurementLog) -> None:
    two = with_known(log, [0, 1])  # two known features: CCDA can never accept
    for r in (run(two, "ekf"), run(two, "isam2", association="own")):
        m = r.metrics
        assert m.fusion is True
        assert m.anchor is None
        match = m.matching
        assert (match.requested, match.achieved) == (True, False)
        assert match.ccda_attempts >= 1
        assert sum(match.ccda_reasons.values()) == match.ccda_attempts
        assert "accepted" not in match.ccda_reasons
        (w,) = [w for w in m.warnings if w.startswith("fusion requested, no match found")]
        assert f"{match.ccda_attempts} CCDA attempts" in w
    # Without fusion nothing is requested and nothing is said.
    m = run(two, "ekf", fusion=False).metrics
    assert m.matching.requested is False
    assert m.warnings == ()


def test_a_graph_consuming_the_ekf_reports_the_ekf_matchings(
    log: MeasurementLog, ekf_run: Run
) -> None:
    m = run(log, "batch", upstream=ekf_run.result).metrics
    assert m.matching.ccda_by == "ekf"
    assert m.matching.ccda_reasons == ekf_run.metrics.matching.ccda_reasons


def test_search_limit_outcomes_are_counted_and_named(log: MeasurementLog, ekf_run: Run) -> None:
    failed = dataclasses.replace(
        ekf_run.result,
        anchor=None,
        matching=MatchAttempts(3, {"search_limit": 2, "ambiguous": 1}),
    )
    m = run_metrics(failed, log)
    assert m.matching.search_limit == 2
    assert m.matching.ccda_reasons == {"ambiguous": 1, "search_limit": 2}
    (w,) = [w for w in m.warnings if w.startswith("fusion requested")]
    assert "search_limit 2, ambiguous 1" in w


def test_known_lines_without_extents_warn_that_the_anchor_degrades(log: MeasurementLog) -> None:
    bare = dataclasses.replace(log, known_map=dataclasses.replace(log.known_map, extents=None))
    n_lines = int(np.sum(log.known_map.kinds == FeatureKind.LINE))
    assert n_lines > 0
    fused = run(bare, "ekf").metrics.warnings
    (w,) = [w for w in fused if w.startswith("known map without extents")]
    assert f"for {n_lines} of its {n_lines} lines" in w
    assert "anchor accuracy can degrade" in w
    # Nothing to degrade without fusion.
    assert run(bare, "ekf", fusion=False).metrics.warnings == ()


def test_an_overconfident_run_is_reported_inconsistent(log: MeasurementLog) -> None:
    # The odometry claims a tenth of its real σ: the filter is overconfident.
    tight = dataclasses.replace(log, odometry_cov=0.01 * np.asarray(log.odometry_cov))
    m = run(tight, "ekf", fusion=False).metrics
    assert m.nees.mean > 6.0
    (w,) = [w for w in m.warnings if w.startswith("estimator inconsistent on this run")]
    assert f"mean {m.nees.mean:.2f}" in w
    assert run(log, "ekf", fusion=False).metrics.warnings == ()


def test_non_finite_covariances_are_counted(log: MeasurementLog, ekf_run: Run) -> None:
    track = ekf_run.result.filtered
    assert track is not None
    covs = np.array(track.covs, copy=True)
    covs[10:13] = np.nan
    bad = dataclasses.replace(ekf_run.result, filtered=PoseTrack(track.poses, covs))
    m = run_metrics(bad, log)
    # Step 0's zero covariance is Wglobal's origin, not a fault: only the three count.
    assert f"vehicle NEES not finite on 3 of {STEPS} steps" in m.warnings[0]


def test_options_that_do_not_apply_are_errors_in_the_library(
    log: MeasurementLog, tmp_path: Path
) -> None:
    with pytest.raises(ValueError, match="the ekf estimator has no option robust"):
        run(log, "ekf", robust="huber")
    with pytest.raises(ValueError, match="the ekf estimator has no option association"):
        run(log, "ekf", association="own")
    with pytest.raises(ValueError, match="no option robust"):
        compare(log, ["ekf"], fusions=(True,), overrides={"ekf": {"robust": "huber"}})
    path = save_log(log, tmp_path / "log.npz")
    with pytest.raises(ValueError, match="seed does not apply to a saved log"):
        prepare_log(str(path), seed=3)
    with pytest.raises(ValueError, match="seed does not apply to the real dataset"):
        prepare_log("carpark", seed=3, data_dir=str(tmp_path))
    with pytest.raises(ValueError, match="a data directory applies to"):
        prepare_log(str(path), data_dir=str(tmp_path))


def test_library_finds_a_dataset_where_the_command_line_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # ``$MAPFUSE_DATA`` is read by the library too: the loader looks in it (and finds
    # no data there), and ``data`` wins over it.
    from mapfuse_core.data.datasets import DatasetError

    monkeypatch.setenv("MAPFUSE_DATA", str(tmp_path))
    missing = re.escape(f"{tmp_path}/acfr_carpark/data_set.mat: no such file")
    with pytest.raises(DatasetError, match=missing):
        prepare_log("carpark")
    with pytest.raises(ValueError, match=r"^data /no/such/dir is not a directory$"):
        prepare_log("carpark", data_dir="/no/such/dir")
    with pytest.raises(ValueError, match=r"^data is empty: give the data directory"):
        prepare_log("carpark", data_dir="")
    monkeypatch.setenv("MAPFUSE_DATA", str(tmp_path / "gone"))
    with pytest.raises(ValueError, match=r"^\$MAPFUSE_DATA .*gone is not a directory$"):
        prepare_log("victoria-park")
    monkeypatch.delenv("MAPFUSE_DATA")
    with pytest.raises(ValueError, match=r"needs a data directory \(data=DIR or \$MAPFUSE_DATA\)"):
        prepare_log("carpark")


def test_cli_prints_each_warning_once_on_stderr_and_keeps_stdout_json(
    log: MeasurementLog, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = save_log(with_known(log, [0, 1]), tmp_path / "two.npz")
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    cap = capsys.readouterr()
    printed = json.loads(cap.out)
    warnings = printed["metrics"]["warnings"]
    assert warnings
    assert warnings == json.loads((out / "metrics.json").read_text())["warnings"]
    lines = [ln for ln in cap.err.splitlines() if ln.startswith("mapfuse: warning: ")]
    assert lines == [f"mapfuse: warning: {w}" for w in warnings]
    # compare labels each run's warnings.
    cmp_out = tmp_path / "cmp"
    argv = ["compare", str(path), "--estimators", "ekf", "--fusion", "on", "--out", str(cmp_out)]
    assert main([*argv, "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "mapfuse: warning: ekf with fusion: fusion requested, no match found" in err
    report = (cmp_out / "report.md").read_text()
    assert "- ekf with fusion: fusion requested, no match found" in report


def test_a_grid_of_identical_trees_reports_the_ambiguous_matchings() -> None:
    # 7 × 7 trees 8 m apart: every overlap fits many shifts, CCDA refuses them all.
    xs = np.arange(-24.0, 25.0, 8.0)
    trees = np.array([[x, y, 0.3] for x in xs for y in xs])
    n = len(trees)
    world = KnownMapArrays(
        np.arange(100, 100 + n), np.ones(n, np.int8), trees, np.zeros((n, 3, 3)), None
    )
    m = run(synthetic_log(60, 0, world=world, radius=16.0), "ekf").metrics
    assert m.anchor is None
    reasons = m.matching.ccda_reasons
    assert reasons.get("ambiguous", 0) >= 1
    assert "accepted" not in reasons
    assert any(w.startswith("fusion requested, no match found") for w in m.warnings)


def test_batch_with_its_own_association_reports_its_matchings(log: MeasurementLog) -> None:
    # Batch decides its own associations in an iSAM2 pass first: its CCDA calls count.
    r = run(log, "batch", association="own")
    m = r.metrics
    # It consumed no other run: the EKF's known-map gate is not reported as its own.
    assert r.result.upstream is None
    assert m.known_map_rejections is None
    assert m.matching.ccda_by == "batch"
    assert m.matching.ccda_attempts >= 1
    assert m.matching.achieved is (m.anchor is not None)
    assert sum(m.matching.ccda_reasons.values()) == m.matching.ccda_attempts
