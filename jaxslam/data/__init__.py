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
fixed-shape :class:`EventLog`.  The application modules :mod:`jaxslam.data.runners` (``jaxslam
dataset``) and :mod:`jaxslam.data.presets` (the MRCLAM / Victoria Park presets and log adapters
of the planar systems) import the systems and are loaded only by name.
"""

from .catalogue import DATASETS as _CATALOGUE
from .events import EventLog, merge_events
from .mrclam import MrclamData, load_mrclam
from .plaza import PlazaData, load_plaza
from .textfile import DataFormatError, MissingDataError, TruncatedLineWarning, read_table
from .util_uwb import TAG_OFFSET, UtilData, load_util, tag_positions

DATASETS = tuple(d.name for d in _CATALOGUE)

# The Victoria Park loader shares the Ackermann geometry of the motion model (a JAX module):
# imported on first use, so that the CLI's early checks (``jaxslam.data.catalogue``) run
# before JAX is imported.
_LAZY = {"AckermannGeometry", "VictoriaParkData", "load_victoria_park"}


def __getattr__(name):
    if name in _LAZY:
        from . import victoria_park

        return getattr(victoria_park, name)
    raise AttributeError(f"module 'jaxslam.data' has no attribute {name!r}")

__all__ = [
    "DATASETS",
    "DataFormatError",
    "TruncatedLineWarning",
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
