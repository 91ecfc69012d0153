"""``jaxslam dataset``: end-to-end on the committed excerpts, bad files, and the JSON/TUM outputs.

The excerpts are seconds long, so these runs check the plumbing (loader → event log →
system → evaluation → JSON, plots, TUM), not accuracy; the accuracy figures come from the
full logs (tests/data_loaders/test_data_full.py for the loaders; docs/datasets.md for the
runs, reproduced by scripts/reproduce_datasets.py).
"""

import json
import pathlib

import numpy as np
import pytest

from jaxslam import cli, metrics

DATA = pathlib.Path(__file__).resolve().parent / "data"
BAD = DATA / "bad"


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.parametrize("argv", [
    ["mrclam", "--robot", "1"],
    ["plaza", "--robot", "2", "--smooth"],
    ["util-uwb", "--tof", "--smooth"],
    # FastSLAM and the Ackermann/NN path are covered by tests/systems/test_planar_*.py in the
    # default suite; their CLI plumbing runs in the slow set (compile time).
    pytest.param(["mrclam", "--robot", "2", "--filter", "fastslam", "--particles", "16"],
                 marks=pytest.mark.slow),
])
def test_dataset_runs_on_excerpts_and_writes_outputs(tmp_path, capsys, argv):
    js = tmp_path / "out.json"
    tum = tmp_path / "traj.txt"
    rc, out, err = _run(["dataset", *argv, "--data", str(DATA), "--json", str(js), "--tum", str(tum),
                         "--plots", str(tmp_path / "plots")], capsys)
    assert rc == 0, err
    doc = json.loads(js.read_text())
    assert doc["dataset"] == argv[0]
    for key in ("config", "metrics", "counts", "timing"):
        assert key in doc
    assert np.isfinite(doc["metrics"]["ate_m"]) and doc["metrics"]["ate_m"] >= 0
    c = doc["counts"]
    assert c["measurements"] > 0 and c["used"] + c["gated"] <= c["measurements"]
    assert doc["timing"]["run_s"] > 0
    t, p, q = metrics.read_tum(tum)
    assert np.all(np.diff(t) >= 0) and np.all(np.isfinite(p))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    pngs = sorted(f.name for f in (tmp_path / "plots").glob("*.png"))
    assert len(pngs) == 2
    which = {"mrclam": "mrclam_robot1", "plaza": "plaza2", "util-uwb": "util_uwb"}[argv[0]]
    assert all(f.startswith(which + "_") for f in pngs), pngs  # robots can share a folder
    if "fastslam" in argv:  # and filters: the FastSLAM run does not overwrite the EKF's figures
        assert all(f.startswith(which + "_fastslam_") for f in pngs), pngs
    assert "ate_m" in out
    if "--smooth" in argv:  # the smoother's figures beside the filter's
        assert doc["config"]["smooth"] is True and "RTS" in doc["config"]["smoother"]
        assert np.isfinite(doc["metrics"]["smoothed_ate_m"]) and "smoothed_ate_m" in out
        assert doc["counts"]["smoother_failed_steps"] == 0
    else:
        assert "smooth" not in doc["config"] and not any(k.startswith("smoothed_") for k in doc["metrics"])


