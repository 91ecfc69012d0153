"""Review of jaxslam/data/plaza.py, scripts/reproduce_plaza_smoothing.py and
benchmarks/bench_bad_inputs.py: GT/DRp row counts against DR and the TD sender column are
checked at file:line; the smoother's failure flags are reported by name; a hanging bad-input case
is killed after --timeout and its row marked.  Expectations are counted from the files with plain
Python or stated by hand, never taken from the code under test."""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import shutil
import time
import types

import numpy as np
import pytest
from data_loader_paths import EXCERPTS, FULL, data_lines

from jaxslam.data import DataFormatError, load_plaza
from jaxslam.errors import InputError

ROOT = pathlib.Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks"


def _copy(tmp_path):
    g = tmp_path / "gtsam"
    shutil.copytree(EXCERPTS / "gtsam", g)
    return g


def _lines(path):
    return path.read_bytes().split(b"\n")


# ------------------------------------------------------------------ (a) row counts, sender id

@pytest.mark.parametrize("which", [1, 2])
@pytest.mark.parametrize("name", ["GT", "DRp"])
def test_plaza_pose_file_one_row_short_is_refused_at_its_last_line(tmp_path, which, name):
    g = _copy(tmp_path)
    f = g / f"Plaza{which}_{name}.txt"
    rows = data_lines(f)
    n_dr = len(data_lines(g / f"Plaza{which}_DR.txt"))
    assert len(rows) == n_dr + 1 == 301  # the committed excerpt: start pose + one per DR row
    last = rows[-2][0]  # the last data line once the final one is gone
    lines = _lines(f)
    del lines[rows[-1][0] - 1]
    f.write_bytes(b"\n".join(lines))
    with pytest.raises(DataFormatError, match=rf"Plaza{which}_{name}\.txt:{last}: .*expected 301 .*300 rows"):
        load_plaza(tmp_path, which)


@pytest.mark.parametrize("name", ["GT", "DRp"])
def test_plaza_pose_file_one_row_long_is_refused_at_the_extra_row(tmp_path, name):
    g = _copy(tmp_path)
    f = g / f"Plaza2_{name}.txt"
    rows = data_lines(f)
    extra = rows[-1][0] + 1  # line number of the appended row
    t = float(rows[-1][1][0]) + 0.1
    text = f.read_bytes()
    if not text.endswith(b"\n"):
        text += b"\n"
    f.write_bytes(text + f"{t!r} 1.0 2.0 0.5\n".encode())
    with pytest.raises(DataFormatError, match=rf"Plaza2_{name}\.txt:{extra}: 302 rows, expected 301"):
        load_plaza(tmp_path, 2)


def test_plaza_dr_row_dropped_is_refused_not_misaligned(tmp_path):
    # a DR row lost in a copy: the increments no longer line up with GT's poses
    g = _copy(tmp_path)
    f = g / "Plaza1_DR.txt"
    rows = data_lines(f)
    lines = _lines(f)
    del lines[rows[-1][0] - 1]
    f.write_bytes(b"\n".join(lines))
    gt_rows = data_lines(g / "Plaza1_GT.txt")
    with pytest.raises(DataFormatError, match=rf"Plaza1_GT\.txt:{gt_rows[-1][0]}: 301 rows, expected 300"):
        load_plaza(tmp_path, 1)


def test_plaza_td_sender_other_than_the_robot_is_refused_at_its_line(tmp_path):
    g = _copy(tmp_path)
    f = g / "Plaza2_TD.txt"
    rows = data_lines(f)
    line_no, fields = rows[17]
    assert float(fields[1]) == 2.0
    lines = _lines(f)
    lines[line_no - 1] = lines[line_no - 1].replace(b"2.0000000000000000e+000", b"5.0000000000000000e+000", 1)
    f.write_bytes(b"\n".join(lines))
    with pytest.raises(DataFormatError, match=rf"Plaza2_TD\.txt:{line_no}: sender id \(column 2\): "
                                              r"expected 2 \(the robot\), got 5"):
        load_plaza(tmp_path, 2)


