"""catalogue.robot_list: the one check of "a list of robot numbers" (catalogue.check_robots and
the real-log tuning targets' _check_robots both use it)."""

from collections import OrderedDict

import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import catalogue
from jaxslam.errors import InputError


def test_robot_list_messages_with_and_without_a_flag():
    assert catalogue.robot_list(range(1, 4), "robots", "--robots") == (1, 2, 3)
    assert catalogue.robot_list([np.int64(2), 2], "--robots", unique=False) == (2, 2)
    with pytest.raises(InputError, match=r"^--robots: expected a list of robot numbers, got 3$"):
        catalogue.robot_list(3, "--robots")
    with pytest.raises(InputError, match=r"^--robots: expected an int >= 1, got 1\.5$"):
        catalogue.robot_list([1, 1.5], "--robots")
    with pytest.raises(InputError, match=r"^robots: expected robot numbers \(--robots\): ints >= 1, got 1\.5$"):
        catalogue.robot_list([1, 1.5], "robots", "--robots")
    with pytest.raises(InputError, match=r"^robots: robot\(s\) \[2\] listed more than once \(--robots\)$"):
        catalogue.robot_list([2, 1, 2], "robots", "--robots")
    with pytest.raises(InputError, match=r"^robots: give at least one robot \(--robots\)$"):
        catalogue.robot_list((), "robots", "--robots", allow_empty=False)


def test_check_robots_refuses_a_mapping_and_a_0d_array_and_allows_repeats():
    """A dict's keys were checked as robots, a 0-d array raised NumPy's bare TypeError."""
    for bad in ({1: 1}, OrderedDict([(1, 2)]), np.array(2)):
        with pytest.raises(InputError, match=r"^--robots: expected a list of robot numbers, got"):
            catalogue.check_robots("mrclam", EXCERPTS, bad)
    catalogue.check_robots("mrclam", EXCERPTS, (r for r in (1, 2, 1)), flag="--robots/--test-robots")
    with pytest.raises(InputError, match=r"^--robots: expected an int >= 1, got 'x'"):
        catalogue.check_robots("mrclam", EXCERPTS, [1, "x"])
