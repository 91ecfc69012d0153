"""Plots of paper 004's sliding-mode attitude runs (ch. 3.4 and 6.1).

* ``*_attitude``: Euler angles (eq. 3.4, deg), angular velocity (rad/s) and torques
  (N m) over time, with the desired angles and the torque limit (Figs 3.2-3.4);
* ``*_state_error``: 10 log10 of |Euler-angle error| (deg; roll and yaw errors wrapped into
  ±180°) and |ω error| (rad/s), as app. B plots them (Figs 3.5-3.7);
* ``*_error``: error quaternion q_e = q ⊗ q_d* (canonical sign, Fig. 6.7), axis-angle
  error θ_e = 2 ln q_e in degrees (Fig. 6.8) and 10 log10(|θ_e,i| in degrees), the
  "decibel" view (Fig. 6.9).

NumPy inputs; matplotlib is imported lazily (Agg).  Long runs are decimated to at most
``max_points`` samples per line (plots only; metrics use every step).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..linalg import check_int, check_numbers, check_scalar
from .flight import _output_dir, plt, save

__all__ = ["plot_all", "db"]

_FLOOR_DB = -120.0


def db(a):
    """10 log10(|a|), floored at −120 dB so exact zeros stay plottable."""
    a = np.abs(np.asarray(a, float))
    with np.errstate(divide="ignore"):
        return np.maximum(10.0 * np.log10(a), _FLOOR_DB)


def _recorded(rollout):
    """``(xa[:-1], x_err, tau)`` of a recorded rollout as arrays of T rows (T ≥ 1), else
    InputError naming the field."""
    arrays = {}
    for field, cols in (("xa", 7), ("x_err", 6), ("tau", 3)):
        if not hasattr(rollout, field):
            raise InputError(f"rollout: expected a jaxslam.control.smc.Rollout, got {type(rollout).__name__}")
        v = getattr(rollout, field)
        if v is None:
            raise InputError(f"rollout.{field}: None; record the run (closed_loop(..., record=True))")
        check_numbers(v, f"rollout.{field}")
        a = np.asarray(v)  # its own dtype (a float32 run is drawn from float32, as before)
        if a.ndim != 2 or a.shape[1] != cols:
            raise InputError(f"rollout.{field}: expected shape (T{' + 1' if field == 'xa' else ''}, {cols}), "
                             f"got {a.shape}")
        arrays[field] = a
    T = arrays["x_err"].shape[0]
    if T < 1:
        raise InputError("rollout.x_err: no steps recorded (T = 0)")
    if arrays["xa"].shape[0] != T + 1:
        raise InputError(f"rollout.xa: expected T + 1 = {T + 1} rows (x_err has T = {T}), "
                         f"got {arrays['xa'].shape[0]}")
    if arrays["tau"].shape[0] != T:
        raise InputError(f"rollout.tau: expected T = {T} rows (one per step of x_err), got {arrays['tau'].shape[0]}")
    return arrays["xa"][:-1], arrays["x_err"], arrays["tau"]


def plot_all(name, dt, rollout, q_d, directory, tau_max=None, max_points=5000):
    """Write the three figures for one recorded run; returns their paths.

    ``rollout``: :class:`jaxslam.control.smc.Rollout` recorded (``record=True``), NumPy;
    ``dt``: step, s; ``q_d``: (4,) desired attitude (finite, unit); ``tau_max``: limit to draw
    (N m); ``max_points``: most samples per line (an int >= 1).  All are checked (an
    :class:`~jaxslam.errors.InputError` naming the argument) and ``directory`` is made and
    checked writable before any figure is drawn.
    """
    from ..control.smc import validate
    from ..geometry.quaternion import euler_from_quat, qcanonical, qconj, qmul

    dt = check_scalar(dt, "dt", lower=0, strict=True)
    xa, x_err, tau = _recorded(rollout)
    q_d = check_numbers(q_d, "q_d")
    validate(q_d=q_d)  # (4,), finite, unit: the desired angles are read off it
    if tau_max is not None:
        tau_max = check_scalar(tau_max, "tau_max", lower=0, strict=True)
    max_points = check_int(max_points, "max_points", lower=1)
    _output_dir(directory, probe=True)
    p = plt()
    T = x_err.shape[0]
    stride = max(1, int(np.ceil(T / max_points)))
    sel = slice(None, None, stride)
    t = (np.arange(T) * dt)[sel]
    q = xa[sel, :4]
    w = xa[sel, 4:]
    eul = np.degrees(np.asarray(euler_from_quat(q)))
    eul_d = np.degrees(np.asarray(euler_from_quat(q_d)))
    labels = ("roll", "pitch", "yaw")
    paths = []

    # Figs 3.2-3.4: attitude, angular velocity, input torque.
    fig, axs = p.subplots(1, 3, figsize=(15, 4.2))
    for i in range(3):
        axs[0].plot(t, eul[:, i], f"C{i}-", label=labels[i])
        axs[0].axhline(eul_d[i], color=f"C{i}", ls=":", lw=0.8)
        axs[1].plot(t, w[:, i], f"C{i}-", label=f"ω{'xyz'[i]}")
        axs[2].plot(t, tau[sel, i], f"C{i}-", label=f"τ{'xyz'[i]}")
    if tau_max is not None:
        for s in (-1, 1):
            axs[2].axhline(s * tau_max, color="k", ls="--", lw=0.8)
    for ax, title, ylab in zip(axs, ("Attitude", "Angular velocity", "Input"),
                               ("angle [deg]", "angular velocity [rad/s]", "torque [N m]")):
        ax.set_title(title)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylab)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{name}: attitude, rates and torques (dotted: desired)")
    paths.append(save(fig, directory, f"{name}_attitude"))

    # Figs 3.5-3.7: state errors in dB (app. B lines 159-183).
    e_eul = eul - eul_d
    e_eul[:, 2] = (e_eul[:, 2] + 180.0) % 360.0 - 180.0
    # roll is in (−180°, 180°] too: a roll of −179° against a desired 179° is 2° off, not 358°
    # (pitch, ±90°, never wraps); rolls within 180° of the desired one are left as they were
    e_eul[:, 0] = np.where(np.abs(e_eul[:, 0]) > 180.0, (e_eul[:, 0] + 180.0) % 360.0 - 180.0, e_eul[:, 0])
    fig, axs = p.subplots(1, 2, figsize=(12, 4.2))
    for i in range(3):
        axs[0].plot(t, db(e_eul[:, i]), f"C{i}-", lw=0.8, label=f"{labels[i]} error")
        axs[1].plot(t, db(x_err[sel, 3 + i]), f"C{i}-", lw=0.8, label=f"ω{'xyz'[i]} error")
    axs[0].set_ylabel("10 log10(|attitude error|) [dB(deg)]")
    axs[1].set_ylabel("10 log10(|angular velocity error|) [dB(rad/s)]")
    for ax in axs:
        ax.set_xlabel("time [s]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{name}: state error")
    paths.append(save(fig, directory, f"{name}_state_error"))

    # Figs 6.7-6.9: error quaternion, axis-angle error, axis-angle error in dB.
    qe = np.asarray(qcanonical(qmul(q, qconj(q_d))))
    th = np.degrees(x_err[sel, :3])
    fig, axs = p.subplots(3, 1, figsize=(9, 10), sharex=True)
    for i in range(4):
        axs[0].plot(t, qe[:, i], f"C{i}-", label=f"q_e{i}")
    for i in range(3):
        axs[1].plot(t, th[:, i], f"C{i}-", label=f"θ_e{'xyz'[i]}")
        axs[2].plot(t, db(th[:, i]), f"C{i}-", lw=0.8, label=f"θ_e{'xyz'[i]}")
    axs[1].plot(t, np.linalg.norm(th, axis=1), "k--", lw=1, label="‖θ_e‖")
    axs[2].plot(t, db(np.linalg.norm(th, axis=1)), "k--", lw=1, label="‖θ_e‖")
    axs[0].set_ylabel("error quaternion q ⊗ q_d*")
    axs[1].set_ylabel("axis-angle error [deg]")
    axs[2].set_ylabel("10 log10(|θ_e| [deg]) [dB]")
    axs[2].set_xlabel("time [s]")
    for ax in axs:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, ncol=4)
    fig.suptitle(f"{name}: attitude error (Figs 6.7-6.9 style)")
    paths.append(save(fig, directory, f"{name}_error"))
    return paths
