"""A one-line progress bar for long host-side loops (Monte Carlo chunks, tuning steps).

No JAX: the standard library and :mod:`jaxslam.errors`.  The bar stays silent for jobs that
finish within about a second (its first line is printed at the first update after ``delay_s``),
so quick runs and tests print nothing.  On a terminal the line is redrawn in place (at most
``min_interval_s`` apart); on a pipe or file, whole lines are written at most every
``log_interval_s`` so logs stay readable.

Updates come from the host between jitted chunks; nothing here is traced.

Compilation blocks the host for seconds before the first chunk, so :meth:`Progress.compiling`
shows it: ``label compiling… 12 s`` redrawn every half second on a terminal (a background
ticker; the compile itself is one blocking call), or one line when it starts and one when
it ends on a pipe.  The ETA counts from the end of compilation and appears only once a unit
is done, so it never extrapolates from compile time.  A final line that would repeat the
last one written is not written again.
"""

from __future__ import annotations

import contextlib
import numbers
import operator
import re
import sys
import threading
import time
from typing import TextIO

from .errors import InputError

__all__ = ["Progress"]


def _count(value, name: str, lower=None) -> int:
    """``value`` as an int (a Python or NumPy integer, not a bool; at least ``lower`` when given),
    else :class:`InputError` naming ``name`` (kept free of JAX: the standard library only)."""
    try:
        v = None if isinstance(value, bool) else operator.index(value)
    except TypeError:
        v = None
    if v is None or (lower is not None and v < lower):
        raise InputError(f"{name}: expected an int{'' if lower is None else f' >= {lower}'}, got {value!r}")
    return v


def _seconds(value, name: str) -> float:
    """``value`` as a finite float ``>= 0`` (an int or a float, not a bool), else
    :class:`InputError` naming ``name`` (a NaN delay printed at once, a NaN interval never)."""
    v = float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else None
    if v is None or not 0.0 <= v < float("inf"):
        raise InputError(f"{name}: expected a finite number of seconds >= 0, got {value!r}")
    return v


# C0 and C1 controls, DEL, and the line and paragraph separators: each would break the bar's one
# line (a newline, a carriage return, a line feed of Unicode's) or move the cursor (an escape).
_CONTROLS = "[\x00-\x1f\x7f-\x9f\u2028\u2029]+"
_CONTROL = re.compile(_CONTROLS)
_CONTROL_AT_ENDS = re.compile(f"\\A{_CONTROLS}|{_CONTROLS}\\Z")


def _one_line(text: str) -> str:
    """``text`` with each run of control characters as one space (none at either end)."""
    return _CONTROL.sub(" ", _CONTROL_AT_ENDS.sub("", text))


