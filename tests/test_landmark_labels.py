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
