"""Every file of tests/data/bad/ makes its loader raise DataFormatError at the right file:line."""

import numpy as np
import pytest
from data_loader_paths import BAD, EXCERPTS

from jaxslam.data import (DataFormatError, MissingDataError, load_mrclam, load_plaza, load_util,
                          load_victoria_park)

# case folder, defective file (relative to the case folder), 1-based line (None: whole file), message
CASES = [
    ("mrclam_truncated", "mrclam6/Robot1_Odometry.dat", 34, r"expected 3 columns, got \d \(truncated line"),
    ("mrclam_columns", "mrclam6/Robot1_Groundtruth.dat", 20, "expected 4 columns, got 5"),
    ("mrclam_nonnumeric", "mrclam6/Robot1_Measurement.dat", 12, "non-numeric field '1.8l5' in column 3"),
    ("mrclam_backwards", "mrclam6/Robot1_Odometry.dat", 30, r"time goes backwards .*\(line 29\)"),
    ("mrclam_unknown_barcode", "mrclam6/Robot1_Measurement.dat", 9, "unknown barcode 99"),
    ("mrclam_missing", "mrclam6/Barcodes.dat", None, r"missing file\(s\) Barcodes\.dat"),
    ("victoria_park_truncated", "victoria_park/measurements.dat", 30, r"expected 4 columns, got \d \(truncated"),
    ("victoria_park_columns", "victoria_park/inputs.dat", 17, "expected 3 columns, got 2"),
    ("victoria_park_nonnumeric", "victoria_park/gps.dat", 7, "non-numeric field '-2.0x0' in column 2"),
    ("victoria_park_backwards", "victoria_park/inputs.dat", 25, "time goes backwards"),
    ("victoria_park_missing", "victoria_park/gps.dat", None, r"missing file\(s\) gps\.dat"),
    ("plaza_truncated", "gtsam/Plaza2_TD.txt", 30, r"expected 4 columns, got \d \(truncated"),
    ("plaza_columns", "gtsam/Plaza1_TL.txt", 4, "expected 3 columns, got 4"),
    ("plaza_nonnumeric", "gtsam/Plaza1_GT.txt", 15, r"non-numeric field 'NaN\?' in column 2"),
    ("plaza_backwards", "gtsam/Plaza1_DR.txt", 10, "time goes backwards"),
    ("plaza_missing", "gtsam/Plaza2_TL.txt", None, r"missing file\(s\) Plaza2_TL\.txt"),
    ("util_truncated", "util_uwb/twr_obs_log1/imu.csv.gz", 31, r"expected 8 columns, got \d \(truncated"),
    ("util_columns", "util_uwb/twr_obs_log1/groundtruth.csv", 23, "expected 8 columns, got 7"),
    ("util_nonnumeric", "util_uwb/twr_obs_log1/uwb_twr.csv", 6, "non-numeric field 'a3' in column 2"),
    ("util_backwards", "util_uwb/twr_obs_log1/uwb_twr.csv", 20, "time goes backwards"),
    ("util_missing", "util_uwb/twr_obs_log1/imu.csv.gz", None, r"missing file\(s\) imu\.csv\.gz"),
    ("util_header", "util_uwb/twr_obs_log1/groundtruth.csv", 1, "expected header 't,x,y,z,qx,qy,qz,qw'"),
]


def _load(case, folder, strict=True):
    if case.startswith("mrclam"):
        return load_mrclam(folder, 1, strict=strict)
    if case.startswith("victoria_park"):
        return load_victoria_park(folder)
    if case.startswith("plaza"):
        return load_plaza(folder, 2 if case in ("plaza_truncated", "plaza_missing") else 1)
    return load_util(folder, "twr_obs_log1")


def test_every_bad_folder_is_tested_and_documented():
    readme = (EXCERPTS / "README.md").read_text()
    folders = sorted(p.name for p in BAD.iterdir() if p.is_dir())
    assert folders == sorted(c[0] for c in CASES)
    for case, rel, line, _ in CASES:
        assert f"| `{case}/` | `{rel}` | {line if line else '—'} |" in readme, case


@pytest.mark.parametrize("case, rel, line, pattern", CASES, ids=[c[0] for c in CASES])
def test_bad_file_raises_at_file_line(case, rel, line, pattern):
    with pytest.raises(DataFormatError, match=pattern) as ei:
        _load(case, BAD / case)
    e = ei.value
    msg = str(e)
    name = rel.rsplit("/", 1)[-1]
    assert name in msg
    assert e.line == line
    if line is None:
        assert isinstance(e, MissingDataError) and isinstance(e, FileNotFoundError)
        assert "looked in" in msg
        assert e.path == str(BAD / case / rel)
    else:
        assert e.path == str(BAD / case / rel)
        assert msg.startswith(f"{BAD / case / rel}:{line}: ")


def test_unknown_barcode_is_dropped_when_not_strict():
    d = _load("mrclam_unknown_barcode", BAD / "mrclam_unknown_barcode", strict=False)
    f = BAD / "mrclam_unknown_barcode" / "mrclam6" / "Robot1_Measurement.dat"
    assert d.report["unknown_barcodes"] == [99, 43]
    assert d.report["unknown_barcode_lines"] == [f"{f}:9", f"{f}:33"]
    assert d.report["landmark_rows"] + d.report["robot_rows"] + 2 == d.report["rows"]["measurement"] == 30


def _mrclam_copy(tmp_path):
    import shutil
    d = tmp_path / "mrclam6"
    shutil.copytree(EXCERPTS / "mrclam6", d)
    return d


def test_landmark_subject_listed_twice_raises_at_its_line(tmp_path):
    """Two surveyed positions for one landmark: refused at the second row's file:line."""
    d = _mrclam_copy(tmp_path)
    f = d / "Landmark_Groundtruth.dat"
    lines = f.read_text().splitlines()
    lines.append(" 6 \t 9.0 \t 9.0 \t 0.0001 \t 0.0001")  # subject 6 again (first at line 5)
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=r"landmark subject 6 listed twice \(first at .*:5\)") as ei:
        load_mrclam(tmp_path, 1)
    assert ei.value.line == len(lines)


def test_nonpositive_range_rows_are_dropped_and_named(tmp_path):
    """A landmark sighting with range <= 0 is no camera measurement: dropped, counted, its line
    named in the report (a whole log is not refused for one row)."""
    d = _mrclam_copy(tmp_path)
    f = d / "Robot1_Measurement.dat"
    clean = load_mrclam(tmp_path, 1)
    lines = f.read_text().splitlines()
    changed = []
    for i, ln in enumerate(lines):
        fields = ln.split()
        if ln.startswith("#") or int(fields[1]) not in clean.landmark_id:
            continue
        fields[2] = "-0.5" if not changed else "0.0"
        lines[i] = " \t ".join(fields)
        changed.append(i + 1)
        if len(changed) == 2:
            break
    f.write_text("\n".join(lines) + "\n")
    got = load_mrclam(tmp_path, 1)
    assert got.report["nonpositive_range_rows"] == 2
    assert got.report["nonpositive_range_lines"] == [f"{f}:{n}" for n in changed]
    assert got.report["landmark_rows"] == clean.report["landmark_rows"] - 2
    assert got.meas.shape[0] == clean.meas.shape[0] - 2 and np.all(got.meas[:, 0] > 0)
    assert clean.report["nonpositive_range_rows"] == 0
