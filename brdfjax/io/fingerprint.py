"""Problem fingerprints: what defines a resumable artefact's problem, stored with it, checked on resume.

A fingerprint is a flat mapping ``component -> value``: each component is
one thing that defines the problem (``model``, ``data[ti20].brdf``,
``data[ti20].grid``, ``priors.rho_s1``, ``likelihood.floor``,
``sampler.n_walkers``, ``file[ti20.exr]`` ...).  A value is either short and
readable (a number, a string such as a prior's description) or, for arrays
and files, ``sha256:<16 hex>`` of their content.  :func:`compare` lists the
components that differ, by name, with the old and new value where readable;
:func:`check_resume` raises :class:`FingerprintMismatch` (an
:class:`~brdfjax.runtime.errors.InputError`: exit 2) naming them.  The chains of
``brdfjax sample`` and the measurement sets of ``brdfjax capture`` carry one;
a study runner gets the same rules by building its own mapping with
:func:`array_digest`, :func:`file_digest` and :func:`value_digest`.

Why a flat mapping and not one digest: a single digest says *that* the
problem changed, the mapping says *what* changed ("priors.rho_s1:
uniform[0, 0.1] -> normal(0.02, 1e-05)").
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.errors import InputError

__all__ = [
    "FingerprintMismatch",
    "array_digest",
    "check_resume",
    "compare",
    "file_digest",
    "fingerprint_digest",
    "value_digest",
]

#: Readable values longer than this are stored as their digest.
MAX_READABLE = 120


class FingerprintMismatch(InputError):
    """A resume of an artefact made for another problem; ``differences`` lists the components that differ."""

    def __init__(self, message: str, differences: list[str]):
        super().__init__(message)
        self.differences = differences


def _short(h: Any) -> str:
    return "sha256:" + h.hexdigest()[:16]


def array_digest(a: Any) -> str:
    """Digest of an array's dtype, shape and bytes (``None``: ``"none"``)."""
    if a is None:
        return "none"
    a = np.ascontiguousarray(np.asarray(a))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return _short(h)


def file_digest(path: str | os.PathLike) -> str:
    """Digest of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return _short(h)


def value_digest(value: Any) -> str | int | float | bool | None:
    """A JSON value as it is stored: itself when short and scalar or a short string, else its digest."""
    if value is None or isinstance(value, bool | int | float):
        return value
    if isinstance(value, str) and len(value) <= MAX_READABLE:
        return value
    text = json.dumps(value, sort_keys=True, default=repr)
    if len(text) <= MAX_READABLE:
        return text
    return _short(hashlib.sha256(text.encode()))


def fingerprint_digest(fp: Mapping[str, Any]) -> str:
    """One digest of a whole fingerprint (for a file name or a log line)."""
    return _short(hashlib.sha256(json.dumps(dict(fp), sort_keys=True, default=repr).encode()))


def compare(stored: Mapping[str, Any], current: Mapping[str, Any]) -> list[str]:
    """The components that differ, one readable line each (empty: the same problem)."""
    out = []
    for key in sorted(set(stored) | set(current)):
        if key not in current:
            out.append(f"{key}: recorded as {stored[key]!r}, absent now")
        elif key not in stored:
            out.append(f"{key}: absent from the recorded problem, now {current[key]!r}")
        elif _norm(stored[key]) != _norm(current[key]):
            a, b = stored[key], current[key]
            if isinstance(a, str) and a.startswith("sha256:") and isinstance(b, str) and b.startswith("sha256:"):
                out.append(f"{key}: content differs ({a} -> {b})")
            else:
                out.append(f"{key}: {a!r} -> {b!r}")
    return out


def _norm(v: Any) -> Any:
    # values come back from JSON/TOML: compare 1 and 1.0, tuples and lists alike
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return v
    if isinstance(v, int | float):
        return float(v)
    if isinstance(v, list | tuple):
        return [_norm(x) for x in v]
    return v


def check_resume(what: str | Path, stored: Mapping[str, Any] | None, current: Mapping[str, Any], how: str = "") -> None:
    """Raise :class:`FingerprintMismatch` naming every component in which ``current`` differs from ``stored``.

    ``what``: the artefact (a file or folder, named in the message); ``how``:
    what the user can do, appended to the message.  ``stored=None`` (an
    artefact written before fingerprints) is a mismatch too: nothing proves
    it is the same problem.
    """
    if stored is None:
        diffs = ["no problem fingerprint is recorded (written by an older brdfjax)"]
    else:
        diffs = compare(stored, current)
    if not diffs:
        return
    lines = "; ".join(diffs[:8]) + (f"; and {len(diffs) - 8} more" if len(diffs) > 8 else "")
    raise FingerprintMismatch(
        f"{what} belongs to another problem and cannot be resumed with this one: {len(diffs)} difference(s): {lines}."
        + (f" {how}" if how else ""),
        diffs,
    )
