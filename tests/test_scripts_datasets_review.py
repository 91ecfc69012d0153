"""Review of scripts/reproduce_datasets.py, reproduce_tuning.py and reproduce_plaza_smoothing.py:
usage errors exit 2 with one line before any compute, shipped results are not replaced by a
smoke run, and the JSONs name no folder of the machine.  Nothing here runs a reproduction
(the parts / the CLI subprocess are replaced by fakes that fail the test if reached)."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import shutil
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"


def _load(rel, name):
    # the scripts call runtime.configure_process() on import: not in this test process
    from unittest import mock

    from jaxslam import runtime

    spec = importlib.util.spec_from_file_location(name, ROOT / rel)
    mod = importlib.util.module_from_spec(spec)
    with mock.patch.object(runtime, "configure_process", lambda *a, **k: {}):
        spec.loader.exec_module(mod)
    return mod


def _one_error_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _exit_code(main, argv):
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(argv))
    return e.value.code


def _no_compute(*a, **k):
    raise AssertionError("computed before the usage error")


# --- scripts/reproduce_datasets.py ----------------------------------------------------------

@pytest.fixture
def rd(monkeypatch):
    mod = _load("scripts/reproduce_datasets.py", "reproduce_datasets_review")
    monkeypatch.setattr(mod.subprocess, "run", _no_compute)
    return mod


@pytest.mark.parametrize("only", ["mrclam_r9_ekf", "mrclam_r1_ekf,plaza_typo", "", ","])
def test_datasets_unknown_or_empty_only_is_a_usage_error_and_keeps_table(rd, tmp_path, capsys, only):
    (tmp_path / "table.md").write_text("old table\n")
    code = _exit_code(rd.main, ["--data", str(DATA), "--out", str(tmp_path), "--only", only])
    assert code == 2 and "--only" in _one_error_line(capsys.readouterr().err)
    assert (tmp_path / "table.md").read_text() == "old table\n"


def test_datasets_missing_data_folder_is_a_usage_error_before_any_case(rd, tmp_path, capsys):
    (tmp_path / "table.md").write_text("old table\n")
    code = _exit_code(rd.main, ["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path)])
    assert code == 2 and "--data" in _one_error_line(capsys.readouterr().err)
    assert (tmp_path / "table.md").read_text() == "old table\n"


def _fake_cli(returncode=0):
    """Stands for ``jaxslam dataset``: writes a JSON naming the data folder as it was given
    (as the CLI does: ``"dir": "data/mrclam6"`` for ``--data data``)."""
    def run(cmd, *a, **k):
        data = cmd[cmd.index("--data") + 1]
        js = pathlib.Path(cmd[cmd.index("--json") + 1])
        if returncode == 0:
            js.write_text(json.dumps({
                "data": {"dir": str(pathlib.Path(data) / "mrclam6"),
                         "lines": [str(pathlib.Path(data) / "mrclam6" / "Robot1_Measurement.dat") + ":33"]},
                "metrics": {"ate_m": 0.125}, "counts": {"used": 3, "gated": 1, "rejected": 0},
                "timing": {"run_s": 0.5}}, indent=1))
        return subprocess.CompletedProcess(cmd, returncode)
    return run


def test_datasets_relative_data_folder_is_written_as_placeholder(rd, tmp_path, monkeypatch, capsys):
    (tmp_path / "mydata" / "mrclam6").mkdir(parents=True)
    out = tmp_path / "out"
    monkeypatch.setattr(rd.subprocess, "run", _fake_cli())
    monkeypatch.chdir(tmp_path)
    rc = rd.main(["--data", "mydata", "--out", str(out), "--only", "mrclam_r1_ekf"])
    assert rc == 0
    doc = json.loads((out / "mrclam_r1_ekf.json").read_text())
    assert doc["data"] == {"dir": "$DATA/mrclam6", "lines": ["$DATA/mrclam6/Robot1_Measurement.dat:33"]}
    assert "| mrclam_r1_ekf | `mrclam --robot 1` | 0.125 |" in (out / "table.md").read_text()


def test_datasets_json_names_no_home_folder(rd, tmp_path, monkeypatch, capsys):
    # the CLI's JSON holds the compilation cache's folder ("/root/.cache/jaxslam/xla" in the
    # shipped results): the machine's home folder is written "~"
    home = tmp_path / "home" / "me"
    monkeypatch.setenv("HOME", str(home))

    def run(cmd, *a, **k):
        js = pathlib.Path(cmd[cmd.index("--json") + 1])
        js.write_text(json.dumps({"timing": {"run_s": 0.5, "cache": {"dir": str(home / ".cache" / "jaxslam" / "xla")}},
                                  "metrics": {}, "counts": {"used": 0, "gated": 0, "rejected": 0}}))
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(rd.subprocess, "run", run)
    assert rd.main(["--data", str(DATA), "--out", str(tmp_path / "out"), "--only", "plaza1_slam"]) == 0
    doc = json.loads((tmp_path / "out" / "plaza1_slam.json").read_text())
    assert doc["timing"]["cache"]["dir"] == "~/.cache/jaxslam/xla"


def test_datasets_failed_case_gives_a_nonzero_exit_code(rd, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(rd.subprocess, "run", _fake_cli(returncode=1))
    rc = rd.main(["--data", str(DATA), "--out", str(tmp_path), "--only", "mrclam_r1_ekf,plaza1_slam"])
    assert rc == 1
    table = (tmp_path / "table.md").read_text()
    assert "| mrclam_r1_ekf | `mrclam --robot 1` | failed |" in table
    assert "| plaza1_slam | `plaza --robot 1` | failed |" in table


# --- scripts/reproduce_tuning.py ------------------------------------------------------------

@pytest.fixture
def rt(monkeypatch, tmp_path):
    mod = _load("scripts/reproduce_tuning.py", "reproduce_tuning_review")
    for name in ("part_oracle", "part_gradcheck", "part_ekf", "part_lqr", "part_loop", "part_nll_flat",
                 "part_uwb"):
        monkeypatch.setattr(mod, name, _no_compute)
    # the default --out is ROOT/docs/results/tuning: a copy of the layout, never the shipped folder
    monkeypatch.setattr(mod, "ROOT", tmp_path / "repo")
    return mod


@pytest.mark.parametrize("argv, needle", [
    (["--parts", "oracle,orcale"], "--parts"),
    (["--parts", "ekf_nlll"], "--parts"),
    (["--parts", "ekf_nll_imux"], "--parts"),
    (["--parts", ","], "--parts"),
    (["--parts", "oracle", "--test-runs", "0"], "--test-runs"),
    (["--parts", "oracle", "--ekf-steps", "-1"], "--ekf-steps"),
    (["--parts", "oracle", "--ekf-lr", "nan"], "--ekf-lr"),
    (["--parts", "nll_flat"], "--parts"),  # needs ekf_nll_imu.json, absent from --out
])
def test_tuning_bad_options_exit_2_before_any_part(rt, tmp_path, capsys, argv, needle):
    out = tmp_path / "out"
    out.mkdir()
    (out / "table.md").write_text("old table\n")
    code = _exit_code(rt.main, [*argv, "--out", str(out), "--cache-dir", ""])
    assert code == 2 and needle in _one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in out.iterdir()) == ["table.md"]
    assert (out / "table.md").read_text() == "old table\n"


@pytest.mark.parametrize("quick_json, argv", [(True, []), (False, ["--quick"])])
def test_tuning_nll_flat_refuses_an_ekf_nll_imu_json_of_other_settings(rt, tmp_path, capsys, quick_json, argv):
    (tmp_path / "ekf_nll_imu.json").write_text(json.dumps({"quick": quick_json}))
    code = _exit_code(rt.main, ["--parts", "nll_flat", *argv, "--out", str(tmp_path), "--cache-dir", ""])
    assert code == 2 and "ekf_nll_imu.json" in _one_error_line(capsys.readouterr().err)


def test_tuning_table_lists_every_ekf_part_the_script_runs(rt, tmp_path):
    # --parts ekf_nees_imu writes ekf_nees_imu.json: its row belongs in table.md
    d = json.loads((ROOT / "docs" / "results" / "tuning" / "ekf_nll_imu.json").read_text())
    d["pos_rmse_ratio_after_over_q_imu"] = 0.8125
    (tmp_path / "ekf_nees_imu.json").write_text(json.dumps(d))
    table = rt.write_table(tmp_path).read_text()
    assert "| nees_imu |" in table and "| 0.812 |" in table and "| tuned (nees_imu) |" in table


def test_tuning_quick_never_writes_into_the_shipped_folder(rt, tmp_path, capsys):
    shipped = tmp_path / "repo" / "docs" / "results" / "tuning"
    shipped.mkdir(parents=True)
    (shipped / "oracle.json").write_text('{"quick": false}\n')
    code = _exit_code(rt.main, ["--quick", "--parts", "oracle", "--cache-dir", ""])
    assert code == 2 and "--quick" in _one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in shipped.iterdir()) == ["oracle.json"]
    assert (shipped / "oracle.json").read_text() == '{"quick": false}\n'


def test_tuning_table_names_quick_results(rt, tmp_path):
    d = json.loads((ROOT / "docs" / "results" / "tuning" / "oracle.json").read_text())
    d["quick"] = True
    (tmp_path / "oracle.json").write_text(json.dumps(d))
    table = rt.write_table(tmp_path).read_text()
    assert "oracle.json are not meaningful" in table


def test_tuning_table_of_the_shipped_results_is_the_shipped_table(rt, tmp_path):
    # regression guard: the table code rebuilds docs/results/tuning/table.md byte for byte
    src = ROOT / "docs" / "results" / "tuning"
    for p in src.glob("*.json"):
        shutil.copy(p, tmp_path / p.name)
    assert rt.write_table(tmp_path).read_text() == (src / "table.md").read_text()


# --- scripts/reproduce_plaza_smoothing.py ---------------------------------------------------

@pytest.fixture
def rp(monkeypatch):
    mod = _load("scripts/reproduce_plaza_smoothing.py", "reproduce_plaza_smoothing_review")
    monkeypatch.setattr(mod, "smooth_log", _no_compute)
    return mod


@pytest.mark.parametrize("argv, needle", [
    (["--robot", "3"], "--robot"),
    (["--robot", "1", "1"], "--robot"),
    (["--iters", "0"], "--iters"),
    (["--damping", "0"], "--damping"),
    (["--damping", "-1"], "--damping"),
    (["--damping", "nan"], "--damping"),
])
def test_plaza_bad_options_exit_2_before_any_compute(rp, capsys, argv, needle):
    code = _exit_code(rp.main, ["--data", str(DATA), *argv])
    assert code == 2 and needle in _one_error_line(capsys.readouterr().err)


def test_plaza_missing_data_and_json_folder_exit_2_before_any_compute(rp, tmp_path, capsys):
    code = _exit_code(rp.main, ["--data", str(tmp_path)])
    assert code == 2 and "--data" in _one_error_line(capsys.readouterr().err)
    code = _exit_code(rp.main, ["--data", str(DATA), "--json", str(tmp_path)])
    assert code == 2 and "--json" in _one_error_line(capsys.readouterr().err)


def test_plaza_beacon_never_initialised_is_one_line_not_an_index_error(tmp_path, capsys):
    # the committed Plaza 1 excerpt is too short for the EKF to initialise every beacon: the
    # smoother's beacon prior (the EKF's final beacons) has no mean for them
    mod = _load("scripts/reproduce_plaza_smoothing.py", "reproduce_plaza_smoothing_review2")
    rc = mod.main(["--data", str(DATA), "--robot", "1", "--iters", "1", "--json", str(tmp_path / "p.json")])
    assert rc == 1
    line = _one_error_line(capsys.readouterr().err)
    assert "--robot 1" in line and "never initialised beacon" in line
    assert not (tmp_path / "p.json").exists()


# --- scripts/gen_api.py ---------------------------------------------------------------------

def test_gen_api_documents_the_package_of_its_own_checkout(tmp_path):
    # a checkout whose jaxslam holds one function: the script copied into it must document that
    # package, not the jaxslam installed in the environment (this repository's)
    (tmp_path / "scripts").mkdir()
    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "scripts" / "gen_api.py", tmp_path / "scripts" / "gen_api.py")
    (tmp_path / "jaxslam").mkdir()
    (tmp_path / "jaxslam" / "__init__.py").write_text(
        '"""Stand-in package."""\n\n\ndef hello(x=1):\n    """Say hello."""\n')
    env = {k: v for k, v in __import__("os").environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([__import__("sys").executable, str(tmp_path / "scripts" / "gen_api.py")],
                          cwd=tmp_path / "docs", env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    api = (tmp_path / "docs" / "api.md").read_text()
    assert "- **`hello(x=1)`**\n  Say hello." in api and "jaxslam.linalg" not in api


# --- argparse's own errors are one line, exit 2, too ------------------------------------------

@pytest.mark.parametrize("script, argv, needle", [
    ("reproduce_datasets", ["--out", "x"], "--data"),
    ("reproduce_tuning", ["--seed", "abc"], "--seed"),
    ("reproduce_plaza_smoothing", ["--data", "d", "--iters", "abc"], "--iters"),
    ("reproduce_plaza_smoothing", ["--data", "d", "--start", "gt"], "--start"),
    ("gen_api", ["--chek"], "--chek"),
])
def test_argparse_errors_are_one_line_exit_2(monkeypatch, capsys, script, argv, needle):
    mod = _load(f"scripts/{script}.py", f"{script}_review_argparse")
    for name in ("part_oracle", "smooth_log", "render"):
        if hasattr(mod, name):
            monkeypatch.setattr(mod, name, _no_compute)
    monkeypatch.setattr(subprocess, "run", _no_compute)
    code = _exit_code(mod.main, argv)
    assert code == 2 and needle in _one_error_line(capsys.readouterr().err)
