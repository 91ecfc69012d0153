"""``jaxslam bench NAME``: a benchmark of the ``benchmarks/`` folder, its table and JSON.

Benchmarks live outside the package, in ``benchmarks/bench_<name>.py`` (module attributes
``DESCRIPTION``, ``add_arguments(parser)``, ``run(args) -> dict``).  The folder is ``--dir
DIR``, else ``./benchmarks``, else the ``benchmarks/`` folder beside the package source
(editable installs); the first of the last two that holds a ``bench_*.py`` wins.  The folder
and the test oracles beside it (``../tests/oracles``: the NumPy twins the benchmarks time
against) are put on ``sys.path`` while a benchmark runs.  ``jaxslam list`` reads ``DESCRIPTION`` without importing the module; ``bench``
fills in ``"benchmark"`` and ``"machine"`` in the JSON when the benchmark leaves them out.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import pathlib
import sys

from jaxslam import files
from jaxslam.errors import InputError

from .common import PROG, Parser, UsageError, echo, finite_float, int_at_least, path_arg, seed_int

__all__ = ["command", "find_benchmarks_dir", "list_benchmarks"]


def find_benchmarks_dir(explicit=None) -> pathlib.Path:
    """The benchmarks folder: ``explicit``, else ``./benchmarks``, else the one beside the package.

    Raises:
      InputError: ``explicit`` is not a folder, or no candidate holds a ``bench_*.py``.
    """
    if explicit:
        p = pathlib.Path(explicit)
        if not p.is_dir():
            raise InputError(f"--dir: {str(p)!r} is not a folder")
        return p
    import jaxslam

    candidates = [pathlib.Path.cwd() / "benchmarks",
                  pathlib.Path(jaxslam.__file__).resolve().parents[1] / "benchmarks"]
    for c in candidates:
        if c.is_dir() and any(c.glob("bench_*.py")):
            return c
    looked = " and ".join(repr(str(c)) for c in dict.fromkeys(candidates))
    raise InputError(f"no benchmarks folder with bench_*.py files found (looked in {looked}); "
                     "pass --dir DIR")


def _description_of(path: pathlib.Path) -> str:
    """``DESCRIPTION`` of a benchmark file, read with ``ast`` (the module is not run)."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    except (OSError, SyntaxError, UnicodeDecodeError, ValueError):
        return "(cannot read DESCRIPTION)"
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else [])
        if any(isinstance(t, ast.Name) and t.id == "DESCRIPTION" for t in targets):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                break
            if isinstance(value, str):
                return " ".join(value.split())
    return "(no DESCRIPTION)"


def list_benchmarks(bench_dir) -> dict[str, str]:
    """``{name: description}`` for the ``bench_<name>.py`` files of ``bench_dir``, sorted."""
    bench_dir = pathlib.Path(bench_dir)
    return {p.stem[len("bench_"):]: _description_of(p)
            for p in sorted(bench_dir.glob("bench_*.py")) if p.stem != "bench_"}


def _load_bench_module(path: pathlib.Path):
    mod_name = f"_jaxslam_bench_{path.stem[len('bench_'):]}"
    spec = importlib.util.spec_from_file_location(mod_name, path)
    if spec is None or spec.loader is None:
        raise InputError(f"cannot load benchmark file {str(path)!r}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = module  # dataclasses and pickling look modules up here
    try:
        spec.loader.exec_module(module)
    except SyntaxError as e:  # the file itself is malformed: an input error naming file:line (exit 2)
        sys.modules.pop(mod_name, None)
        raise InputError(f"benchmark {str(path)!r}: line {e.lineno}: {type(e).__name__}: {e.msg}") from None
    except BaseException:
        sys.modules.pop(mod_name, None)
        raise
    missing = [a for a in ("DESCRIPTION", "add_arguments", "run") if not hasattr(module, a)]
    if missing:
        raise InputError(f"benchmark {str(path)!r} lacks {', '.join(missing)} "
                         "(needs DESCRIPTION, add_arguments(parser), run(args))")
    return module


class _CheckedOptions:
    """The parser a benchmark's ``add_arguments`` fills, with its plain number types checked: a
    ``float`` option must be finite, an ``int`` one a count >= 1 (``--warmup`` >= 0, ``--seed``
    a PRNG seed in [0, 2**63), as ``jaxslam run --seed``), so that a bad value is a usage error
    naming the option (exit 2), not an internal error from inside the benchmark.  The groups it
    makes (``add_argument_group``, ``add_mutually_exclusive_group``) check theirs the same way.

    An option string that ``jaxslam bench`` itself takes (``--dir``, ``--json``, ``--debug``,
    ``-h``/``--help``) is refused with a usage error naming the benchmark and the option (it was
    argparse's "conflicting option string", an internal error)."""

    def __init__(self, parser, bench: str = "", reserved=()):
        self._p = parser
        self._bench = bench
        self._reserved = frozenset(reserved)

    def add_argument(self, *names, **kw):
        clash = [n for n in names if isinstance(n, str) and n in self._reserved]
        if clash:
            raise UsageError(f"{PROG} bench: benchmark {self._bench!r} defines {', '.join(clash)}, "
                             f"an option of '{PROG} bench' itself ({', '.join(sorted(self._reserved))}); "
                             "rename it in the benchmark's add_arguments")
        if kw.get("type") is float:
            kw["type"] = finite_float
        elif kw.get("type") is int:
            kw["type"] = (seed_int if "--seed" in names
                          else int_at_least(0 if "--warmup" in names else 1))
        return self._p.add_argument(*names, **kw)

    def add_argument_group(self, *args, **kw):
        return _CheckedOptions(self._p.add_argument_group(*args, **kw), self._bench, self._reserved)

    def add_mutually_exclusive_group(self, *args, **kw):
        return _CheckedOptions(self._p.add_mutually_exclusive_group(*args, **kw), self._bench,
                               self._reserved)

    def __getattr__(self, attr):
        return getattr(self._p, attr)


def _bench_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dir", metavar="DIR", type=path_arg,
                   help="benchmarks folder (default: ./benchmarks, else the one beside the "
                        "jaxslam source)")
    p.add_argument("--json", metavar="PATH", help="write the bench JSON here")
    p.add_argument("--debug", action="store_true",
                   help="print the traceback of an internal failure (also JAXSLAM_DEBUG=1)")


