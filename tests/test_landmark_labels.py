"""Which true feature an estimated landmark stands for: the majority of its labels."""

from __future__ import annotations

import numpy as np
import pytest

from mapfuse_core.evaluation import landmark_labels


def test_majority_of_the_landmarks_labelled_observations_wins_over_its_first() -> None:
    obs_landmark = np.array([0, 0, 0, 0, 1, 1, -1])
    labels = np.array([24, 30, 30, -1, 7, 7, 30])
    assert landmark_labels(obs_landmark, labels, [0, 1]) == [30, 7]


def test_unlabelled_or_unobserved_landmark_gets_minus_one() -> None:
    obs_landmark = np.array([0, 0, 1])
    labels = np.array([-1, -1, 5])
    assert landmark_labels(obs_landmark, labels, [0, 2, 1]) == [-1, -1, 5]


def test_a_tie_goes_to_the_label_seen_first() -> None:
    obs_landmark = np.array([3, 3, 3, 3])
    labels = np.array([9, 4, 4, 9])
    assert landmark_labels(obs_landmark, labels, [3]) == [9]
    # The smaller label seen first wins too: the tie is not broken by value.
    assert landmark_labels(obs_landmark, np.array([4, 9, 9, 4]), [3]) == [4]


def test_unassociated_observations_do_not_count() -> None:
    obs_landmark = np.array([-1, -1, 2])
    labels = np.array([8, 8, 1])
    assert landmark_labels(obs_landmark, labels, [2]) == [1]


def test_mismatched_lengths_are_an_error_naming_both_shapes() -> None:
    with pytest.raises(ValueError, match=r"obs_landmark has shape \(3,\), labels \(2,\)"):
        landmark_labels(np.zeros(3, dtype=int), np.zeros(2, dtype=int), [0])


@pytest.mark.slow
def test_ekf_pairing_of_a_landmark_started_by_clutter_carries_its_majority_label() -> None:
    """loop600's first 160 steps with clutter, seed 12: a spurious detection on known
    tree 31 starts the landmark that 72 observations of tree 31 then join; the EKF's
    pairing of it must carry 31, not the clutter's −1."""
    import dataclasses

    from mapfuse.runner import run
    from mapfuse_core.sim.clutter import ClutterParams
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import simulate

    clutter = ClutterParams(features_per_scan=5, circle_fraction=0.5, outlier_fraction=0.1)
    scenario = dataclasses.replace(load_scenario("loop600"), steps=160)
    log = simulate(scenario, seed=12, workers=1, clutter=clutter).log
    result = run(log, "ekf").result
    assert result.anchor is not None
    assert result.decisions is not None
    known = np.asarray(result.decisions.obs_known_id)
    true_ids = np.asarray(log.feat_true_id[: known.size])[known == 31]
    assert true_ids[0] == -1  # the landmark's first observation is the clutter
    assert np.count_nonzero(true_ids == 31) > 0.9 * true_ids.size
    assert (31, 31) in result.anchor.pairings
    assert all(label == kid for label, kid in result.anchor.pairings)
