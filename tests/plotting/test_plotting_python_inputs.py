"""Output paths and plot inputs from Python (probe items 22-24): an unwritable folder, a full disk
or a folder that cannot be made is an InputError naming the path (files.atomic_write, and so
plotting.flight.save and metrics.write_tum), every plot_all checks its folder before it draws,
tuning.plot_all drops the parameter figure only when there are no parameters, before_after and
attitude.plot_all check what they read."""

import errno
import os
import pathlib
import pickle

import numpy as np
import pytest
from folders import unwritable_folder as _unwritable_folder

from jaxslam import files
from jaxslam.errors import InputError
from jaxslam.metrics import write_tum
from jaxslam.plotting import attitude, dataset, fastslam, flight, lines, slam3d, uwb
from jaxslam.plotting import tuning as pt


def _tum_args(T=3):
    return np.arange(T, dtype=float), np.zeros((T, 3))


# ---------------------------------------------------------------- 22: output paths


def test_atomic_write_and_write_tum_name_an_unwritable_folder(tmp_path):
    ro = _unwritable_folder(tmp_path)
    with pytest.raises(InputError, match=rf"^path: cannot write '{ro}/zz\.txt' \(.+\)$") as got:
        files.atomic_write(ro / "zz.txt", lambda f: f.write("x"))
    # also the OSError it came from: a caller that names its option from strerror still can
    assert isinstance(got.value, OSError) and got.value.strerror and got.value.errno
    assert got.value.filename == str(ro / "zz.txt")
    with pytest.raises(InputError, match=rf"^path: cannot write '{ro}/zz\.txt'"):
        write_tum(ro / "zz.txt", *_tum_args())
    # a folder that cannot be made
    with pytest.raises(InputError, match=rf"^path: cannot write '{ro}/no/such/zz\.txt'"):
        files.atomic_write(ro / "no" / "such" / "zz.txt", lambda f: f.write("x"))


