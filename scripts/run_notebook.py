#!/usr/bin/env python
"""Execute a Jupyter notebook without Jupyter: a tiny, dependency-free executor.

    python scripts/run_notebook.py NOTEBOOK.ipynb [--out EXECUTED.ipynb] [--inplace] [--cwd DIR]

The code cells run in order in one namespace (as one kernel would), in this Python
process.  For each cell the executor records, in the nbformat-4 cell outputs:

* what the cell printed on stdout / stderr (``stream`` outputs);
* the value of a last bare expression (``execute_result``, ``text/plain`` repr), as
  Jupyter shows it (not when it is None or the cell ends with ``;``);
* every matplotlib figure left open at the end of the cell (``display_data`` with a PNG);
  figures are closed afterwards, and ``plt.show()`` is a no-op (Agg backend);
* an exception as an ``error`` output (name, value, traceback); execution stops there,
  the partially executed notebook is still written, and the exit code is 1.

Line magics and shell escapes (lines starting with ``%`` or ``!``) are not supported and
are skipped with a note on stderr (replaced by ``pass`` at their indentation, so a block
that holds one still parses).  A notebook that cannot be read (missing, not JSON, not
nbformat 4), ``--inplace`` with ``--out``, an ``--out`` whose folder does not exist or a
``--cwd`` that is not a folder is a usage error: one line on stderr, exit code 2, nothing
run (so is an ``--out`` that is a folder, lies under a file or cannot be written, and an
empty ``--out`` or ``--cwd``).  The notebook is read once; the executed one is written
atomically (:func:`jaxslam.files.atomic_write`).  Only the standard library, this repository's
``jaxslam`` (its argument types and file writer; no JAX) and (if the notebook uses it)
matplotlib are needed; no jupyter, nbformat or nbconvert.

Library use: ``execute(path, out_path=None, cwd=None) -> (notebook dict, error or None)``.
"""

from __future__ import annotations

import ast
import base64
import contextlib
import io
import json
import os
import pathlib
import sys
import time
import tokenize
import traceback

from jaxslam import files
from jaxslam.cli.common import ScriptParser, path_arg

__all__ = ["execute", "main"]


def _source(cell) -> str:
    src = cell.get("source", "")
    return "".join(src) if isinstance(src, list) else str(src)


def _lines(text: str) -> list:
    return text.splitlines(keepends=True)


def _strip_magics(src: str, where: str) -> str:
    out = []
    for ln in src.splitlines():
        if ln.lstrip().startswith(("%", "!")):
            print(f"run_notebook: {where}: skipped unsupported line {ln.strip()!r}", file=sys.stderr)
            indent = ln[:len(ln) - len(ln.lstrip())]  # kept: the line may sit in a block
            out.append(indent + "pass  # " + ln.strip())
        else:
            out.append(ln)
    return "\n".join(out)


def _figures_png():
    """PNG bytes of every open matplotlib figure (then closed); [] without matplotlib."""
    plt = sys.modules.get("matplotlib.pyplot")
    if plt is None:
        return []
    pngs = []
    for num in plt.get_fignums():
        fig = plt.figure(num)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
        pngs.append(buf.getvalue())
    plt.close("all")
    return pngs


def _prepare_matplotlib():
    os.environ.setdefault("MPLBACKEND", "Agg")
    try:
        import matplotlib

        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt

        plt.show = lambda *a, **k: None  # figures are captured at the end of each cell
    except ImportError:
        pass


def _ends_with_semicolon(code: str) -> bool:
    """Whether the cell's last token (comments aside) is ``;``: Jupyter then shows no value."""
    last = None
    try:
        for tok in tokenize.generate_tokens(io.StringIO(code).readline):
            if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                                tokenize.DEDENT, tokenize.ENDMARKER):
                last = tok
    except (tokenize.TokenError, SyntaxError):
        return False
    return last is not None and last.type == tokenize.OP and last.string == ";"


def _run_cell(code: str, ns: dict, name: str):
    """Execute ``code``; returns (value of a last bare expression or None)."""
    tree = ast.parse(code, filename=name, mode="exec")
    last = None
    if tree.body and isinstance(tree.body[-1], ast.Expr):
        last = ast.Expression(tree.body.pop().value)
    exec(compile(tree, name, "exec"), ns)  # noqa: S102 - executing the notebook is the point
    if last is None:
        return None
    value = eval(compile(last, name, "eval"), ns)  # noqa: S307 - always run (a ';' only hides it)
    return None if _ends_with_semicolon(code) else value


def execute(path, out_path=None, cwd=None):
    """Execute the notebook at ``path``; write it (with outputs) to ``out_path`` if given.

    Returns ``(notebook dict, error)`` where ``error`` is None or a dict
    ``{"cell": index, "ename", "evalue"}`` of the first failing cell.  Every code cell's
    outputs and execution count are cleared first (as Jupyter's "restart and run all"), so
    cells after a failing one hold no outputs of an earlier execution.  The output file is
    written atomically (a temporary file renamed over it): an interrupted or failed write
    never leaves a truncated notebook, which matters with ``--inplace``.
    """
    path = pathlib.Path(path)
    return _execute(_read(path), path, out_path, cwd)


