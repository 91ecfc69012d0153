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
