"""The ``--params`` file: read it, check it against the target's schema, describe the schema.

A ``--params`` file is a JSON object of *sections* (``"noise"``, ``"controller"``,
``"filter"``), each an object of named numbers, vectors and matrices.  ``jaxslam tune``
writes them (``--params-out``, or its whole ``--json`` report, which holds the sections at
its top level); ``jaxslam run SCENARIO --params`` reads them, checked here against the
scenario's schema.  (A ``jaxslam dataset NAME --params`` file, ``{"dataset": NAME, "noise":
{...}}``, is read with :func:`load`; its top level is checked by :func:`check_dataset_sections`,
its ``noise`` keys by :func:`jaxslam.data.runners.dataset_params` and its values by the system's
``params_from_dict``.)

A *schema* is ``{section: {key: default}}`` built from the target's own default parameters,
so it cannot drift from what the target reads: a value is valid when it has the default's
shape, is finite, and — where the default is a symmetric positive semi-definite matrix (a
covariance, an LQR weight) — is symmetric PSD too, and may be given as its diagonal.
Booleans must be booleans.

Decisions
- Unknown sections, unknown keys, wrong shapes, non-finite entries, non-PSD matrices and a
  file written for another scenario or dataset are :class:`InputError` s naming the key
  (``--params: noise.Qc: ...``): a typo never silently falls back to the default.
- Provenance: a file may say which ``"scenario"`` (or ``"dataset"``) it was made for; a
  mismatch is an error whose message says how to apply the file anyway (delete the key).
- The accepted values are returned unchanged (lists as read), so the target converts them
  exactly as before; this module only decides whether they are acceptable.
- Host-side NumPy; nothing here is traced.
"""

from __future__ import annotations

import json
import pathlib
import textwrap
from typing import Any, Mapping

import numpy as np

from jaxslam.errors import InputError, has_bool

__all__ = ["load", "check", "check_sections", "check_dataset_sections", "describe", "TUNE_REPORT_KEYS"]

#: Top-level keys of a ``jaxslam tune --json`` report besides its parameter sections (the report
#: is itself a ``--params`` file; these keys are read by nothing that takes ``--params``).
TUNE_REPORT_KEYS = frozenset({
    "scenario", "dataset", "target", "loss", "before", "after", "params_before", "params_after",
    "history", "references", "stopped", "n_skipped", "n_dropped_runs", "steps", "lr", "config", "timing", "memory",
    "eval_command", "eval_note", "versions", "interrupted", "steps_done",
})

# Symmetry and PSD tolerances relative to the matrix's largest magnitude (JSON round trips of
# float64 matrices are exact; 1e-9 leaves room for hand-written decimals).
_SYM_RTOL = 1e-9
_PSD_RTOL = 1e-12


def load(path, *, name: str = "--params") -> dict:
    """Read a ``--params`` JSON file whose top level is an object.

    ``name``: the option the messages name (a command that reads such a file through another
    option passes it, e.g. ``"--compare"``).

    ``NaN``, ``Infinity`` and a number beyond float range (``1e999``) are read, as Python's
    ``json`` reads them, as non-finite floats: :func:`check` (and a dataset's checks) refuse
    them naming the key.

    Raises:
      InputError: the file is missing or unreadable, is not valid JSON, repeats a key within
        one object (JSON parsers keep only the last, so a hand-edited value would be silently
        dropped), holds an integer of more digits than Python converts (4300; far beyond a
        float's range) or nests arrays and objects too deeply for the parser, or its top
        level is not an object.
    """
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{name}: file {str(path)!r} not found") from None
    except IsADirectoryError:
        raise InputError(f"{name}: {str(path)!r} is a folder, not a JSON file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{name}: cannot read {str(path)!r}: {getattr(e, 'strerror', None) or e}") from None
    def unique_keys(pairs):
        obj = {}
        for key, value in pairs:
            if key in obj:
                raise InputError(f"{name}: {str(path)!r} gives the key {key!r} twice in one object "
                                 "(only one value can hold; remove the other)")
            obj[key] = value
        return obj

    def checked_int(digits):  # (int() refuses over sys.get_int_max_str_digits() digits: a bare ValueError)
        try:
            return int(digits)
        except ValueError:
            raise InputError(f"{name}: {str(path)!r} holds an integer of {len(digits.lstrip('-'))} digits, "
                             "more than can be read (no float is that large: the largest is about "
                             "1.8e308)") from None

    try:
        obj = json.loads(text, object_pairs_hook=unique_keys, parse_int=checked_int)
    except json.JSONDecodeError as e:
        raise InputError(
            f"{name}: {str(path)!r} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})"
        ) from None
    except RecursionError:  # ('[' * 100000: the parser recurses once per level)
        raise InputError(f"{name}: {str(path)!r} nests arrays or objects too deeply to be read "
                         "(a --params file needs a few levels)") from None
    if not isinstance(obj, dict):
        raise InputError(f"{name}: {str(path)!r} must hold a JSON object, got {type(obj).__name__}")
    return obj


