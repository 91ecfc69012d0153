"""Shared pieces of the ``jaxslam`` command: the argument parser that turns errors into exit
code 2, argparse value types, output, and the compile part of every timing JSON.

No import-time side effects, and nothing heavier than the standard library at import.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading

__all__ = ["PROG", "DEBUG_ENV", "UsageError", "Parser", "ScriptParser", "path_arg", "int_at_least", "finite_float",
           "nonnegative_float", "positive_float", "positive_int", "seed_int", "echo", "compile_timing", "fmt",
           "one_line", "silence_stdout", "native_stdout_to_stderr", "reader_gone_safe_stdout", "counting_interrupts",
           "raise_if_interrupted"]

PROG = "jaxslam"
DEBUG_ENV = "JAXSLAM_DEBUG"


class UsageError(Exception):
    """A command-line usage error (exit code 2)."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors become one-line :class:`UsageError` s, and which takes
    options only by their whole names (an abbreviation such as ``--processe`` would be read
    by one parser and passed on, unrecognised, by another)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message):  # noqa: D401 - argparse API
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


class ScriptParser(argparse.ArgumentParser):
    """The argument parser of the repository's scripts (``scripts/*.py``): every usage error,
    argparse's own (a missing or unknown option, a value its ``type`` refuses) and the script's
    (``parser.error(message)``), is one line ``PROG: error: MESSAGE`` on stderr and exit code 2,
    with no usage block and no traceback.  Give ``prog`` (the script's file name): argparse's
    default is ``sys.argv[0]``, which is not the script when its ``main`` is called in-process.
    Abbreviated options are refused (``--out`` is not ``--output``), as by the CLI's parser."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message):  # noqa: D401 - argparse API
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)

    def output_dir(self, flag: str, path):
        """:func:`jaxslam.files.prepare_dir` for option ``flag``, an unusable folder (an existing
        file, one under a file, one that cannot be written) as this parser's usage error: one
        line, exit 2, before any compute."""
        from ..errors import InputError
        from ..files import prepare_dir

        try:
            return prepare_dir(flag, path)
        except InputError as e:
            self.error(str(e))

    def data_root(self, path, flag: str = "--data") -> str:
        """:func:`jaxslam.data.catalogue.data_root` of option ``flag`` (``path``, else
        ``$JAXSLAM_DATA_DIR``), a missing folder as this parser's usage error (one line, exit 2;
        an unset variable was a KeyError traceback)."""
        from ..data import catalogue
        from ..errors import InputError

        try:
            return str(catalogue.data_root(path, flag=flag))
        except InputError as e:
            self.error(one_line(str(e)))

    def data_folder(self, flag: str, path: str, default: str, holds: str) -> str:
        """``path``, the data folder of option ``flag`` that defaults to ``default`` (a folder
        beside the checkout: the package's own runs never need it), checked before any import of
        JAX: the default missing, or a folder without ``holds/``, is this parser's usage error."""
        import os

        if path == default and not os.path.isdir(path):
            self.error(f"{flag}: {path!r} (the default when {flag} is not given) is not a folder; "
                       f"give {flag}, the folder holding {holds}/")
        if not os.path.isdir(os.path.join(path, holds)):  # (a traceback after the imports, before)
            self.error(f"{flag}: {path!r} holds no {holds}/ folder")
        return path

    def output_file(self, flag: str, path, create: bool = True):
        """:func:`jaxslam.files.prepare_file` for option ``flag`` (``create=False`` creates
        nothing), an unusable path as this parser's usage error, as :meth:`output_dir`."""
        from ..errors import InputError
        from ..files import prepare_file

        try:
            return prepare_file(flag, path, create=create)
        except InputError as e:
            self.error(str(e))


def path_arg(text: str) -> str:
    """argparse type: a file or folder path, not empty ('' used to mean "not given" and fell back
    to the default folder, or acted on the current one)."""
    if text.strip() == "":
        raise argparse.ArgumentTypeError("'' is not a path (leave the option out for its default)")
    return text


def int_at_least(lo: int):
    """argparse type: an int >= ``lo`` (shared by ``jaxslam tune``)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {value}")
        return value

    return parse


def finite_float(text: str) -> float:
    """argparse type: a finite float (NaN and ±inf are never a meaningful option value)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0 (shared by ``jaxslam tune``)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def nonnegative_float(text: str) -> float:
    """argparse type: a finite float >= 0 (a weight that may be switched off)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


positive_int = int_at_least(1)


def seed_int(text: str) -> int:
    """argparse type: a PRNG seed, an int in [0, 2**63)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63), got {value}")
    return value


def echo(text: str = "") -> None:
    """One line on stdout, flushed (the progress bar writes to stderr)."""
    print(text, file=sys.stdout, flush=True)


def compile_timing(acct) -> dict:
    """The compile part of a command's timing JSON, from a :class:`jaxslam.compilation.CompileAccount`.

    ``compile_s`` = trace + lower + XLA compile of every program the command built (cache loads
    included); ``cache`` says whether the persistent cache was on and how often it served.
    """
    from jaxslam import compilation

    folder = compilation.enabled_dir()
    return {
        "compile_s": acct.total_s,
        "trace_s": acct.trace_s,
        "lower_s": acct.lower_s,
        "backend_compile_s": acct.compile_s,
        "programs": acct.programs,
        "cache": {"dir": None if folder is None else str(folder), "hits": acct.cache_hits,
                  "misses": acct.cache_misses},
    }


def fmt(x) -> str:
    """A metric value as the tables print it (None: nan)."""
    from jaxslam.io import _fmt_num

    return _fmt_num(float("nan") if x is None else float(x))


