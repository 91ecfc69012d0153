"""One source for the real-log targets' default robots, one rule for a UTIL flight folder, and
no silent odometry delay on a window without sightings.

Oracles, by hand from the files and the design:

* ``tests/data/mrclam6`` robot 1: ground truth starts at 1248444648.509, odometry at .009 + 0.5 s,
  the first sightings at 649.617 (1.108 s in: landmarks 41, 18 and 54, each its first sighting),
  the next after 649.709; so the first 1.0 s hold no sighting and the first 1.2 s only first ones;
* a UTIL flight folder is named ``*_obs_log*`` and holds ``groundtruth.csv`` itself or in a
  subfolder (``catalogue.util_flight``); the layouts below are written out with the flights they
  hold.
"""

from __future__ import annotations

import inspect
import pathlib
import shutil
import subprocess
import sys

import pytest

from jaxslam.data import catalogue
from jaxslam.data.textfile import MissingDataError
from jaxslam.errors import InputError

REPO = pathlib.Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
UTIL = DATA / "util_uwb"


# --- 1. the default training robots: the targets' own, read by the CLI -----------------------------

def test_the_factories_defaults_are_the_declared_robots():
    from jaxslam.tuning import targets
    from jaxslam.tuning.targets import mrclam, plaza

    for fn, scen in ((mrclam.mrclam_noise, "mrclam"), (plaza.plaza_noise, "plaza")):
        sig = inspect.signature(fn).parameters
        assert sig["robots"].default == targets.DEFAULT_ROBOTS[scen]["robots"]
        assert sig["test_robots"].default == targets.DEFAULT_ROBOTS[scen]["test_robots"]
    # the protocol of docs/datasets.md: train on robots 1-4, hold out 5; Plaza 1, hold out 2
    assert targets.DEFAULT_ROBOTS == {"mrclam": {"robots": (1, 2, 3, 4), "test_robots": (5,)},
                                      "plaza": {"robots": (1,), "test_robots": (2,)}}


def test_the_cli_counts_the_training_logs_from_the_targets_defaults(monkeypatch):
    # the CLI kept its own copy (1, 2, 3, 4): a target default of two robots still allowed 3 per batch
    from jaxslam.cli import tune
    from jaxslam.tuning import targets

    monkeypatch.setitem(targets.DEFAULT_ROBOTS, "mrclam", {"robots": (1, 2), "test_robots": (3,)})
    args = tune.build_parser(with_targets=False).parse_args(["mrclam", "--data", str(DATA), "--batch-size", "3"])
    with pytest.raises(InputError, match=r"^--batch-size: 3 is more than the 2 training logs of mrclam \(--robots\)"):
        tune._plan(args)
    text = tune.build_parser(with_targets=False).format_help()
    assert "mrclam, default 1,2;" in " ".join(text.split())  # the help states the same defaults


