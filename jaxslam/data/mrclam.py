"""UTIAS MRCLAM (Multi-Robot Cooperative Localization and Mapping) loader.

Origin: K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, "The UTIAS
Multi-Robot Cooperative Localization and Mapping Dataset", *International
Journal of Robotics Research* 30(8):969–974, 2011
(asrl.utias.utoronto.ca/datasets/mrclam/).  No licence is stated for the data
files; cite the IJRR paper.  Indoor arena of about 15 m × 8 m, five iRobot
Create robots with a monocular camera, 15 barcoded cylindrical landmarks,
Vicon ground truth (about 1 mm).

Files read (whitespace-separated, tabs and spaces mixed, 4 ``#`` header lines):

=============================  ==============================================
``RobotN_Odometry.dat``        time [s], v [m/s], ω [rad/s]
``RobotN_Measurement.dat``     time [s], **barcode** (the header says
                               "Subject #"), range [m], bearing [rad]
                               (robot frame, 0 ahead, counter-clockwise +)
``RobotN_Groundtruth.dat``     time [s], x [m], y [m], θ [rad] in [−π, π]
``Landmark_Groundtruth.dat``   subject (6–20), x, y, σx, σy [m]
``Barcodes.dat``               subject, barcode
=============================  ==============================================

Quirks handled:

* The measurement file holds barcodes, not subjects: they are mapped through
  ``Barcodes.dat``.  Subjects 1–5 are the *robots*; those rows are removed and
  counted (``report["robot_rows"]``).  Barcodes found in no table are camera
  false positives (Dataset 6, Robot 1: one row with barcode 43): by default
  they are dropped and listed as ``file:line`` in
  ``report["unknown_barcode_lines"]``; ``strict=True`` raises
  :class:`~jaxslam.data.textfile.DataFormatError` at that line instead.
* Times are Unix epoch seconds with 1 ms resolution.  ``t0`` keeps the
  absolute epoch of the dataset start (the first ground-truth row); all
  returned times are ``t − t0`` as float64, rounded to 1 µs to remove the
  representation noise of a 1.2e9-s float (the files have 1 ms resolution).
* Several measurement rows share a time (one camera frame sees several
  landmarks); some readings repeat a barcode's previous reading identically
  (``report["repeated_readings"]``, 37 for Dataset 6 Robot 1).  Rows
  identical in every field to an earlier row at the same time are counted in
  ``report["duplicate_rows"]``.  Nothing is removed for either.
* Odometry is irregular (about 70 Hz, gaps up to 1 s) and may repeat a
  timestamp (Dataset 6 Robot 2 once): kept, and listed in
  ``report["odometry_duplicate_times"]`` / ``..._lines``.
* Odometry starts about 12 s after ground truth (the robot stands still);
  Robot 1 of Dataset 6 stops at +771.9 s and its odometry continues with zero
  velocities: evaluate only where ground truth exists.
* Only the original ``RobotN_Measurement.dat`` is read (never the derived
  ``RobotN_Measurement_x.dat`` of some redistributions).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import InputError, check_flag
from .textfile import ID_MAX, int_column, read_table, resolve_dataset_dir

__all__ = ["MrclamData", "load_mrclam", "ROBOT_SUBJECTS"]

ROBOT_SUBJECTS = (1, 2, 3, 4, 5)
_TIME_DECIMALS = 6  # relative times rounded to 1 µs


class MrclamData(NamedTuple):
    """One MRCLAM robot's streams (NumPy; times in s relative to ``t0``).

    robot: robot number (1–5).
    t0: absolute Unix epoch [s] of the dataset start (first ground-truth row).
    odom_t: (N,) odometry times; odom: (N, 2) [v m/s, ω rad/s].
    gt_t: (M,) ground-truth times; gt: (M, 3) [x m, y m, θ rad].
    meas_t: (K,) landmark-measurement times (robot and unknown-barcode rows
      removed); meas: (K, 2) [range m, bearing rad]; meas_id: (K,) int32
      landmark subject number (6–20).
    landmark_id: (L,) int32 subject; landmark_xy: (L, 2) [m];
      landmark_std: (L, 2) [σx, σy] m  (from ``Landmark_Groundtruth.dat``).
    barcodes: (S, 2) int32 [subject, barcode] (``Barcodes.dat``).
    report: counts and provenance (see :func:`load_mrclam`).
    """

    robot: int
    t0: float
    odom_t: np.ndarray
    odom: np.ndarray
    gt_t: np.ndarray
    gt: np.ndarray
    meas_t: np.ndarray
    meas: np.ndarray
    meas_id: np.ndarray
    landmark_id: np.ndarray
    landmark_xy: np.ndarray
    landmark_std: np.ndarray
    barcodes: np.ndarray
    report: dict

    def landmark_positions(self) -> dict:
        """``{subject: (x, y)}`` of the surveyed landmarks."""
        return {int(i): (float(x), float(y)) for i, (x, y) in zip(self.landmark_id, self.landmark_xy)}


def _files(robot: int) -> dict:
    return {
        "odometry": f"Robot{robot}_Odometry.dat",
        "measurement": f"Robot{robot}_Measurement.dat",
        "groundtruth": f"Robot{robot}_Groundtruth.dat",
        "landmark_groundtruth": "Landmark_Groundtruth.dat",
        "barcodes": "Barcodes.dat",
    }


def load_mrclam(path, robot: int, strict: bool = False) -> MrclamData:
    """Load one robot of an MRCLAM dataset (files as in Dataset 6).

    Args:
      path: the dataset folder (e.g. ``…/mrclam6``) or a parent folder that
        contains ``mrclam6/``.
      robot: robot number 1–5 (its ``RobotN_*.dat`` files must exist).
      strict: ``True``: raise :class:`DataFormatError` at the first measurement row
        whose barcode is in no table; ``False`` (default): drop it and report it.

    Returns:
      :class:`MrclamData`.  ``report`` holds: ``dir``; ``rows`` (data rows read
      per file); ``landmark_rows``; ``robot_rows`` (rows of other robots,
      removed); ``unknown_barcode_rows`` with ``unknown_barcodes`` (values) and
      ``unknown_barcode_lines`` (``"file:line"``); ``nonpositive_range_rows`` with
      ``nonpositive_range_lines`` (rows with range ≤ 0, dropped); ``duplicate_rows`` (rows
      identical to an earlier row with the same time); ``repeated_readings``
      (a barcode's range and bearing identical to its previous reading);
      ``distinct_measurement_times``; ``landmarks_seen``;
      ``odometry_duplicate_times`` (relative times) and
      ``odometry_duplicate_lines``; ``t0``; ``t_end`` (last time of any stream,
      relative).

    Raises:
      InputError: ``robot`` is not an integer in 1–5, or ``strict`` is not True / False.
      MissingDataError: a file is missing (the message lists the folders
        looked in and the missing files).
      DataFormatError: a malformed file (``file:line`` in the message), an
        inconsistent barcode table, a landmark subject listed twice in
        ``Landmark_Groundtruth.dat`` or with a negative σx / σy, or (``strict``) an
        unknown barcode.
    """
    if isinstance(robot, bool) or not isinstance(robot, (int, np.integer)) or not 1 <= int(robot) <= 5:
        raise InputError(f"robot: expected an integer 1–5, got {robot!r}")
    robot = int(robot)
    strict = check_flag(strict, "strict")  # (a string "no" was truthy: strict mode silently on)
    names = _files(robot)
    d = resolve_dataset_dir(path, "mrclam6", list(names.values()), f"MRCLAM robot {robot}")
    f = {k: d / v for k, v in names.items()}

    odo = read_table(f["odometry"], 3, time_cols=0)
    gtt = read_table(f["groundtruth"], 4, time_cols=0)
    mea = read_table(f["measurement"], 4, time_cols=0)
    lmt = read_table(f["landmark_groundtruth"], 5)
    bct = read_table(f["barcodes"], 2)

    # Barcode table: subject -> barcode, both unique.
    subj = int_column(bct, 0, "subject", lo=1, hi=ID_MAX, unique=True)
    bcode = int_column(bct, 1, "barcode", lo=0, hi=ID_MAX, unique=True)
    b2s = dict(zip(bcode.tolist(), subj.tolist()))

    lm_id = int_column(lmt, 0, "subject", lo=1, hi=ID_MAX)
    _, first, inv = np.unique(lm_id, return_index=True, return_inverse=True)
    dup = np.nonzero(first[inv] != np.arange(lm_id.size))[0]
    if dup.size:  # two surveyed positions for one landmark: which one is the truth?
        i = int(dup[0])
        raise lmt.error(i, f"landmark subject {int(lm_id[i])} listed twice (first at {lmt.where(int(first[inv[i]]))})")
    neg_std = np.nonzero(np.any(lmt.data[:, 3:5] < 0, axis=1))[0]
    if neg_std.size:  # a standard deviation is never negative (a sign lost in a conversion?)
        i = int(neg_std[0])
        raise lmt.error(i, f"landmark subject {int(lm_id[i])}: negative standard deviation "
                           f"(σx, σy) = {lmt.data[i, 3:5].tolist()}")
    robot_in_lm = np.isin(lm_id, ROBOT_SUBJECTS)
    if robot_in_lm.any():
        i = int(np.argmax(robot_in_lm))
        raise lmt.error(i, f"landmark subject {int(lm_id[i])} is a robot (subjects 1–5)")

    # Measurements: barcode -> subject; split robots / landmarks / unknown.
    mb = int_column(mea, 1, "barcode", lo=0)
    ms = np.array([b2s.get(b, -1) for b in mb.tolist()], dtype=np.int64)
    unknown = ms < 0
    if strict and unknown.any():
        i = int(np.argmax(unknown))
        raise mea.error(i, f"unknown barcode {int(mb[i])} (not in {f['barcodes'].name})")
    is_robot = np.isin(ms, ROBOT_SUBJECTS)
    # A range that is not positive cannot come from the camera: the row is dropped and named
    # (a whole log is not refused for one such row; NaN and Inf are refused by the reader).
    bad_range = mea.data[:, 2] <= 0
    is_lm = ~unknown & ~is_robot & ~bad_range

    # Duplicates and repeats (counted on all rows, in file order).
    m = mea.data
    seen, dup_rows = {}, 0
    last_reading, repeats = {}, 0
    for t, b, r, br in m.tolist():
        key = (b, r, br)
        s = seen.setdefault(t, set())
        if key in s:
            dup_rows += 1
        s.add(key)
        if last_reading.get(b) == (r, br):
            repeats += 1
        last_reading[b] = (r, br)

    t0 = float(gtt.data[0, 0])

    def rel(t):
        return np.round(t - t0, _TIME_DECIMALS)

    odom_t = rel(odo.data[:, 0])
    dup_t = np.nonzero(np.diff(odo.data[:, 0]) == 0)[0] + 1
    meas_t_all = rel(m[:, 0])
    gt_t = rel(gtt.data[:, 0])
    t_end = float(max(odom_t[-1], gt_t[-1], meas_t_all[-1]))

    report = {
        "dataset": "mrclam",
        "robot": robot,
        "dir": str(d),
        "rows": {k: int(t.data.shape[0]) for k, t in
                 (("odometry", odo), ("groundtruth", gtt), ("measurement", mea),
                  ("landmark_groundtruth", lmt), ("barcodes", bct))},
        "landmark_rows": int(is_lm.sum()),
        "robot_rows": int(is_robot.sum()),
        "unknown_barcode_rows": int(unknown.sum()),
        "unknown_barcodes": [int(b) for b in mb[unknown]],
        "unknown_barcode_lines": [mea.where(int(i)) for i in np.nonzero(unknown)[0]],
        "nonpositive_range_rows": int(bad_range.sum()),
        "nonpositive_range_lines": [mea.where(int(i)) for i in np.nonzero(bad_range)[0]],
        "duplicate_rows": int(dup_rows),
        "repeated_readings": int(repeats),
        "distinct_measurement_times": int(np.unique(m[:, 0]).size),
        "distinct_landmark_times": int(np.unique(m[is_lm, 0]).size),
        "landmarks_seen": int(np.unique(ms[is_lm]).size),
        "odometry_duplicate_times": [float(x) for x in odom_t[dup_t]],
        "odometry_duplicate_lines": [odo.where(int(i)) for i in dup_t],
        "t0": t0,
        "t_end": t_end,
    }
    return MrclamData(
        robot=robot,
        t0=t0,
        odom_t=odom_t,
        odom=np.ascontiguousarray(odo.data[:, 1:3]),
        gt_t=gt_t,
        gt=np.ascontiguousarray(gtt.data[:, 1:4]),
        meas_t=meas_t_all[is_lm],
        meas=np.ascontiguousarray(m[is_lm][:, 2:4]),
        meas_id=ms[is_lm].astype(np.int32),
        landmark_id=lm_id.astype(np.int32),
        landmark_xy=np.ascontiguousarray(lmt.data[:, 1:3]),
        landmark_std=np.ascontiguousarray(lmt.data[:, 3:5]),
        barcodes=np.stack([subj, bcode], axis=1).astype(np.int32),
        report=report,
    )
