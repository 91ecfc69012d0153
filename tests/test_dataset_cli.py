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


@pytest.mark.slow
def test_dataset_victoria_park_excerpt(tmp_path, capsys):
    rc, out, err = _run(["dataset", "victoria-park", "--data", str(DATA), "--float32",
                         "--json", str(tmp_path / "vp.json")], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "vp.json").read_text())
    assert doc["config"]["dtype"] == "float32"
    assert doc["counts"]["landmarks_mapped"] > 0
    assert doc["counts"]["measurements"] >= doc["counts"]["used"]


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
