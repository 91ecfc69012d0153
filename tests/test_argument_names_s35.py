"""Argument names passed to a callee instead of rewritten in its message (review s35).

Callers that re-raised a callee's InputError with the argument name changed by string surgery
now pass their names in (``metrics.map_error(names=)``, ``paramfile.load(name=)``,
``dflqr.validate(names=)``, ``files.atomic_write(name=)``).  The messages the callers gave are
pinned whole here (they must not change); the tests that failed before the change are marked.
Also: the Victoria Park dead-reckoning motion cache (``runners._ackermann_motion``).
"""

from __future__ import annotations

import errno
import json
import re

import jax.numpy as jnp
import numpy as np
import pytest
from folders import unwritable_folder as _unwritable_folder

from jaxslam import files, metrics, paramfile
from jaxslam.control import dflqr
from jaxslam.data import runners as R
from jaxslam.dynamics.planar import AckermannGeometry
from jaxslam.errors import InputError
from jaxslam.sim.scenarios.tracking import controller_from_dict
from jaxslam.systems import util_range as ur
from jaxslam.tuning.targets import loop

LM = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, -1.0]])


def _line():
    t = np.linspace(0.0, 10.0, 51)
    return t, np.stack([t, 0.5 * t, np.zeros_like(t)], 1)


def _raises(fn, message):
    """``fn()`` raises an InputError whose message is exactly ``message``."""
    with pytest.raises(InputError) as info:
        fn()
    assert str(info.value) == message
    return info.value


# ------------------------------------------------------------------ metrics.map_error / evaluate_planar

@pytest.mark.parametrize("kw, message", [
    (dict(lm_ids=None, lm_true_ids=[1, 2, 3]), "lm_ids: expected numeric landmark ids, got None"),
    (dict(lm_ids=[1, 2, 3], lm_true_ids=None), "lm_true_ids: expected numeric landmark ids, got None"),
    (dict(lm_ids=["a", "b", "c"], lm_true_ids=[1, 2, 3]),
     "lm_ids: expected numeric landmark ids, got ['a', 'b', 'c']"),
    (dict(lm_ids=[1.5, 2, 3], lm_true_ids=[1, 2, 3]),
     "lm_ids: expected whole-number landmark ids on the rows in use (a fractional or non-finite id would "
     "be truncated onto another landmark)"),
    (dict(lm_ids=[1, 2, 3], lm_true_ids=[1, 2, np.nan]),
     "lm_true_ids: expected whole-number landmark ids on the rows in use (a fractional or non-finite id "
     "would be truncated onto another landmark)"),
    (dict(lm_ids=[1, 1, 3], lm_true_ids=[1, 2, 3]),
     "lm_ids: each id may appear once among the rows in use, repeated: [1]"),
    (dict(lm_ids=[1, 2, 3], lm_true_ids=[2, 2, 3]),
     "lm_true_ids: each true landmark id must appear once, repeated: [2]"),
])
def test_evaluate_planar_map_error_messages_are_unchanged(kw, message):
    # guard: every map_error failure evaluate_planar can reach (lm and lm_true are checked
    # before, so only the id checks); the old prefix rewrite covered them all, no input
    # escaped with map_error's est_ids / true_ids
    t, pose = _line()
    _raises(lambda: R.evaluate_planar(t, pose, t, pose, lm=LM, lm_true=LM, **kw), message)


def test_map_error_names_its_arguments_as_told():
    # (new: map_error took no names)
    names = ("lm", "lm_ids", "lm_true", "lm_true_ids")
    _raises(lambda: metrics.map_error(LM, [1, 1, 3], LM, [1, 2, 3], names=names),
            "lm_ids: each id may appear once among the rows in use, repeated: [1]")
    _raises(lambda: metrics.map_error(LM, [1, 2, 3], LM, [1, 2, 2], names=names),
            "lm_true_ids: each true landmark id must appear once, repeated: [2]")
    _raises(lambda: metrics.map_error(LM, [1, 2.5, 3], LM, [1, 2, 3], names=names),
            "lm_ids: expected whole-number landmark ids on the rows in use (a fractional or non-finite id "
            "would be truncated onto another landmark)")
    with pytest.raises(InputError, match=r"^lm: "):
        metrics.map_error(LM.astype(complex), [1, 2, 3], LM, [1, 2, 3], names=names)
    with pytest.raises(InputError, match=r"^lm_true: "):
        metrics.map_error(LM, [1, 2, 3], [["a", "b"]] * 3, [1, 2, 3], names=names)
    # left out: map_error's own names, as before
    _raises(lambda: metrics.map_error(LM, [1, 1, 3], LM, [1, 2, 3]),
            "est_ids: each id may appear once among the rows in use, repeated: [1]")
    for bad in (("a", "b"), "lm", ("a", "b", "c", ""), None):
        with pytest.raises(InputError, match=r"^names: expected four argument names"):
            metrics.map_error(LM, [1, 2, 3], LM, [1, 2, 3], names=bad)


