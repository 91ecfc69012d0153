"""Flight plots: 3D path vs reference, position / attitude / inputs over time.

Matplotlib is imported lazily (Agg backend) so importing jaxslam never pulls it in.
Every function takes NumPy arrays, returns the Figure, and ``save`` writes PNGs.
"""

from __future__ import annotations

import contextlib
import os
import pathlib

import numpy as np

from jaxslam.errors import InputError
from jaxslam.files import atomic_write, prepare_dir
from jaxslam.linalg import check_numbers

__all__ = ["plt", "save", "keep_margins", "trajectory_3d", "states_over_time", "inputs_over_time"]


def _columns(x, name: str, cols: int, rows=None):
    """``x`` as a float (T, ≥ ``cols``) array (``rows``: T required), else InputError naming ``name``."""
    if x is None:
        raise InputError(f"{name}: expected a (T, {cols}) array, got None")
    a = check_numbers(x, name)
    if a.ndim != 2 or a.shape[1] < cols:
        raise InputError(f"{name}: expected shape (T, {cols}" + ("+" if cols > 1 else "") + f"), got {a.shape}")
    if rows is not None and a.shape[0] != rows:
        raise InputError(f"{name}: expected {rows} rows (one per time), got {a.shape[0]}")
    return a


def _points(x, name: str):
    """Optional (n, 3) points: None or an empty sequence as None, else :func:`_columns` (a
    scalar or a string is an InputError naming ``name``; ``len`` failed on it with a TypeError)."""
    if x is None:
        return None
    try:
        if not len(x):
            return None
    except TypeError:  # no length (a scalar): _columns names it
        pass
    return _columns(x, name, 3)


def _times(t):
    """``t`` as a float (T,) array of times, else InputError naming ``t`` (a string, even "1.5",
    is not a time)."""
    t = check_numbers(t, "t")
    if t.ndim != 1:
        raise InputError(f"t: expected shape (T,), got {t.shape}")
    return t


def plt():
    """matplotlib.pyplot with the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as _plt

    return _plt


def _output_dir(directory, probe: bool = False) -> pathlib.Path:
    """``directory`` as the Path of a folder, made (with its parents) when missing; with
    ``probe`` also checked writable by creating and removing a file in it
    (:func:`jaxslam.files.prepare_dir`), as every ``plot_all`` does before it draws anything.
    Else :class:`InputError` naming ``directory``."""
    if directory is None:
        raise InputError("directory: expected a folder path, got None")
    if not isinstance(directory, (str, os.PathLike)):
        raise InputError(f"directory: expected a folder path, got {directory!r}"[:300])
    d = pathlib.Path(directory)
    try:
        if d.exists() and not d.is_dir():
            raise InputError(f"directory: {str(d)!r} is a file, not a folder")
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"directory: cannot create {str(d)!r}: {e.strerror or e}") from None
    if probe:
        prepare_dir("directory", d)
    return d


@contextlib.contextmanager
def closing_on_error():
    """Close the figures opened inside the block when it raises (a check that fails halfway
    through a ``plot_all``, e.g. a covariance that is not PSD, left its figure open in pyplot)."""
    p = plt()
    before = set(p.get_fignums())
    try:
        yield p
    except BaseException:
        for n in set(p.get_fignums()) - before:
            p.close(n)
        raise


def save(fig, directory, name) -> pathlib.Path:
    """Save ``fig`` as ``directory/name.png`` (directory created, written atomically), close it.

    The figure is drawn once: ``bbox_inches="tight"`` (and the layout engines) draw it
    twice to measure it, which was 0.45 s of every figure here; margins are set instead
    (``subplots_adjust``, fixed in inches with room for a suptitle, unless a layout engine is
    already set).  A folder that cannot be written (or a full disk) is an :class:`InputError`
    naming ``directory`` and the file (also the ``OSError`` it came from: ``errno``,
    ``strerror``); a folder already at ``directory/name.png`` one naming ``name``.
    """
    if not hasattr(fig, "savefig"):
        raise InputError(f"fig: expected a matplotlib Figure, got {type(fig).__name__}")
    if directory is None:
        raise InputError("directory: expected a folder path, got None")
    if not isinstance(name, str) or not name or pathlib.Path(name).name != name:
        raise InputError(f"name: expected a plain file name (no folder part), got {name!r}")
    d = _output_dir(directory)
    path = d / f"{name}.png"
    try:
        taken = path.is_dir()  # a folder already named name.png: the name is at fault, not directory
    except OSError:
        taken = False  # (atomic_write names the folder that cannot be searched)
    if taken:  # (refused as the name checks above: the figure stays open for another name)
        raise InputError(f"name: {str(path)!r} is a folder; give another file name")
    if fig.get_layout_engine() is None:
        # margins in inches (tick labels, axis label, titles), as fractions of this figure: a
        # fixed fraction clipped the axis labels and titles of the smaller figures
        w, h = fig.get_size_inches()
        top_in = 0.75 if fig.get_suptitle() else 0.4
        fig.subplots_adjust(left=min(0.8 / w, 0.2), right=1.0 - min(0.25 / w, 0.05), bottom=min(0.6 / h, 0.2),
                            top=1.0 - min(top_in / h, 0.2), hspace=0.4, wspace=0.3)
    try:  # atomically: an interrupted plot never leaves a truncated PNG
        atomic_write(path, lambda f: fig.savefig(f, dpi=110, format="png"), mode="wb", name="directory")
    finally:
        plt().close(fig)
    return path


def keep_margins(fig, **margins):
    """Fix the margins of ``fig``'s subplot grids (``left``, ``right``, ``bottom``, ``top``,
    ``wspace``, ``hspace``) so that :func:`jaxslam.plotting.flight.save`'s default
    ``subplots_adjust`` leaves them alone: they are set on each grid, which then ignores the
    figure's.  No layout engine is set, so the figure is still drawn once."""
    grids = []
    for ax in fig.axes:
        spec = ax.get_subplotspec()
        if spec is not None:
            gs = spec.get_topmost_subplotspec().get_gridspec()
            if all(gs is not g for g in grids):
                grids.append(gs)
    for gs in grids:
        gs.update(**margins)
    return fig


