"""The real datasets jaxslam runs, where they are, and which of them a folder holds.

One table (:data:`DATASETS`) feeds ``jaxslam list``, ``jaxslam dataset --help`` and the early
checks of ``jaxslam dataset`` / ``jaxslam tune``: the data root is ``--data DIR``, else the
environment variable ``JAXSLAM_DATA_DIR``; a ``--robot`` the folder does not hold is refused
with the robots it does hold, before any file is parsed or anything is compiled.

Standard library only (file names, no parsing, no JAX); the loaders read the files.
"""

from __future__ import annotations

import os
import pathlib
import re
from collections.abc import Mapping
from typing import NamedTuple, Optional


from ..errors import InputError, check_flag, check_int

__all__ = ["DATA_ENV", "Dataset", "DATASETS", "OPTION_DEFAULTS", "APPLIES", "data_root", "find",
           "robots_found", "robot_list", "check_robot", "check_robots", "check_options", "util_flight",
           "util_flights"]

#: environment variable naming the data root (the folder with mrclam6/, victoria_park/, ...)
DATA_ENV = "JAXSLAM_DATA_DIR"


class Dataset(NamedTuple):
    """One dataset: CLI name, the sub-folder it lives in under the data root, a one-line
    description, and the file-name pattern whose number is ``--robot`` (None: no choice)."""

    name: str
    subdir: str
    description: str
    robot_pattern: Optional[str] = None
    robot_meaning: str = ""


DATASETS = (
    Dataset("mrclam", "mrclam6",
            "UTIAS MRCLAM 6: unicycle odometry, range-bearing to 15 barcoded landmarks, Vicon truth",
            r"Robot(\d+)_Odometry\.dat", "MRCLAM robot"),
    Dataset("victoria-park", "victoria_park",
            "ACFR Victoria Park: Ackermann car, laser tree detections, unknown association, GPS"),
    Dataset("util-uwb", "util_uwb",
            "UTIL UWB TWR flight: range-only EKF with a range-bias state, Vicon truth"),
    Dataset("plaza", "gtsam",
            "CMU Plaza 1/2: odometry + range-only SLAM with unknown beacons",
            r"Plaza(\d+)_DR\.txt", "Plaza sequence"),
)

_BY_NAME = {d.name: d for d in DATASETS}

#: The options of ``jaxslam dataset`` / :func:`jaxslam.data.runners.run_dataset` with their
#: defaults, and the datasets each applies to.
OPTION_DEFAULTS = {"robot": 1, "filter": "ekf", "ids": "known", "anchors": None, "tof": False,
                   "calibrated": False, "particles": None, "seed": 0, "params": None, "smooth": False}
APPLIES = {
    "mrclam": {"robot", "filter", "ids", "calibrated", "particles", "seed", "params", "smooth"},
    "victoria-park": {"filter", "particles", "seed", "params"},
    "util-uwb": {"anchors", "tof", "smooth", "params"},
    "plaza": {"robot", "anchors", "smooth", "params"},
}


#: The values of the choice options (``anchors`` None: the dataset's default).
_CHOICES = {"filter": ("ekf", "fastslam"), "ids": ("known", "hidden"), "anchors": (None, "known", "unknown")}
_FLAGS = ("tof", "calibrated", "smooth")


def _dataset(name) -> Dataset:
    if not isinstance(name, str) or name not in _BY_NAME:
        raise InputError(f"dataset: unknown name {name!r} (choose from {', '.join(sorted(_BY_NAME))})"[:300])
    return _BY_NAME[name]


def _given(key, value) -> bool:
    """``value`` differs from the option's default (an array, whose ``!=`` has no single truth
    value, counts as given)."""
    default = OPTION_DEFAULTS[key]
    if value is default:
        return False
    try:
        return not bool(value == default)
    except (TypeError, ValueError):
        return True