def test_measurements_outside_the_run_are_counted_and_said(tmp_path, capsys):
    # the second half of robot 1's sightings stamped 10^5 s late (clocks that disagree): they are
    # dropped, and the run says how many instead of looking like a run that saw little
    data = tmp_path / "mrclam6"
    data.mkdir()
    for f in (DATA / "mrclam6").iterdir():
        (data / f.name).write_bytes(f.read_bytes())
    lines = (data / "Robot1_Measurement.dat").read_text().splitlines()
    rows = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    late = rows[len(rows) // 2:]
    for i in late:
        parts = lines[i].split()
        lines[i] = "\t".join([f"{float(parts[0]) + 1e5:.3f}"] + parts[1:])
    (data / "Robot1_Measurement.dat").write_text("\n".join(lines) + "\n")
    js = tmp_path / "out.json"
    rc, out, err = _run(["dataset", "mrclam", "--robot", "1", "--data", str(data), "--json", str(js)], capsys)
    assert rc == 0, err
    doc = json.loads(js.read_text())
    # every late row is a landmark sighting or another robot's (the loader keeps the landmarks')
    assert 0 < doc["counts"]["outside_window"] <= len(late)
    assert f"{doc['counts']['outside_window']} of" in out and "outside the run's time span" in out


def test_a_log_cut_inside_its_last_number_runs_with_a_warning_naming_the_line(tmp_path, capsys):
    data = tmp_path / "mrclam6"
    data.mkdir()
    for f in (DATA / "mrclam6").iterdir():
        (data / f.name).write_bytes(f.read_bytes())
    odo = data / "Robot1_Odometry.dat"
    text = odo.read_text()
    assert text.endswith(" 0.000\n")
    odo.write_text(text[:-3])  # "... 0.000" cut to "... 0.0": still a number
    n = text.count("\n")
    js = tmp_path / "out.json"
    rc, out, err = _run(["dataset", "mrclam", "--robot", "1", "--data", str(data), "--json", str(js)], capsys)
    assert rc == 0, err
    lines = [ln for ln in err.splitlines() if "no line end" in ln]
    assert lines == [f"jaxslam: warning: {odo}:{n}: the last line has no line end (file cut short?); read as it "
                     "stands, its last number may be incomplete"], err


def _mrclam_other_dataset(root: pathlib.Path) -> pathlib.Path:
    """Robot 1's excerpt laid out as another MRCLAM dataset might be: unpacked as
    ``root/MRCLAM_Dataset9/``, landmark subjects renumbered 6–20 → 31–45 and five more (46–50,
    new barcodes) sighted twice each in the first frame (10 rows in one camera frame), and the
    three rows of the frame before it stamped 1000 s early (a clock offset: before any odometry)."""
    d = root / "MRCLAM_Dataset9"
    d.mkdir(parents=True)
    src = DATA / "mrclam6"
    for name in ("Robot1_Odometry.dat", "Robot1_Groundtruth.dat"):
        (d / name).write_bytes((src / name).read_bytes())

    def body(name):
        return [ln for ln in (src / name).read_text().splitlines() if ln.strip() and not ln.startswith("#")]

    bc = [ln.split() for ln in body("Barcodes.dat")]
    bc = [(int(a) + 25 if int(a) > 5 else int(a), int(b)) for a, b in bc] + [(45 + k, 100 + k) for k in range(1, 6)]
    (d / "Barcodes.dat").write_text("\n".join(f"{a}\t{b}" for a, b in bc) + "\n")
    lm = [ln.split() for ln in body("Landmark_Groundtruth.dat")]
    lm = [[str(int(r[0]) + 25)] + r[1:] for r in lm] + [[str(45 + k), f"{k}.0", "1.0", "0.001", "0.001"]
                                                        for k in range(1, 6)]
    (d / "Landmark_Groundtruth.dat").write_text("\n".join("\t".join(r) for r in lm) + "\n")
    rows = [ln.split() for ln in body("Robot1_Measurement.dat")]
    t0 = rows[0][0]
    extra = [[t0, str(100 + k), "3.0", "0.1"] for k in range(1, 6)] * 2  # 5 new landmarks, twice each
    rows = rows[:3] + extra + rows[3:]
    for r in rows[:3]:  # the first frame's three rows: two landmark sightings and one of robot 3
        r[0] = f"{float(r[0]) - 1000:.3f}"
    (d / "Robot1_Measurement.dat").write_text("\n".join("\t".join(r) for r in rows) + "\n")
    return d


def test_mrclam_from_another_dataset_maps_every_landmark_and_says_what_it_dropped(tmp_path, capsys):
    """A MRCLAM folder laid out as another dataset might be (``_mrclam_other_dataset``): the
    parent folder is enough, the known-id capacity follows the landmark table (20 subjects, none
    refused), a frame of 10 rows loses none (K follows the log), and the sightings stamped before
    the odometry are counted and said (they used to be applied to a robot that had not moved)."""
    d = _mrclam_other_dataset(tmp_path / "parent")
    js = tmp_path / "out.json"
    rc, out, err = _run(["dataset", "mrclam", "--robot", "1", "--data", str(tmp_path / "parent"), "--json", str(js)],
                        capsys)
    assert rc == 0, err
    doc = json.loads(js.read_text())
    c, rep = doc["counts"], doc["loader_report"]
    assert rep["dir"] == str(d)
    assert c["overflow"] == 0 and "capacity_overflow" not in c["status_flags"] and "CAPACITY" not in err
    assert c["outside_window"] == 2 and "outside the run's time span" in out
    # every landmark row is in the run or counted outside it (none dropped beyond K)
    assert c["measurements"] + c["outside_window"] == rep["landmark_rows"]
    assert c["dropped_beyond_K"] == 0 and "beyond" not in " ".join(doc["notes"])
    # one slot per subject of the table (20, five more than dataset 6), every landmark seen mapped
    assert doc["config"]["capacity"] == 20 and c["landmarks_mapped"] == rep["landmarks_seen"] == 8


@pytest.mark.slow
def test_mrclam_from_another_dataset_fastslam_maps_its_landmarks(tmp_path, capsys):
    # the end-to-end FastSLAM run of the folder above (slow: its compile); with dataset 6's fixed
    # subject offset every sighting overflowed and the run was dead reckoning
    _mrclam_other_dataset(tmp_path / "parent")
    js = tmp_path / "out.json"
    rc, out, err = _run(["dataset", "mrclam", "--robot", "1", "--filter", "fastslam", "--particles", "16",
                         "--data", str(tmp_path / "parent"), "--json", str(js)], capsys)
    assert rc == 0, err
    doc = json.loads(js.read_text())
    assert doc["counts"]["overflow"] == 0 and doc["counts"]["landmarks_mapped"] == doc["loader_report"]["landmarks_seen"]


def test_fastslam_known_ids_slots_follow_the_landmark_table():
    """FastSLAM's known-id slots come from the table's subjects (id_map[j] in slot j), not from
    dataset 6's 6–20: renumbered subjects map onto 0… and an id outside the table is refused
    (slot = capacity, counted as overflow by the core), never folded onto another landmark."""
    from jaxslam.data import runners

    subjects = np.array([31, 32, 40, 45], np.int32)
    cfg, prm, id_map, _ = runners._mrclam_fastslam(1, 8, "known", subjects, 9)
    assert cfg.capacity == 4 and cfg.K == 9 and id_map is subjects
    _, _, none_map, _ = runners._mrclam_fastslam(1, 8, "hidden", subjects, 9)
    assert none_map is None
    ids = np.array([[31, 45, 7, -1], [40, 32, 46, 31]])
    mask = np.array([[True, True, True, False], [True, True, True, True]])
    np.testing.assert_array_equal(runners._known_slots(ids, mask, subjects), [[0, 3, 4, 4], [2, 1, 4, 0]])


def test_util_ground_truth_is_never_extrapolated(tmp_path, capsys):
    """UTIL with motion capture that ends early (a cut file): the ranges after it are not
    evaluated against a held pose (they were, silently: a full-flight variant gave 0.905 m
    against 0.213 m) but counted in a note; motion capture that misses the ranges entirely is
    an exit-2 error, as for the other datasets."""
    src = DATA / "util_uwb"
    dst = tmp_path / "util_uwb"
    for f in src.rglob("*"):
        if f.is_file():
            (dst / f.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
            (dst / f.relative_to(src)).write_bytes(f.read_bytes())
    gt = dst / "twr_obs_log1" / "groundtruth.csv"
    lines = gt.read_text().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) <= 20.6]
    gt.write_text("\n".join(keep) + "\n")
    js = tmp_path / "out.json"
    rc, out, err = _run(["dataset", "util-uwb", "--data", str(tmp_path), "--json", str(js)], capsys)
    assert rc == 0, err
    doc = json.loads(js.read_text())
    note = [n for n in doc["notes"] if "outside the motion capture's span" in n]
    assert len(note) == 1 and int(note[0].split()[0]) > 0
    shifted = [lines[0]] + [",".join([f"{float(ln.split(',')[0]) + 100:.6f}"] + ln.split(",")[1:]) for ln in lines[1:]]
    gt.write_text("\n".join(shifted) + "\n")
    rc, _, err = _run(["dataset", "util-uwb", "--data", str(tmp_path)], capsys)
    assert rc == 2 and "inside the motion capture's span" in err