def one_line(text: str, limit: int = 400) -> str:
    """The first non-empty line of ``text``, cut at ``limit`` characters (error messages)."""
    first = next((ln.strip() for ln in str(text).splitlines() if ln.strip()), "")
    return first if len(first) <= limit else first[: limit - 3] + "..."


def silence_stdout(fd: int = 1) -> None:
    """Point file descriptor ``fd`` (stdout) at the null device, so that what C++ libraries print
    there (gloo's 'Rank 0 is connected ...') goes too, and writes to a closed pipe are dropped."""
    import os

    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


class _ReaderGoneSafe:
    """``sys.stdout`` while a command runs: when the reader of a pipe leaves (``jaxslam run ...
    | head -1``), stdout is pointed at the null device and the command goes on, so that the
    files it was asked for are still written (a ``BrokenPipeError`` at the first table line
    used to end the command there, with exit 0 and no ``--json``)."""

    def __init__(self, stream):
        self._stream = stream

    def _gone(self):
        try:
            silence_stdout(self._stream.fileno())
        except (OSError, ValueError, AttributeError):  # no descriptor (a test's capture)
            pass

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._gone()
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._gone()

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def native_stdout_to_stderr(null: bool = False):
    """Within: what native code writes on file descriptor 1 goes to stderr (fd 2; with ``null``
    everything on it, Python's prints too, goes to the null device: ``--quiet``), while
    ``sys.stdout`` still writes to the real stdout.  A process of a group (``jaxslam run ...
    --processes P``) runs within it: gloo prints "[Gloo] Rank 0 is connected to 1 peer ranks
    ..." on stdout at the group's first collective, which mixed into the table a user may pipe;
    nothing is hidden, it is on stderr.  Nothing changes where ``sys.stdout`` is not descriptor
    1 (a test's capture) or a descriptor cannot be duplicated; on exit descriptor 1 and
    ``sys.stdout`` are as before (a reader that left meanwhile: the null device, as
    :class:`_ReaderGoneSafe` leaves it)."""
    import os

    stream = sys.stdout
    try:
        if stream.fileno() != 1:
            raise ValueError
        stream.flush()
        real = os.dup(1)
    except (OSError, ValueError, AttributeError):  # (io.UnsupportedOperation is both)
        yield
        return
    if null:  # everything on descriptor 1 goes, Python's prints too (sys.stdout writes there)
        try:
            silence_stdout(1)
            yield
        finally:
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
            _flush_c_stdio()
            os.dup2(real, 1)
            os.close(real)
        return
    try:
        inner = getattr(stream, "_stream", stream)
        mine = open(real, "w", encoding=getattr(inner, "encoding", None) or "utf-8",  # noqa: SIM115
                    errors=getattr(inner, "errors", None) or "strict", closefd=False)
        mine.reconfigure(line_buffering=bool(getattr(inner, "line_buffering", False)))
        os.dup2(2, 1)
    except (OSError, ValueError, LookupError):
        os.close(real)
        yield
        return
    sys.stdout = _ReaderGoneSafe(mine) if isinstance(stream, _ReaderGoneSafe) else mine
    ours = sys.stdout
    try:
        yield
    finally:
        try:
            ours.flush()
        except (OSError, ValueError):
            pass
        _flush_c_stdio()  # what native code left in C's stdout buffer goes to stderr too
        if sys.stdout is ours:
            sys.stdout = stream
        os.dup2(real, 1)
        os.close(real)
        try:
            mine.close()
        except (OSError, ValueError):
            pass


def _flush_c_stdio() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library to ask (not POSIX)
        pass


@contextlib.contextmanager
def reader_gone_safe_stdout():
    """Within: ``sys.stdout`` survives its pipe's reader leaving (:class:`_ReaderGoneSafe`)."""
    stream = sys.stdout
    sys.stdout = _ReaderGoneSafe(stream)
    try:
        yield
    finally:
        if isinstance(sys.stdout, _ReaderGoneSafe) and sys.stdout._stream is stream:
            sys.stdout = stream


# Ctrl-C while a command runs.  Python drops an exception raised where it cannot propagate -- a
# gc callback (JAX runs one while it starts), a __del__, a weakref callback -- and prints only
# "Exception ignored in ...".  Measured: a Ctrl-C in the first ~5 s of `jaxslam run` / `jaxslam
# dataset` was lost that way 4 times in 4, and the command ran to its end and replaced the
# existing --json.  So the command's SIGINT handler also counts, and the count is read before
# anything is written.
_sigints = 0


@contextlib.contextmanager
def counting_interrupts():
    """Within: SIGINT raises ``KeyboardInterrupt`` as Python's default handler does, and is counted
    for :func:`raise_if_interrupted`; a dropped one prints no "Exception ignored" traceback.  Only
    in the main thread and over the default handler (a caller's own handler is left alone);
    restored on exit."""
    global _sigints
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def handler(signum, frame):
        global _sigints
        _sigints += 1
        raise KeyboardInterrupt

    hook = sys.unraisablehook

    def quiet(unraisable):  # a dropped Ctrl-C is counted and reported as "interrupted", no traceback
        if unraisable.exc_type is not KeyboardInterrupt:
            hook(unraisable)

    _sigints = 0
    signal.signal(signal.SIGINT, handler)
    sys.unraisablehook = quiet
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.unraisablehook = hook
        _sigints = 0


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` when a Ctrl-C arrived under :func:`counting_interrupts` whose
    exception nothing acted on (it was dropped, above).  A command calls it when its work has
    finished uninterrupted, before it writes a file."""
    if _sigints:
        raise KeyboardInterrupt
