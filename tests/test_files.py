"""Output paths checked before compute (jaxslam.files) and the --params schema (jaxslam.paramfile)."""

from __future__ import annotations


import numpy as np
import pytest
from folders import unwritable_folder as _unwritable_folder

from jaxslam import files, paramfile
from jaxslam.errors import InputError


def test_prepare_file_creates_parents_and_refuses_folders_and_files_in_the_way(tmp_path):
    p = files.prepare_file("--json", tmp_path / "a" / "b" / "r.json")
    assert p.parent.is_dir() and not p.exists()  # the folder is made, the file is not
    assert list(p.parent.iterdir()) == []  # the write probe is removed
    with pytest.raises(InputError, match=r"--json: .* is a folder; give a file path"):
        files.prepare_file("--json", tmp_path / "a")
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match=r"--json: '.*f' is a file, so '.*f/r.json' cannot be created"):
        files.prepare_file("--json", tmp_path / "f" / "r.json")
    with pytest.raises(InputError, match=r"--tum: '.*f' is a file"):
        files.prepare_file("--tum", tmp_path / "f" / "deeper" / "t.txt")


def test_prepare_dir(tmp_path):
    d = files.prepare_dir("--plots", tmp_path / "p" / "q")
    assert d.is_dir() and list(d.iterdir()) == []
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="--plots: .* exists and is not a folder"):
        files.prepare_dir("--plots", tmp_path / "f")


def test_unwritable_folder_is_refused_naming_the_option(tmp_path):
    ro = _unwritable_folder(tmp_path)
    with pytest.raises(InputError, match=r"--json: cannot write into .*\("):
        files.prepare_file("--json", ro / "r.json")
    with pytest.raises(InputError, match=r"--plots: cannot write into"):
        files.prepare_dir("--plots", ro)


SCHEMA = {"noise": {"Q": np.diag([1.0, 2.0]), "r": 0.1, "gain": np.ones(3), "flag": False,
                    "A": np.array([[0.0, 1.0], [-1.0, 0.0]])}}  # A: not symmetric, so any 2×2 passes


@pytest.mark.parametrize("value, ok", [
    ([[1, 0], [0, 1]], True), ([3, 4], True), ([0, 0], True),  # PSD, diagonal, zero (PSD)
    ([[1, 2], [2, 1]], False), ([-1, 1], False), ([[1, 0.5], [0, 1]], False), ([1, 2, 3], False),
    ([[1, float("nan")], [float("nan"), 1]], False), ("x", False),
])
def test_covariance_values(value, ok):
    doc = {"noise": {"Q": value}}
    if ok:
        assert paramfile.check(doc, SCHEMA, target="t") == doc
    else:
        with pytest.raises(InputError, match=r"--params: noise\.Q: "):
            paramfile.check(doc, SCHEMA, target="t")


def test_other_shapes_and_types():
    assert paramfile.check({"noise": {"A": [[5, 6], [7, 8]], "r": 2, "flag": True}}, SCHEMA, target="t")
    for doc, needle in (({"noise": {"r": [1]}}, "noise.r: expected a number"),
                        ({"noise": {"gain": [[1, 2, 3]]}}, "noise.gain: expected 3, got shape 1×3"),
                        ({"noise": {"flag": 1}}, "noise.flag: expected true or false"),
                        ({"noise": {"r": True}}, "noise.r: expected numbers"),
                        ({"noise": {"A": [1, 2]}}, r"noise.A: expected 2×2, got shape 2$")):
        with pytest.raises(InputError, match=needle):
            paramfile.check(doc, SCHEMA, target="t")


def test_provenance_and_no_schema():
    assert paramfile.check({"scenario": "t", "noise": {}}, SCHEMA, target="t") == {"noise": {}}
    with pytest.raises(InputError, match="delete its 'scenario' key"):
        paramfile.check({"scenario": "u", "noise": {}}, SCHEMA, target="t")
    with pytest.raises(InputError, match="takes no --params file"):
        paramfile.check({"noise": {}}, None, target="t")
    assert paramfile.check({"scenario": "t"}, None, target="t") == {}
    text = " ".join(paramfile.describe(SCHEMA).split())
    assert "Q (2×2 symmetric PSD or 2 diagonal values)" in text and "flag (true/false)" in text
    assert "A (2×2)" in text and "r (a number)" in text


def test_prepare_file_without_create_makes_nothing_and_still_refuses(tmp_path):
    # (jaxslam bench checks --json this way before its own options are parsed)
    target = tmp_path / "a" / "b" / "x.json"
    assert files.prepare_file("--json", target, create=False) == target
    assert not (tmp_path / "a").exists() and list(tmp_path.iterdir()) == []
    (tmp_path / "f").write_text("")
    with pytest.raises(InputError, match=r"^--json: '.*/f' is a file, so"):
        files.prepare_file("--json", tmp_path / "f" / "x.json", create=False)
    files.prepare_file("--json", target)  # the default makes the folders
    assert (tmp_path / "a" / "b").is_dir()


def test_symbolic_links_are_checked_where_they_lead(tmp_path):
    """prepare_file probes the folder a link leads to (atomic_write writes there), and a link
    that cannot be followed (a loop) is an InputError naming the flag in prepare_file,
    distinct_outputs and atomic_write (a bare RuntimeError reached the end of a run before)."""
    loop = tmp_path / "loop.json"
    loop.symlink_to(loop)
    for call in (lambda: files.prepare_file("--json", loop), lambda: files.distinct_outputs(json=loop)):
        with pytest.raises(InputError, match=r"^--json: .*loop\.json' is a symbolic link that cannot be followed"):
            call()
    with pytest.raises(InputError, match=r"^path: .*symbolic link that cannot be followed"):
        files.atomic_write(loop, lambda f: f.write("x"))
    (tmp_path / "afile").write_text("")
    link = tmp_path / "out.json"
    link.symlink_to(tmp_path / "afile" / "run.json")  # leads under a file: nothing can be written there
    with pytest.raises(InputError, match=r"^--json: "):
        files.prepare_file("--json", link)
    ok = tmp_path / "ok.json"
    ok.symlink_to(tmp_path / "real" / "run.json")
    assert files.prepare_file("--json", ok) == ok and (tmp_path / "real").is_dir()
    files.atomic_write(ok, lambda f: f.write("{}"))
    assert ok.is_symlink() and (tmp_path / "real" / "run.json").read_text() == "{}"