def test_stream_span_notes():
    from jaxslam.data import runners

    assert runners._span_notes(np.array([0.0, 100.0]), np.array([1.0, 101.0])) == []
    end, = runners._span_notes(np.array([0.0, 5.0]), np.array([1.0, 21.0]), "odometry inputs", "laser scans")
    assert end.startswith("the odometry inputs end 16.0 s before the last of the laser scans") and "held" in end
    start, = runners._span_notes(np.array([15.0, 30.0]), np.array([0.0, 30.0]))
    assert "start 15.0 s after the first" in start
    inc, = runners._span_notes(np.array([0.0, 5.0]), np.array([0.0, 1005.0]), held=False)
    assert "no motion is applied" in inc


@pytest.mark.slow
def test_dataset_victoria_park_excerpt(tmp_path, capsys):
    rc, out, err = _run(["dataset", "victoria-park", "--data", str(DATA), "--float32",
                         "--json", str(tmp_path / "vp.json")], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "vp.json").read_text())
    assert doc["config"]["dtype"] == "float32"
    assert doc["counts"]["landmarks_mapped"] > 0
    assert doc["counts"]["measurements"] >= doc["counts"]["used"]


def test_victoria_park_error_figure_marks_gps_jumps(tmp_path, capsys, monkeypatch):
    # The excerpt holds one GPS jump already (line 44: 9.4 m/s); one more fix is moved 5 m here
    # (25 m/s to both neighbours at 0.2 s spacing).  The fixes of a jump (both ends of a step
    # faster than 8 m/s), counted in NumPy from the file, are what the JSON counts and the
    # error figure marks.
    from jaxslam.plotting import dataset as dplot

    def jumps(path):
        g = np.loadtxt(path)
        fast = np.hypot(*np.diff(g[:, 1:], axis=0).T) / np.diff(g[:, 0]) > 8.0
        return int(np.count_nonzero(np.r_[fast, False] | np.r_[False, fast]))

    data = tmp_path / "victoria_park"
    data.mkdir()
    for f in (DATA / "victoria_park").iterdir():
        (data / f.name).write_bytes(f.read_bytes())
    rows = (data / "gps.dat").read_text().splitlines()
    t, x, y = (float(v) for v in rows[60].split())
    rows[60] = f"{t:10.3f} {x + 5.0:10.3f} {y:10.3f}"
    (data / "gps.dat").write_text("\n".join(rows) + "\n")
    labels, save = {}, dplot.save
    monkeypatch.setattr(dplot, "save", lambda fig, d, name: (
        labels.setdefault(name, [ln.get_label() for a in fig.axes for ln in a.get_lines()]), save(fig, d, name))[1])
    for folder, n in ((DATA, jumps(DATA / "victoria_park" / "gps.dat")), (tmp_path, jumps(data / "gps.dat"))):
        labels.clear()
        js = tmp_path / "vp.json"
        rc, _, err = _run(["dataset", "victoria-park", "--data", str(folder), "--json", str(js),
                           "--plots", str(tmp_path / "plots")], capsys)
        assert rc == 0, err
        assert json.loads(js.read_text())["metrics"]["gps_fixes_removed"] == n
        assert f"{n} × GPS jump (> 8 m/s to a neighbouring fix)" in labels["victoria_park_errors"], labels
    assert n == 5  # 2 + 3: the moved fix and its two neighbours