def test_map_error_with_names_gives_the_same_figures():
    me = metrics.map_error(LM, [7, 8, 9], LM[::-1] + 0.5, [9, 8, 7], transform=(np.eye(2), np.zeros(2)))
    me2 = metrics.map_error(LM, [7, 8, 9], LM[::-1] + 0.5, [9, 8, 7], transform=(np.eye(2), np.zeros(2)),
                            names=("lm", "lm_ids", "lm_true", "lm_true_ids"))
    np.testing.assert_array_equal(me2.errors, np.full(3, np.hypot(0.5, 0.5)))  # by hand
    np.testing.assert_array_equal(me2.errors, me.errors)
    np.testing.assert_array_equal(me2.ids, [7, 8, 9])


# ------------------------------------------------------------------ util_range.util_events (left as is)

@pytest.mark.parametrize("ids, message", [
    ([0.0, 1.5, 2.0], "anchor_id: expected whole-number ids (a fractional or non-finite id would be "
                      "truncated onto another landmark)"),
    ([0.0, np.nan, 2.0], "anchor_id: expected whole-number ids (a fractional or non-finite id would be "
                         "truncated onto another landmark)"),
    (np.array([0, 2**32 - 1, 1], np.int64),
     "anchor_id: id 4294967295 at index 1 does not fit int32 ([-2147483648, 2147483647]: the ids are "
     "stored as int32)"),
    (["a", "b", "c"], "anchor_id: expected integer ids (-1 for none), got dtype <U1"),
])
def test_util_events_anchor_id_messages_are_pinned(ids, message):
    # guard: events._ids names its argument meas_ids, which util_events rewrites; every message
    # starts with the name, so the first occurrence replaced is the name (no input escapes)
    _raises(lambda: ur.util_events([0.0, 0.1, 0.2], ids, [1.0, 2.0, 3.0]), message)


# ------------------------------------------------------------------ paramfile.load / loop.controller_file

def _bad_files(tmp_path):
    (tmp_path / "dup.json").write_text('{"controller": {"kp": [1, 1, 1], "kp": [2, 2, 2]}}')
    (tmp_path / "bad.json").write_text('{"controller": ')
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "folder.json").mkdir()
    return [
        (tmp_path / "missing--params.json", "file {!r} not found"),
        (tmp_path / "folder.json", "{!r} is a folder, not a JSON file"),
        (tmp_path / "bad.json", "{!r} is not valid JSON (line 1, column 16: Expecting value)"),
        (tmp_path / "dup.json", "{!r} gives the key 'kp' twice in one object (only one value can hold; "
                                "remove the other)"),
        (tmp_path / "list.json", "{!r} must hold a JSON object, got list"),
    ]


def test_compare_file_errors_name_compare(tmp_path):
    # guard: the same messages as the rewrite gave ("--params" -> "--compare" once; every message
    # started with it), here with "--params" in the file name too
    for path, text in _bad_files(tmp_path):
        msg = text.format(str(path))
        _raises(lambda: loop.controller_file(path, dflqr.paper000_params()), "--compare: " + msg)
        _raises(lambda: paramfile.load(path), "--params: " + msg)  # its default, unchanged


def test_paramfile_load_takes_the_option_name(tmp_path):
    # (new: load named --params only)
    for path, text in _bad_files(tmp_path):
        _raises(lambda: paramfile.load(path, name="--other"), "--other: " + text.format(str(path)))


def test_compare_file_is_read_and_checked(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"controller": {"kp": [1.0, 2.0, 3.0]}}))
    ctrl = loop.controller_file(p, dflqr.paper000_params())
    assert tuple(ctrl.pd.kp) == (1.0, 2.0, 3.0)
    p.write_text(json.dumps({"controller": {"kp": [1.0, 2.0]}}))
    _raises(lambda: loop.controller_file(p, dflqr.paper000_params()),
            "params.controller.kp: expected shape (3,), got (2,)")


# ------------------------------------------------------------------ tracking.controller_from_dict / dflqr.validate

@pytest.mark.parametrize("d, message", [
    ({"kp": 1.0}, "params.controller.kp: expected shape (3,), got ()"),
    ({"kd": 2}, "params.controller.kd: expected shape (3,), got ()"),
])
def test_controller_from_dict_single_number_gain_is_an_input_error(d, message):
    # failed before: tuple() of the number raised a bare TypeError ('float' object is not iterable)
    _raises(lambda: controller_from_dict(d, dflqr.paper000_params()), message)


