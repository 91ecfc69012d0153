"""Folders the tests need from the machine."""

import os
import pathlib

import pytest


def unwritable_folder(tmp_path) -> pathlib.Path:
    """A folder in which no file can be created: a read-only one, or (root ignores permission
    bits) /proc or /sys, where creating a file fails; the test is skipped where there is none."""
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        return ro
    for d in (pathlib.Path("/proc"), pathlib.Path("/sys")):
        try:
            (d / ".jaxslam-probe").touch()
        except OSError:
            return d
    pytest.skip("no folder here that this user cannot write into")
