"""A repository script (``scripts/NAME.py``) loaded as a module in a test process.

The scripts call ``runtime.configure_process()`` on import (OpenBLAS threads, XLA flags); in a
test process that is already configured, so it is replaced by a no-op while the module loads.
"""

import importlib.util
import pathlib
from unittest import mock

ROOT = pathlib.Path(__file__).resolve().parents[2]


def load_script(name: str, tag: str = "test"):
    """``scripts/{name}.py`` as a fresh module (named ``{name}_{tag}``; not put in ``sys.modules``)."""
    from jaxslam import runtime

    spec = importlib.util.spec_from_file_location(f"{name}_{tag}", ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    with mock.patch.object(runtime, "configure_process", lambda *a, **k: {}):
        spec.loader.exec_module(mod)
    return mod


def no_compute(*a, **k):
    """Stands in for anything that computes: a usage error must come before it."""
    raise AssertionError("computed before the usage error")


# Run a script as ``python PROBE SCRIPT ARGS...``: its stderr ends with whether JAX was imported
# (a script must answer --help and usage errors before it imports JAX).
JAX_PROBE = """
import runpy, sys
sys.argv = [sys.argv[1], *sys.argv[2:]]
try:
    runpy.run_path(sys.argv[0], run_name="__main__")
finally:
    print("JAX LOADED" if "jax" in sys.modules else "no jax", file=sys.stderr)
"""


def one_error_line(call, capsys):
    """The one line a script's usage error prints on stderr (asserting exit 2, one line and no
    traceback) when ``call()`` runs it in this process."""
    import pytest

    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        call()
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert e.value.code == 2 and len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def guarded_loader(monkeypatch, compute, tag: str):
    """``load(script)``: the script loaded (:func:`load_script`) with the names in ``compute``, the
    CLI's ``main`` (the reproduce scripts run it) and ``subprocess.run`` (reproduce_datasets)
    replaced by :func:`no_compute`: a usage error must come before any of them."""
    import subprocess

    import jaxslam.cli

    monkeypatch.setattr(jaxslam.cli, "main", no_compute)
    monkeypatch.setattr(subprocess, "run", no_compute)

    def load(script):
        mod = load_script(script, tag)
        for name in compute:
            if hasattr(mod, name):
                monkeypatch.setattr(mod, name, no_compute)
        return mod

    return load
