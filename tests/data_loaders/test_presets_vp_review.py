"""Review of jaxslam.data.presets and jaxslam.data.victoria_park (w3).

Victoria Park's ``measurements.dat`` holds time, range [m], laser bearing [rad] in 0…π and tree
diameter (data README): a row with a range <= 0 or a bearing outside 0…π is a malformed file,
refused with DataFormatError at its file:line (it was read silently).  The ``--params`` readers
refuse an int too large for a float (JSON ``1000…0``) with InputError (a bare OverflowError
before), and ``victoria_park_params`` names a bad argument (a TypeError before).  Expected values
are written by hand or parsed with plain Python, never taken from the code under test.
"""

import json
import math
import shutil
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import DataFormatError, load_victoria_park
from jaxslam.data import presets as P
from jaxslam.errors import InputError


def _vp_copy(tmp_path):
    d = tmp_path / "victoria_park"
    shutil.copytree(EXCERPTS / "victoria_park", d)
    return d


def _set_field(path, nth_data_line, col, text):
    """Replace column ``col`` (0-based) of the ``nth_data_line``-th data line; returns its 1-based line."""
    lines = path.read_text().split("\n")
    seen = -1
    for i, ln in enumerate(lines):
        if not ln.strip() or ln.strip().startswith("#"):
            continue
        seen += 1
        if seen == nth_data_line:
            f = ln.split()
            f[col] = text
            lines[i] = "   ".join(f)
            path.write_text("\n".join(lines))
            return i + 1
    raise AssertionError("excerpt too short")


@pytest.mark.parametrize("col, text, match", [
    (1, "-12.74537", r"range \(column 2\): expected a positive distance \[m\], got -12\.74537"),
    (1, "0.0", r"range \(column 2\): expected a positive distance \[m\], got 0\.0"),
    (2, "90.0", r"bearing \(column 3\): expected a laser-frame angle in \[0, pi\] rad, got 90\.0"),
    (2, "-0.5", r"bearing \(column 3\): expected a laser-frame angle in \[0, pi\] rad, got -0\.5"),
])
def test_vp_detection_outside_documented_format_is_refused_at_file_line(tmp_path, col, text, match):
    d = _vp_copy(tmp_path)
    f = d / "measurements.dat"
    line = _set_field(f, 7, col, text)
    with pytest.raises(DataFormatError, match=match) as ei:
        load_victoria_park(tmp_path)
    assert ei.value.line == line and ei.value.path == str(f)
    assert str(ei.value).startswith(f"{f}:{line}: ")


def test_vp_documented_bounds_still_load(tmp_path):
    # bearings exactly 0 and π - 1e-5 and a tiny positive range are inside the documented format
    d = _vp_copy(tmp_path)
    f = d / "measurements.dat"
    _set_field(f, 3, 2, "0.0")
    _set_field(f, 4, 2, "3.14158")
    _set_field(f, 5, 1, "0.001")
    v = load_victoria_park(tmp_path)
    rows = [ln.split() for ln in f.read_text().split("\n") if ln.strip() and not ln.strip().startswith("#")]
    assert v.det.shape == (len(rows), 2)
    assert v.det_bearing_laser[3] == 0.0 and v.det_bearing_laser[4] == 3.14158
    assert v.det[3, 1] == pytest.approx(-math.pi / 2) and v.det[5, 0] == 0.001
    assert [float(r[1]) for r in rows] == v.det[:, 0].tolist()


def test_vp_shipped_excerpt_ranges_and_bearings_inside_format():
    # the excerpt loads (a plain-Python parse agrees): the new check refuses nothing shipped
    v = load_victoria_park(EXCERPTS)
    rows = [ln.split() for ln in (EXCERPTS / "victoria_park" / "measurements.dat").read_text().splitlines()
            if ln.strip() and not ln.strip().startswith("#")]
    assert v.det_bearing_laser.tolist() == [float(r[2]) for r in rows]
    assert min(float(r[1]) for r in rows) > 0


@pytest.mark.parametrize("reader, key", [(P.util_params_from_dict, "sigma_r"), (P.util_params_from_dict, "q_acc"),
                                         (P.plaza_params_from_dict, "q_bias"), (P.plaza_params_from_dict, "bias0")])
def test_params_from_dict_refuses_int_beyond_float_range(reader, key):
    noise = json.loads('{"%s": 1%s}' % (key, "0" * 400))  # JSON reads it as a Python int
    assert isinstance(noise[key], int)
    with pytest.raises(InputError, match=rf"^--params: noise\.{key}: expected a finite number, got 1000"):
        reader(noise)
    with pytest.raises(InputError, match=rf"^--params: noise\.{key}: expected a finite number"):
        reader({key: -(10 ** 400)})


