"""MRCLAM's barcode table: a subject or a barcode listed twice is refused at its second line,
naming the first (int_column(unique=True), which the loader's own loop repeated before)."""

import shutil

import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import DataFormatError, load_mrclam


@pytest.mark.parametrize("row, match", [
    ("  2 \t 99", r"Barcodes\.dat:\d+: subject 2 listed twice \(first at .*Barcodes\.dat:6\)"),
    (" 99 \t 14", r"Barcodes\.dat:\d+: barcode 14 listed twice \(first at .*Barcodes\.dat:6\)"),
])
def test_barcode_table_repeat_is_refused_at_its_line(tmp_path, row, match):
    d = tmp_path / "mrclam6"
    shutil.copytree(EXCERPTS / "mrclam6", d)
    f = d / "Barcodes.dat"
    lines = f.read_text().splitlines()
    lines.append(row)
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=match) as ei:
        load_mrclam(tmp_path, 1)
    assert ei.value.line == len(lines)
