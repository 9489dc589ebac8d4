"""Atomic file output: every file brdfjax writes goes through :func:`atomic_output`."""

from __future__ import annotations

import json
import os
import secrets
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .errors import InputError

__all__ = ["atomic_output", "check_output_dir", "write_json_atomic"]


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


def check_output_dir(path: str | os.PathLike, what: str = "--out") -> Path:
    """Check that ``path`` can be an output folder, before any work; nothing is created.

    Refuses (:class:`~brdfjax.runtime.errors.InputError`, exit 2) a path that is a
    file, or whose nearest existing ancestor is not a writable folder (e.g.
    ``/proc/x``, a read-only mount).  Returns the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{what} {path}: is a file, not a folder; give a folder for the output")
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{what} {path}: {probe} is a file, so the folder cannot be created there")
    try:  # the only sure test (root passes os.access on /proc, a read-only mount fails only on writing)
        os.rmdir(tempfile.mkdtemp(prefix=".brdfjax-write-test-", dir=probe))
    except OSError as e:
        raise InputError(
            f"{what} {path}: cannot create anything in {probe} ({e.strerror or e}); choose an output folder you can write to"
        ) from None
    return path
