"""One rule for event times (finite, non-decreasing): merge_events and the range-only logs."""

import numpy as np
import pytest

from jaxslam.data.events import check_times, merge_events
from jaxslam.errors import InputError


def test_check_times_names_the_first_bad_index():
    check_times(np.array([0.0, 0.0, 1.0]), "t")  # equal times: one event
    check_times(np.zeros(0), "t")
    with pytest.raises(InputError, match=r"^t: non-finite time at index 1$"):
        check_times([0.0, np.nan, 1.0], "t")
    with pytest.raises(InputError, match=r"^t: time decreases at index 2 \(1\.0 → 0\.5\)$"):
        check_times([0.0, 1.0, 0.5], "t")
    # full precision for epoch stamps (MRCLAM's are ~1.2e9 s)
    with pytest.raises(InputError, match=r"^log\.t: time decreases at index 1 \(1248272272\.841 → 1248272272\.84\)$"):
        check_times(np.array([1248272272.841, 1248272272.84]), "log.t")


def test_merge_events_uses_it():
    with pytest.raises(InputError, match=r"^meas_t: time decreases at index 1"):
        merge_events([0.0, 1.0], np.zeros((2, 1)), [1.0, 0.5], np.zeros((2, 1)))
    with pytest.raises(InputError, match=r"^input_t: non-finite time at index 0"):
        merge_events([np.inf, 1.0], np.zeros((2, 1)), [0.5], np.zeros((1, 1)))