@pytest.mark.parametrize("root", [EXCERPTS, FULL])
@pytest.mark.parametrize("which", [1, 2])
def test_plaza_shipped_files_still_load_to_the_file_values(root, which):
    g = root / "gtsam"
    if not (g / f"Plaza{which}_DR.txt").is_file():
        pytest.skip("full data absent")
    p = load_plaza(root, which)
    dr = np.array([[float(v) for v in f] for _, f in data_lines(g / f"Plaza{which}_DR.txt")])
    gt = np.array([[float(v) for v in f] for _, f in data_lines(g / f"Plaza{which}_GT.txt")])
    drp = np.array([[float(v) for v in f] for _, f in data_lines(g / f"Plaza{which}_DRp.txt")])
    td = np.array([[float(v) for v in f] for _, f in data_lines(g / f"Plaza{which}_TD.txt")])
    np.testing.assert_array_equal(p.dr, dr[:, 1:])
    np.testing.assert_array_equal(p.dr_t, dr[:, 0])
    np.testing.assert_array_equal(p.gt, gt[:, 1:])
    np.testing.assert_array_equal(p.drp, drp[:, 1:])
    order = np.argsort(td[:, 0], kind="stable")
    np.testing.assert_array_equal(p.td_range, td[order, 3])
    assert len(gt) == len(drp) == len(dr) + 1 and set(td[:, 1]) == {2.0}


# ------------------------------------------------------------------ (b) smoother flags reported

def _script():
    from unittest import mock

    from jaxslam import runtime

    spec = importlib.util.spec_from_file_location("reproduce_plaza_smoothing_misc",
                                                  ROOT / "scripts" / "reproduce_plaza_smoothing.py")
    mod = importlib.util.module_from_spec(spec)
    with mock.patch.object(runtime, "configure_process", lambda *a, **k: {}):
        spec.loader.exec_module(mod)
    return mod


def test_plaza_smoothing_reports_every_smoother_flag_not_only_not_converged():
    mod = _script()
    # bit 5 (32) = not_psd, bit 7 (128) = not_converged, bit 1 (2) = non_finite: jaxslam/errors.py
    assert mod.status_fields(np.array([0, 32, 0], np.int32)) == {"converged": True, "status": ["not_psd"]}
    assert mod.status_fields(np.array([128, 2, 0], np.int32)) == {"converged": False,
                                                                  "status": ["non_finite", "not_converged"]}
    assert mod.status_fields(np.zeros(4, np.int32)) == {"converged": True, "status": []}


# ------------------------------------------------------------------ (c) bench: per-case timeout

@pytest.fixture
def bench_mod(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import bench_bad_inputs

    return bench_bad_inputs


def test_bench_bad_inputs_kills_a_hanging_case_and_marks_its_row(bench_mod, monkeypatch, tmp_path):
    # a stand-in interpreter: "import jax" and a normal case exit 2 at once, the "hang" case sleeps
    fake = tmp_path / "fakepy"
    fake.write_text('#!/bin/sh\ncase "$*" in *hang*) sleep 60;; esac\nexit 2\n')
    fake.chmod(0o755)
    monkeypatch.setattr(bench_mod, "sys", types.SimpleNamespace(executable=str(fake)))
    cat = types.SimpleNamespace(DATA=tmp_path / "data", _files=lambda d: None,
                                _cases=lambda d: [(["run", "--ok"], "--ok", None),
                                                  (["run", "--hang"], "--hang", None)])
    monkeypatch.setattr(bench_mod, "_catalogue", lambda: cat)
    t0 = time.perf_counter()
    out = bench_mod.run(argparse.Namespace(repeats=3, timeout=1.0))
    assert time.perf_counter() - t0 < 30  # not the 3 x 60 s of the hanging case
    ok, hang = out["results"]
    assert (ok["exit_code"], ok["timed_out"]) == (2, False)
    assert (hang["exit_code"], hang["timed_out"], hang["jaxslam_s"]) == (None, True, 1.0)
    assert out["targets"][0]["met"] is False


def test_bench_bad_inputs_timeout_option(bench_mod):
    p = argparse.ArgumentParser()
    bench_mod.add_arguments(p)
    assert p.parse_args([]).timeout == 60.0
    with pytest.raises(InputError, match=r"--timeout: expected seconds > 0, got 0\.0"):
        bench_mod.run(argparse.Namespace(repeats=1, timeout=0.0))


def test_bench_bad_inputs_bad_timeout_is_exit_2_one_line(capsys):
    from jaxslam import cli

    assert cli.main(["bench", "bad_inputs", "--dir", str(BENCH), "--timeout", "-1"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--timeout" in err[0] and "Traceback" not in err[0], err


def test_plaza_smoothing_json_under_a_file_is_exit_2_before_any_compute(tmp_path, monkeypatch, capsys):
    # --json below a regular file cannot be written: said at once (exit 2, one line naming --json),
    # not as a traceback after every log was smoothed
    mod = _script()

    def no_compute(*a):
        raise AssertionError("smooth_log reached: --json was not checked before the compute")

    monkeypatch.setattr(mod, "smooth_log", no_compute)
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(SystemExit) as e:
        mod.main(["--data", str(EXCERPTS), "--robot", "2", "--json", str(tmp_path / "f.txt" / "p.json")])
    assert e.value.code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--json" in err[0] and "Traceback" not in err[0], err