def _fmt_time(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


class Progress:
    """Progress of a job of ``total`` units, shown as ``label [####....] done/total``.

    Args:
      total: number of units (runs, steps), an int ``>= 0`` (0: an open-ended count).
      label: short text in front of the bar, a str (None: no label, as ``""``).
      enabled: ``False`` makes every method a no-op.
      stream: where to print (default ``sys.stderr``).
      delay_s: print nothing until this much time has passed (s).
      width: bar width in characters, an int ``>= 1``.
      min_interval_s, log_interval_s: least time between two lines on a terminal / a pipe (s).

    ``delay_s`` and the intervals are finite numbers ``>= 0`` (Python or NumPy floats or ints),
    else :class:`~jaxslam.errors.InputError` naming them; so is a ``label`` that is not a str
    or None (a number or bytes was printed as its repr, ``b'mc'``).  The bar is one line: in a
    label (given here or set later as ``progress.label``) each run of control characters (a
    newline, a tab, a carriage return, an escape, ...) becomes one space, and at either end
    none.

    Use ``update(n_done)`` with an absolute count or ``advance(k)`` with an
    increment, then ``close()`` (or use it as a context manager).
    """

    def __init__(
        self,
        total: int,
        label: str = "",
        enabled: bool = True,
        stream: TextIO | None = None,
        *,
        delay_s: float = 1.0,
        width: int = 30,
        min_interval_s: float = 0.1,
        log_interval_s: float = 5.0,
        clock=time.monotonic,
    ):
        self.total = _count(total, "total", lower=0)
        self.label = label
        self.enabled = bool(enabled)
        self.stream = sys.stderr if stream is None else stream
        self.delay_s = _seconds(delay_s, "delay_s")
        self.width = _count(width, "width", lower=1)
        self._clock = clock
        self._start = clock()
        self._run_start = None  # end of compilation (``compiling``), else the start
        self._done = 0
        self._last_text = None
        self._lock = threading.Lock()
        self._last_print = None  # time of the last bar line written (None: redraw at the next update)
        self._shown = False  # a bar line has been written (close then finishes it)
        self._closed = False
        try:
            self._tty = bool(self.stream.isatty())
        except (AttributeError, ValueError):
            self._tty = False
        min_interval_s = _seconds(min_interval_s, "min_interval_s")
        log_interval_s = _seconds(log_interval_s, "log_interval_s")
        self._interval = min_interval_s if self._tty else log_interval_s

    @property
    def label(self) -> str:
        """The text in front of the bar (a str; one line, see the class docstring)."""
        return self._label

    @label.setter
    def label(self, value) -> None:
        if value is not None and not isinstance(value, str):
            raise InputError(f"label: expected a str or None, got {type(value).__name__} {value!r}")
        self._label = "" if value is None else _one_line(value)

    @classmethod
    def null(cls) -> "Progress":
        """A disabled progress bar (every call is a no-op)."""
        return cls(0, "", enabled=False)

    @property
    def n_done(self) -> int:
        """Units done so far."""
        return self._done

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n_done: int) -> None:
        """Set the number of finished units, an int (clipped to ``[0, total]``)."""
        n = _count(n_done, "n_done")
        self._done = min(max(0, n), self.total) if self.total else max(0, n)
        self._maybe_print()

    def advance(self, k: int = 1) -> None:
        """Add ``k`` finished units (an int)."""
        self.update(self._done + _count(k, "k"))

    def note(self, text: str) -> None:
        """Print a line of its own; on a terminal the bar is cleared first (redrawn at the next
        update), on a pipe it is one more line."""
        if not self.enabled or self._closed:
            return
        with self._lock:
            try:
                self.stream.write(("\r\x1b[K" if self._tty else "") + text + "\n")
                self.stream.flush()
            except (OSError, ValueError):
                self.enabled = False
        self._last_print = None if self._tty else self._last_print

    def close(self) -> None:
        """Finish the line (only if something was printed)."""
        if self._closed:
            return
        self._closed = True
        if self.enabled and self._shown:
            text = self._line(self._clock() - self._start)
            if self._tty:
                self._write(text, final=True)
            elif text != self._last_text:  # a pipe already holds the last line
                self._write(text, final=True)

    def _maybe_print(self) -> None:
        if not self.enabled or self._closed:
            return
        now = self._clock()
        elapsed = now - self._start
        if elapsed < self.delay_s:
            return
        if self._last_print is not None and now - self._last_print < self._interval:
            return
        self._last_print = now
        self._shown = True
        self._write(self._line(elapsed), final=False)

    def _line(self, elapsed: float) -> str:
        head = f"{self.label} " if self.label else ""
        if self.total:
            frac = self._done / self.total
            filled = int(round(frac * self.width))
            bar = "[" + "#" * filled + "." * (self.width - filled) + "]"
            text = f"{head}{bar} {self._done}/{self.total} {_fmt_time(elapsed)}"
            if 0 < self._done < self.total:
                t0 = self._start if self._run_start is None else self._run_start
                ran = max(0.0, self._clock() - t0)
                text += f" ETA {_fmt_time(ran * (self.total - self._done) / self._done)}"
            return text
        return f"{head}{self._done} done {_fmt_time(elapsed)}"

    @contextlib.contextmanager
    def compiling(self, what: str = "compiling"):
        """Show ``label compiling… N s`` while the block runs (module docstring); ``what`` is
        made one line as a label is."""
        if isinstance(what, str):
            what = _one_line(what)
        if not self.enabled or self._closed:
            yield
            self._run_start = self._clock()
            return
        t0 = self._clock()
        head = f"{self.label} " if self.label else ""
        stop = threading.Event()
        shown = []

        def tick():
            # On a pipe: one line once the delay has passed; on a terminal: redraw.
            while not stop.wait(0.5 if self._tty else 0.25):
                el = self._clock() - t0
                if el < self.delay_s:
                    continue
                if self._tty:
                    self._write(f"{head}{what}… {el:.0f} s", final=False)
                    shown.append(True)
                elif not shown:
                    self._write(f"{head}{what}…", final=False)
                    shown.append(True)

        th = threading.Thread(target=tick, name="jaxslam-progress", daemon=True)
        th.start()
        try:
            yield
        finally:
            stop.set()
            th.join()
            el = self._clock() - t0
            if shown:
                self._write(f"{head}compiled in {el:.1f} s", final=True)
            self._run_start = self._clock()

    def _write(self, text: str, final: bool) -> None:
        with self._lock:
            self._write_locked(text, final)
        self._last_text = text

    def _write_locked(self, text: str, final: bool) -> None:
        try:
            if self._tty:
                self.stream.write("\r\x1b[K" + text + ("\n" if final else ""))
            else:
                self.stream.write(text + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            self.enabled = False  # a closed or broken stream must not kill the run