def test_the_default_robots_are_known_without_jax():
    code = ("import sys\nfrom jaxslam.cli import main\n"
            f"rc = main(['tune', 'plaza', '--data', {str(DATA)!r}, '--batch-size', '2'])\n"
            "print(rc, 'jax' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=str(REPO))
    assert proc.stdout.split() == ["2", "False"], proc.stderr[-2000:]
    assert "--batch-size: 2 is more than the 1 training log of plaza" in proc.stderr


# --- 2. a UTIL flight folder: the catalogue and the loader by one rule ----------------------------

def _flights_listed(root) -> list:
    """The flights the loader says it found, from its message for a flight that is not there."""
    from jaxslam.data.util_uwb import load_util

    with pytest.raises(MissingDataError, match=r"flight 'nope' not found") as ei:
        load_util(root, "nope")
    found = str(ei.value).rsplit("flights found: ", 1)[1].rstrip(")")
    return [] if found == "none" else [s.strip(" '") for s in found.strip("[]").split(",")]


def test_dot_inside_a_flight_is_found_by_the_catalogue_as_the_loader_reads_it(monkeypatch):
    # the loader read "." inside a flight; the catalogue (`jaxslam list`, the --json guard) found nothing
    monkeypatch.chdir(UTIL / "twr_obs_log1")
    assert catalogue.find("util-uwb", ".") == pathlib.Path(".")
    assert catalogue.util_flight(".")
    assert catalogue.find("util-uwb", "..") == pathlib.Path("..")  # util_uwb: the folder of the flights
    assert not catalogue.util_flight("..")  # (not a flight itself)


def test_a_link_to_a_flight_is_found_by_the_catalogue_as_the_loader_reads_it(tmp_path):
    from jaxslam.data.util_uwb import load_util

    link = tmp_path / "mylink"
    link.symlink_to(UTIL / "twr_obs_log1", target_is_directory=True)
    assert load_util(link).flight == "twr_obs_log1"  # the flight folder given itself, by what it resolves to
    assert catalogue.find("util-uwb", link) == link  # was None: the name "mylink" has no _obs_log


def test_dataset_cli_refuses_to_overwrite_a_file_of_the_flight_given_as_dot(tmp_path, monkeypatch, run_cli):
    # `jaxslam dataset util-uwb --data . --json uwb_twr.csv` inside the flight replaced the ranges with JSON
    shutil.copytree(UTIL, tmp_path / "util_uwb")
    flight = tmp_path / "util_uwb" / "twr_obs_log1"
    before = (flight / "uwb_twr.csv").read_bytes()
    monkeypatch.chdir(flight)
    rc, out, err = run_cli(["dataset", "util-uwb", "--data", ".", "--json", "uwb_twr.csv", "--quiet"])
    assert rc == 2 and err.strip().splitlines() == [err.strip()] and "--json: 'uwb_twr.csv'" in err, err
    assert (flight / "uwb_twr.csv").read_bytes() == before


@pytest.mark.parametrize("flag", ["--json", "--tum"])
def test_dataset_cli_refuses_to_overwrite_the_anchors_file_beside_the_flight_given(tmp_path, monkeypatch, run_cli,
                                                                                   flag):
    # the loader reads util_uwb/anchors_const3.csv from beside the flight folder: with --data . inside
    # the flight, `--json ../anchors_const3.csv` replaced it (the next run failed on its header)
    shutil.copytree(UTIL, tmp_path / "util_uwb")
    anchors = tmp_path / "util_uwb" / "anchors_const3.csv"
    before = anchors.read_bytes()
    monkeypatch.chdir(tmp_path / "util_uwb" / "twr_obs_log1")
    rc, out, err = run_cli(["dataset", "util-uwb", "--data", ".", flag, "../anchors_const3.csv", "--quiet"])
    assert rc == 2 and err.strip().splitlines() == [err.strip()], err
    assert f"{flag}: '../anchors_const3.csv' is a file of the util-uwb dataset in {str(anchors.parent)!r}" in err, err
    assert anchors.read_bytes() == before


def _twice_nested(root):
    shutil.copytree(UTIL / "tdoa2_obs_log1", root / "util_uwb" / "tdoa2_obs_log1" / "tdoa2_obs_log1")
    shutil.copy(UTIL / "anchors_const3.csv", root / "util_uwb")
    return root, ["tdoa2_obs_log1"], root / "util_uwb"


def _not_a_flight_name(root):
    shutil.copytree(UTIL / "twr_obs_log1", root / "util_uwb" / "myflight")
    shutil.copy(UTIL / "anchors_const3.csv", root / "util_uwb")
    return root, [], None


def _another_flight_given(root):
    shutil.copytree(UTIL, root / "util_uwb")
    flight = root / "util_uwb" / "tdoa2_obs_log1"
    return flight, ["tdoa2_obs_log1"], flight


@pytest.mark.parametrize("layout", [_twice_nested, _not_a_flight_name, _another_flight_given])
def test_the_loader_lists_the_flights_the_catalogue_finds(tmp_path, layout):
    # before: the loader listed "none" for the twice-nested flight and for a flight given itself
    # (both found by the catalogue), and listed myflight/ (not found by the catalogue)
    from jaxslam.data.util_uwb import load_util

    root, flights, folder = layout(tmp_path)
    assert _flights_listed(root) == flights
    assert catalogue.find("util-uwb", root) == folder
    for name in flights:  # and each listed flight loads under that name
        assert load_util(root, name).flight == name


def test_the_loader_uses_the_catalogue_rule():
    from jaxslam.data import util_uwb

    assert util_uwb.util_flight is catalogue.util_flight and util_uwb.util_flights is catalogue.util_flights
    assert catalogue.util_flights(UTIL) == [UTIL / "tdoa2_obs_log1", UTIL / "twr_obs_log1"]
    assert catalogue.util_flights(DATA / "mrclam6") == [] and catalogue.util_flights(DATA / "nope") == []


# --- 3. --odometry-delay auto on a window without sightings -----------------------------------------

def _setup():
    import jax.numpy as jnp

    from jaxslam.data import presets
    from jaxslam.tuning.targets import mrclam as RL

    base = presets.mrclam_params(1, dtype=jnp.float64, preset="hand")
    K, cap = RL.mrclam_layout(DATA, [1])
    return RL, RL.planar_physical(RL.planar_theta0(base), base), RL.mrclam_train_config(K, cap)


@pytest.mark.parametrize("t_max", [1.0, 1.2])  # no sighting; only first sightings (they place landmarks)
def test_a_window_without_updating_sightings_is_an_error_not_delay_0(t_max):
    # every delay scored 0 / 1 = 0, and min() picked the first, 0 s, silently
    RL, p, cfg = _setup()
    with pytest.raises(InputError, match=rf"^--window: no sighting in the first {t_max:g} s of robot\(s\) 1 updates "
                                         r"the filter .*give a longer --window or --odometry-delay S$"):
        RL.select_odometry_delay(DATA, [1], p, cfg, t_max=t_max)


def test_the_delay_is_still_chosen_where_sightings_update_the_filter():
    RL, p, cfg = _setup()
    best, table = RL.select_odometry_delay(DATA, [1], p, cfg, t_max=3.0, grid=(0.0, 0.2))
    assert set(table) == {0.0, 0.2} and best == min(table, key=table.get)
    assert all(v != 0.0 for v in table.values())
    # the robots as a generator: read once (it was empty from the second delay on)
    assert RL.select_odometry_delay(DATA, (r for r in [1]), p, cfg, t_max=3.0, grid=(0.0, 0.2)) == (best, table)


def test_util_events_refuses_no_anchor_ids():
    # np.size(None) is 1: with one range, anchor_id=None was read as id -1 ("no id")
    from jaxslam.systems import util_range

    with pytest.raises(InputError, match="^anchor_id: expected the anchor id of each range, got None$"):
        util_range.util_events([0.0], None, [1.0])


def test_tune_mrclam_says_so_in_one_line(run_cli):
    rc, out, err = run_cli(["tune", "mrclam", "--data", str(DATA), "--robots", "1", "--test-robots", "none",
                            "--window", "1", "--quiet"])
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith("jaxslam tune: error: --window: no sighting in the first 1 s of robot(s) 1 "), err