def test_a_full_disk_is_an_input_error_and_leaves_no_temporary_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def full(f):
        f.write("partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(InputError, match=rf"^path: cannot write '{target}' \(No space left on device\)") as got:
        files.atomic_write(target, full)
    assert got.value.errno == errno.ENOSPC and isinstance(got.value, OSError)
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"] and target.read_text() == "old"
    # the error pickles (a worker process can hand it back) and keeps its message
    back = pickle.loads(pickle.dumps(got.value))
    assert str(back) == str(got.value) and back.errno == errno.ENOSPC and isinstance(back, InputError)
    if pathlib.Path("/dev/full").exists():  # a device is written into directly: the same error
        with pytest.raises(InputError, match=r"^path: cannot write '/dev/full' \(No space left on device\)"):
            files.atomic_write("/dev/full", lambda f: f.write("x" * 100))
        with pytest.raises(InputError, match=r"^path: cannot write '/dev/full'"):
            write_tum("/dev/full", *_tum_args())


def test_other_errors_of_the_write_function_pass_through(tmp_path):
    def reads_elsewhere(f):
        open(tmp_path / "no" / "input.txt")  # an OSError about another file: the caller's own

    with pytest.raises(FileNotFoundError) as got:
        files.atomic_write(tmp_path / "a.txt", reads_elsewhere)
    assert not isinstance(got.value, InputError)

    def reader_left(f):
        raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    with pytest.raises(BrokenPipeError):  # the CLI's quiet exit (`| head`) stays as it was
        files.atomic_write(tmp_path / "b.txt", reader_left)
    assert list(tmp_path.iterdir()) == []
    # a valid path: written as before, mode 0666 less the umask
    p = files.atomic_write(tmp_path / "sub" / "c.txt", lambda f: f.write("ok"))
    assert p.read_text() == "ok" and list(p.parent.iterdir()) == [p]
    assert (p.stat().st_mode & 0o777) == (0o666 & ~files._UMASK)


def test_save_names_directory(tmp_path):
    fig = flight.plt().figure()
    with pytest.raises(InputError, match=r"^directory: expected a folder path, got 5$"):
        flight.save(fig, 5, "x")
    flight.plt().close(fig)  # (a refused argument leaves the figure open: the caller may retry)
    ro = _unwritable_folder(tmp_path)
    with pytest.raises(InputError, match=rf"^directory: cannot write '{ro}/x\.png' \(.+\)$"):
        flight.save(flight.plt().figure(), ro, "x")
    assert flight.plt().get_fignums() == []  # closed all the same


def test_save_names_name_when_a_folder_has_its_file_name(tmp_path):
    # directory/x.png a folder: the name is at fault (was "directory: '.../x.png' is a folder")
    (tmp_path / "x.png").mkdir()
    fig = flight.plt().figure()
    with pytest.raises(InputError, match=rf"^name: '{tmp_path}/x\.png' is a folder; give another file name$"):
        flight.save(fig, tmp_path, "x")
    assert (tmp_path / "x.png").is_dir() and flight.plt().get_fignums() == [fig.number]  # left open
    assert flight.save(fig, tmp_path, "y") == tmp_path / "y.png" and (tmp_path / "y.png").stat().st_size > 0
    assert flight.plt().get_fignums() == []


def test_before_after_takes_any_iterable_of_metric_names():
    # dict_keys and NumPy arrays of names worked before this session's list/tuple/set check
    rep = _report()
    keys = {"nll": 1, "pos_rmse_m": 2}.keys()
    for metrics in (keys, np.array(["nll", "pos_rmse_m"]), (m for m in ("nll", "pos_rmse_m")), ["nll", "pos_rmse_m"]):
        fig = pt.before_after(rep, metrics=metrics)
        titles = sorted(ax.get_title().split("\n")[0] for ax in fig.axes if ax.get_title())
        assert titles == ["nll", "pos_rmse_m"], titles
        flight.plt().close(fig)
    for bad in ("nll", 5, [1, 2], np.array([1.0])):
        with pytest.raises(InputError, match=r"^metrics: expected a list of statistic names"):
            pt.before_after(rep, metrics=bad)
    with pytest.raises(InputError, match=r"^metrics: expected at least one statistic name"):
        pt.before_after(rep, metrics=np.array([], dtype=str))


def _history(params=True, steps=3):
    h = []
    for s in range(steps):
        rec = {"step": s, "loss": 2.0 - 0.5 * s}
        if params:
            rec["params"] = {"Q": [0.1 * (s + 1), 0.2], "R": [0.3]}
        h.append(rec)
    return h


def _report(history=None, before=None, after=None, **extra):
    side = {"metrics": {"pos_rmse_m": {"mean": 1.0}, "nll": {"mean": 2.0}},
            "consistency": {"anees": 3.0, "anees_bounds": [1.0, 5.0]}}
    return {"scenario": "s", "target": "t", "loss": "mse",
            "history": _history() if history is None else history,
            "before": side if before is None else before, "after": side if after is None else after, **extra}


def _blocker(tmp_path):
    b = tmp_path / "afile"
    b.write_text("x")
    return b


@pytest.mark.parametrize("call", [
    lambda d: fastslam.plot_all("n", None, None, None, d),
    lambda d: lines.plot_all("n", None, None, None, None, None, None, d),
    lambda d: slam3d.plot_all("n", None, None, None, None, None, None, None, d, None),
    lambda d: uwb.plot_all("n", None, None, None, None, None, None, None, None, d),
    lambda d: dataset.plot_run(None, d),
    lambda d: pt.plot_all(_report(), d),
], ids=["fastslam", "lines", "slam3d", "uwb", "dataset", "tuning"])
def test_every_plot_all_checks_its_folder_before_drawing(tmp_path, call):
    # (the other arguments are never read: the folder is checked first)
    with pytest.raises(InputError, match=r"^directory: .* is a file, not a folder"):
        call(_blocker(tmp_path))
    with pytest.raises(InputError, match=r"^directory: expected a folder path, got 5"):
        call(5)
    ro = _unwritable_folder(tmp_path)
    with pytest.raises(InputError, match=rf"^directory: cannot write into '{ro}' \("):
        call(ro)
    assert flight.plt().get_fignums() == []


# ---------------------------------------------------------------- 23: tuning figures


def test_tuning_plot_all_leaves_out_the_params_figure_only_without_params(tmp_path):
    got = pt.plot_all(_report(history=_history(params=False)), tmp_path / "a")
    assert [p.name for p in got] == ["s_t_mse_loss.png", "s_t_mse_before_after.png"]
    got = pt.plot_all(_report(), tmp_path / "b")
    assert [p.name for p in got] == ["s_t_mse_loss.png", "s_t_mse_params.png", "s_t_mse_before_after.png"]


@pytest.mark.parametrize("change, msg", [
    (lambda h: h[1]["params"].update(Q=[0.1, 0.2, 0.3]), r"record 1's params\['Q'\] has 3 values, record 0's 2"),
    (lambda h: h[2]["params"].update(Q=["0.1", "0.2"]), r"record 2's params\['Q'\] must be a non-empty list of numbers"),
    (lambda h: h[1]["params"].pop("R"), r"record 1's 'params' names \['Q'\], expected \['Q', 'R'\]"),
    (lambda h: h[0].update(params=[1.0]), r"record 0's 'params' must be an object"),
    (lambda h: h[1].update(loss="1.5"), r"record 1's 'loss' is not a number"),
])
def test_tuning_plot_all_refuses_bad_params_naming_the_key(tmp_path, change, msg):
    h = _history()
    change(h)
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"^report\['history'\]: " + msg):
        pt.plot_all(_report(history=h), out)
    assert not out.exists() and flight.plt().get_fignums() == []  # nothing made, nothing drawn
    if "params" in msg:
        with pytest.raises(InputError, match=r"^history: " + msg):
            pt.param_trajectories(h)
    with pytest.raises(ValueError, match="no 'params' records"):  # (as before)
        pt.param_trajectories(_history(params=False))


def _side(metrics, consistency=None):
    return {"metrics": metrics, "consistency": consistency}


