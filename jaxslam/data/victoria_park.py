"""Victoria Park (Sydney) loader: Ackermann car, laser tree detections, GPS.

Origin: J. Guivant, E. Nebot, "Optimization of the simultaneous localization
and map-building algorithm for real-time implementation", *IEEE Trans.
Robotics and Automation* 17(3):242–257, 2001; data of the Australian Centre
for Field Robotics (ACFR), University of Sydney.  The ``.dat`` files are those
of K. Leung and F. Inostroza's RFS-SLAM (``data/VictoriaPark``), made by its
``DataConvert_Matlab_to_ASCII.m`` (ACFR ``detectTrees`` run on every laser
scan).  No licence is stated for the data; cite Guivant and Nebot.

Files read (whitespace-separated; times in s since the first message of the
log, shared by all files):

=====================  ===================================================
``inputs.dat``         time, encoder speed v_e [m/s] (rear-left wheel),
                       steering α [rad]; 40 Hz
``measurements.dat``   time, range [m], bearing [rad] **laser frame, 0…π**
                       (π/2 straight ahead), tree diameter [m]; one row per
                       detected tree, all rows of a scan share its time
``gps.dat``            time, x [m], y [m] in (roughly) the vehicle's
                       starting frame; nominally 5 Hz, with dropouts
=====================  ===================================================

Quirks handled / documented:

* Bearings are returned both raw (``det_bearing_laser``, 0…π) and relative to
  the vehicle heading: ``bearing − π/2`` (in ``det[:, 1]``), as RFS-SLAM's
  ``MeasurementModel_VictoriaPark`` does.
* A detection with a range <= 0 m or a laser bearing outside 0…π contradicts
  the format above: :class:`DataFormatError` at its ``file:line``.
* Scans without any detected tree leave no row, so ``report["scans"]``
  counts the scans *with* detections (distinct times): 7230 in the full file.
* The vehicle model's geometry (RFS-SLAM ``cfg`` files, ACFR Ute notes) is in
  :class:`AckermannGeometry`: the state (x, y, φ) is the *laser's* position
  with the vehicle heading, and with ``v_c = v_e / (1 − tan α · H/L)``::

      ẋ = v_c cos φ − (v_c/L) tan α (a sin φ + b cos φ)
      ẏ = v_c sin φ + (v_c/L) tan α (a cos φ − b sin φ)
      φ̇ = (v_c/L) tan α

  RFS-SLAM holds each input until the next input time (Euler steps).
* GPS gives position only; it starts at about (−2.0, −1.9) m while the laser
  pose starts at (0, 0, 0), and its rotation into the odometry frame is
  approximate: align (SE(2)) before computing an error against it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..dynamics.planar import AckermannGeometry  # the model's geometry, one definition
from .textfile import read_table, resolve_dataset_dir

__all__ = ["AckermannGeometry", "VictoriaParkData", "load_victoria_park", "FILES"]

FILES = {"inputs": "inputs.dat", "measurements": "measurements.dat", "gps": "gps.dat"}


class VictoriaParkData(NamedTuple):
    """Victoria Park streams (NumPy; times in s since the log's first message).

    input_t: (N,); inputs: (N, 2) [encoder speed v_e m/s, steering α rad].
    det_t: (K,) detection times (rows of one scan share a time);
    det: (K, 2) [range m, bearing rad relative to the vehicle heading
      (= laser bearing − π/2)]; det_bearing_laser: (K,) raw laser-frame
      bearing (0…π); det_diameter: (K,) tree diameter [m].
    gps_t: (G,); gps: (G, 2) [x m, y m].
    geometry: :class:`AckermannGeometry`.
    report: counts (see :func:`load_victoria_park`).
    """

    input_t: np.ndarray
    inputs: np.ndarray
    det_t: np.ndarray
    det: np.ndarray
    det_bearing_laser: np.ndarray
    det_diameter: np.ndarray
    gps_t: np.ndarray
    gps: np.ndarray
    geometry: AckermannGeometry
    report: dict


def _check_detections(mea) -> None:
    """The documented format of ``measurements.dat``: a range is a distance (> 0 m) and the laser
    bearing lies in 0…π (the shipped log: 1.48–75.3 m, 0.113–3.089 rad).  A row outside that —
    a sign lost, a bearing in degrees or already relative to the heading — is a malformed file:
    :class:`DataFormatError` at its ``file:line`` (it was read silently before)."""
    r, b = mea.data[:, 1], mea.data[:, 2]
    bad_r = ~(r > 0)
    if bad_r.any():
        i = int(np.argmax(bad_r))
        raise mea.error(i, f"range (column 2): expected a positive distance [m], got {float(r[i])!r}")
    bad_b = ~((b >= 0) & (b <= np.pi))
    if bad_b.any():
        i = int(np.argmax(bad_b))
        raise mea.error(i, f"bearing (column 3): expected a laser-frame angle in [0, pi] rad, got {float(b[i])!r}")


def load_victoria_park(path) -> VictoriaParkData:
    """Load Victoria Park from ``inputs.dat``, ``measurements.dat``, ``gps.dat``.

    Args:
      path: the ``victoria_park`` folder or a parent that contains it.

    Returns:
      :class:`VictoriaParkData`; ``report`` holds ``dir``, ``rows`` (per file),
      ``detections``, ``scans`` (scans with at least one detection = distinct
      detection times), ``max_detections_per_scan``, ``t_start``/``t_end``.

    Raises:
      MissingDataError: a file is missing (the folders looked in are listed).
      DataFormatError: a malformed file (``file:line`` in the message),
        including time going backwards in any file, and a detection whose range
        is not positive or whose laser bearing lies outside 0…π (the documented
        format of ``measurements.dat``).
    """
    d = resolve_dataset_dir(path, "victoria_park", list(FILES.values()), "Victoria Park")
    inp = read_table(d / FILES["inputs"], 3, time_cols=0)
    mea = read_table(d / FILES["measurements"], 4, time_cols=0)
    gps = read_table(d / FILES["gps"], 3, time_cols=0)
    _check_detections(mea)
    det_t = mea.data[:, 0].copy()
    _, counts = np.unique(det_t, return_counts=True)
    bearing_laser = mea.data[:, 2].copy()
    det = np.stack([mea.data[:, 1], bearing_laser - np.pi / 2], axis=1)
    report = {
        "dataset": "victoria-park",
        "dir": str(d),
        "rows": {"inputs": int(inp.data.shape[0]), "measurements": int(mea.data.shape[0]),
                 "gps": int(gps.data.shape[0])},
        "detections": int(mea.data.shape[0]),
        "scans": int(counts.size),
        "max_detections_per_scan": int(counts.max()),
        "t_start": float(min(inp.data[0, 0], det_t[0], gps.data[0, 0])),
        "t_end": float(max(inp.data[-1, 0], det_t[-1], gps.data[-1, 0])),
    }
    return VictoriaParkData(
        input_t=inp.data[:, 0].copy(),
        inputs=np.ascontiguousarray(inp.data[:, 1:3]),
        det_t=det_t,
        det=det,
        det_bearing_laser=bearing_laser,
        det_diameter=mea.data[:, 3].copy(),
        gps_t=gps.data[:, 0].copy(),
        gps=np.ascontiguousarray(gps.data[:, 1:3]),
        geometry=AckermannGeometry(),
        report=report,
    )
