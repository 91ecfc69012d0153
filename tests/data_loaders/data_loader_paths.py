"""Paths shared by the loader tests (imported by several test files of tests/data_loaders).

``EXCERPTS``: the committed excerpts (``tests/data``).  ``FULL``: the full data folder,
``$JAXSLAM_DATA_DIR`` if set, else ``../shared/data`` next to the repository; tests on the full
files skip when it is absent (a fresh clone has no such folder).
"""

import os
from pathlib import Path

import pytest

EXCERPTS = Path(__file__).resolve().parents[1] / "data"
BAD = EXCERPTS / "bad"
FULL = Path(os.environ.get("JAXSLAM_DATA_DIR")
            or Path(__file__).resolve().parents[2].parent / "shared" / "data")


def data_lines(path, comment="#", skip=0):
    """(1-based line number, fields) of every data line, parsed with plain Python."""
    out = []
    with open(path, encoding="utf-8", newline="") as f:
        for i, s in enumerate(f.read().split("\n"), start=1):
            s = s.strip()
            if i <= skip or not s or s.startswith(comment):
                continue
            out.append((i, s.replace(",", " ").split()))
    return out


def needs_full(*parts):
    """Skip marker: the full-data folder (or a sub-path of it) is absent."""
    p = FULL.joinpath(*parts)
    return pytest.mark.skipif(not p.exists(), reason=f"full dataset not available at {p}")
