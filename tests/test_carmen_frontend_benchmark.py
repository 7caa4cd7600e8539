"""``benchmarks/carmen_frontend.py``: the wrong re-observations of a run, and which of
them a join made, on constructed decisions against a constructed plan."""

from __future__ import annotations

import numpy as np
import pytest

from tests.scripts import load_benchmark
from tests.test_same_wall import FRAMES, _plan


@pytest.fixture(scope="module")
def bench():  # type: ignore[no-untyped-def]
    return load_benchmark("carmen_frontend")


def test_wrong_reobservations_tell_a_joins_merge_from_the_measurement_association(
    bench,  # type: ignore[no-untyped-def]
) -> None:
    # Walls 0 and 1: one line a doorway apart; wall 2: a parallel wall 1 m off.
    plan = _plan([(0.0, 0.0, 0.0, 1.5), (4.0, 0.0, 0.0, 1.5), (0.0, 1.0, 0.0, 1.5)], FRAMES[1])
    # Landmark 7 took local tracks 10 (wall 0, five observations, one of them really
    # wall 2: the measurement association's error) and 11 (wall 2 twice, then wall 1:
    # a join's merge, and a collinear piece that is no error).
    local = np.array([10, 10, 10, 10, 10, 10, 11, 11, 11])
    labels = np.array([0, 0, 0, 2, 0, 0, 2, 2, 1])
    steps = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8])
    landmark = np.full(9, 7)
    ro = bench.wrong_reobservations(landmark, labels, steps, plan, local)
    assert (ro.judged, ro.wrong, ro.wrong_strict, ro.wrong_at_join) == (8, 3, 4, 2)
    # Without local tracks every error is the measurement association's.
    ro = bench.wrong_reobservations(landmark, labels, steps, plan)
    assert (ro.wrong, ro.wrong_at_join) == (3, 0)


def _line_log(lines: list[tuple[float, float, float]], labels: list[int]):  # type: ignore[no-untyped-def]
    """One line observation per scan, at the origin, of each ``(x, y, θ)`` in ``W``."""
    from mapfuse_core.data.datasets.common import empty_map
    from mapfuse_core.geometry.features import FeatureKind
    from mapfuse_core.measlog import MeasurementLog

    m = len(lines)
    return MeasurementLog(
        scenario="off-wall",
        seed=0,
        timestamps=np.arange(m, dtype=float),
        odometry=np.zeros((m, 3)),
        odometry_cov=np.array([np.eye(3) * 1e-4] * m),
        feat_step=np.arange(m, dtype=np.int64),
        feat_kind=np.full(m, int(FeatureKind.LINE), dtype=np.int8),
        feat_params=np.array(lines, dtype=float),
        # σ 1 cm across the line and 0.06° in angle; along it, where the segment lies.
        feat_cov=np.tile(np.diag([0.25, 1e-4, 1e-6]), (m, 1, 1)),
        feat_true_id=np.array(labels, dtype=np.int64),
        feat_n_points=np.full(m, 50, dtype=np.int64),
        feat_extent=np.tile([-0.5, 0.5], (m, 1)),
        known_map=empty_map(),
        true_poses=np.zeros((m, 3)),
    )


def test_off_wall_observations_count_unlabelled_segments_off_the_landmarks_wall(
    bench,  # type: ignore[no-untyped-def]
) -> None:
    # Wall 0 along y = 2; wall 1 a recess 0.5 m behind it past its end; wall 2 the same
    # line as wall 0 beyond a doorway.
    plan = _plan([(0.0, 2.0, 0.0, 1.5), (3.0, 2.5, 0.0, 1.0), (5.0, 2.0, 0.0, 1.0)], FRAMES[0])
    lines = [
        (0.0, 2.0, 0.0),  # wall 0, labelled (three times: the majority)
        (0.5, 2.0, 0.0),
        (-0.5, 2.0, 0.0),
        (5.0, 2.0, 0.0),  # wall 2, labelled: on wall 0's line, not off
        (3.0, 2.5, 0.0),  # the recess, unlabelled: 0.5 m = 50 σ off wall 0's line
        (1.8, 2.005, 0.0),  # unlabelled past wall 0's end, on its line: not off
        (3.0, 2.5, 0.0),  # the recess, labelled: off
        (-1.0, 2.08, 0.0),  # unlabelled, 8 cm off: past the gate (d² 32), not far off
        (0.0, 3.0, 0.0),  # landmark 6: unlabelled only, no majority, not judged
    ]
    log = _line_log(lines, [0, 0, 0, 2, -1, -1, 1, -1, -1])
    landmark = np.array([5, 5, 5, 5, 5, 5, 5, 5, 6])
    ow = bench.off_wall_observations(landmark, log, plan)
    # The recess seen unlabelled is far off (d² 1,250); the 8 cm piece is the tail.
    assert (ow.judged, ow.off, ow.landmarks, ow.far) == (8, 3, 1, 1)
    # The labelled-only count sees the labelled recess alone.
    ro = bench.wrong_reobservations(landmark, log.feat_true_id, log.feat_step, plan)
    assert ro.wrong == 1


def test_estimator_names_take_a_kernel_and_the_reference_association(
    bench,  # type: ignore[no-untyped-def]
) -> None:
    assert bench.backend_and_kernel("batch") == ("batch", {})
    assert bench.backend_and_kernel("batch+gauss") == ("batch", {"graph": {"robust": None}})
    assert bench.backend_and_kernel("isam2@truth") == ("isam2", {"association": "truth"})
    assert bench.backend_and_kernel("batch+huber@truth") == (
        "batch",
        {"association": "truth", "graph": {"robust": "huber"}},
    )
    assert bench.backend_and_kernel("isam2@own") == ("isam2", {"association": "own"})
    with pytest.raises(ValueError, match="@truth or @own"):
        bench.backend_and_kernel("batch@given")


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (("--line-model-gate", "alone"), "line_model_gate='alone' needs line_model_error="),
        (("--line-model-shape", "length"), "line_model_shape='length' needs line_model_error"),
    ],
)
def test_line_terms_without_estimated_terms_are_refused_before_any_log_is_read(
    bench,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    option: tuple[str, str],
    message: str,
) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr("sys.argv", ["carmen_frontend.py", "--data", "/nonexistent", *option])
    with pytest.raises(SystemExit) as exc:
        bench.main()
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_the_length_shape_reaches_the_loader(bench, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    seen: list[object] = []

    def loader(path, options=None):  # type: ignore[no-untyped-def]
        seen.append(options)
        raise SystemExit(0)

    monkeypatch.setattr(bench, "load_carmen", loader)
    monkeypatch.setattr(bench, "resolve_logs", lambda data, logs: ["x.log"])
    argv = [
        "carmen_frontend.py",
        "--line-model-error",
        "correlated",
        "--line-model-shape",
        "length",
    ]
    monkeypatch.setattr("sys.argv", argv)
    with pytest.raises(SystemExit):
        bench.main()
    assert [o.line_model_shape for o in seen] == ["length"]  # type: ignore[attr-defined]
