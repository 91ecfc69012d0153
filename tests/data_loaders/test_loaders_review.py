"""Review fixes of the loaders (mrclam, plaza, util_uwb) and the catalogue.

Expectations are written by hand or parsed with plain Python, never taken from the loader.
"""

import shutil

import numpy as np
import pytest

from jaxslam.data import DataFormatError
from jaxslam.data import catalogue
from jaxslam.data.mrclam import load_mrclam
from jaxslam.data.plaza import load_plaza
from jaxslam.data.util_uwb import load_util
from jaxslam.errors import InputError

from data_loader_paths import EXCERPTS


def _copy(tmp_path, name):
    d = tmp_path / name
    shutil.copytree(EXCERPTS / name, d)
    return d


def _first_data_line(path, skip=0):
    """(0-based index into lines, lines) of the first data line (plain Python)."""
    lines = path.read_text().split("\n")
    for i, s in enumerate(lines):
        if i >= skip and s.strip() and not s.strip().startswith("#"):
            return i, lines
    raise AssertionError("no data line")


def test_mrclam_strict_must_be_true_or_false():
    # "no" is truthy: it used to switch strict mode on (robot 1's excerpt then raised at its
    # unknown barcode); robot 2 loaded with no complaint.
    for robot in (1, 2):
        with pytest.raises(InputError, match=r"^strict: expected True or False, got 'no'") as ei:
            load_mrclam(EXCERPTS / "mrclam6", robot, strict="no")
        assert not isinstance(ei.value, DataFormatError)
    with pytest.raises(InputError, match=r"^strict: "):
        load_mrclam(EXCERPTS / "mrclam6", 2, strict=1)


def test_mrclam_negative_landmark_std_is_refused_at_its_line(tmp_path):
    d = _copy(tmp_path, "mrclam6")
    f = d / "Landmark_Groundtruth.dat"
    i, lines = _first_data_line(f)
    fields = lines[i].split()
    fields[4] = "-0.00027395"  # σy of subject 6
    lines[i] = " ".join(fields)
    f.write_text("\n".join(lines))
    with pytest.raises(DataFormatError, match=r"negative standard deviation") as ei:
        load_mrclam(d, 1)
    assert ei.value.line == i + 1 and ei.value.path == str(f)


def test_plaza_start_pose_heading_minus_pi_is_returned_as_plus_pi():
    # documented range (−π, π]: arctan2 gave −π for a heading of exactly −π
    p = load_plaza(EXCERPTS / "gtsam", 1)
    for heading, offset in ((-np.pi, 0.0), (-2 * np.pi, np.pi), (np.pi, 0.0), (0.0, np.pi)):
        q = p._replace(gt=np.array([[1.5, -2.0, heading]]), heading_offset=offset)
        x, y, th = q.start_pose()
        assert (x, y) == (1.5, -2.0)
        assert th == np.pi, (heading, offset, th)
    # away from the boundary nothing changes: 3.0 + π wraps to 3.0 − π
    q = p._replace(gt=np.array([[0.0, 0.0, 3.0]]), heading_offset=np.pi)
    assert q.start_pose()[2] == pytest.approx(3.0 - np.pi, abs=1e-15)


def test_util_flight_dotdot_is_not_a_flight_name():
    # ".." named the parent of the flight folder: "several folders ... hold the files"
    with pytest.raises(InputError, match=r"^flight: expected a flight folder name") as ei:
        load_util(EXCERPTS / "util_uwb" / "twr_obs_log1", "..")
    assert not isinstance(ei.value, DataFormatError)


@pytest.mark.parametrize("which", ["groundtruth", "anchors"])
def test_util_zero_quaternion_is_refused_at_its_line(tmp_path, which):
    d = _copy(tmp_path, "util_uwb")
    f = d / ("twr_obs_log1/groundtruth.csv" if which == "groundtruth" else "anchors_const3.csv")
    lines = f.read_text().split("\n")
    k = 3  # the third data line (line 1 is the header)
    fields = lines[k].split(",")
    fields[4:8] = ["0", "0", "0", "0"]
    lines[k] = ",".join(fields)
    f.write_text("\n".join(lines))
    # it used to load, and tag_positions then refused "q_xyzw ... at index (2,)" without a file
    with pytest.raises(DataFormatError, match=r"zero quaternion") as ei:
        load_util(d, "twr_obs_log1")
    assert ei.value.path == str(f) and ei.value.line == k + 1


def test_catalogue_robot_numbers_are_the_loaders_file_names(tmp_path):
    d = tmp_path / "mrclam6"
    d.mkdir()
    for n in ("Robot01_Odometry.dat", "Robot0_Odometry.dat", "Robot2_Odometry.dat"):
        (d / n).write_text("")
    # the loader opens Robot1_Odometry.dat, which is absent; robot 0 is never a robot
    assert catalogue.robots_found("mrclam", tmp_path) == [2]
    with pytest.raises(InputError, match=r"--robot: MRCLAM robot 1 is not in .*\(found: 2\)"):
        catalogue.check_robot("mrclam", tmp_path, 1)
    catalogue.check_robot("mrclam", tmp_path, 2)


def test_check_options_names_an_option_the_dataset_does_not_take_first():
    # util-uwb has no --filter choice; it was told "--params ... does not apply to --filter fastslam"
    with pytest.raises(InputError, match=r"^util-uwb: --filter do\(es\) not apply here"):
        catalogue.check_options("util-uwb", {"filter": "fastslam", "params": object()})
    # util-uwb takes --smooth but not --ids; it was told "--smooth needs known landmark ids"
    with pytest.raises(InputError, match=r"^util-uwb: --ids do\(es\) not apply here"):
        catalogue.check_options("util-uwb", {"ids": "hidden", "smooth": True})
    # where the options apply, the pair rules still hold
    with pytest.raises(InputError, match=r"^mrclam: --params sets the EKF's noise"):
        catalogue.check_options("mrclam", {"filter": "fastslam", "params": object()})
    with pytest.raises(InputError, match=r"^mrclam: --smooth smooths the EKF's run"):
        catalogue.check_options("mrclam", {"filter": "fastslam", "smooth": True})
    with pytest.raises(InputError, match=r"^mrclam: --smooth needs known landmark ids"):
        catalogue.check_options("mrclam", {"ids": "hidden", "smooth": True})
    catalogue.check_options("mrclam", {"filter": "fastslam", "particles": 8, "seed": 3})