def check_options(name: str, options: dict) -> None:
    """Refuse an option set away from its default for a dataset it does not apply to (never
    silently ignored), ``--particles`` / ``--seed`` without ``--filter fastslam``, and
    ``--params`` with it; and a value an option does not take: ``filter`` "ekf" | "fastslam",
    ``ids`` "known" | "hidden", ``anchors`` None | "known" | "unknown", ``robot`` an int >= 1,
    ``tof`` / ``calibrated`` / ``smooth`` True | False (a misspelt choice used to run another
    method).  Raises :class:`InputError` naming the dataset and the options."""
    _dataset(name)
    unknown = set(options) - set(OPTION_DEFAULTS)
    if unknown:
        raise InputError(f"dataset: unknown option(s) {sorted(unknown, key=str)}")
    for k, allowed in _CHOICES.items():
        v = options.get(k, OPTION_DEFAULTS[k])
        if not (v is None or isinstance(v, str)) or v not in allowed:
            raise InputError(f"{name}: --{k}: expected one of {', '.join(map(repr, allowed))}, got {v!r}"[:300])
    if "robot" in options:
        check_int(options["robot"], f"{name}: --robot", 1)
    for k in _FLAGS:  # (a string "no" is truthy)
        check_flag(options.get(k, OPTION_DEFAULTS[k]), f"{name}: --{k}")
    misplaced = [k for k, v in options.items() if _given(k, v) and k not in APPLIES[name]]
    fastslam = options.get("filter", "ekf") == "fastslam"
    if not fastslam:
        misplaced += [k for k in ("particles", "seed") if _given(k, options.get(k, OPTION_DEFAULTS[k]))]
    # An option the dataset does not take is named first: util-uwb --filter fastslam --params
    # was told "--params ... does not apply to --filter fastslam" (util-uwb has no such filter).
    if misplaced:
        flags = ", ".join("--" + k for k in sorted(set(misplaced)))
        hint = (" (range-only logs run the EKF only: the particle core registers range-bearing "
                "landmarks)" if "filter" in misplaced else "")
        raise InputError(f"{name}: {flags} do(es) not apply here; {name} takes "
                         f"{', '.join('--' + k for k in sorted(APPLIES[name]))}"
                         + (" (--particles/--seed with --filter fastslam)" if "particles" in APPLIES[name] else "")
                         + hint)
    if fastslam and options.get("params") is not None:
        raise InputError(f"{name}: --params sets the EKF's noise; it does not apply to --filter fastslam")
    if fastslam and options.get("smooth"):
        raise InputError(f"{name}: --smooth smooths the EKF's run; it does not apply to --filter fastslam")
    if options.get("smooth") and options.get("ids") == "hidden":
        # nearest-neighbour registrations carry no landmark id, which the map-static smoother
        # needs to pair a step's map with the final one
        raise InputError(f"{name}: --smooth needs known landmark ids; it does not combine with --ids hidden")


def data_root(value, flag: str = "--data") -> pathlib.Path:
    """The data root: ``value`` (the ``--data`` argument), else ``$JAXSLAM_DATA_DIR``.

    Raises:
      InputError: neither is given, ``value`` is not a path (str or os.PathLike), or the folder
        does not exist.
    """
    source = flag
    if value is not None and not isinstance(value, (str, os.PathLike)):  # (5 raised a bare TypeError)
        raise InputError(f"{flag}: expected a folder path (str or os.PathLike), got {value!r}"[:300])
    if not value:
        value, source = os.environ.get(DATA_ENV, "").strip(), f"${DATA_ENV}"
        if not value:
            raise InputError(f"{flag}: the dataset folder is required (give {flag} DIR or set "
                             f"{DATA_ENV}=DIR, the folder holding mrclam6/, victoria_park/, ...)")
    p = pathlib.Path(value).expanduser()
    if not p.is_dir():
        raise InputError(f"{source}: {str(p)!r} is not a folder")
    return p


def find(name: str, root) -> Optional[pathlib.Path]:
    """The folder of dataset ``name`` under ``root`` (``root`` itself or ``root/subdir``), or None.

    Raises :class:`InputError` for an unknown ``name`` or a ``root`` that is not a path."""
    d = _dataset(name)
    if not isinstance(root, (str, os.PathLike)):
        raise InputError(f"root: expected a folder path (str or os.PathLike), got {root!r}"[:300])
    root = pathlib.Path(root)
    for cand in ((root,) if root.name == d.subdir else (root / d.subdir, root)):
        if cand.is_dir() and _holds(d, cand):
            return cand
    return None


def _holds(d: Dataset, folder: pathlib.Path) -> bool:
    if d.robot_pattern is not None:
        return bool(_robots_in(d, folder))
    if d.name == "victoria-park":
        return (folder / "measurements.dat").is_file()
    if d.name == "util-uwb":  # the folder of the flights, or one flight's folder itself
        return util_flight(folder) or bool(util_flights(folder))
    return False


#: what a UTIL flight folder's name holds (``twr_obs_log1``, ``tdoa2_obs_log1``), and the file it holds
UTIL_FLIGHT_NAME, UTIL_FLIGHT_FILE = "_obs_log", "groundtruth.csv"