def _read(path: pathlib.Path) -> dict:
    """The notebook at ``path`` (``OSError``, ``ValueError`` when it is not an nbformat-4 JSON)."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(nb, dict) or nb.get("nbformat") != 4:
        raise ValueError(f"{path}: only nbformat 4 notebooks are supported")
    return nb


def _execute(nb: dict, path: pathlib.Path, out_path, cwd):
    """:func:`execute` on the notebook ``nb`` read from ``path``."""
    for cell in nb.get("cells", []):
        if cell.get("cell_type") == "code":
            cell["outputs"], cell["execution_count"] = [], None
    _prepare_matplotlib()
    ns = {"__name__": "__main__", "__file__": str(path.resolve())}
    old_cwd = os.getcwd()
    os.chdir(cwd or path.resolve().parent)
    error = None
    count = 0
    try:
        for i, cell in enumerate(nb.get("cells", [])):
            if cell.get("cell_type") != "code":
                continue
            count += 1
            cell["execution_count"] = count
            outputs = []
            out, err = io.StringIO(), io.StringIO()
            name = f"<cell {count}>"
            t0 = time.perf_counter()
            value, exc = None, None
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    value = _run_cell(_strip_magics(_source(cell), name), ns, name)
                except BaseException as e:  # noqa: BLE001 - recorded in the notebook, like a kernel
                    exc = e
                    tb = traceback.format_exception(type(e), e, e.__traceback__)
            for stream, buf in (("stdout", out), ("stderr", err)):
                if buf.getvalue():
                    outputs.append({"output_type": "stream", "name": stream, "text": _lines(buf.getvalue())})
            if value is not None and exc is None:
                outputs.append({"output_type": "execute_result", "execution_count": count,
                                "data": {"text/plain": _lines(repr(value))}, "metadata": {}})
            for png in _figures_png():
                outputs.append({"output_type": "display_data", "metadata": {},
                                "data": {"image/png": base64.b64encode(png).decode("ascii"),
                                         "text/plain": ["<Figure>"]}})
            if exc is not None:
                outputs.append({"output_type": "error", "ename": type(exc).__name__, "evalue": str(exc),
                                "traceback": [ln.rstrip("\n") for ln in tb]})
            cell["outputs"] = outputs
            cell.setdefault("metadata", {})["jaxslam_run_s"] = round(time.perf_counter() - t0, 3)
            if exc is not None:
                error = {"cell": i, "ename": type(exc).__name__, "evalue": str(exc)}
                if isinstance(exc, KeyboardInterrupt):
                    raise exc
                break
    finally:
        os.chdir(old_cwd)
    if out_path is not None:
        _write_atomic(pathlib.Path(out_path), nb)
    return nb, error


def _write_atomic(path: pathlib.Path, nb: dict) -> None:
    """``nb`` as JSON in ``path``, through :func:`jaxslam.files.atomic_write`."""
    text = json.dumps(nb, indent=1, ensure_ascii=False) + "\n"
    try:
        data = text.encode("utf-8")
    except UnicodeEncodeError:  # e.g. a lone surrogate printed by a cell: ASCII JSON (\u escapes)
        data = (json.dumps(nb, indent=1) + "\n").encode("ascii")
    files.atomic_write(path, lambda f: f.write(data), mode="wb")


def main(argv=None) -> int:
    p = ScriptParser(prog="run_notebook.py", description=__doc__.split("\n\n")[0])
    p.add_argument("notebook", type=path_arg)
    p.add_argument("--out", type=path_arg,
                   help="where to write the executed notebook (default: NAME.executed.ipynb)")
    p.add_argument("--inplace", action="store_true", help="overwrite the input notebook with the outputs")
    p.add_argument("--cwd", type=path_arg, help="working directory of the cells (default: the notebook's folder)")
    a = p.parse_args(argv)
    if a.inplace and a.out is not None:
        p.error("--inplace and --out exclude each other")
    src = pathlib.Path(a.notebook)
    out = src if a.inplace else pathlib.Path(a.out) if a.out is not None else src.with_suffix(".executed.ipynb")
    try:  # a notebook that cannot be read: one line and exit 2, before anything runs
        nb = _read(src)
    except OSError as e:
        p.error(f"{src}: cannot read the notebook: {e.strerror or e}")
    except UnicodeDecodeError as e:
        p.error(f"{src}: not UTF-8 text ({e.reason} at byte {e.start})")
    except json.JSONDecodeError as e:
        p.error(f"{src}:{e.lineno}: not a JSON notebook: {e.msg} (column {e.colno})")
    except ValueError as e:  # not nbformat 4
        p.error(str(e))
    # the output is checked now, before any cell runs: the executed notebook must not be lost
    if not out.resolve().parent.is_dir():
        p.error(f"--out: the folder of {str(out)!r} does not exist")
    # a folder, a path under a file, a folder that cannot be written
    p.output_file("--inplace" if a.inplace else "--out", out, create=False)
    if a.cwd is not None and not pathlib.Path(a.cwd).is_dir():
        p.error(f"--cwd: {a.cwd!r} is not a folder")
    t0 = time.perf_counter()
    _, error = _execute(nb, src, out, a.cwd)
    dt = time.perf_counter() - t0
    if error:
        print(f"run_notebook: cell {error['cell']} failed: {error['ename']}: {error['evalue']} "
              f"(after {dt:.1f} s); wrote {out}", file=sys.stderr)
        return 1
    print(f"run_notebook: executed {src} in {dt:.1f} s; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