def _ned_to_enu_up(p):
    """Plot coordinates: north, east, altitude (−z) so 'up' is up on screen."""
    return p[..., 0], p[..., 1], -p[..., 2]


def trajectory_3d(truth_pos, ref_pos, est_pos=None, landmarks=None, est_landmarks=None,
                  title="Trajectory"):
    """3D path: true (solid), desired (dash-dot), estimated (dashed), landmarks.

    ``landmarks`` / ``est_landmarks``: (n, 3+) points, or None / empty to leave them out."""
    truth_pos, ref_pos = _columns(truth_pos, "truth_pos", 3), _columns(ref_pos, "ref_pos", 3)
    if est_pos is not None:
        est_pos = _columns(est_pos, "est_pos", 3)
    landmarks = _points(landmarks, "landmarks")
    est_landmarks = _points(est_landmarks, "est_landmarks")
    p = plt()
    fig = p.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*_ned_to_enu_up(ref_pos), "k-.", lw=1, label="desired")
    ax.plot(*_ned_to_enu_up(truth_pos), "C0-", lw=1.5, label="true")
    if est_pos is not None:
        ax.plot(*_ned_to_enu_up(est_pos), "C1--", lw=1.2, label="estimated")
    if landmarks is not None and len(landmarks):
        ax.scatter(*_ned_to_enu_up(landmarks), c="g", marker="^", s=25, label="landmarks (true)")
    if est_landmarks is not None and len(est_landmarks):
        ax.scatter(*_ned_to_enu_up(est_landmarks), c="r", marker="x", s=25, label="landmarks (est.)")
    ax.set_xlabel("north [m]")
    ax.set_ylabel("east [m]")
    ax.set_zlabel("altitude [m]")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=8)
    return fig


def states_over_time(t, truth, ref, title="Tracking"):
    """Position vs desired, tracking error, Euler angles (deg) over time."""
    t = _times(t)
    truth = _columns(truth, "truth", 9, rows=t.shape[0])
    ref = _columns(ref, "ref", 4, rows=t.shape[0])
    p = plt()
    fig, axs = p.subplots(3, 1, figsize=(9, 8), sharex=True)
    names = ["north", "east", "down"]
    for i in range(3):
        axs[0].plot(t, truth[:, i], f"C{i}-", label=f"{names[i]} true")
        axs[0].plot(t, ref[:, i], f"C{i}:", label=f"{names[i]} desired")
    axs[0].set_ylabel("position [m]")
    axs[0].legend(ncol=3, fontsize=7)
    err = np.linalg.norm(truth[:, :3] - ref[:, :3], axis=1)
    axs[1].semilogy(t, np.maximum(err, 1e-6), "k-")
    axs[1].set_ylabel("‖ρ − ρ_d‖ [m]")
    axs[1].grid(True, which="both", alpha=0.3)
    for i, n in enumerate(["φ", "θ", "ψ"]):
        axs[2].plot(t, np.degrees(truth[:, 6 + i]), f"C{i}-", label=n)
    axs[2].plot(t, np.degrees(ref[:, 3]), "C2:", label="ψ desired")
    axs[2].set_ylabel("attitude [deg]")
    axs[2].set_xlabel("time [s]")
    axs[2].legend(ncol=4, fontsize=7)
    fig.suptitle(title)
    return fig


def inputs_over_time(t, u, title="Inputs"):
    """Thrust [N] and torques [N m] over time."""
    t = _times(t)
    u = _columns(u, "u", 4, rows=t.shape[0])
    p = plt()
    fig, axs = p.subplots(2, 1, figsize=(9, 5), sharex=True)
    axs[0].plot(t, u[:, 0], "k-")
    axs[0].set_ylabel("thrust f_T [N]")
    for i, n in enumerate(["τ_φ", "τ_θ", "τ_ψ"]):
        axs[1].plot(t, u[:, 1 + i], f"C{i}-", label=n)
    axs[1].set_ylabel("torque [N m]")
    axs[1].set_xlabel("time [s]")
    axs[1].legend(ncol=3, fontsize=7)
    fig.suptitle(title)
    return fig
