"""Numeric text tables with error messages that point at ``file:line``.

The real-dataset loaders (:mod:`jaxslam.data.mrclam`, ``victoria_park``,
``plaza``, ``util_uwb``) read every file through :func:`read_table`.  It accepts
whitespace-separated (tabs and spaces mixed, CRLF line ends, trailing
delimiters) and comma-separated files, ``#`` comment/header lines, a fixed
number of header rows (optionally checked against the expected column names)
and gzip-compressed files, and it refuses bad input with a
:class:`DataFormatError` whose message starts with ``path:line:`` (1-based):

* a truncated line or a wrong number of columns,
* a field that is not a number,
* a non-finite value (``nan``/``inf``) where it is not allowed,
* time going backwards in a time column (equal times are allowed).

A last line without a line end that still parses (a file cut inside its last number reads as
a shorter, valid number) is read, with a :class:`TruncatedLineWarning` naming ``path:line``:
every file of the supported datasets ends with a line end, so its absence says the file may
have been cut short.

Speed: the whole file is parsed by ``np.loadtxt`` (a C parser) in one call;
only when that fails, or when a check on the parsed array fails, is the
offending line located (by a Python scan, or from the row index), so a
70 000-line file loads in well under a second.

Everything here is host-side NumPy; nothing needs JAX.
"""

from __future__ import annotations

import gzip as _gzip
import operator
import os
import warnings
import zlib
from pathlib import Path
from typing import NamedTuple, Optional, Sequence, Union

import numpy as np

from ..errors import InputError, check_int

__all__ = [
    "DataFormatError",
    "MissingDataError",
    "TruncatedLineWarning",
    "Table",
    "read_table",
    "int_column",
    "resolve_dataset_dir",
    "location",
    "path_arg",
    "ID_MAX",
]

PathLike = Union[str, os.PathLike]

#: the largest id a loader keeps (ids become int32 event labels): :func:`int_column`'s ``hi``
ID_MAX = int(np.iinfo(np.int32).max)


class DataFormatError(InputError):
    """A data file is malformed (or missing); the message names ``path:line``.

    Attributes:
      path: the file (a ``str``).
      line: 1-based line number of the offending line, or ``None`` when the
        problem concerns the whole file (missing, empty, corrupt gzip).
      reason: the message without the location prefix.

    ``str(err)`` is ``"{path}:{line}: {reason}"`` (``"{path}: {reason}"`` when
    ``line`` is ``None``).  It is an :class:`~jaxslam.errors.InputError` and
    therefore a ``ValueError``.
    """

    def __init__(self, path: PathLike, line: Optional[int], reason: str):
        self.path = str(path)
        self.line = None if line is None else int(line)
        self.reason = str(reason)
        super().__init__(self._text())

    def _text(self) -> str:
        if self.line is None:
            return f"{self.path}: {self.reason}"
        return f"{self.path}:{self.line}: {self.reason}"

    def __str__(self) -> str:  # OSError (MissingDataError) would format its own
        return self._text()

    def __reduce__(self):
        return (type(self), (self.path, self.line, self.reason))


class MissingDataError(DataFormatError, FileNotFoundError):
    """A data file or dataset folder does not exist (``line`` is ``None``).

    Also a ``FileNotFoundError``, so ``except FileNotFoundError`` catches it.
    """


class TruncatedLineWarning(UserWarning):
    """The last line of a data file has no line end: the file may have been cut short, and the
    line's last number may be incomplete.  The line is read as it stands (module docstring)."""


