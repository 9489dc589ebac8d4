"""File formats at the edge of brdfjax (the core never does I/O).

:mod:`brdfjax.io.exr`: one rendered frame as a single-part OpenEXR file.
:func:`atomic_output`: write a file under a temporary name, then rename it.
"""

from __future__ import annotations

from .atomic import atomic_output as atomic_output, write_json_atomic as write_json_atomic
from .exr import (
    CHANNELS as CHANNELS,
    ExrError as ExrError,
    FrameData as FrameData,
    read_frame_exr as read_frame_exr,
    write_frame_exr as write_frame_exr,
)
