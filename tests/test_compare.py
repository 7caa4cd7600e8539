"""Backend comparison: every backend × fusion on one log, its report and its figures."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mapfuse.comparison import (
    FIGURE_FILES,
    Comparison,
    compare,
    report_markdown,
    write_comparison,
)
from mapfuse.figures import (
    ccda_figure,
    fig6_errors_bounds,
    fig7_error_fusion,
    fig10_maps,
    nees_figure,
    run_label,
    timing_figure,
)
from mapfuse.runner import run
from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.matching.ccda import ccda_match
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from tests.synthetic import synthetic_log

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(150, 0)


@pytest.fixture(scope="module")
def progress_calls() -> list[tuple[str, int, int]]:
    return []


@pytest.fixture(scope="module")
def comparison(log: MeasurementLog, progress_calls: list[tuple[str, int, int]]) -> Comparison:
    return compare(log, progress=lambda label, k, n: progress_calls.append((label, k, n)))


@pytest.fixture(scope="module")
def no_truth() -> Comparison:
    # A real-data-like log: same measurements, no true poses nor world.
    log = dataclasses.replace(synthetic_log(100, 1), true_poses=None, world=None)
    return compare(log)


def test_every_backend_with_and_without_fusion(comparison: Comparison) -> None:
    got = [(m.estimator, m.fusion) for m in comparison.metrics]
    assert got == [(b, f) for f in (True, False) for b in ("ekf", "batch", "isam2")]
    for r in comparison.runs:
        assert r.poses.shape == (comparison.log.n_steps, 3)
        assert r.metrics.steps == comparison.log.n_steps
    assert comparison.has_truth
    assert comparison.get("isam2", False).metrics.estimator == "isam2"
    with pytest.raises(KeyError, match="no batch run"):
        dataclasses.replace(comparison, runs=comparison.runs[:1]).get("batch", True)


def test_graph_runs_reuse_the_ekf_decisions_of_their_fusion_setting(
    comparison: Comparison,
) -> None:
    for fusion in (True, False):
        ekf = comparison.get("ekf", fusion).result
        assert ekf.fusion is fusion
        # The EKF itself ran with that setting: it made map matchings only when fusing.
        assert (ekf.matching is not None) is fusion
        for b in ("batch", "isam2"):
            graph = comparison.get(b, fusion)
            # The very object: the EKF was not run a second time.
            assert graph.result.upstream is ekf
            assert graph.metrics.association == "ekf"


def test_progress_is_labelled_per_run(
    comparison: Comparison, progress_calls: list[tuple[str, int, int]]
) -> None:
    # Requesting ``comparison`` makes the calls exist whichever worker runs this test.
    labels = {label for label, _, _ in progress_calls}
    assert labels == {
        f"{b} {w} fusion" for b in ("ekf", "batch", "isam2") for w in ("with", "without")
    }
    for label in labels:
        last = [(k, n) for lab, k, n in progress_calls if lab == label][-1]
        assert last[0] == last[1], f"{label} did not report completion"


def test_subset_of_backends(log: MeasurementLog) -> None:
    c = compare(log, ("isam2",), fusions=(True,))
    assert [(m.estimator, m.fusion) for m in c.metrics] == [("isam2", True)]
    upstream = c.runs[0].result.upstream  # the decisions still came from an EKF run
    assert upstream is not None
    assert upstream.estimator == "ekf"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"estimators": ("ekf", "gtsam")}, "unknown estimator 'gtsam'"),
        ({"estimators": ()}, "estimators must be distinct registered names"),
        ({"estimators": ("ekf", "ekf")}, "estimators must be distinct registered names"),
        ({"fusions": (True, True)}, "fusions must be distinct"),
    ],
)
def test_bad_arguments(log: MeasurementLog, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        compare(log, **kwargs)  # type: ignore[arg-type]


def test_write_comparison(comparison: Comparison, tmp_path: Path) -> None:
    paths = write_comparison(comparison, tmp_path / "out")
    out = tmp_path / "out"
    assert json.loads((out / "comparison.json").read_text()) == json.loads(
        json.dumps([m.to_json() for m in comparison.metrics])
    )
    for name in FIGURE_FILES:
        p = out / name
        if name.startswith("gps_"):
            # Real data only: a simulated log is compared with truth instead.
            assert not p.exists(), name
            continue
        assert p.is_file(), name
        assert p.read_bytes()[:8] == PNG
        assert paths[name.removesuffix(".png")] == str(p)
    report = (out / "report.md").read_text()
    assert paths["report"] == str(out / "report.md")
    main, changes = report.split("## Known-map changes")
    table = [
        line for line in main.splitlines() if line.startswith("| ") and not line.startswith("| ---")
    ]
    # Every fused run with an anchor gets a row of change counts (no truth: no P / R).
    change_rows = [line for line in changes.splitlines() if line.startswith("| ")]
    assert change_rows[0].startswith("| run | confirmed | moved | missing")
    assert {r.split(" | ")[0][2:] for r in change_rows[2:]} == {"ekf", "batch", "isam2"}
    # Header, six runs, two iSAM2 filtered rows; no paper rows: not the paper's drive.
    assert len(table) == 1 + 6 + 2
    for col in (
        "position RMSE [m]",
        "heading RMSE [mrad]",
        "NEES mean",
        "anchor error",
        "run time",
    ):
        assert col in table[0]
    for b in ("ekf", "batch", "isam2"):
        for w in ("with", "without"):
            assert any(line.startswith(f"| {b} {w} fusion") for line in table)
    # The paper's numbers are for its own drive only (test_paper_rows_only_for_its_drive).
    assert "paper" not in main.split("Notes:")[0]
    assert "3.8 cm" not in report
    assert "synthetic-ring" in report
    assert "no ground truth" not in report
    ekf = comparison.get("ekf", True).metrics
    assert ekf.position_error is not None
    assert f"{ekf.position_error.rmse:.3f}" in table[1]


@pytest.mark.parametrize(
    ("scenario", "paper", "scale_note"),
    [("loop600", True, False), ("loop600-sparse", True, True), ("synthetic-ring", False, False)],
)
def test_paper_rows_only_for_its_drive(
    comparison: Comparison, scenario: str, paper: bool, scale_note: bool
) -> None:
    named = dataclasses.replace(
        comparison, log=dataclasses.replace(comparison.log, scenario=scenario)
    )
    report = report_markdown(named)
    assert ("*paper: EKF with fusion*" in report) is paper
    assert ("*paper: EKF without fusion*" in report) is paper
    assert ("< 0.15" in report) is paper
    assert ("≈ 0.50" in report) is paper
    # The paper's anchor, 3.8 cm from the truth, in the notes.
    assert ("0.038" in report) is paper
    assert ("3.8 cm" in report) is paper
    assert ("Rows in *italics*" in report) is paper
    assert ("only a scale reference" in report) is scale_note
    # Without truth (real data named like the paper's scenario), no paper rows either.
    blind = dataclasses.replace(named, log=dataclasses.replace(named.log, true_poses=None))
    assert "*paper:" not in report_markdown(blind)
    assert "3.8 cm" not in report_markdown(blind)


def test_log_without_truth_is_stated(no_truth: Comparison, tmp_path: Path) -> None:
    assert not no_truth.has_truth
    paths = write_comparison(no_truth, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "**This log has no ground truth**" in report
    assert "no truth" in report
    assert {k for k in paths if not k.startswith("runs/")} == {
        "comparison",
        "report",
        "fig10_maps",
        "timing",
    }
    assert not (tmp_path / "fig6_errors_bounds.png").exists()
    for m in json.loads((tmp_path / "comparison.json").read_text()):
        assert m["position_error_m"] is None
    with pytest.raises(ValueError, match="no true poses"):
        fig6_errors_bounds(no_truth.get("ekf", True))


def _check_axes(fig: object, n_axes: int) -> None:
    axes = fig.axes  # type: ignore[attr-defined]
    assert len(axes) == n_axes
    for ax in axes:
        assert "[" in ax.get_xlabel(), ax.get_xlabel()  # a unit
        assert "[" in ax.get_ylabel(), ax.get_ylabel()
        assert ax.get_legend() is not None or ax.get_title()


def test_figures_have_labelled_axes_and_titles(comparison: Comparison) -> None:
    runs = comparison.runs
    fig = fig6_errors_bounds(comparison.get("ekf", True))
    assert fig.get_suptitle().startswith("Fig. 6")
    assert [ax.get_ylabel() for ax in fig.axes] == ["x error [m]", "y error [m]", "θ error [rad]"]
    assert fig.axes[0].get_legend() is not None
    fig = fig7_error_fusion(runs)
    _check_axes(fig, 2)
    assert [ax.get_title() for ax in fig.axes] == ["with map fusion", "without map fusion"]
    for ax in fig.axes:
        labels = ax.get_legend_handles_labels()[1]
        assert any(lab.startswith("ekf: RMSE") for lab in labels)
        assert any("isam2" in lab for lab in labels)
        assert any("paper" in lab for lab in labels)
    assert fig.get_suptitle().startswith("Fig. 7")
    fig = nees_figure(runs)
    _check_axes(fig, 2)
    assert fig.axes[0].get_yscale() == "log"
    assert any("χ²" in lab for lab in fig.axes[0].get_legend_handles_labels()[1])
    assert any("filtered" in lab for lab in fig.axes[0].get_legend_handles_labels()[1])
    fig = timing_figure(runs)
    _check_axes(fig, 2)
    assert fig.axes[1].get_yscale() == "log"
    assert "per step [ms]" in fig.axes[0].get_ylabel()


def test_fig10_is_in_the_known_map_frame(comparison: Comparison) -> None:
    fused, plain = comparison.get("ekf", True), comparison.get("batch", False)
    fig = fig10_maps([fused, plain])
    _check_axes(fig, 2)
    assert "estimated anchor" in fig.axes[0].get_title()
    assert "true start pose" in fig.axes[1].get_title()
    assert "Wknown" in fig.axes[0].get_xlabel()
    # The estimated trajectory, drawn through the anchor, lies on the true one (W = Wknown).
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    est = np.column_stack(lines["estimated trajectory"].get_data())
    truth = comparison.log.true_poses
    assert truth is not None
    assert np.max(np.hypot(*(est - truth[:, :2]).T)) < 0.5


def test_ccda_figure(log: MeasurementLog) -> None:
    known = log.known_map
    T = np.array([5.0, -3.0, 0.4])  # x^B_A: the SLAM frame A seen from the known map B
    pairs = zip(known.kinds, known.params, strict=True)
    params = np.array([express_in(FeatureKind(int(k)), T, p)[0] for k, p in pairs])
    map_a = KnownMapArrays(known.ids, known.kinds, params, known.covs + 1e-4 * np.eye(3))
    res = ccda_match(map_a, known)
    assert res.accepted
    fig = ccda_figure(map_a, known, res, x_B_A_true=T)
    _check_axes(fig, 2)
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert any(lab.startswith("pairings") for lab in labels)


def test_a_log_without_known_map_is_compared_once_and_not_labelled_fused(
    log: MeasurementLog,
) -> None:
    k = log.known_map
    empty = KnownMapArrays(k.ids[:0], k.kinds[:0], k.params[:0], k.covs[:0])
    no_map = compare(dataclasses.replace(log, known_map=empty), ("ekf", "batch"))
    assert [(m.estimator, m.fusion) for m in no_map.metrics] == [
        ("ekf", False),
        ("batch", False),
    ]
    assert run_label(no_map.get("ekf", False)) == "ekf"
    # Asked for fusion on such a log, a run is made and reported without it.
    alone = run(no_map.log, "ekf", fusion=True)
    assert alone.metrics.fusion is False
    np.testing.assert_array_equal(alone.poses, no_map.get("ekf", False).poses)
    assert run_label(compare(log, ("ekf",)).get("ekf", True)) == "ekf with fusion"