def command(rest: list[str]) -> int:
    """``jaxslam bench NAME [--dir DIR] [--json PATH] [benchmark options]``."""
    base = Parser(prog=f"{PROG} bench", add_help=False)
    base.add_argument("name", nargs="?")
    base.add_argument("-h", "--help", action="store_true")
    _bench_common(base)
    pre, _ = base.parse_known_args(rest)

    if pre.name is None:
        try:
            bench_dir = find_benchmarks_dir(pre.dir)
            names = ", ".join(list_benchmarks(bench_dir)) or "(none)"
        except InputError as e:
            if not pre.help:
                raise
            names = f"(none: {e})"
        if pre.help:
            p = Parser(prog=f"{PROG} bench", usage=f"{PROG} bench NAME [options] [benchmark options]",
                        description="Run a benchmark (benchmarks/bench_NAME.py) and write its JSON.",
                        epilog=f"benchmarks: {names}\n'{PROG} bench NAME --help' lists its options.",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
            p.add_argument("name", metavar="NAME", help="benchmark name")
            _bench_common(p)
            p.print_help()
            return 0
        raise UsageError(f"{PROG} bench: missing NAME; available benchmarks: {names}")

    name = pre.name
    name = name[: -len(".py")] if name.endswith(".py") else name
    name = name[len("bench_"):] if name.startswith("bench_") else name
    bench_dir = find_benchmarks_dir(pre.dir)
    available = list_benchmarks(bench_dir)
    if name not in available:
        raise InputError(f"unknown benchmark {pre.name!r} in {str(bench_dir)!r}; available: "
                         f"{', '.join(available) or '(none)'}")

    # before anything runs, creating nothing: a run that stops at its options leaves no folder
    json_path = files.prepare_file("--json", pre.json, create=False) if pre.json is not None else None
    path = bench_dir / f"bench_{name}.py"
    files.distinct_outputs(json=json_path, inputs={"benchmark": path})  # never the benchmark's own source
    import jax

    jax.config.update("jax_enable_x64", True)  # benchmarks choose float32 by passing float32 arrays
    from jaxslam import io

    added = [str(bench_dir.resolve())]
    oracles = bench_dir.resolve().parent / "tests" / "oracles"  # the NumPy twins
    if oracles.is_dir():
        added.append(str(oracles))
    sys.path[:0] = added
    try:
        module = _load_bench_module(path)
        p = Parser(prog=f"{PROG} bench {name}", description=str(module.DESCRIPTION))
        p.add_argument("name", metavar="NAME", help="benchmark name")
        _bench_common(p)
        module.add_arguments(_CheckedOptions(p, str(path), p._option_string_actions))
        args = p.parse_args(rest)
        result = module.run(args)
    finally:
        for a in added:
            try:
                sys.path.remove(a)
            except ValueError:
                pass
    if not isinstance(result, dict) or not isinstance(result.get("results"), list):
        raise TypeError(f"benchmark {name!r}: run(args) must return a dict with a 'results' list")
    result = {"benchmark": name, **result}
    result.setdefault("machine", io.machine_info())

    if json_path is not None:  # the run is done: now its folders may be created
        json_path = files.prepare_file("--json", json_path)
    echo(_format_bench_table(result))
    if json_path is not None:
        path = io.write_json(json_path, result)
        echo(f"wrote {path}")
    return 0


def _format_bench_table(result: dict) -> str:
    header = ("case", "jaxslam_s", "reference_s", "speedup")

    def cell(row, key):
        v = row.get(key)
        if v is None:
            return "-"
        if key == "case":
            return str(v)
        try:
            v = float(v)
        except (TypeError, ValueError):
            return str(v)
        return f"{v:.2f}x" if key == "speedup" else f"{v:.4g}"

    refs = sorted({str(r["reference"]) for r in result["results"] if isinstance(r, dict) and r.get("reference")})
    rows = [header] + [tuple(cell(r, k) for k in header) for r in result["results"] if isinstance(r, dict)]
    if len(refs) > 1:  # rows against different references: say which on each row
        rows = [rows[0] + ("vs",)] + [row + (f"[{refs.index(str(r['reference'])) + 1}]"
                                             if r.get("reference") else "-",)
                                      for row, r in zip(rows[1:], (r for r in result["results"]
                                                                   if isinstance(r, dict)))]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [f"benchmark {result.get('benchmark')}"]
    for j, r in enumerate(rows):
        lines.append("  ".join([r[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(r[1:], widths[1:])]))
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    if len(refs) == 1:
        lines.append("reference: " + refs[0])
    elif refs:
        lines.append("speedup = reference_s / jaxslam_s, against the row's reference (vs):")
        lines += [f"  [{i}] {ref}" for i, ref in enumerate(refs, 1)]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main
