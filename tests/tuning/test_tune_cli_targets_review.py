"""Review of ``jaxslam tune`` on the real logs (cli/tune.py, targets/mrclam.py).

Oracles: the number of training logs counted by hand from the options (mrclam: --robots,
default 1,2,3,4; plaza: --robots, default 1; util-uwb and victoria-park: one log); the
commands written out by hand for each held-out robot.
"""

import pathlib
import shlex
import shutil

import pytest

from jaxslam.cli import tune
from jaxslam.errors import InputError

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


@pytest.fixture
def no_build(monkeypatch):
    """Building a target fails the test: the refusals below must come before it."""
    from jaxslam.tuning import targets

    def fail(*a, **k):
        raise AssertionError("the target was built before the option was checked")

    monkeypatch.setattr(targets, "get", fail)


@pytest.mark.parametrize("argv, n_logs", [
    (["victoria-park", "--data", str(DATA), "--batch-size", "2"], "1 training log "),
    (["util-uwb", "--data", str(DATA), "--batch-size", "3"], "1 training log "),
    (["mrclam", "--data", str(DATA), "--robots", "1", "--test-robots", "2", "--batch-size", "2"],
     "1 training log "),
    (["mrclam", "--data", str(DATA), "--batch-size", "5"], "4 training logs "),  # default robots 1,2,3,4
    (["plaza", "--data", str(DATA), "--batch-size", "2"], "1 training log "),  # default sequence 1
])
def test_real_log_batch_size_above_the_training_logs_is_refused_before_the_build(argv, n_logs, run_cli, no_build):
    rc, out, err = run_cli(["tune", *argv])
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"jaxslam tune: error: --batch-size: {argv[-1]} is more than "
                                                   f"the {n_logs}"), err


@pytest.mark.parametrize("argv", [
    ["victoria-park", "--data", str(DATA), "--batch-size", "1"],
    ["mrclam", "--data", str(DATA), "--robots", "1,2", "--test-robots", "none", "--batch-size", "2"],
    ["mrclam", "--data", str(DATA), "--batch-size", "4"],
    ["plaza", "--data", str(DATA), "--robots", "1,2", "--test-robots", "none", "--batch-size", "2"],
])
def test_real_log_batch_size_up_to_the_training_logs_is_not_refused(argv):
    args = tune.build_parser(with_targets=False).parse_args(argv)
    try:
        tune._plan(args)
    except InputError as e:  # another check may refuse the (excerpt) folder, never --batch-size
        assert not str(e).startswith("--batch-size"), e


def test_mrclam_eval_command_names_every_held_out_robot(tmp_path, capsys):
    from jaxslam.tuning.targets import mrclam as RL

    data = tmp_path / "mrclam6"
    shutil.copytree(DATA / "mrclam6", data)
    for kind in ("Groundtruth", "Measurement", "Odometry"):  # a third robot: robot 2's log again
        shutil.copy(data / f"Robot2_{kind}.dat", data / f"Robot3_{kind}.dat")
    tg = RL.mrclam_noise(data=tmp_path, robots=(1,), test_robots=(2, 3), t_max=10.0, odometry_delay=0.0)
    assert tg.config["test_robots"] == [2, 3]
    assert tg.eval_command == ("jaxslam dataset mrclam --data DIR --robot 2 --params TUNED.json && "
                               "jaxslam dataset mrclam --data DIR --robot 3 --params TUNED.json")
    # the printed command puts the file written and the folder given into each robot's command
    rep = {"scenario": "mrclam", "target": "noise", "loss": "nll", "steps": 1, "lr": 0.1, "_tables": "",
           "_physical_after": {}, "stopped": None, "eval_command": tg.eval_command}
    tune._print_report(rep, tmp_path / "tuned file.json", tmp_path)
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("run the tuned parameters: "))
    cmds = [shlex.split(c) for c in line.split(": ", 1)[1].split(" && ")]
    assert [c[c.index("--robot") + 1] for c in cmds] == ["2", "3"]
    assert all(c[c.index("--params") + 1] == str(tmp_path / "tuned file.json") for c in cmds)
    assert all(c[c.index("--data") + 1] == str(tmp_path) for c in cmds)


def test_mrclam_eval_command_of_one_robot_is_unchanged():
    from jaxslam.tuning.targets import mrclam as RL

    assert RL._eval_command([5]) == "jaxslam dataset mrclam --data DIR --robot 5 --params TUNED.json"


def test_select_odometry_delay_compiles_once_and_matches_per_log_sums():
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxslam import compilation
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as pe
    from jaxslam.tuning.targets import mrclam as RL

    base = presets.mrclam_params(1, dtype=jnp.float64, preset="hand")
    K, cap = RL.mrclam_layout(DATA, [1])
    cfg = RL.mrclam_train_config(K, cap)
    p = RL.planar_physical(RL.planar_theta0(base), base)
    grid = (0.0, 0.1, 0.2)
    first = RL.select_odometry_delay(DATA, [1], p, cfg, t_max=10.0, grid=grid)
    with compilation.account() as acc:
        best, table = RL.select_odometry_delay(DATA, [1], p, cfg, t_max=10.0, grid=grid)
    assert acc.result.programs == 0, acc.result  # a jit made per call recompiled every time
    assert (best, table) == first
    # oracle: each delay's unpadded log through the filter, the NLL summed over its scalars in NumPy
    want = {}
    for d in grid:
        logs, _ = RL.mrclam_logs(DATA, [1], np.float64, 10.0, odometry_delay=d, K=K)
        res = pe.run(jax.tree.map(lambda a: jnp.asarray(a[0]), logs), cfg._replace(block=0), p)
        want[d] = float(np.sum(np.asarray(res.nll)) / max(float(np.sum(np.asarray(res.nll_dof))), 1.0))
    assert set(table) == set(want)
    for d in grid:
        assert table[d] == pytest.approx(want[d], rel=1e-9, abs=1e-12), d
    assert best == min(want, key=want.get)


@pytest.mark.parametrize("argv, first", [
    # one training log: --batch-size 1 draws no minibatch, so --seed would be ignored
    (["victoria-park", "--data", str(DATA), "--batch-size", "1", "--seed", "3"], "--seed"),
    (["mrclam", "--data", str(DATA), "--robots", "1", "--test-robots", "2", "--batch-size", "1", "--seed", "3"],
     "--seed"),
    # --robots is not victoria-park's: refused by name, not counted as its training logs
    (["victoria-park", "--data", str(DATA), "--robots", "1,2", "--batch-size", "2"], "--robots"),
])
def test_real_log_options_that_would_be_ignored_are_refused_by_name(argv, first, run_cli, no_build):
    rc, out, err = run_cli(["tune", *argv])
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"jaxslam tune: error: {first}:"), err


def test_real_log_seed_is_taken_when_it_seeds_minibatches():
    # 2 of the 4 default mrclam robots per step: --seed draws them
    args = tune.build_parser(with_targets=False).parse_args(
        ["mrclam", "--data", str(DATA), "--batch-size", "2", "--seed", "3"])
    plan = tune._plan(args)
    assert plan[4] is True and plan[5]["data"] == DATA  # (the default robots are the target's to check)