def test_cli_params_file_with_huge_int_exits_2_with_one_line(tmp_path):
    f = tmp_path / "p.json"
    f.write_text('{"dataset": "util-uwb", "noise": {"sigma_r": 1%s}}' % ("0" * 400))
    r = subprocess.run([sys.executable, "-m", "jaxslam", "dataset", "util-uwb", "--data", str(EXCERPTS),
                        "--params", str(f)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "noise.sigma_r: expected a finite number" in r.stderr


@pytest.mark.parametrize("kw, match", [
    (dict(sigma_r="a"), r"^sigma_r: expected a positive finite scalar, got 'a'"),
    (dict(sigma_r=0.0), r"^sigma_r: expected a positive finite scalar"),
    (dict(sigma_b=float("nan")), r"^sigma_b: expected a positive finite scalar"),
    (dict(sigma_v=-0.7), r"^sigma_v: expected a non-negative finite scalar"),
    (dict(sigma_a=None), r"^sigma_a: expected a non-negative finite scalar"),
    (dict(prune_min_obs=None), r"^prune_min_obs: expected a finite scalar, got None"),
    (dict(prune_min_obs="4"), r"^prune_min_obs: expected a finite scalar"),
])
def test_victoria_park_params_names_a_bad_argument(kw, match):
    with pytest.raises(InputError, match=match):
        P.victoria_park_params(**kw)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_victoria_park_params_defaults_are_the_documented_numbers(dtype):
    # docstring: σ_v 0.7, σ_α 0.06, σ_r 0.25 m, σ_β 0.375°, range 5-40 m, pruning 4 matches in 2 s
    p = P.victoria_park_params(dtype=dtype)
    sb = 0.375 * 3.141592653589793 / 180.0
    np.testing.assert_allclose(np.asarray(p.M_c), np.diag([0.49, 0.0036]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.R), np.diag([0.0625, sb * sb]), rtol=1e-6)
    assert np.asarray(p.R).dtype == np.dtype(dtype) and np.asarray(p.M_c).dtype == np.dtype(dtype)
    assert (p.range_min, p.range_max, p.prune_window_s, p.prune_min_obs) == (5.0, 40.0, 2.0, 4.0)
    q = P.victoria_park_params(sigma_v=0.0, prune_window_s=None, prune_min_obs=np.int64(3), dtype=dtype)
    assert float(np.asarray(q.M_c)[0, 0]) == 0.0 and q.prune_window_s is None and q.prune_min_obs == 3.0


@pytest.mark.parametrize("kw, match", [
    (dict(sigma_v="a"), r"^sigma_v: expected a non-negative finite scalar, got 'a'"),
    (dict(sigma_w=float("inf")), r"^sigma_w: expected a non-negative finite scalar"),
    (dict(r_scale=None), r"^r_scale: expected a positive finite scalar, got None"),
    (dict(r_scale=0.0), r"^r_scale: expected a positive finite scalar"),
])
def test_mrclam_hand_params_name_a_bad_argument(kw, match):
    for extra in (dict(preset="hand"), dict(corrected=True)):
        with pytest.raises(InputError, match=match):
            P.mrclam_params(1, **kw, **extra)
    P.mrclam_params(1, **kw)  # the fitted preset does not read them (its docstring)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_mrclam_hand_params_numbers(dtype):
    # hand preset, robot 1: R = diag((0.053·1.4826)², (0.0074·1.4826)²)·4, M_c = diag(0.01², 0.02²)
    p = P.mrclam_params(1, preset="hand", dtype=dtype)
    np.testing.assert_allclose(np.asarray(p.R), np.diag([(0.053 * 1.4826) ** 2 * 4, (0.0074 * 1.4826) ** 2 * 4]),
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.M_c), np.diag([1e-4, 4e-4]), rtol=1e-6)
    assert np.asarray(p.R).dtype == np.dtype(dtype)


def test_anchor_offset_with_int_beyond_float_range_is_named():
    with pytest.raises(InputError, match=r"^--params: noise\.anchor_offset: expected a list of finite offsets"):
        P.util_params_from_dict(json.loads('{"anchor_offset": [0.1, 1%s]}' % ("0" * 400)))
    got = P.util_params_from_dict({"anchor_offset": [0.1, -0.2]}).anchor_offset
    assert np.asarray(got).tolist() == [0.1, -0.2]


def test_mrclam_log_range_model_with_int_beyond_float_range_is_named():
    from types import SimpleNamespace

    data = SimpleNamespace(meas=np.array([[1.0, 0.1]]))  # refused before anything else is read
    with pytest.raises(InputError, match=r"^range_model: expected two finite numbers \(k0, k2\) or None"):
        P.mrclam_log(data, range_model=(10 ** 400, 0.0))
