"""UTIL UWB (UTIAS DSL) loader: Crazyflie flights with UWB ranges, IMU, Vicon.

Origin: W. Zhao, A. Goudar, X. Qiao, A. P. Schoellig, "UTIL: An
Ultra-wideband Time-difference-of-arrival Indoor Localization Dataset",
*IJRR* 43(10):1443–1456, 2024 (github.com/utiasDSL/util-uwb-dataset).  The
two flights (``twr_obs_log1``, ``tdoa2_obs_log1``, 7 June 2021) are raw
SD-card logs from the repository's history, decoded to one CSV per stream
(float32 values kept exactly).  They use **anchor constellation 3**.  No
licence is stated; cite the IJRR paper.

Layout: ``util_uwb/anchors_const3.csv`` plus one folder per flight, named
``*_obs_log*`` (:func:`jaxslam.data.catalogue.util_flight`: the rule by which
this loader lists the flights it found and ``jaxslam list`` finds the dataset),
holding (every CSV has one header row, checked against the expected column names):

===================  =====================================================
``uwb_twr.csv``      t [s], anchor_id (0–7), range [m]  (TWR flight)
``uwb_tdoa.csv``     t [s], idA, idB, tdoa [m] = ‖p − a_B‖ − ‖p − a_A‖
                     (TDOA2 flight)
``imu.csv.gz``       t_acc, acc_x/y/z [**g**], t_gyro, gyro_x/y/z
                     [**deg/s**]; body frame, about 1 kHz
``groundtruth.csv``  t, x, y, z [m], qx, qy, qz, qw (body → Vicon frame),
                     about 200 Hz
``tof.csv``          t [s], tof [m]: downward laser height, about 23 Hz
                     (optional: empty arrays when the file is absent)
===================  =====================================================

Units converted here: acceleration × :data:`G` (9.81) → m/s², gyro
deg/s → rad/s.  Quaternions stay in (qx, qy, qz, qw) order.

Times are seconds since the first event of that flight's log (each flight
has its own origin).  The UWB tag sits at :data:`TAG_OFFSET` in the body
frame; :func:`tag_positions` gives its position ``p + R(q)·t_uv``.

Quirks (documented, not corrected): TWR ranges have a bias of about −0.22 m
and anchors 6 and 7 heavy positive tails (obstacles block the line of sight);
the TDOA flight has a few stray anchor pairs besides the consecutive ones.
The drone sits on the ground at the start of both flights.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from .catalogue import UTIL_FLIGHT_FILE, util_flight, util_flights
from .textfile import ID_MAX, MissingDataError, int_column, path_arg, read_table, resolve_dataset_dir

__all__ = ["UtilData", "load_util", "tag_positions", "TAG_OFFSET", "G"]

TAG_OFFSET = (-0.01245, 0.00127, 0.0908)
"""UWB tag position in the body frame [m] (the repository's ESKF script)."""

G = 9.81
"""Accelerometer scale: the logs are in g; the dataset's scripts use 9.81."""


ANCHORS_FILE = "anchors_const3.csv"
_HEADERS = {
    "uwb_twr.csv": ("t", "anchor_id", "range"),
    "uwb_tdoa.csv": ("t", "idA", "idB", "tdoa"),
    "imu.csv.gz": ("t_acc", "acc_x", "acc_y", "acc_z", "t_gyro", "gyro_x", "gyro_y", "gyro_z"),
    "groundtruth.csv": ("t", "x", "y", "z", "qx", "qy", "qz", "qw"),
    "tof.csv": ("t", "tof"),
    ANCHORS_FILE: ("anchor_id", "x", "y", "z", "qx", "qy", "qz", "qw"),
}


class UtilData(NamedTuple):
    """One UTIL flight (NumPy; times in s since the log start; SI units).

    flight: folder name.
    twr_t: (R,); twr_anchor: (R,) int32; twr_range: (R,) [m]  (empty for the
      TDOA flight).
    tdoa_t: (D,); tdoa_pair: (D, 2) int32 (idA, idB); tdoa: (D,) [m]
      (empty for the TWR flight).
    imu_t: (I,) accelerometer times; imu_t_gyro: (I,) gyro times (paired row
      by row, within 0.2 ms); acc: (I, 3) [m/s²]; gyro: (I, 3) [rad/s].
    gt_t: (P,); gt_p: (P, 3) [m]; gt_q: (P, 4) (qx, qy, qz, qw), body → world.
    anchor_id: (A,) int32; anchor_p: (A, 3) [m]; anchor_q: (A, 4) (qx, qy, qz, qw).
    tag_offset: (3,) :data:`TAG_OFFSET`.
    report: counts (see :func:`load_util`).
    tof_t: (F,); tof: (F,) [m] downward laser (ToF) height readings, measured along the
      body's −z axis from the sensor (empty when ``tof.csv`` is absent).
    """

    flight: str
    twr_t: np.ndarray
    twr_anchor: np.ndarray
    twr_range: np.ndarray
    tdoa_t: np.ndarray
    tdoa_pair: np.ndarray
    tdoa: np.ndarray
    imu_t: np.ndarray
    imu_t_gyro: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray
    gt_t: np.ndarray
    gt_p: np.ndarray
    gt_q: np.ndarray
    anchor_id: np.ndarray
    anchor_p: np.ndarray
    anchor_q: np.ndarray
    tag_offset: np.ndarray
    report: dict
    tof_t: np.ndarray = np.zeros(0)
    tof: np.ndarray = np.zeros(0)

    def tag_positions(self) -> np.ndarray:
        """(P, 3) ground-truth tag positions ``gt_p + R(gt_q)·tag_offset``."""
        return tag_positions(self.gt_p, self.gt_q, self.tag_offset)


def tag_positions(p, q_xyzw, offset=TAG_OFFSET) -> np.ndarray:
    """Position of a body-fixed point: ``p + R(q)·offset`` (NumPy, broadcasts).

    Args:
      p: (..., 3) body positions.
      q_xyzw: (..., 4) body → world quaternions in (qx, qy, qz, qw) order
        (normalised here).
      offset: (3,) or (..., 3) point in the body frame; default the UWB tag.

    Raises:
      InputError: an argument is not real numbers, its last axis is not 3 (``p``, ``offset``)
        or 4 (``q_xyzw``), the leading shapes do not broadcast, or a quaternion is zero or
        not finite (it has no rotation: the result was NaN).
    """
    from ..dynamics._checks import check_last_dim, real_numbers
    from ..geometry.quaternion import qrotate

    p = check_last_dim(real_numbers(p, "p"), 3, "p")
    q = check_last_dim(real_numbers(q_xyzw, "q_xyzw"), 4, "q_xyzw")
    off = check_last_dim(real_numbers(offset, "offset"), 3, "offset")
    try:
        np.broadcast_shapes(p.shape[:-1], q.shape[:-1], off.shape[:-1])
    except ValueError:
        raise InputError(f"p, q_xyzw, offset: leading shapes {p.shape[:-1]}, {q.shape[:-1]}, {off.shape[:-1]} "
                         "do not broadcast") from None
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    bad = ~(np.isfinite(n) & (n > 0))
    if bad.any():
        i = tuple(int(j) for j in np.argwhere(bad)[0][:-1])
        raise InputError(f"q_xyzw: quaternion {q[i].tolist()}{f' at index {i}' if i else ''} is zero or not finite "
                         "(no rotation: the position would be NaN)")
    q = q / n
    # qrotate takes scalar-first quaternions.  Without x64 it rotates in float32: the offset
    # is ~0.1 m, so that costs ~1e-8 m; the positions themselves are added in float64.
    r = np.asarray(qrotate(q[..., [3, 0, 1, 2]], off), np.float64)
    return p + r


def _flight_dir(path, flight: str) -> tuple:
    base = path_arg(path)
    if base.resolve().name == flight and base.is_dir():  # the flight folder itself: its parent holds the anchors
        base = base.resolve()  # ("." has "." for its parent)
        return base.parent, base
    cands = [base, base / "util_uwb"]
    for c in cands:
        if (c / flight).is_dir():
            return c, c / flight
    # the flights found, by the catalogue's rule (catalogue.util_flight): it listed any folder holding
    # groundtruth.csv, and neither a twice-nested flight nor the folder given, which the catalogue finds
    found = {x.name for c in cands for x in util_flights(c)}
    if util_flight(base):  # a flight of another name given itself
        found.add(base.resolve().name)
    avail = sorted(found)
    raise MissingDataError(base / flight, None,
                           f"UTIL flight {flight!r} not found (looked in "
                           f"{' or '.join(str(c) for c in cands)}; flights found: {avail or 'none'})")


def load_util(path, flight: str = "twr_obs_log1") -> UtilData:
    """Load one UTIL UWB flight.

    Args:
      path: the ``util_uwb`` folder, a parent that contains it, or the flight folder itself.
      flight: the flight folder (``"twr_obs_log1"`` or ``"tdoa2_obs_log1"``).
        It must hold ``groundtruth.csv``, ``imu.csv.gz`` and at least one of
        ``uwb_twr.csv`` / ``uwb_tdoa.csv``; ``anchors_const3.csv`` lies in the
        ``util_uwb`` folder (or in the flight folder).

    Returns:
      :class:`UtilData`; ``report`` holds ``dir``, ``rows`` (per file),
      ``ranges_per_anchor`` (TWR), ``tdoa_pairs`` (``{(idA, idB): count}``),
      ``t_end`` (last time of any loaded stream), ``imu_pairing_max_dt``,
      ``tof_rows`` (rows of the optional ``tof.csv``; 0 when absent).

    Raises:
      MissingDataError: the flight folder or a file is missing (the message
        lists what was looked for and the flights found:
        :func:`jaxslam.data.catalogue.util_flight`).
      DataFormatError: a malformed file (``file:line``), a header that does not
        match the expected columns, time going backwards, an anchor listed twice
        in the anchors file, an anchor id that is not in it, or a zero quaternion
        (no rotation) in ``groundtruth.csv`` or the anchors file.
      InputError: ``path`` is not a path or ``flight`` not a folder name.
    """
    if not isinstance(flight, str) or not flight or Path(flight).name != flight or flight == "..":
        raise InputError(f"flight: expected a flight folder name such as 'twr_obs_log1', got {flight!r}"[:300])
    root, fd = _flight_dir(path, flight)
    afile = fd / ANCHORS_FILE if (fd / ANCHORS_FILE).is_file() else root / ANCHORS_FILE
    if not afile.is_file():
        raise MissingDataError(afile, None, f"UTIL anchors file not found (looked in {root} and {fd})")
    fd = resolve_dataset_dir(fd, fd.name, [UTIL_FLIGHT_FILE, "imu.csv.gz"], f"UTIL flight {flight}")
    has_twr, has_tdoa = (fd / "uwb_twr.csv").is_file(), (fd / "uwb_tdoa.csv").is_file()
    if not (has_twr or has_tdoa):
        raise MissingDataError(fd, None, "UTIL flight: missing file uwb_twr.csv or uwb_tdoa.csv "
                                         "(neither found)")

    def csv(name, n, **kw):
        return read_table((afile if name == ANCHORS_FILE else fd / name), n, delimiter=",",
                          header_rows=1, header=_HEADERS[name], **kw)

    anc = csv(ANCHORS_FILE, 8)
    # one surveyed position per anchor; ids are stored as int32
    anchor_id = int_column(anc, 0, "anchor_id", lo=0, hi=ID_MAX, unique=True)
    gt = csv("groundtruth.csv", 8, time_cols=0)
    for tab in (anc, gt):  # a zero quaternion has no rotation: tag_positions would refuse it later
        zero = np.nonzero(~(np.linalg.norm(tab.data[:, 4:8], axis=1) > 0))[0]  # without the file:line
        if zero.size:
            raise tab.error(int(zero[0]), f"zero quaternion (qx, qy, qz, qw) = {tab.data[zero[0], 4:8].tolist()} "
                                          "(no rotation)")
    imu = csv("imu.csv.gz", 8, time_cols=(0, 4))
    rows = {"anchors": int(anc.data.shape[0]), "groundtruth": int(gt.data.shape[0]),
            "imu": int(imu.data.shape[0])}
    ends = [gt.data[-1, 0], imu.data[-1, 0], imu.data[-1, 4]]
    report = {"dataset": "util-uwb", "flight": fd.name, "dir": str(fd), "anchors_file": str(afile)}

    def check_ids(tab, ids, what):
        ok = np.isin(ids, anchor_id)
        if not ok.all():
            i = int(np.argmax(~ok))
            raise tab.error(i, f"{what} {int(ids[i])} is not in {afile.name} (ids {anchor_id.tolist()})")

    twr_t, twr_a, twr_r = np.zeros(0), np.zeros(0, np.int32), np.zeros(0)
    if has_twr:
        twr = csv("uwb_twr.csv", 3, time_cols=0, allow_empty=True)
        twr_a = int_column(twr, 1, "anchor_id", lo=0)
        check_ids(twr, twr_a, "anchor id")
        twr_t, twr_r, twr_a = twr.data[:, 0].copy(), twr.data[:, 2].copy(), twr_a.astype(np.int32)
        rows["uwb_twr"] = int(twr.data.shape[0])
        ids, cnt = np.unique(twr_a, return_counts=True)
        report["ranges_per_anchor"] = dict(zip(ids.tolist(), cnt.tolist()))
        if twr_t.size:
            ends.append(twr_t[-1])
    tdoa_t, tdoa_pair, tdoa = np.zeros(0), np.zeros((0, 2), np.int32), np.zeros(0)
    if has_tdoa:
        td = csv("uwb_tdoa.csv", 4, time_cols=0, allow_empty=True)
        ia = int_column(td, 1, "idA", lo=0)
        ib = int_column(td, 2, "idB", lo=0)
        check_ids(td, ia, "idA")
        check_ids(td, ib, "idB")
        tdoa_t, tdoa = td.data[:, 0].copy(), td.data[:, 3].copy()
        tdoa_pair = np.stack([ia, ib], axis=1).astype(np.int32)
        rows["uwb_tdoa"] = int(td.data.shape[0])
        pairs, cnt = np.unique(tdoa_pair, axis=0, return_counts=True)
        report["tdoa_pairs"] = {(int(a), int(b)): int(c) for (a, b), c in zip(pairs, cnt)}
        if tdoa_t.size:
            ends.append(tdoa_t[-1])
    tof_t, tof = np.zeros(0), np.zeros(0)
    if (fd / "tof.csv").is_file():
        tf = csv("tof.csv", 2, time_cols=0, allow_empty=True)
        tof_t, tof = tf.data[:, 0].copy(), tf.data[:, 1].copy()
        if tof_t.size:
            ends.append(tof_t[-1])
    report["tof_rows"] = int(tof_t.size)
    report["rows"] = rows
    report["t_end"] = float(max(ends))
    report["imu_pairing_max_dt"] = float(np.max(np.abs(imu.data[:, 0] - imu.data[:, 4])))
    return UtilData(
        flight=fd.name,
        twr_t=twr_t,
        twr_anchor=twr_a,
        twr_range=twr_r,
        tdoa_t=tdoa_t,
        tdoa_pair=tdoa_pair,
        tdoa=tdoa,
        imu_t=imu.data[:, 0].copy(),
        imu_t_gyro=imu.data[:, 4].copy(),
        acc=imu.data[:, 1:4] * G,
        gyro=np.deg2rad(imu.data[:, 5:8]),
        gt_t=gt.data[:, 0].copy(),
        gt_p=np.ascontiguousarray(gt.data[:, 1:4]),
        gt_q=np.ascontiguousarray(gt.data[:, 4:8]),
        anchor_id=anchor_id.astype(np.int32),
        anchor_p=np.ascontiguousarray(anc.data[:, 1:4]),
        anchor_q=np.ascontiguousarray(anc.data[:, 4:8]),
        tag_offset=np.asarray(TAG_OFFSET, dtype=np.float64),
        report=report,
        tof_t=tof_t,
        tof=tof,
    )
