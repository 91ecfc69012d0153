"""Review of jaxslam.data.runners and jaxslam.data.catalogue (landmark-id errors, t_window,
the util-uwb folder test, data_root's argument).

Each test compares against an independent expectation (hand-computed values, NumPy).
"""

import json
import math

import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam import io
from jaxslam.data import catalogue
from jaxslam.data import runners as R
from jaxslam.errors import InputError


def _line(n=20):
    t = np.arange(float(n))
    pose = np.c_[t, 0.5 * t, np.zeros(n)]  # the estimate equals the reference: alignment = identity
    return t, pose


LM = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, -1.0]])
LM_TRUE = np.array([[1.0, 2.3], [3.4, 4.0], [5.0, -1.0]])  # errors 0.3, 0.4, 0 by id


def test_evaluate_planar_map_error_matches_numpy():
    t, pose = _line()
    m, _ = R.evaluate_planar(t, pose, t, pose, lm=LM, lm_ids=[7, 8, 9], lm_true=LM_TRUE[::-1],
                             lm_true_ids=[9, 8, 7])
    expect = math.sqrt((0.3 ** 2 + 0.4 ** 2 + 0.0) / 3)
    assert m["map_err_m"] == pytest.approx(expect, abs=1e-9)
    assert m["map_err_max_m"] == pytest.approx(0.4, abs=1e-9)
    assert m["landmarks_compared"] == 3


@pytest.mark.parametrize("kw, name", [
    (dict(lm_ids=[1.5, 2, 3], lm_true_ids=[1, 2, 3]), "lm_ids"),  # fractional: truncated onto id 1
    (dict(lm_ids=[1, 1, 3], lm_true_ids=[1, 2, 3]), "lm_ids"),  # repeated
    (dict(lm_ids=None, lm_true_ids=[1, 2, 3]), "lm_ids"),  # missing with lm_true given
    (dict(lm_ids=[1, 2, 3], lm_true_ids=[1, 1, 3]), "lm_true_ids"),  # repeated
    (dict(lm_ids=[1, 2, 3], lm_true_ids=None), "lm_true_ids"),  # missing
])
def test_evaluate_planar_landmark_id_errors_name_its_arguments(kw, name):
    # (they named map_error's est_ids / true_ids, which evaluate_planar does not have)
    t, pose = _line()
    with pytest.raises(InputError, match=f"^{name}:"):
        R.evaluate_planar(t, pose, t, pose, lm=LM, lm_true=LM_TRUE, **kw)


@pytest.mark.parametrize("t_window", [float("nan"), -5.0, 0.0, float("inf"), "30", True, [30.0]])
def test_util_uwb_t_window_checked_before_any_file(t_window, tmp_path):
    # an empty folder: the check comes before the loader looks for the flight
    with pytest.raises(InputError, match="^t_window: expected a positive finite scalar"):
        R.run_util_uwb(tmp_path, anchors="unknown", t_window=t_window)
    with pytest.raises(InputError, match="^t_window:"):  # not silently ignored with known anchors
        R.run_util_uwb(tmp_path, t_window=t_window)


def _flight(folder):
    folder.mkdir(parents=True)
    (folder / "groundtruth.csv").write_text("t,x\n")
    return folder