def path_arg(path, name: str = "path") -> Path:
    """``path`` as a :class:`~pathlib.Path` when it is a ``str`` or ``os.PathLike``, else
    :class:`InputError` naming ``name`` (``Path(None)`` was a bare ``TypeError``)."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"{name}: expected a file or folder path (str or os.PathLike), got {path!r}"[:300])
    return Path(path)


def _column_index(value, name: str, ncols: int) -> int:
    """One column index, an int in [-ncols, ncols) as NumPy indexes (-1: the last column),
    returned in [0, ncols); else :class:`InputError` naming ``name``."""
    try:
        c = None if isinstance(value, (bool, np.bool_)) else operator.index(value)
    except TypeError:
        c = None
    if c is None:
        raise InputError(f"{name}: expected an int column index, got {value!r}"[:300])
    if not -ncols <= c < ncols:
        raise InputError(f"{name}: column index {c} is out of range for {ncols} column(s) "
                         f"(indices are 0-based; -1 is the last)")
    return int(c) % ncols


def _columns_arg(value, name: str, ncols: int) -> list:
    """Column indices (an int or a sequence of ints) in [-ncols, ncols), as indices in
    [0, ncols); else :class:`InputError`."""
    many = not isinstance(value, (int, np.integer)) or isinstance(value, (bool, np.bool_))
    try:
        items = list(value) if many else [value]
    except TypeError:  # not iterable
        items = None
    if items is None or (many and isinstance(value, (str, bytes))):
        raise InputError(f"{name}: expected a column index or a sequence of them, got {value!r}"[:300])
    return [_column_index(c, name, ncols) for c in items]


def location(path: PathLike, line: int) -> str:
    """``"path:line"``, the form used in reports and error messages."""
    return f"{path}:{int(line)}"


class Table(NamedTuple):
    """A parsed numeric table.

    data: (n, ncols) float64; lines: (n,) int64 1-based source line of each
    row; path: the file read (``str``).
    """

    data: np.ndarray
    lines: np.ndarray
    path: str

    def error(self, row: int, reason: str) -> DataFormatError:
        """A :class:`DataFormatError` located at data row ``row``."""
        return DataFormatError(self.path, int(self.lines[row]), reason)

    def where(self, row: int) -> str:
        """``"path:line"`` of data row ``row``."""
        return location(self.path, int(self.lines[row]))


def _read_text(path: Path, gz: bool) -> str:
    if not path.is_file():
        raise MissingDataError(path, None, "file not found")
    try:
        if gz:
            with _gzip.open(path, "rb") as f:
                raw = f.read()
        else:
            raw = path.read_bytes()
    except (EOFError, zlib.error, _gzip.BadGzipFile) as e:
        raise DataFormatError(path, None, f"corrupt or truncated gzip stream ({e})") from None
    return raw.decode("utf-8-sig", errors="replace")  # a byte-order mark (spreadsheet CSV) is not data


def _split(s: str, delimiter: Optional[str]) -> list:
    if delimiter is None:
        return s.split()
    fields = [f.strip() for f in s.split(delimiter)]
    if fields and fields[-1] == "" and len(fields) > 1:
        fields.pop()  # a trailing delimiter ("1,2,3,") is not an extra column
    return fields


def _scan(path, rows, ncols, delimiter, truncated_last):
    """Python line scan: raise at the first malformed line (or return None)."""
    last = len(rows) - 1
    for k, (lineno, s) in enumerate(rows):
        fields = _split(s, delimiter)
        cut = " (truncated line: no newline at end of file)" if (k == last and truncated_last) else ""
        if len(fields) != ncols:
            raise DataFormatError(path, lineno, f"expected {ncols} columns, got {len(fields)}{cut}")
        for j, f in enumerate(fields):
            try:
                if not f.isascii() or "_" in f:  # Python's float() reads '1_000' and other scripts' digits
                    raise ValueError(f)
                float(f)
            except ValueError:
                raise DataFormatError(
                    path, lineno, f"non-numeric field {f!r} in column {j + 1}{cut}") from None
    return None


def read_table(path: PathLike, ncols: int, *, delimiter: Optional[str] = None,
               header_rows: int = 0, header: Optional[Sequence[str]] = None,
               comments: Optional[str] = "#", gz: Optional[bool] = None,
               time_cols: Union[int, Sequence[int], None] = None,
               finite: Union[bool, Sequence[int]] = True,
               allow_empty: bool = False) -> Table:
    """Read a numeric table, raising :class:`DataFormatError` at ``path:line``.

    Args:
      path: the file.
      ncols: the exact number of columns every data line must have (an int >= 1).
      delimiter: ``None`` for any run of whitespace (tabs/spaces mixed), or a
        single character such as ``","``.  A trailing delimiter is ignored.
      header_rows: lines skipped at the top before comment handling (e.g. a
        CSV header row); an int >= 0.
      header: if given (with ``header_rows >= 1``), the expected column names
        of the first header row; a mismatch raises at line 1.
      comments: lines whose first non-blank characters are this prefix are
        skipped (anywhere in the file); ``None`` to disable.  Blank lines are
        always skipped.
      gz: read through gzip (True/False, or 1/0); default: when the name ends
        in ``.gz``.
      time_cols: column index (or indices; 0-based, in ``[-ncols, ncols)``,
        -1 the last as in NumPy) holding times that must not decrease (equal
        consecutive times are allowed).
      finite: ``True``: every value must be finite; a sequence of column
        indices (as ``time_cols``): only those columns; ``False``: no check.
      allow_empty: accept a file without data rows (returns a (0, ncols)
        table); True/False, or 1/0.

    Returns:
      :class:`Table` ``(data, lines, path)``.

    Raises:
      InputError: an argument is not of the kind described above (named in the message).
      MissingDataError: the file does not exist.
      DataFormatError: see the module docstring.
    """
    p = path_arg(path)
    ncols = check_int(ncols, "ncols", 1)
    header_rows = check_int(header_rows, "header_rows", 0)  # -1 read the last line as a data row
    if delimiter is not None and not (isinstance(delimiter, str) and len(delimiter) == 1):
        raise InputError(f"delimiter: expected None (whitespace) or one character, got {delimiter!r}"[:300])
    if comments is not None and not (isinstance(comments, str) and comments):
        raise InputError(f"comments: expected None or a non-empty prefix string, got {comments!r}"[:300])
    if header is not None and header_rows < 1:
        raise InputError("header: the expected column names are checked against the first header row; "
                         "give header_rows >= 1")
    flags = {}
    for flag, v in (("gz", gz), ("allow_empty", allow_empty)):
        if flag == "gz" and v is None:
            flags[flag] = None
            continue
        # True/False, or the ints 0 and 1 (read as truth values before)
        is_int = isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
        if not (isinstance(v, (bool, np.bool_)) or (is_int and v in (0, 1))):
            raise InputError(f"{flag}: expected True or False{' (or None)' if flag == 'gz' else ''}, got {v!r}"[:300])
        flags[flag] = bool(v)
    gz, allow_empty = flags["gz"], flags["allow_empty"]
    tcs = None if time_cols is None else _columns_arg(time_cols, "time_cols", ncols)
    finite = bool(finite) if isinstance(finite, (bool, np.bool_)) else _columns_arg(finite, "finite", ncols)
    spath = str(p)
    if gz is None:
        gz = p.name.endswith(".gz")
    text = _read_text(p, gz)
    all_lines = text.split("\n")
    truncated_last = bool(text) and not text.endswith("\n")
    if all_lines and all_lines[-1] == "":
        all_lines.pop()
    if header_rows:
        if len(all_lines) < header_rows:
            raise DataFormatError(spath, max(len(all_lines), 1),
                                  f"expected {header_rows} header line(s), file has {len(all_lines)} line(s)")
        if header is not None:
            got = _split(all_lines[0].rstrip("\r"), delimiter)
            if [g.strip() for g in got] != list(header):
                sep = delimiter or " "
                raise DataFormatError(spath, 1, f"expected header {sep.join(header)!r}, "
                                                f"got {all_lines[0].rstrip(chr(13))!r}")
    rows = []
    for i in range(header_rows, len(all_lines)):
        s = all_lines[i].rstrip("\r")
        t = s.strip()
        if not t or (comments is not None and t.startswith(comments)):
            continue
        rows.append((i + 1, s))
    if not rows:
        if allow_empty:
            return Table(np.zeros((0, ncols)), np.zeros((0,), np.int64), spath)
        raise DataFormatError(spath, len(all_lines) or None, "no data rows")
    lines = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
    data = None
    try:
        data = np.loadtxt([r[1] for r in rows], dtype=np.float64, delimiter=delimiter,
                          comments=None, ndmin=2)
    except ValueError:
        data = None
    if data is None or data.shape != (len(rows), ncols):
        _scan(spath, rows, ncols, delimiter, truncated_last)
        # loadtxt refused something the scan accepts (should not happen): parse by hand
        data = np.array([[float(f) for f in _split(s, delimiter)] for _, s in rows], dtype=np.float64)
    tab = Table(data, lines, spath)
    if truncated_last and rows[-1][0] == len(all_lines):
        warnings.warn(f"jaxslam: {spath}:{rows[-1][0]}: the last line has no line end (file cut short?); "
                      "read as it stands, its last number may be incomplete", TruncatedLineWarning, stacklevel=2)
    if finite is not False:
        cols = list(range(ncols)) if finite is True else finite
        sub = data[:, cols]
        bad = ~np.isfinite(sub)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise tab.error(int(r), f"non-finite value {float(sub[r, c])!r} in column {cols[c] + 1}")
    if tcs is not None:
        for c in tcs:
            rows = np.flatnonzero(~np.isnan(data[:, c]))  # (a NaN time, kept by finite=False, must
            d = np.diff(data[rows, c])                    # not hide a step back across it)
            if d.size and np.any(d < 0):
                k = int(np.argmax(d < 0))
                r, r0 = int(rows[k + 1]), int(rows[k])
                raise tab.error(r, f"time goes backwards in column {c + 1}: {float(data[r, c])!r} after "
                                   f"{float(data[r0, c])!r} (line {int(lines[r0])})")
    return tab


def int_column(tab: Table, col: int, name: str, lo: Optional[int] = None,
               hi: Optional[int] = None, unique: bool = False) -> np.ndarray:
    """Column ``col`` of ``tab`` (0-based; -1 the last) as int64, checked integral (and in
    [lo, hi], and, with ``unique``, listed once).

    Integer fields may be written as floats (``2.0000000000000000e+000``).  A value beyond the
    int64 range is refused too (it used to wrap around).  Raises :class:`DataFormatError` at the
    first offending line (for a repeated value: the second line, naming the first).
    """
    col = _column_index(col, "col", tab.data.shape[1])  # -1: the last column, as NumPy indexed it before
    v = tab.data[:, col]
    r = np.rint(v)
    wide = ~((r >= -(2.0 ** 63)) & (r < 2.0 ** 63))  # 1e30 wrapped to -2**63
    bad = (r != v) | wide
    if lo is not None:
        bad |= r < lo
    if hi is not None:
        bad |= r > hi
    if bad.any():
        i = int(np.argmax(bad))
        if wide[i]:  # checked first: 1e30 with lo=0 is not "expected an integer >= 0"
            rng = " in the int64 range"
        else:
            rng = {(False, False): f" in [{lo}, {hi}]", (False, True): f" >= {lo}", (True, False): f" <= {hi}",
                   (True, True): ""}[(lo is None, hi is None)]
        raise tab.error(i, f"{name} (column {col + 1}): expected an integer{rng}, got {float(v[i])!r}")
    out = r.astype(np.int64)
    if unique:
        _, first, inv = np.unique(out, return_index=True, return_inverse=True)
        dup = np.nonzero(first[inv] != np.arange(out.size))[0]
        if dup.size:  # e.g. two surveyed positions for one anchor: which one is the truth?
            i = int(dup[0])
            raise tab.error(i, f"{name} {int(out[i])} listed twice (first at {tab.where(int(first[inv[i]]))})")
    return out


def resolve_dataset_dir(path: PathLike, subdir: str, required: Sequence[str], what: str) -> Path:
    """Find the folder holding ``required`` files: ``path`` itself, ``path/subdir``, or else
    the one subfolder of ``path`` that holds them all (e.g. an unpacked ``MRCLAM_Dataset9/``).

    Raises :class:`MissingDataError` listing the folders looked in and the
    files missing from the best candidate (or naming the subfolders when several qualify).
    """
    base = path_arg(path)
    cands = [base, base / subdir] if base.name != subdir else [base]
    best, best_n = None, -1
    for c in cands:
        n = sum((c / f).is_file() for f in required) if c.is_dir() else -1
        if n > best_n:
            best, best_n = c, n
    if best is not None and best_n == len(required):
        return best
    if base.is_dir():
        subs = sorted(c for c in base.iterdir() if c.is_dir() and all((c / f).is_file() for f in required))
        if len(subs) == 1:
            return subs[0]
        if len(subs) > 1:
            raise MissingDataError(base, None, f"{what}: several folders in {base} hold the files "
                                               f"({', '.join(c.name for c in subs)}); name one with --data")
    looked = " or ".join(str(c) for c in cands)
    if best_n <= 0:
        raise MissingDataError(base, None, f"{what}: no dataset files found; looked in {looked} "
                                           f"for {', '.join(required)}")
    missing = [f for f in required if not (best / f).is_file()]
    where = best / missing[0] if len(missing) == 1 else best
    raise MissingDataError(where, None, f"{what}: missing file(s) {', '.join(missing)} "
                                        f"(looked in {looked})")