@pytest.mark.parametrize("report, msg", [
    (_report(before=_side({"a": {"mean": "abc"}}), after=_side({"a": {"mean": 1.0}})),
     r"^report\['before'\]\['metrics'\]\['a'\]\['mean'\]: expected a number or null, got 'abc'"),
    (_report(before=_side({"a": {"mean": 1.0}}), after=_side({"a": {"mean": "1.5"}})),
     r"^report\['after'\]\['metrics'\]\['a'\]\['mean'\]: expected a number or null"),
    (_report(before=_side({"a": 1.0}), after=_side({"a": {"mean": 1.0}})),
     r"^report\['before'\]\['metrics'\]\['a'\]: expected a summary"),
    (_report(before=_side({"a": {"mean": 1.0}, "b": {"mean": 2.0}}), after=_side({"a": {"mean": 1.0}})),
     r"^report\['after'\]\['metrics'\]: missing \['b'\]"),
    (_report(history=[], before=_side({}), after=_side({})), r"^report: nothing to compare before/after"),
    (_report(before=_side({}, {"anees": 1.0}), after=_side({}, {"anees": "2"})),
     r"^report\['after'\]\['consistency'\]\['anees'\]: expected a number or null"),
    (_report(before=_side({}, {"anees": 1.0}), after=_side({}, {"anees": 2.0, "anees_bounds": "ab"})),
     r"^report\['after'\]\['consistency'\]\['anees_bounds'\]: expected \[low, high\] numbers"),
    (_report(references={"odd": None}), r"^report\['references'\]\['odd'\]: must hold a 'metrics' object"),
])
def test_before_after_checks_what_it_reads(tmp_path, report, msg):
    with pytest.raises(InputError, match=msg):
        pt.before_after(report)
    with pytest.raises(InputError, match=msg):
        pt.plot_all(report, tmp_path / "out")
    assert not (tmp_path / "out").exists() and flight.plt().get_fignums() == []


def test_before_after_refuses_an_empty_metrics_list_and_accepts_numbers():
    with pytest.raises(InputError, match=r"^metrics: expected at least one statistic name"):
        pt.before_after(_report(), metrics=[])
    fig = pt.before_after(_report(before=_side({"a": {"mean": np.float32(1.0)}, "b": {"mean": None}}),
                                  after=_side({"a": {"mean": 2}, "b": {"mean": float("nan")}})))
    assert any(ax.get_title().startswith("a\nafter +100.0 %") for ax in fig.axes)


# ---------------------------------------------------------------- 24: attitude figures


def _rollout(T=12, tau_rows=None, **fields):
    from jaxslam.control.smc import Rollout

    q = np.zeros((T + 1, 7))
    ang = np.linspace(0.0, 0.5, T + 1)
    q[:, 0], q[:, 3] = np.cos(ang / 2), np.sin(ang / 2)
    kw = {"xa": q, "x_err": np.full((T, 6), 1e-3), "tau": np.zeros((T if tau_rows is None else tau_rows, 3))}
    kw.update(fields)
    return Rollout(xa_final=q[-1], norms=np.zeros((T, 3)), **kw)


QD = np.array([np.cos(np.pi / 12), 0.0, 0.0, np.sin(np.pi / 12)])


@pytest.mark.parametrize("kw, msg", [
    ({"rollout": _rollout(tau_rows=5)}, r"^rollout\.tau: expected T = 12 rows"),
    ({"rollout": _rollout(tau=None)}, r"^rollout\.tau: None; record the run"),
    ({"rollout": _rollout(xa=np.zeros((12, 7)))}, r"^rollout\.xa: expected T \+ 1 = 13 rows"),
    ({"max_points": 0}, r"^max_points: expected an int >= 1, got 0"),
    ({"max_points": 2.5}, r"^max_points: expected an int >= 1"),
    ({"q_d": QD[:3]}, r"^q_d: expected shape \(4,?\), got \(3,\)"),
    ({"q_d": np.zeros(4)}, r"^q_d: expected a finite unit quaternion"),
    ({"q_d": ["1", 0, 0, 0]}, r"^q_d: expected numbers"),
    ({"dt": -0.01}, r"^dt: expected a positive finite scalar"),
    ({"tau_max": "0.18"}, r"^tau_max: expected a positive finite scalar"),
])
def test_attitude_plot_all_checks_its_inputs_first(tmp_path, kw, msg):
    args = {"name": "a", "dt": 0.01, "rollout": _rollout(), "q_d": QD, "directory": tmp_path / "out",
            "tau_max": 0.18, "max_points": 5000, **kw}
    with pytest.raises(InputError, match=msg):
        attitude.plot_all(**args)
    assert not (tmp_path / "out").exists() and flight.plt().get_fignums() == []


def test_attitude_plot_all_draws_a_valid_run_decimated(tmp_path):
    paths = attitude.plot_all("a", 0.01, _rollout(), QD, tmp_path / "out", tau_max=0.18, max_points=5)
    assert [p.name for p in paths] == ["a_attitude.png", "a_state_error.png", "a_error.png"]
    assert all(p.stat().st_size > 1000 for p in paths)
    with pytest.raises(InputError, match=r"^directory: .* is a file, not a folder"):
        attitude.plot_all("a", 0.01, _rollout(), QD, _blocker(tmp_path))