@pytest.mark.parametrize("d, message", [
    ({"Q": [1, 1, 1, 1, 1, 1, -1]}, "params.controller.Q: not positive semi-definite (smallest eigenvalue -1)"),
    ({"Q": [[1, 2], [3, 4]]}, "params.controller.Q: expected shape (7, 7), got (2, 2)"),
    ({"R": [0, 1, 1, 1]}, "params.controller.R: not positive definite (smallest eigenvalue 0)"),
    ({"R": 1.0}, "params.controller.R: expected a square matrix, got shape ()"),
    ({"kp": [1, 2]}, "params.controller.kp: expected shape (3,), got (2,)"),
    ({"kd": [-1, 0, 0]}, "params.controller.kd: must be finite and >= 0, got [-1.0, 0.0, 0.0]"),
    ({"kp": [[1.0], [2.0], [3.0]]}, "params.controller.kp: expected shape (3,), got (3, 1)"),
])
def test_controller_from_dict_messages_are_unchanged(d, message):
    # guard: the rewrite renamed every validate message of a key in d (they all start with the name)
    _raises(lambda: controller_from_dict(d, dflqr.paper000_params()), message)


def test_controller_from_dict_keeps_the_default_fields_own_name():
    # a bad field of the default (not in d) keeps validate's name, as before
    bad = dflqr.paper000_params()._replace(Q=np.eye(3))
    _raises(lambda: controller_from_dict({"kp": [1.0, 1.0, 1.0]}, bad), "params.Q: expected shape (7, 7), got (3, 3)")


def test_dflqr_validate_takes_names():
    # (new: validate took no names)
    p = dflqr.paper000_params()
    _raises(lambda: dflqr.validate(p._replace(Q=np.eye(3)), names={"Q": "ctrl.Q"}),
            "ctrl.Q: expected shape (7, 7), got (3, 3)")
    _raises(lambda: dflqr.validate(p._replace(R=-np.eye(4)), names={"Q": "ctrl.Q"}),
            "params.R: not positive definite (smallest eigenvalue -1)")  # left out: its own name
    bad_pd = p.pd._replace(kd=(1.0, -1.0, 0.0))
    _raises(lambda: dflqr.validate(p._replace(pd=bad_pd), names={"kd": "gains.kd"}),
            "gains.kd: must be finite and >= 0, got [1.0, -1.0, 0.0]")
    _raises(lambda: dflqr.validate(p._replace(pd=bad_pd)), "params.pd.kd: must be finite and >= 0, got [1.0, -1.0, 0.0]")
    assert dflqr.validate(p, names={"Q": "x"}) is p
    for bad in ({"quad": "x"}, {"Q": ""}, ["Q"], {"Q": 1}):
        with pytest.raises(InputError, match=r"^names: expected a dict of names"):
            dflqr.validate(p, names=bad)


# ------------------------------------------------------------------ files.atomic_write / plotting.flight.save / io

def test_atomic_write_takes_the_name_of_its_path(tmp_path):
    # (new: atomic_write named it "path" only)
    (tmp_path / "f").write_text("x")
    _raises(lambda: files.atomic_write(tmp_path / "f" / "x.txt", lambda f: f.write("x"), name="--out"),
            f"--out: {str(tmp_path / 'f')!r} is a file, so {str(tmp_path / 'f' / 'x.txt')!r} cannot be created")
    _raises(lambda: files.atomic_write(tmp_path, lambda f: f.write("x"), name="--out"),
            f"--out: {str(tmp_path)!r} is a folder; give a file path")
    _raises(lambda: files.atomic_write(5, lambda f: f.write("x"), name="--out"),
            "--out: expected a file or folder path, got 5")
    _raises(lambda: files.atomic_write(tmp_path, lambda f: f.write("x")),  # the default, unchanged
            f"path: {str(tmp_path)!r} is a folder; give a file path")
    ro = _unwritable_folder(tmp_path)
    e = _raises_match(lambda: files.atomic_write(ro / "x.txt", lambda f: f.write("x"), name="--out"),
                      rf"^--out: cannot write '{re.escape(str(ro))}/x\.txt' \(.+\)$")
    assert isinstance(e, OSError) and e.errno is not None
    with pytest.raises(InputError, match=r"^name: expected the name of the path argument"):
        files.atomic_write(tmp_path / "y.txt", lambda f: f.write("x"), name="")


def _raises_match(fn, pattern):
    with pytest.raises(InputError, match=pattern) as info:
        fn()
    return info.value