@pytest.mark.parametrize("case, needle", [
    ("mrclam_truncated", "Robot1_"),
    ("victoria_park_columns", ".dat:"),
    ("plaza_backwards", "Plaza"),
    ("util_nonnumeric", ".csv:"),
])
def test_dataset_bad_input_is_one_line_exit_2(capsys, case, needle):
    name = {"mrclam": "mrclam", "victoria": "victoria-park", "plaza": "plaza", "util": "util-uwb"}[case.split("_")[0]]
    rc, out, err = _run(["dataset", name, "--data", str(BAD / case)], capsys)
    assert rc == 2
    line = err.strip()
    assert "\n" not in line and needle in line and "Traceback" not in line
    # the message carries file:line
    assert any(part.strip().isdigit() for part in line.split(":"))


def test_dataset_option_misuse_is_an_input_error(capsys):
    rc, _, err = _run(["dataset", "plaza", "--data", str(DATA), "--robot", "3"], capsys)
    assert rc == 2 and "--robot: Plaza sequence 3 is not in" in err and "(found: 1, 2)" in err
    rc, _, err = _run(["dataset", "util-uwb", "--data", str(DATA), "--filter", "fastslam"], capsys)
    assert rc == 2 and "--filter" in err and "EKF only" in err
    rc, _, err = _run(["dataset", "victoria-park", "--data", str(DATA), "--ids", "hidden"], capsys)
    assert rc == 2 and "--ids" in err
    rc, _, err = _run(["dataset", "mrclam", "--data", str(DATA), "--particles", "5"], capsys)
    assert rc == 2 and "--particles" in err
    rc, _, err = _run(["dataset", "victoria-park", "--data", str(DATA), "--smooth"], capsys)
    assert rc == 2 and "--smooth" in err
    rc, _, err = _run(["dataset", "mrclam", "--data", str(DATA), "--filter", "fastslam", "--smooth"], capsys)
    assert rc == 2 and "--smooth" in err and "fastslam" in err
    rc, _, err = _run(["dataset", "mrclam", "--data", str(DATA), "--ids", "hidden", "--smooth"], capsys)
    assert rc == 2 and "--smooth" in err and "--ids hidden" in err
    rc, _, err = _run(["dataset", "util-uwb", "--data", str(DATA), "--anchors", "unknown"], capsys)
    assert rc == 2 and "start-up window" in err  # the excerpt has motion capture over 20-21 s only
    rc, _, err = _run(["dataset", "plaza", "--data", str(DATA), "--tum", str(DATA)], capsys)
    assert rc == 2 and "--tum" in err
    rc, _, err = _run(["dataset", "mrclam", "--data", str(DATA), "--robot", "7"], capsys)
    assert rc == 2 and "--robot: MRCLAM robot 7 is not in" in err and "(found: 1, 2)" in err
    rc, _, err = _run(["dataset", "mrclam", "--data", str(DATA), "--robot", "3"], capsys)
    assert rc == 2 and "(found: 1, 2)" in err  # the excerpts hold robots 1 and 2


class _Captured(Exception):
    pass


@pytest.mark.parametrize("params, window", [(None, 2.0), ({"prune_window_s": None}, None), (None, "known")])
def test_mrclam_hidden_ids_prune_at_capacity_64_unless_params_say_otherwise(tmp_path, monkeypatch, params, window):
    # ids hidden: capacity 64 and Victoria Park's pruning rule (docs/datasets.md); a --params file
    # that sets prune_window_s keeps its own; known ids: neither
    from jaxslam.data import presets, runners

    def capture(log, pose0, filter, config, prm, *a, **k):
        raise _Captured(config, prm)

    monkeypatch.setattr(runners, "_planar_run", capture)
    obj = None if params is None else {"dataset": "mrclam", "noise": params}
    with pytest.raises(_Captured) as e:
        runners.run_mrclam(DATA, robot=1, ids="known" if window == "known" else "hidden", params=obj)
    config, prm = e.value.args
    if window == "known":
        assert config.capacity == 16 and prm.prune_window_s is None
        return
    assert config.capacity == 64 and config.association == "nn"
    assert prm.prune_window_s == window
    if window is not None:
        assert (prm.prune_window_s, prm.prune_min_obs) == presets.MRCLAM_NN_PRUNING == (2.0, 4.0)