def _shape_text(shape) -> str:
    return "a number" if not shape else "×".join(str(n) for n in shape)


def _is_square(d: np.ndarray) -> bool:
    return d.ndim == 2 and d.shape[0] == d.shape[1]


def _symmetric_psd(d: np.ndarray) -> bool:
    if not _is_square(d) or not np.all(np.isfinite(d)):
        return False
    scale = max(float(np.max(np.abs(d))), 1e-300)
    if np.max(np.abs(d - d.T)) > _SYM_RTOL * scale:
        return False
    return float(np.min(np.linalg.eigvalsh(d))) >= -_PSD_RTOL * scale


def _check_value(name: str, value: Any, default: Any) -> Any:
    if isinstance(default, (bool, np.bool_)):
        if not isinstance(value, bool):
            raise InputError(f"{name}: expected true or false, got {value!r}")
        return value
    from jaxslam.linalg import check_numbers  # here: linalg imports JAX, which the CLI's quick exits never need

    d = np.asarray(default, np.float64)
    try:  # check_numbers refuses strings ("0.5" would pass NumPy's conversion and stay a string)
        a = check_numbers(value, name)
    except InputError:
        raise InputError(f"{name}: expected numbers ({_shape_text(d.shape)}), got {value!r}"[:300]) from None
    except OverflowError:  # a JSON integer beyond float range (10**400): not a finite number
        raise InputError(f"{name}: holds a number too large for a float (beyond ±1.8e308)") from None
    if has_bool(value):  # true/false are not numbers, inside a list neither (they were returned as bools)
        raise InputError(f"{name}: expected numbers ({_shape_text(d.shape)}), got {value!r}"[:300])
    psd = _symmetric_psd(d)  # a covariance or weight: diagonal form accepted, PSD required
    diagonal = psd and a.shape == d.shape[:1]
    if a.shape != d.shape and not diagonal:
        want = _shape_text(d.shape) + (f" (or its {d.shape[0]} diagonal values)" if psd else "")
        raise InputError(f"{name}: expected {want}, got shape {_shape_text(a.shape) if a.ndim else 'a number'}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: holds a non-finite value (NaN or infinity)")
    if psd:
        full = np.diag(a) if diagonal else a
        scale = max(float(np.max(np.abs(full))), 1e-300)
        if np.max(np.abs(full - full.T)) > _SYM_RTOL * scale:
            raise InputError(f"{name}: not symmetric (largest |A - Aᵀ| {np.max(np.abs(full - full.T)):.3g})")
        low = float(np.min(np.linalg.eigvalsh(full)))
        if low < -_PSD_RTOL * scale:
            raise InputError(f"{name}: not positive semi-definite (smallest eigenvalue {low:.3g})")
    return value


def check_sections(obj: Mapping, sections: tuple | None, *, target: str, where: str = "--params") -> None:
    """The first part of :func:`check`, which needs only the names of the schema's sections
    (``None``: the target takes no file): ``obj`` is a JSON object, written for no dataset and
    for no other scenario, with no key but those sections (and the provenance and ``jaxslam
    tune`` report keys).  Needs no JAX, so ``jaxslam run`` calls it before importing it.

    Raises:
      InputError: naming the offending key (the messages of :func:`check`).
    """
    if not isinstance(obj, Mapping):
        raise InputError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    kind = "scenario"  # the provenance key a file may hold
    if obj.get("dataset") is not None:
        raise InputError(f"{where}: the file is for dataset {obj['dataset']!r} (use it with "
                         f"'jaxslam dataset {obj['dataset']} --params'), not for scenario {target!r}")
    made_for = obj.get(kind)
    if made_for is not None and made_for != target:
        raise InputError(f"{where}: key '{kind}' is {made_for!r}, this run is {target!r}: the file was "
                         f"made for another {kind} (delete its '{kind}' key to apply it anyway)")
    report = "params_after" in obj  # a whole `jaxslam tune --json` report
    extra = TUNE_REPORT_KEYS if report else {kind, "interrupted"}
    unknown = sorted(set(obj) - set(sections or ()) - set(extra))
    if sections is None:
        if unknown:
            raise InputError(f"{where}: {kind} {target!r} takes no --params file (it has no tunable "
                             f"parameters; the file sets {unknown})")
        return
    if unknown:
        raise InputError(f"{where}: unknown key(s) {unknown}; {kind} {target!r} reads "
                         f"{', '.join(repr(s) for s in sections)}"
                         + (f" (and '{kind}')" if kind not in sections else ""))


