"""Atomic file output: every file brdfjax writes goes through :func:`atomic_output`."""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["atomic_output", "write_json_atomic"]


@contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name is hidden (``.<name>.<pid>.<random>.tmp``) and lives in
    the same folder, so ``os.replace`` is atomic: readers see the old file or
    the whole new one, never a partial write.  On any error the temporary
    file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_json_atomic(path: str | os.PathLike, data: Any, *, allow_nan: bool = True) -> Path:
    """Write ``data`` as indented JSON (UTF-8, trailing newline) through :func:`atomic_output`; returns the path.

    ``allow_nan=False`` refuses NaN and infinities (``ValueError``), for strict JSON.
    """
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=allow_nan) + "\n", encoding="utf-8")
    return Path(path)
