"""File formats at the edge of brdfjax (the core never does I/O).

:mod:`brdfjax.io.exr`: one rendered frame as a single-part OpenEXR file.
:func:`atomic_output`: write a file under a temporary name, then rename it.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["CHANNELS", "ExrError", "FrameData", "atomic_output", "read_frame_exr", "write_frame_exr"]


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


from .exr import (  # noqa: E402  (exr imports atomic_output from here)
    CHANNELS as CHANNELS,
    ExrError as ExrError,
    FrameData as FrameData,
    read_frame_exr as read_frame_exr,
    write_frame_exr as write_frame_exr,
)
