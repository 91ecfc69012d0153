"""Real-dataset loaders (host-side NumPy) and the event-log merge for ``lax.scan``.

Loaders take the dataset folder (or a parent holding it) as an argument; the
package never needs a fixed data location.  Every malformed file raises
:class:`DataFormatError` with ``file:line`` in its message; a missing file or
folder raises :class:`MissingDataError` (also a ``FileNotFoundError``).

============================  ==================================================
``"mrclam"``                  :func:`load_mrclam` — UTIAS MRCLAM (Leung et al.,
                              IJRR 2011): odometry, camera range-bearing to
                              barcoded landmarks, Vicon ground truth
``"victoria-park"``           :func:`load_victoria_park` — ACFR Victoria Park
                              (Guivant & Nebot 2001): Ackermann inputs, laser
                              tree detections, GPS
``"util-uwb"``                :func:`load_util` — UTIL UWB (Zhao et al., IJRR
                              2024): UWB TWR/TDOA, IMU, Vicon, anchors
``"plaza"``                   :func:`load_plaza` — CMU Plaza 1/2 range-only
                              data (Djugash, Singh, Kantor et al.)
============================  ==================================================

:func:`merge_events` turns an input stream and a measurement stream into one
fixed-shape :class:`EventLog`.
"""

from .events import EventLog, merge_events
from .mrclam import MrclamData, load_mrclam
from .plaza import PlazaData, load_plaza
from .textfile import DataFormatError, MissingDataError, read_table
from .util_uwb import TAG_OFFSET, UtilData, load_util, tag_positions
from .victoria_park import AckermannGeometry, VictoriaParkData, load_victoria_park

DATASETS = ("mrclam", "victoria-park", "util-uwb", "plaza")

__all__ = [
    "DATASETS",
    "DataFormatError",
    "MissingDataError",
    "read_table",
    "EventLog",
    "merge_events",
    "MrclamData",
    "load_mrclam",
    "VictoriaParkData",
    "AckermannGeometry",
    "load_victoria_park",
    "PlazaData",
    "load_plaza",
    "UtilData",
    "load_util",
    "tag_positions",
    "TAG_OFFSET",
]