def test_catalogue_util_uwb_needs_a_flight_folder(tmp_path):
    a = tmp_path / "a"
    a.mkdir()
    (a / "notes_obs_log.txt").write_text("not a flight\n")  # a file with the name
    assert catalogue.find("util-uwb", a) is None
    b = tmp_path / "b"
    (b / "twr_obs_log1").mkdir(parents=True)  # an empty folder with the name
    assert catalogue.find("util-uwb", b) is None
    c = tmp_path / "c"
    (c / "x_obs_log").mkdir(parents=True)
    (c / "x_obs_log" / "groundtruth.csv").mkdir()  # groundtruth.csv a folder, not a file
    assert catalogue.find("util-uwb", c) is None
    # real layouts still found: the folder of the flights, the flight itself, the committed excerpt
    good = tmp_path / "good"
    fl = _flight(good / "util_uwb" / "twr_obs_log1")
    assert catalogue.find("util-uwb", good) == good / "util_uwb"
    assert catalogue.find("util-uwb", good / "util_uwb") == good / "util_uwb"
    assert catalogue.find("util-uwb", fl) == fl
    assert catalogue.find("util-uwb", EXCERPTS) == EXCERPTS / "util_uwb"
    assert catalogue.find("util-uwb", EXCERPTS / "util_uwb" / "twr_obs_log1") == EXCERPTS / "util_uwb" / "twr_obs_log1"


@pytest.mark.parametrize("value", [5, 1.5, b"/tmp", ["/tmp"]])
def test_data_root_refuses_a_non_path(value):
    with pytest.raises(InputError, match=r"^--data: expected a folder path \(str or os.PathLike\)"):
        catalogue.data_root(value)


def test_data_root_path_and_env_unchanged(tmp_path, monkeypatch):
    assert catalogue.data_root(tmp_path) == tmp_path
    monkeypatch.setenv(catalogue.DATA_ENV, str(tmp_path))
    assert catalogue.data_root(None) == tmp_path
    assert catalogue.data_root("") == tmp_path


def test_nan_timing_written_as_null_json(tmp_path):
    # timed_run(twice=False) gives compile_s NaN; the CLI's writer must keep the file strict JSON
    out, comp, run_s = R.timed_run(lambda: np.float64(1.0), twice=False)
    assert math.isnan(comp) and run_s >= 0
    p = io.write_json(tmp_path / "r.json", {"timing": {"compile_s": comp, "run_s": run_s}})
    doc = json.loads(p.read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON token {c}"))
    assert doc["timing"]["compile_s"] is None


@pytest.mark.parametrize("anchors", ["known", "unknown"])
def test_util_uwb_flight_without_ranges_is_a_data_error(anchors, tmp_path):
    # uwb_twr.csv with its header only: --anchors unknown raised a bare IndexError
    import shutil

    from jaxslam.data.textfile import DataFormatError

    root = tmp_path / "util_uwb"
    shutil.copytree(EXCERPTS / "util_uwb", root)
    f = root / "twr_obs_log1" / "uwb_twr.csv"
    f.write_text(f.read_text().splitlines()[0] + "\n")
    with pytest.raises(DataFormatError, match="uwb_twr.csv: util-uwb: the flight has no two-way ranges") as e:
        R.run_util_uwb(root, anchors=anchors)
    assert e.value.path.endswith("uwb_twr.csv")


def _unicycle_numpy(pose0, u, dt):
    s = np.array(pose0, float)
    out = []
    for (v, w), h in zip(u, dt):
        x, y, p = s
        s = np.array([x + v / w * (np.sin(p + w * h) - np.sin(p)), y + v / w * (np.cos(p) - np.cos(p + w * h)),
                      (p + w * h + np.pi) % (2 * np.pi) - np.pi])
        out.append(s)
    return np.array(out)


def test_dead_reckoning_compiles_once_and_matches_numpy():
    from jaxslam import compilation
    from jaxslam.dynamics import planar

    u = np.c_[np.linspace(0.5, 1.5, 40), np.linspace(0.2, -0.3, 40) + 0.011]  # no w == 0
    dt = np.full(40, 0.25)
    R.dead_reckoning(planar.unicycle, np.zeros(3), u, dt)  # compiles (shape 40)
    with compilation.account() as acct:  # (the eager scan compiled again at every call)
        p = np.asarray(R.dead_reckoning(planar.unicycle, np.array([1.0, -2.0, 0.3]), u, dt))
    assert acct.result.programs == 0
    np.testing.assert_allclose(p, _unicycle_numpy([1.0, -2.0, 0.3], u, dt), atol=1e-9)
