"""Edge inputs of check_psd (badly scaled, near overflow), Progress's label, a Ctrl-C in a group
of Monte Carlo processes, and trim_ends without max_gap.  Each test failed on the code before."""

import io
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from jaxslam.errors import InputError


# --------------------------------------------------------------------------- linalg.check_psd

def test_check_psd_strict_takes_a_badly_scaled_pd_matrix():
    # variances 1e200 and 1: positive definite (NumPy's Cholesky factors them exactly); the
    # strict test said "not positive definite (smallest eigenvalue 1)", its floor being
    # 1e-12 x the largest entry (1e188)
    from jaxslam.linalg import check_psd

    for M in (np.diag([1e200, 1.0]), np.diag([1.0, 1e-200]), np.array([[1e200, 1e100], [1e100, 2.0]])):
        np.linalg.cholesky(M)  # the oracle: PD
        assert check_psd(M, "M", strict=True) is M
    check_psd(np.stack([np.eye(2), np.diag([1e200, 1.0])]), "R", strict=True, stack=True)
    # singular ones stay refused, however scaled
    for M in (np.diag([1e200, 0.0]), np.array([[1e200, 1e100], [1e100, 1.0]]), np.full((2, 2), 1e200)):
        with pytest.raises(InputError, match=r"^M: not positive definite \(smallest eigenvalue"):
            check_psd(M, "M", strict=True)
    with pytest.raises(InputError, match=r"^R\[1\]: not positive definite"):
        check_psd(np.stack([np.diag([1e200, 1.0]), np.diag([1.0, 0.0])]), "R", strict=True, stack=True)


def test_check_psd_near_overflow_is_judged_not_waved_through():
    # S + S.T overflowed to inf: NaN eigenvalues, and NaN compared False, so both passed
    from jaxslam.linalg import check_psd

    with np.errstate(all="raise"):  # nor a RuntimeWarning on the way
        with pytest.raises(InputError, match=r"^M: not positive semi-definite \(smallest eigenvalue -1e\+308\)"):
            check_psd(np.diag([1e308, -1e308]), "M")
        with pytest.raises(InputError, match=r"^M: not positive definite \(smallest eigenvalue 0\)"):
            check_psd(np.diag([1.7e308, 0.0]), "M", strict=True)
        check_psd(np.diag([1.7e308, 1.0]), "M", strict=True)
        check_psd(np.full((2, 2), 1e308), "M")


def test_check_psd_decisions_for_ordinary_matrices_are_the_documented_ones():
    # variances within 1/tol of each other (random rotations of eigenvalues 1, 0.7, lam_min):
    # PSD iff lam_min >= -1e-12 x max(1, largest entry), PD iff lam_min > 1e-12 x largest entry
    # (lam_min a factor 3 or more from either floor; near the PD floor the unit-diagonal
    # rescaling, which would accept some of them, is not used)
    from jaxslam.linalg import check_psd

    rng = np.random.default_rng(35)
    for lam_min in (-1e-2, -1e-11, -1e-13, 0.0, 1e-14, 1e-13, 3e-13, 1e-11, 1e-3, 0.5):
        for _ in range(20):
            Q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
            M = (Q * np.array([1.0, 0.7, lam_min])) @ Q.T
            M = 0.5 * (M + M.T)
            mag = np.max(np.abs(M))
            assert 0.5 < mag <= 1.0 and np.min(np.diag(M)) > 1e-12 * mag
            for strict, ok in ((False, lam_min >= -1e-12), (True, lam_min > 1e-12 * mag)):
                if ok:
                    check_psd(M, "M", strict=strict)
                else:
                    with pytest.raises(InputError, match="^M: not positive"):
                        check_psd(M, "M", strict=strict)


# --------------------------------------------------------------------------- Progress(label=None)

def test_progress_label_none_is_no_label_and_a_non_string_is_refused():
    from jaxslam.progress import Progress

    t = iter(range(0, 100, 2))
    s = io.StringIO()
    p = Progress(4, None, stream=s, clock=lambda: float(next(t)), delay_s=0.0)
    assert p.label == ""  # was None: the attribute a caller reads (or appends to) is a str
    p.update(2)
    p.close()
    assert s.getvalue().startswith("[###") and "None" not in s.getvalue()
    for bad in (b"mc", 5, ["mc"]):  # printed as their repr ("b'mc' [###...")
        with pytest.raises(InputError, match=r"^label: expected a str or None"):
            Progress(4, bad, stream=io.StringIO())


# --------------------------------------------------------------------------- Ctrl-C in a group

_GROUP = textwrap.dedent("""
    import os, signal, sys
    # Ctrl-C as a terminal delivers it: a suite started in the background without job control
    # (nohup ... &) hands its children SIGINT ignored, and Python then keeps ignoring it
    signal.signal(signal.SIGINT, signal.default_int_handler)
    pid, port, who = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    from jaxslam.sim import distributed, monte_carlo
    distributed.initialize(f"127.0.0.1:{port}", 2, pid)
    import jax

    def fn(key):
        return {"x": jax.random.normal(key, ())}

    class P:  # a real SIGINT (Ctrl-C) to this process after its first chunk of 2 runs
        def update(self, n):
            if who in ("all", str(pid)):
                os.kill(os.getpid(), signal.SIGINT)

    try:
        r = monte_carlo.run(fn, 0, 8, chunk=2, progress=P())
        print(f"RESULT runs={r.runs} interrupted={r.interrupted} rows={r.out['x'].shape[0]}", flush=True)
    except KeyboardInterrupt:
        print("INTERRUPTED", flush=True)
""")


@pytest.mark.parametrize("who", ["all", "1", "none"])
def test_a_ctrl_c_in_a_group_of_processes_interrupts_every_process(tmp_path, who):
    # before: both interrupted -> each returned runs 8, interrupted False, with 4 rows (runs 0,
    # 1, 4, 5 as runs 0-3); one interrupted -> gloo aborted both ("collective mismatch")
    from jaxslam.sim import distributed

    script = tmp_path / "group.py"
    script.write_text(_GROUP)
    port = str(distributed.free_port())
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs = [subprocess.Popen([sys.executable, str(script), str(i), port, who], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env) for i in range(2)]
    outs = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=120)
            outs.append((p.returncode, out.strip().splitlines()[-1:] or [""], err))
    finally:
        for p in procs:  # none left running, whatever happened
            if p.poll() is None:
                p.kill()
                p.wait()
    want = "RESULT runs=8 interrupted=False rows=8" if who == "none" else "INTERRUPTED"
    for rc, last, err in outs:
        assert rc == 0 and last == [want], (rc, last, err[-2000:])


# --------------------------------------------------------------------------- lines.trim_ends

def test_trim_ends_without_max_gap_is_refused_not_ignored():
    import jax

    from jaxslam.features import lines as L

    x = np.linspace(-2.0, 2.0, 60)
    pts = np.stack([x, np.full_like(x, 1.5)], axis=1)
    bad = L.DEFAULT_RANSAC._replace(trim_ends=3)  # max_gap 0: the same 60 inliers as trim_ends 0
    with pytest.raises(InputError, match=r"^cfg\.trim_ends: .*max_gap"):
        L.check_ransac_config(bad)
    with pytest.raises(InputError, match=r"^cfg\.trim_ends: .*max_gap"):
        L.extract_lines(jax.random.PRNGKey(0), pts, np.ones(60, bool), bad)
    L.check_ransac_config(L.DEFAULT_RANSAC._replace(max_gap=10, trim_ends=3))  # paper 004's setting
    L.check_ransac_config(L.DEFAULT_RANSAC._replace(max_gap=10))
