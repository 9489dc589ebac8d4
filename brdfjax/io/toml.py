"""TOML writing: the one writer every brdfjax TOML file goes through (configs, manifests, capture state).

Reading uses the standard library's :mod:`tomllib`; writing uses ``tomli-w`` (its counterpart, kept by the
same authors), after turning NumPy scalars and arrays and tuples into the plain Python values it accepts.
What it writes: nested tables, arrays of tables, inline tables inside arrays, strings (any characters,
escaped), booleans, integers, floats (``nan``, ``inf`` and ``-inf`` included), and keys of any text (quoted
where needed, e.g. ``"0.5" = 0.01``).  ``tomllib.loads(dumps(doc)) == doc`` for every such document.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from ..runtime.atomic import atomic_output

__all__ = ["dumps", "write"]


def _plain(v: Any, where: str) -> Any:
    """``v`` as the plain Python types tomli-w writes; ``TypeError`` naming the key for anything else."""
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        return float(v)
    if isinstance(v, str):
        return v
    if isinstance(v, os.PathLike):
        return os.fspath(v)
    if isinstance(v, Mapping):
        return {str(k): _plain(x, f"{where}.{k}" if where else str(k)) for k, x in v.items()}
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return [_plain(x, f"{where}[{i}]") for i, x in enumerate(v)]
    raise TypeError(f"cannot write {type(v).__name__} to TOML (at {where or 'the top level'})")


def dumps(doc: Mapping[str, Any], *, header: str | None = None) -> str:
    """``doc`` as TOML text; ``header`` (any lines) is written first as ``#`` comments.

    Tables whose values are all plain come out as ``[table]`` sections, lists of mappings as inline tables
    inside an array (both read back by :mod:`tomllib` as the same dicts and lists).
    """
    if not isinstance(doc, Mapping):
        raise TypeError(f"a TOML document is a mapping, not {type(doc).__name__}")
    text = tomli_w.dumps(_plain(doc, ""))
    if header:
        text = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines()) + "\n" + text
    return text


def write(path: str | os.PathLike, doc: Mapping[str, Any], *, header: str | None = None) -> Path:
    """Write ``doc`` (see :func:`dumps`) to ``path`` atomically (UTF-8); returns the path."""
    text = dumps(doc, header=header)
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
