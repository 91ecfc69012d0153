"""CMU Plaza 1 / Plaza 2 range-only SLAM data loader (text files, not the .mat).

Origin: Carnegie Mellon Robotics Institute, range-only SLAM with sensor
networks (J. Djugash, S. Singh, G. Kantor et al.); original page
frc.ri.cmu.edu/projects/emergencyresponse/RangeData/ (format in ``log.html``).
The ``DR``/``TD`` files ship with gtsam (``gtsam/Data/``, Simplified BSD for
gtsam itself; no licence is stated for the data).  A ground vehicle carries a
radio that ranges to 4 fixed nodes (ids 0, 1, 5, 6), in the manner of UWB.

Files read (``N`` = 1 or 2; times in s on the vehicle's clock):

==================  ====================================================
``PlazaN_DR.txt``   time, distance travelled since the previous row d
                    [m], heading change dθ [rad]: odometry increments,
                    composed as ``Pose2(d, 0, dθ)`` (forward d, then turn)
``PlazaN_TD.txt``   time, sender id (2, the robot), node id, range [m]
``PlazaN_GT.txt``   time, x [m], y [m], heading [rad] (GPS ground truth;
                    one ``#`` header line; one more row than DR)
``PlazaN_DRp.txt``  time, x, y, heading: the dead-reckoned path (as GT:
                    one ``#`` header line; one more row than DR)
``PlazaN_TL.txt``   node id, x [m], y [m] (surveyed node positions)
==================  ====================================================

``DR``/``TD`` have tab-separated columns with a trailing tab and CRLF line
ends; both are accepted.

Quirks handled:

* **Plaza 2's heading is offset by π**: its GT heading points opposite to the
  direction of travel.  ``PlazaData.heading_offset`` is π for Plaza 2 and 0
  for Plaza 1, and :meth:`PlazaData.start_pose` returns
  ``(x₀, y₀, θ₀ + heading_offset)`` wrapped to (−π, π] — the pose to start
  dead reckoning from, as gtsam's examples do (``headingOffset = π``; C++
  start pose (−34.2086, 45.3008, π − 2.021089)).
* ``Plaza1_TD.txt`` is not in time order: two blocks of ranges (lines 1989
  and 2867) jump back by 64 s and 50 s.  The ranges are stably sorted by
  time; ``report["td_out_of_order_lines"]`` lists the lines where time went
  backwards.  All other files must be in time order.
* ``DR`` rows are increments, each applied once at its own time, so a repeated DR time
  (a duplicated line) would apply that motion twice: it is refused at its line (the
  shipped files never repeat a DR time).  Repeated times elsewhere are harmless.
* Ranges are biased (median +2.8 m against GT and TL) and have outliers;
  nothing is corrected here.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import InputError, check_int
from .textfile import ID_MAX, int_column, read_table, resolve_dataset_dir

__all__ = ["PlazaData", "load_plaza", "HEADING_OFFSET"]

HEADING_OFFSET = {1: 0.0, 2: float(np.pi)}
SENDER_ID = 2  # column 2 of TD: the robot's own node id (every row of both logs)


class PlazaData(NamedTuple):
    """One CMU Plaza set (NumPy; times in s on the vehicle clock).

    which: 1 or 2.
    dr_t: (N,); dr: (N, 2) [d m, dθ rad] odometry increments.
    td_t: (R,) range times (sorted); td_sender: (R,) int; td_node: (R,) int
      node id; td_range: (R,) [m].
    gt_t: (N+1,); gt: (N+1, 3) [x, y, heading] ground truth.
    drp_t: (N+1,); drp: (N+1, 3) the file's dead-reckoned path.
    node_id: (4,) int; node_xy: (4, 2) surveyed node positions [m].
    heading_offset: add to GT heading to get the direction of travel (π for
      Plaza 2, 0 for Plaza 1).
    report: counts (see :func:`load_plaza`).
    """

    which: int
    dr_t: np.ndarray
    dr: np.ndarray
    td_t: np.ndarray
    td_sender: np.ndarray
    td_node: np.ndarray
    td_range: np.ndarray
    gt_t: np.ndarray
    gt: np.ndarray
    drp_t: np.ndarray
    drp: np.ndarray
    node_id: np.ndarray
    node_xy: np.ndarray
    heading_offset: float
    report: dict

    def start_pose(self) -> np.ndarray:
        """(3,) start pose for dead reckoning: GT₀ with heading + ``heading_offset``."""
        x, y, th = self.gt[0]
        th = th + self.heading_offset
        th = float(np.arctan2(np.sin(th), np.cos(th)))
        if th <= -np.pi:  # arctan2 gives −π for a heading of −π (sin −0): the range is (−π, π]
            th = float(np.pi)
        return np.array([x, y, th])


def load_plaza(path, which: int) -> PlazaData:
    """Load CMU Plaza 1 or 2 from the ``PlazaN_*.txt`` files.

    Args:
      path: the ``gtsam`` folder holding ``PlazaN_*.txt`` or a parent that
        contains ``gtsam/``.
      which: 1 or 2.

    Returns:
      :class:`PlazaData`; ``report`` holds ``dir``, ``rows`` (per file),
      ``nodes`` (ids ranged to), ``td_out_of_order`` (count of backward time
      steps in TD) with ``td_out_of_order_lines`` (``"file:line"``), ``t_start``,
      ``t_end``.

    Raises:
      InputError: ``which`` is not the int 1 or 2, or ``path`` is not a path.
      MissingDataError: a file is missing.
      DataFormatError: a malformed file (``file:line``), time going backwards
        in DR/GT/DRp, a repeated DR time, GT or DRp not exactly one row longer
        than DR, a TD sender other than the robot (2), non-integer ids, a node
        listed twice in TL, or a range to a node absent from TL.
    """
    which_arg = which
    try:  # an int: np.True_ == 1 loaded Plaza 1, 2.0 passed as 2
        which = check_int(which, "which", 1)
    except InputError:
        which = None
    if which not in (1, 2):
        raise InputError(f"which: expected 1 or 2 (Plaza 1 or Plaza 2), got {which_arg!r}"[:300])
    names = {k: f"Plaza{which}_{k}.txt" for k in ("DR", "TD", "GT", "DRp", "TL")}
    d = resolve_dataset_dir(path, "gtsam", list(names.values()), f"CMU Plaza {which}")
    dr = read_table(d / names["DR"], 3, time_cols=0)
    td = read_table(d / names["TD"], 4)
    gt = read_table(d / names["GT"], 4, time_cols=0)
    drp = read_table(d / names["DRp"], 4, time_cols=0)
    tl = read_table(d / names["TL"], 3)
    rep = np.nonzero(np.diff(dr.data[:, 0]) == 0)[0] + 1
    if rep.size:
        i = int(rep[0])
        raise dr.error(i, f"time {float(dr.data[i, 0])!r} repeats (line {int(dr.lines[i - 1])}): DR rows "
                          "are odometry increments, so a repeated row would apply its motion twice")

    n_dr = dr.data.shape[0]
    for k, tab in (("GT", gt), ("DRp", drp)):  # the pose before the first increment, then one per DR row
        n = tab.data.shape[0]
        if n > n_dr + 1:
            raise tab.error(n_dr + 1, f"{n} rows, expected {n_dr + 1} (one more than the {n_dr} rows of "
                                      f"{names['DR']}: the start pose, then one pose per DR row)")
        if n < n_dr + 1:
            raise tab.error(n - 1, f"the file ends after {n} rows, expected {n_dr + 1} (one more than the "
                                   f"{n_dr} rows of {names['DR']}: the start pose, then one pose per DR row)")
    node_id = int_column(tl, 0, "node id", lo=0, hi=ID_MAX, unique=True)  # one surveyed position each
    sender = int_column(td, 1, "sender id", lo=0, hi=ID_MAX)
    other = np.nonzero(sender != SENDER_ID)[0]
    if other.size:  # the format has one sender, the robot: a range between two fixed nodes is not a robot range
        i = int(other[0])
        raise td.error(i, f"sender id (column 2): expected {SENDER_ID} (the robot), got {int(sender[i])}")
    node = int_column(td, 2, "node id", lo=0, hi=ID_MAX)
    known = np.isin(node, node_id)
    if not known.all():
        i = int(np.argmax(~known))
        raise td.error(i, f"range to node {int(node[i])}, which is not in {names['TL']} "
                          f"(nodes {sorted(node_id.tolist())})")
    back = np.nonzero(np.diff(td.data[:, 0]) < 0)[0] + 1
    order = np.argsort(td.data[:, 0], kind="stable")
    tdd = td.data[order]
    report = {
        "dataset": "plaza",
        "which": which,
        "dir": str(d),
        "rows": {k: int(t.data.shape[0]) for k, t in
                 (("DR", dr), ("TD", td), ("GT", gt), ("DRp", drp), ("TL", tl))},
        "nodes": sorted(np.unique(node).tolist()),
        "td_out_of_order": int(back.size),
        "td_out_of_order_lines": [td.where(int(i)) for i in back],
        "t_start": float(min(dr.data[0, 0], tdd[0, 0], gt.data[0, 0])),
        "t_end": float(max(dr.data[-1, 0], tdd[-1, 0], gt.data[-1, 0])),
    }
    return PlazaData(
        which=which,
        dr_t=dr.data[:, 0].copy(),
        dr=np.ascontiguousarray(dr.data[:, 1:3]),
        td_t=tdd[:, 0].copy(),
        td_sender=sender[order],
        td_node=node[order],
        td_range=tdd[:, 3].copy(),
        gt_t=gt.data[:, 0].copy(),
        gt=np.ascontiguousarray(gt.data[:, 1:4]),
        drp_t=drp.data[:, 0].copy(),
        drp=np.ascontiguousarray(drp.data[:, 1:4]),
        node_id=node_id,
        node_xy=np.ascontiguousarray(tl.data[:, 1:3]),
        heading_offset=HEADING_OFFSET[which],
        report=report,
    )
