"""Development: how far could a better motion model take UTIL's range-only position?

    python scripts/study_util_motion_floor.py [DATA_DIR] [--json PATH]

An oracle study with the motion-capture truth (never used to choose anything shipped): the
TWR flight's airborne ranges are cut into windows of W seconds; inside each window the tag's
*relative* motion is taken from the truth (what a perfect IMU-driven model would know), and only
a constant 3-D offset of the window is fitted to the ranges (robust Gauss-Newton, Huber
k = 1.345 on the MAD scale).  The RMS of those offsets is the position error that even perfect
relative motion over W seconds leaves.  Three range models:

* ``common_bias_true``: one range bias for the flight, the median residual against the truth;
* ``common_bias_fitted``: the bias fitted in each window with the offset (what a filter does);
* ``per_anchor_true``: each anchor's own median residual against the truth.

The constant-velocity filter that ships (0.213 m airborne RMSE) averages over about a second.
Output: printed table and, with ``--json``, the figures (docs/datasets.md, UTIL section).
"""

import json
import os

import numpy as np

from jaxslam.cli.common import ScriptParser, one_line, path_arg
from jaxslam.data.util_uwb import load_util
from jaxslam.errors import InputError

WINDOWS = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
HUBER_K = 1.345
DEFAULT_DATA = "../shared/data"  # the data folder when not given (a checkout beside the shared data)


def window_offsets(p, a, rng, bias, W, t, fit_bias):
    """Per window: (offset (3,), fitted bias or None) from robust Gauss-Newton."""
    out = []
    for t0 in np.arange(t.min(), t.max() - W + 1e-9, W):
        m = (t >= t0) & (t < t0 + W)
        if m.sum() < 8:
            continue
        theta = np.zeros(4 if fit_bias else 3)
        for _ in range(30):
            q = p[m] + theta[:3]
            dd = q - a[m]
            rr = np.linalg.norm(dd, axis=1)
            b = bias[m] + (theta[3] if fit_bias else 0.0)
            e = rng[m] - b - rr
            J = dd / rr[:, None]
            if fit_bias:
                J = np.concatenate([J, np.ones((J.shape[0], 1))], axis=1)
            s = 1.4826 * np.median(np.abs(e)) + 1e-3
            w = np.sqrt(np.minimum(1.0, HUBER_K * s / (np.abs(e) + 1e-12)))
            step = np.linalg.lstsq(J * w[:, None], e * w, rcond=None)[0]
            theta += step
            if np.max(np.abs(step)) < 1e-9:
                break
        out.append(theta)
    return np.asarray(out)


def main(argv=None):
    ap = ScriptParser(prog="study_util_motion_floor.py", description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=os.environ.get("JAXSLAM_DATA_DIR", DEFAULT_DATA), type=path_arg,
                    help=f"the folder holding util_uwb/ (default: $JAXSLAM_DATA_DIR, else {DEFAULT_DATA})")
    ap.add_argument("--json", default=None, type=path_arg)
    args = ap.parse_args(argv)
    if args.json:  # an unusable path (a folder, under a file): one usage line, before the fits
        ap.output_file("--json", args.json)
    if args.data == DEFAULT_DATA and not os.environ.get("JAXSLAM_DATA_DIR") and not os.path.isdir(args.data):
        ap.error(f"data: {args.data!r} (the default when neither data nor $JAXSLAM_DATA_DIR is given) is not a "
                 "folder; give the data folder (the one holding util_uwb/)")
    try:  # a missing or malformed log: likewise
        d = load_util(os.path.join(args.data, "util_uwb") if os.path.isdir(os.path.join(args.data, "util_uwb"))
                      else args.data)
    except InputError as e:
        ap.error(f"data: {one_line(str(e)) or type(e).__name__}")
    tag = d.tag_positions()
    t = d.twr_t
    inside = (t > d.gt_t[0]) & (t < d.gt_t[-1])
    p = np.stack([np.interp(t, d.gt_t, tag[:, k]) for k in range(3)], axis=1)
    air = inside & (p[:, 2] > 0.3)  # the evaluation's airborne samples
    anchors = {int(i): d.anchor_p[j] for j, i in enumerate(d.anchor_id)}
    a = np.stack([anchors[int(i)] for i in d.twr_anchor])
    res = d.twr_range - np.linalg.norm(a - p, axis=1)
    common = np.full(t.shape, np.median(res[air]))
    per_anchor = np.zeros(t.shape)
    med_by_anchor = {}
    for i in np.unique(d.twr_anchor[air]):
        m = air & (d.twr_anchor == i)
        med_by_anchor[int(i)] = float(np.median(res[m]))
        per_anchor[d.twr_anchor == i] = med_by_anchor[int(i)]
    p, a, rng, t = p[air], a[air], d.twr_range[air], t[air]
    models = {"common_bias_true": (common[air], False), "common_bias_fitted": (common[air], True),
              "per_anchor_true": (per_anchor[air], False)}
    table = {}
    print(f"{'W [s]':>6}  " + "  ".join(f"{k:>34}" for k in models))
    for W in WINDOWS:
        row = {}
        for name, (bias, fit_bias) in models.items():
            th = window_offsets(p, a, rng, bias, W, t, fit_bias)
            off = th[:, :3]
            row[name] = {"windows": int(len(th)), "rms_m": float(np.sqrt(np.mean(np.sum(off ** 2, 1)))),
                         "vertical_rms_m": float(np.sqrt(np.mean(off[:, 2] ** 2))),
                         "vertical_mean_m": float(np.mean(off[:, 2])),
                         "horizontal_rms_m": float(np.sqrt(np.mean(np.sum(off[:, :2] ** 2, 1))))}
        table[str(W)] = row
        print(f"{W:6.1f}  " + "  ".join(
            f"{r['rms_m']:.3f} (vert {r['vertical_rms_m']:.3f}, mean {r['vertical_mean_m']:+.3f}) n={r['windows']:3d}"
            for r in row.values()))
    out = {"flight": d.flight, "airborne_ranges": int(air.sum()), "huber_k": HUBER_K,
           "median_residual_m": float(np.median(res[air])), "per_anchor_median_residual_m": med_by_anchor,
           "windows_s": list(WINDOWS), "offset_rms": table,
           "note": "oracle study with the motion-capture truth: relative motion inside each window "
                   "from the truth, a constant 3-D offset per window fitted to the ranges; nothing "
                   "shipped was chosen with it"}
    if args.json:
        tmp = args.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump(out, f, indent=2)
        os.replace(tmp, args.json)
        print("wrote", args.json)


if __name__ == "__main__":
    main()