def check_dataset_sections(obj, name: str) -> None:
    """The top level of a ``jaxslam dataset NAME --params`` object (``{"dataset": NAME, "noise":
    {...}}``, optionally ``"log"``, or a whole ``jaxslam tune`` report): a JSON object, made
    for dataset ``name``, with a ``noise`` object.  Needs no JAX (``jaxslam dataset`` calls it
    before importing it); the ``noise`` keys are the runner's to check
    (:func:`jaxslam.data.runners.dataset_params`).

    Raises:
      InputError: naming the offending key.
    """
    if not isinstance(obj, dict):
        raise InputError(f"--params: expected a JSON object, got {type(obj).__name__}")
    unknown = sorted(set(obj) - {"dataset", "noise", "log"} - TUNE_REPORT_KEYS, key=str)
    if unknown:
        raise InputError(f"--params: unknown key(s) {unknown}; a dataset --params file holds "
                         "'dataset', 'noise' and optionally 'log' (written by 'jaxslam tune')")
    if "dataset" not in obj or "noise" not in obj:
        missing = [k for k in ("dataset", "noise") if k not in obj]
        raise InputError(f"--params: missing key(s) {missing}; a dataset --params file holds "
                         "'dataset' and 'noise' (written by 'jaxslam tune')")
    if obj["dataset"] != name:
        raise InputError(f"--params: key 'dataset' is {obj['dataset']!r}, this run is {name!r}: "
                         "the file's noise was fitted for another dataset")
    if not isinstance(obj["noise"], dict):
        raise InputError(f"--params: key 'noise' must be an object, got {type(obj['noise']).__name__}")


def check(obj: Mapping, schema: Mapping[str, Mapping[str, Any]] | None, *, target: str,
          where: str = "--params") -> dict:
    """The parameter sections of ``obj``, checked against ``schema``.

    Args:
      obj: the parsed file (:func:`load`).
      schema: ``{section: {key: default}}`` of the target, or ``None`` when it takes no file.
      target: the scenario's name, for provenance (the file's ``"scenario"`` key) and messages.
    Returns:
      ``{section: {key: value}}`` with the sections ``obj`` sets (values as read).
    Raises:
      InputError: naming the offending key (module docstring).
    """
    check_sections(obj, None if schema is None else tuple(schema), target=target, where=where)
    if schema is None:
        return {}
    sections = dict(schema)
    out = {}
    for section, defaults in sections.items():
        if section not in obj:
            continue
        given = obj[section]
        if not isinstance(given, Mapping):
            raise InputError(f"{where}: {section}: expected an object of named values, got "
                             f"{type(given).__name__}")
        bad = sorted(set(given) - set(defaults))
        if bad:
            raise InputError(f"{where}: {section}: unknown key(s) {bad}; expected {', '.join(defaults)}")
        out[section] = {k: _check_value(f"{where}: {section}.{k}", v, defaults[k]) for k, v in given.items()}
    return out


def describe(schema: Mapping[str, Mapping[str, Any]] | None) -> str:
    """Lines listing a schema's sections and keys with shapes (for ``--help``)."""
    if schema is None:
        return "  (none: this target takes no --params file)"
    lines = []
    for section, defaults in schema.items():
        parts = []
        for k, d in defaults.items():
            if isinstance(d, (bool, np.bool_)):
                parts.append(f"{k} (true/false)")
                continue
            a = np.asarray(d, np.float64)
            text = _shape_text(a.shape)
            if _symmetric_psd(a):
                text += f" symmetric PSD or {a.shape[0]} diagonal values"
            parts.append(f"{k} ({text})")
        lines.append(textwrap.fill(f"  {section}: " + ", ".join(parts), width=88,
                                   subsequent_indent="      ", break_on_hyphens=False))
    return "\n".join(lines)