def util_flight(folder) -> bool:
    """``folder`` is a UTIL flight folder: the one rule of this catalogue and of the UTIL loader's
    list of the flights it found (:func:`jaxslam.data.util_uwb.load_util`).

    A folder named ``*_obs_log*`` — as given or as it resolves to (``.`` inside a flight, a link
    to one), as the loader takes a flight folder given itself — holding ``groundtruth.csv``
    itself or in a subfolder (a twice-nested unzip, ``twr_obs_log1/twr_obs_log1/``: the loader
    reads the one subfolder holding the files).  A file, or an empty folder, of such a name is
    not one; nor is a folder that cannot be read.
    """
    try:
        folder = pathlib.Path(folder)
        if not folder.is_dir():
            return False
        if UTIL_FLIGHT_NAME not in folder.name:  # "." / ".." / a link: the name of the folder it is
            elsewhere = folder.name in ("", "..") or folder.is_symlink()
            if not (elsewhere and UTIL_FLIGHT_NAME in folder.resolve().name):
                return False
        return (folder / UTIL_FLIGHT_FILE).is_file() or any(
            c.is_dir() and (c / UTIL_FLIGHT_FILE).is_file() for c in folder.iterdir())
    except (OSError, RuntimeError, TypeError, ValueError):  # unreadable, a link loop, not a path
        return False


def util_flights(folder) -> list:
    """The UTIL flight folders (:func:`util_flight`) in ``folder``, by name ([] if it cannot be read)."""
    try:
        return sorted((c for c in pathlib.Path(folder).iterdir() if util_flight(c)), key=lambda c: c.name)
    except (OSError, RuntimeError, TypeError, ValueError):
        return []


def _robots_in(d: Dataset, folder: pathlib.Path) -> list:
    pat = re.compile(d.robot_pattern)
    found = set()
    try:
        for entry in folder.iterdir():
            m = pat.fullmatch(entry.name)
            # only the names the loaders open: Robot1_…, not Robot01_… (read as 1) or Robot0_…
            if m and m.group(1) == str(int(m.group(1))) and int(m.group(1)) >= 1:
                found.add(int(m.group(1)))
    except OSError:
        return []
    return sorted(found)


def robots_found(name: str, root) -> list:
    """The ``--robot`` numbers dataset ``name`` has under ``root`` ([] if none or not applicable)."""
    d = _dataset(name)
    folder = find(name, root)
    return [] if folder is None or d.robot_pattern is None else _robots_in(d, folder)


def robot_list(value, name: str, flag: str = "", *, allow_empty: bool = True, unique: bool = True) -> tuple:
    """``value`` (robot / sequence numbers: a list, tuple, range, generator or any other iterable
    but a string, bytes or a mapping) as a tuple of ints >= 1, else :class:`InputError` naming
    ``name`` (and, when given, the CLI ``flag``): a string ("12" read as robots 1 and 2), a
    mapping, a fractional number (1.7 truncated to robot 1), with ``unique`` a repeated robot
    (trained on twice) or, unless ``allow_empty``, no robot.  Whether the robots are in a
    folder is :func:`check_robots`'s question."""
    hint = f" ({flag})" if flag else ""
    items = None
    if not isinstance(value, (str, bytes, Mapping)):
        try:
            items = tuple(value)
        except TypeError:  # not iterable (a number, None, a 0-d array)
            items = None
    if items is None:
        raise InputError(f"{name}: expected a list of robot numbers{hint}, got {value!r}"[:300])
    what = f"robot numbers{hint}: ints" if flag else "an int"
    out = tuple(check_int(r, name, 1, what=what) for r in items)
    dup = sorted({r for r in out if out.count(r) > 1}) if unique else []
    if dup:
        raise InputError(f"{name}: robot(s) {dup} listed more than once{hint}")
    if not out and not allow_empty:
        raise InputError(f"{name}: give at least one robot{hint}")
    return out


def check_robots(name: str, root, robots, flag: str = "--robots") -> None:
    """:func:`check_robot` for each of ``robots`` (a :func:`robot_list`, repeats allowed: a
    training and a held-out list together)."""
    for r in robot_list(robots, flag, unique=False):  # "13" was checked digit by digit
        check_robot(name, root, r, flag=flag)


def check_robot(name: str, root, robot: int, flag: str = "--robot") -> None:
    """Refuse a robot number the folder does not hold, naming those it does hold.

    A dataset without robots, or a folder where the dataset is not found at all (the loader
    then says which files it looked for), is left to the loader.
    """
    d = _dataset(name)
    robot = check_int(robot, flag, 1)  # "1" was "not in the folder (found: 1, 2)"
    if d.robot_pattern is None or find(name, root) is None:
        return
    have = robots_found(name, root)
    if robot not in have:
        raise InputError(f"{flag}: {d.robot_meaning} {robot} is not in {str(find(name, root))!r} "
                         f"(found: {', '.join(map(str, have))})")