def test_flight_save_failed_write_is_also_the_oserror(tmp_path):
    # failed before: save re-raised a plain InputError with the name rewritten, dropping the
    # OSError side (errno, strerror) that files.atomic_write documents for a failed write
    from jaxslam.plotting import flight

    ro = _unwritable_folder(tmp_path)
    e = _raises_match(lambda: flight.save(flight.plt().figure(), ro, "x"),
                      rf"^directory: cannot write '{re.escape(str(ro))}/x\.png' \(.+\)$")
    assert isinstance(e, OSError) and e.errno in (errno.EACCES, errno.EPERM, errno.ENOENT, errno.EROFS)
    assert e.strerror and str(e).endswith(f"({e.strerror})")
    assert flight.plt().get_fignums() == []  # closed all the same


def test_write_json_messages_are_unchanged(tmp_path):
    # guard (io.write_json keeps its wrapping: atomic_write already names its argument "path")
    from jaxslam import io

    (tmp_path / "f").write_text("x")
    p = tmp_path / "f" / "x.json"
    _raises(lambda: io.write_json(p, {}),
            f"path: cannot write JSON to {str(p)!r}: {str(tmp_path / 'f')!r} is a file, so {str(p)!r} "
            "cannot be created")
    _raises(lambda: io.write_json(tmp_path, {}),
            f"path: cannot write JSON to {str(tmp_path)!r}: {str(tmp_path)!r} is a folder; give a file path")


# ------------------------------------------------------------------ runners._ackermann_motion cache

_U = jnp.asarray([[1.0, 0.1], [2.0, -0.2], [1.5, 0.05]], jnp.float32)
_DT = jnp.asarray([0.1, 0.1, 0.2], jnp.float32)
_P0 = jnp.zeros(3, jnp.float32)


def test_ackermann_motion_cache_serves_no_equal_geometry_of_other_types():
    # failed before: keyed on the geometry's value, the partial of an equal geometry of NumPy
    # float64 fields (asked for first) was returned for the loader's Python floats, and the
    # float32 dead reckoning then failed in scan (float64 constants); a value no other test uses
    floats = AckermannGeometry(L=2.5, H=0.5, a=1.25, b=0.25)
    np64 = AckermannGeometry(*map(np.float64, floats))
    assert np64 == floats  # (equal, and equal hashes: one lru_cache key before)
    R._ackermann_motion(np64)
    motion = R._ackermann_motion(floats)
    assert all(type(v) is float for v in motion.keywords["geom"])
    out = R.dead_reckoning(motion, _P0, _U, _DT)
    assert out.dtype == jnp.float32 and out.shape == (3, 3)
    # the same poses as the model called by hand with the loader's geometry, step by step
    s, want = _P0, []
    from jaxslam.dynamics import planar

    for k in range(3):
        s = planar.ackermann(s, _U[k], _DT[k], floats)
        want.append(np.asarray(s))
    np.testing.assert_allclose(np.asarray(out), np.stack(want), rtol=1e-6, atol=1e-6)


def test_ackermann_motion_cache_tells_signed_zeros_apart_and_compiles_once():
    g0 = AckermannGeometry(L=2.5, H=0.5, a=0.0, b=0.0)
    gm = AckermannGeometry(L=2.5, H=0.5, a=-0.0, b=-0.0)
    m0, mm = R._ackermann_motion(g0), R._ackermann_motion(gm)
    assert m0 is not mm
    assert [np.signbit(v) for v in mm.keywords["geom"]] == [False, False, True, True]
    assert R._ackermann_motion(AckermannGeometry(L=2.5, H=0.5, a=0.0, b=0.0)) is m0  # cached: one program
    n0 = R._dead_reckoning_jit._cache_size()
    R.dead_reckoning(m0, _P0, _U, _DT)
    n1 = R._dead_reckoning_jit._cache_size()
    R.dead_reckoning(R._ackermann_motion(AckermannGeometry(L=2.5, H=0.5, a=0.0, b=0.0)), _P0, _U, _DT)
    assert R._dead_reckoning_jit._cache_size() == n1 <= n0 + 1


def test_ackermann_motion_of_another_geometry_is_traced_not_kept():
    # a NumPy or an unhashable geometry: a plain function (traced each call, nothing kept)
    g = AckermannGeometry(L=jnp.asarray(2.5), H=0.5, a=1.25, b=0.25)
    motion = R._ackermann_motion(g)
    n0 = R._dead_reckoning_jit._cache_size()
    out = R.dead_reckoning(motion, jnp.zeros(3), _U.astype(jnp.float64), _DT.astype(jnp.float64))
    assert R._dead_reckoning_jit._cache_size() == n0 and out.shape == (3, 3)
    ref = R.dead_reckoning(R._ackermann_motion(AckermannGeometry(L=2.5, H=0.5, a=1.25, b=0.25)),
                           jnp.zeros(3), _U.astype(jnp.float64), _DT.astype(jnp.float64))
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-12, atol=1e-12)
