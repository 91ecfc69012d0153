"""Argument checks of benchmarks/bench_ekfslam.py, bench_lines.py and bench_uwb.py: a bad option
is the CLI's exit 2 with a one-line message naming it, before any compute (each case here takes
about a second; nothing is timed or compiled)."""

import argparse
import pathlib
import sys

import pytest

from jaxslam import cli
from jaxslam.errors import InputError

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_ekfslam  # noqa: E402


def _bench(capsys, name, *opts):
    rc = cli.main(["bench", name, "--dir", str(BENCH), *opts])
    err = capsys.readouterr().err
    return rc, err


@pytest.mark.parametrize("name", ["ekfslam", "lines", "uwb"])
@pytest.mark.parametrize("parts", [",", " , "])
def test_empty_parts_is_exit_2(capsys, name, parts):
    rc, err = _bench(capsys, name, "--parts", parts)
    assert rc == 2
    assert "--parts" in err and "internal error" not in err
    assert len(err.strip().splitlines()) == 1


def test_ekfslam_plots_not_a_folder_is_exit_2_before_the_study(capsys, tmp_path):
    f = tmp_path / "a_file"
    f.write_text("x")
    rc, err = _bench(capsys, "ekfslam", "--parts", "study", "--plots", str(f), "--calls", "1",
                     "--study-maps", "5", "--study-obs", "1")
    assert rc == 2 and "--plots" in err and "internal error" not in err
    assert f.read_text() == "x"


def test_ekfslam_plots_without_the_study_part_is_exit_2(capsys, tmp_path):
    d = tmp_path / "plots"
    rc, err = _bench(capsys, "ekfslam", "--parts", "mc", "--plots", str(d))
    assert rc == 2 and "--plots" in err and "study" in err
    assert not d.exists()


@pytest.mark.parametrize("runs", ["abc", "0", "1,-2"])
@pytest.mark.parametrize("parts", ["slam", "ransac"])
def test_lines_slam_runs_checked_before_compute(capsys, runs, parts):
    rc, err = _bench(capsys, "lines", "--parts", parts, "--slam-runs", runs)
    assert rc == 2 and "--slam-runs" in err and "internal error" not in err
    assert len(err.strip().splitlines()) == 1  # no progress line: nothing ran


def test_ekfslam_help_says_what_repeats_and_pairs_do(capsys):
    assert cli.main(["bench", "ekfslam", "--dir", str(BENCH), "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "the mc part uses min(REPEATS, 3)" in out
    assert "used only when --capacities includes both 64 and 256" in out


def test_ekfslam_child_input_error_is_an_input_error(tmp_path):
    """A fresh child process (OpenBLAS threads set) that stops on a bad option hands its
    InputError to the parent (the CLI's exit 2), not a CalledProcessError (exit 1)."""
    opts = {k: None for k in bench_ekfslam._OPTION_DESTS}
    opts.update(parts="full", capacities="abc", study_maps="5", study_obs="1", mc_runs="1")
    with pytest.raises(InputError, match="--capacities"):
        bench_ekfslam._spawn(argparse.Namespace(**opts), {"full"}, 1, "1 thread")
