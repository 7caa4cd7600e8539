"""The EKF's tentative features (``EKFConfig.tentative_min_sightings``): clutter seen
once never enters the map, and a run without clutter is unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from ekf_reference.config import EKFConfig
from mapfuse.runner import Run, run
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log, with_clutter

STEPS, CLUTTER = 120, 5  # 600 spurious detections, half trunks, half short walls


@pytest.fixture(scope="module")
def clean() -> MeasurementLog:
    return synthetic_log(STEPS, 0)


@pytest.fixture(scope="module")
def cluttered(clean: MeasurementLog) -> MeasurementLog:
    return with_clutter(clean, CLUTTER, seed=0)


@pytest.fixture(scope="module")
def paper(clean: MeasurementLog) -> Run:
    return run(clean, "ekf")


def test_the_papers_method_keeps_every_spurious_detection(cluttered: MeasurementLog) -> None:
    m = run(cluttered, "ekf").metrics.map
    # Clutter is drawn uniformly, so nearly every detection is a new feature seen once.
    assert m.seen_once >= 0.95 * STEPS * CLUTTER
    assert m.tentative_dropped == 0


def test_two_sightings_drop_nearly_all_clutter_and_keep_the_estimate(
    cluttered: MeasurementLog, paper: Run
) -> None:
    r = run(cluttered, "ekf", tentative_min_sightings=2)
    m, p = r.metrics, paper.metrics
    assert m.map.tentative_dropped >= 0.99 * STEPS * CLUTTER
    assert m.map.seen_once == 0
    # At most a few clutter features seen twice by chance survive (measured: 2).
    assert m.map.features <= p.map.features + 5
    assert m.map.matched_known == p.map.matched_known
    # Same estimate as the clean run to 5 % (measured: 0.032 against 0.0317 m RMSE).
    assert m.position_error.rmse == pytest.approx(p.position_error.rmse, rel=0.05)
    assert m.anchor is not None
    assert m.anchor.correct_pairings == m.anchor.pairings
    # The dropped detections' observations are unassociated in the decisions.
    assert r.result.decisions is not None
    spurious = np.asarray(cluttered.feat_true_id) < 0
    lm = np.asarray(r.result.decisions.obs_landmark)
    assert np.mean(lm[spurious] < 0) >= 0.99


def test_without_clutter_two_sightings_change_nothing(clean: MeasurementLog, paper: Run) -> None:
    m, p = run(clean, "ekf", tentative_min_sightings=2).metrics, paper.metrics
    assert m.map.features == p.map.features
    assert m.anchor.pairings == p.anchor.pairings
    assert m.position_error.rmse == pytest.approx(p.position_error.rmse, rel=1e-2)
    assert m.nees.mean == pytest.approx(p.nees.mean, rel=1e-2)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tentative_min_sightings": 0}, "tentative_min_sightings must be an int >= 1"),
        ({"tentative_window_steps": 2.5}, "tentative_window_steps must be an int >= 1"),
        (
            {"tentative_min_sightings": 4, "tentative_window_steps": 3},
            "tentative_window_steps (3) must be >= tentative_min_sightings (4)",
        ),
    ],
)
def test_bad_tentative_settings_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        EKFConfig(**kwargs)  # type: ignore[arg-type]
