"""Review of jaxslam/cli/bench.py, jaxslam/progress.py and jaxslam/tuning/params.py: a benchmark
that defines one of ``jaxslam bench``'s own options is a usage error naming it (exit 2), as are
the options of its argument groups; the log-diagonal / log-Cholesky constructors check the range
of the dtype θ really gets (float32 without x64), refuse an empty matrix with an InputError, and
agree with NumPy re-derivations and finite differences; ``Progress(width=40.0)`` stays refused,
as ``errors.check_int`` refuses a float count."""

import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli
from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.tuning import params as P

_BENCH = '''
DESCRIPTION = "review benchmark"


def add_arguments(parser):
{body}


def run(args):
    return {{"results": [{{"case": "a", "jaxslam_s": 1.0}}]}}
'''


def _bench_dir(tmp_path, body):
    d = tmp_path / "benches"
    d.mkdir()
    (d / "bench_mine.py").write_text(_BENCH.format(body=textwrap.indent(textwrap.dedent(body), "    ")))
    return d


@pytest.mark.parametrize("opt", ["--dir", "--json", "--debug", "--help"])
def test_bench_defining_an_own_option_of_bench_is_a_usage_error_naming_it(tmp_path, capsys, opt):
    d = _bench_dir(tmp_path, f'parser.add_argument("{opt}", type=str)')
    rc = cli.main(["bench", "mine", "--dir", str(d)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "internal error" not in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert opt in err and "bench_mine.py" in err, err


def test_bench_option_in_a_group_defining_json_is_a_usage_error(tmp_path, capsys):
    d = _bench_dir(tmp_path, '''
        g = parser.add_argument_group("mine")
        g.add_argument("--json", type=str)''')
    rc = cli.main(["bench", "mine", "--dir", str(d)])
    err = capsys.readouterr().err
    assert rc == 2 and "--json" in err and "internal error" not in err, err


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_bench_float_option_of_a_group_must_be_finite(tmp_path, capsys, value):
    d = _bench_dir(tmp_path, '''
        g = parser.add_mutually_exclusive_group()
        g.add_argument("--scale", type=float, default=1.0)''')
    rc = cli.main(["bench", "mine", "--dir", str(d), "--scale", value])
    err = capsys.readouterr().err
    assert rc == 2 and "--scale" in err and "internal error" not in err, err


def test_bench_benchmark_with_own_distinct_options_still_runs(tmp_path, capsys):
    d = _bench_dir(tmp_path, 'parser.add_argument("--jsonl", type=str)')
    rc = cli.main(["bench", "mine", "--dir", str(d), "--jsonl", "x"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "benchmark mine" in out.out


# --------------------------------------------------------------------------- progress


def test_progress_integral_float_width_stays_refused_as_check_int_does():
    with pytest.raises(InputError, match=r"^width: "):
        Progress(4, width=40.0)


# --------------------------------------------------------------------------- tuning params


def _numpy_log_chol(M):
    L = np.linalg.cholesky(M)
    d = np.diag(L)
    r, c = np.tril_indices(len(M), -1)
    return np.concatenate([np.log(d), (L / d[:, None])[r, c]])


def _numpy_cov(theta, n):
    r, c = np.tril_indices(n, -1)
    C = np.eye(n)
    C[r, c] = theta[n:]
    L = np.exp(theta[:n])[:, None] * C
    return L @ L.T


@pytest.mark.parametrize("n", [1, 2, 4])
def test_log_chol_matches_numpy_and_finite_differences(n):
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    M = A @ A.T + 0.3 * np.eye(n)
    th = np.asarray(P.log_chol_from_cov(M, dtype=jnp.float64))
    np.testing.assert_allclose(th, _numpy_log_chol(M), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(P.cov_from_log_chol(jnp.asarray(th), n)), M, rtol=1e-12, atol=1e-12)
    W = rng.normal(size=(n, n))
    g = np.asarray(jax.grad(lambda t: jnp.sum(jnp.asarray(W) * P.cov_from_log_chol(t, n)))(jnp.asarray(th)))
    eps = 1e-6
    fd = np.array([(np.sum(W * _numpy_cov(th + eps * e, n)) - np.sum(W * _numpy_cov(th - eps * e, n))) / (2 * eps)
                   for e in np.eye(len(th))])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)


def test_log_diag_floor_matches_hand_values():
    th = np.asarray(P.log_diag_from_cov([0.0, 2.0, 0.1], floor=0.5, dtype=jnp.float64))
    np.testing.assert_allclose(th, np.log([0.5, 2.0, 0.5]), rtol=1e-15)


@pytest.mark.parametrize("ctor", [P.log_diag_from_cov, P.log_chol_from_cov])
def test_empty_matrix_is_an_input_error_naming_it(ctor):
    with pytest.raises(InputError, match=r"^Q: "):
        ctor(np.zeros((0, 0)), name="Q")


def test_default_dtype_without_x64_checks_float32_range():
    # a fresh process without x64: the default dtype is float32, whose range 1e-50 is outside
    code = textwrap.dedent('''
        import jax, numpy as np
        assert not jax.config.jax_enable_x64
        from jaxslam.errors import InputError
        from jaxslam.tuning import params as P
        for ctor, M in ((P.log_diag_from_cov, [1e-50, 1.0]), (P.log_chol_from_cov, np.diag([1e39, 1e38]))):
            try:
                th = ctor(M)
            except InputError as e:
                assert "float32" in str(e), e
            else:
                raise SystemExit(f"no error: theta {th} dtype {th.dtype}")
        th = P.log_diag_from_cov([2.0, 3.0])
        assert th.dtype == np.float32, th.dtype
        print("ok")
    ''')
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stdout + res.stderr


def _float32_one_ulp_asymmetric():
    M = np.array([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 0.5]], np.float32)
    M[0, 1] = np.nextafter(M[0, 1], np.float32(1))  # float32 rounding of a product, say
    return M


@pytest.mark.parametrize("via", ["log_chol_from_cov", "theta_from_cov", "pack"])
def test_log_chol_takes_a_float32_matrix_symmetric_to_its_precision(via):
    M = _float32_one_ulp_asymmetric()
    if via == "log_chol_from_cov":
        th = P.log_chol_from_cov(M, dtype=jnp.float32)
    elif via == "theta_from_cov":
        th = P.theta_from_cov(P.CovSpec("chol", 3), M, dtype=jnp.float32)
    else:
        th = P.pack({"R": P.CovSpec("chol", 3)}, {"R": M}, dtype=jnp.float32)["R"]
    S = 0.5 * (M.astype(np.float64) + M.astype(np.float64).T)
    assert th.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(th, np.float64), _numpy_log_chol(S), rtol=1e-6, atol=1e-6)


def test_log_chol_still_refuses_a_float64_matrix_off_by_float32_rounding():
    M = _float32_one_ulp_asymmetric().astype(np.float64)
    with pytest.raises(InputError, match="^M: not symmetric"):
        P.log_chol_from_cov(M)
