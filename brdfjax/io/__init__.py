"""File formats at the edge of brdfjax (the core never does I/O).

:mod:`brdfjax.io.header`: the frame header -- the one mapping of a Detector
and a Frame to file attributes and back (simulated, reduced and raw frames).
:mod:`brdfjax.io.exr`: one rendered or reduced frame as a single-part OpenEXR
file (:class:`ExrFrame`).
:mod:`brdfjax.io.toml`: the one TOML writer (``dumps``, ``write``; reading is :mod:`tomllib`).
:func:`atomic_output`: write a file under a temporary name, then rename it
(every file brdfjax writes goes through it; :func:`write_json_atomic` for JSON).
"""

from __future__ import annotations

from ..runtime.atomic import atomic_output, check_output_dir, write_json_atomic
from .exr import CHANNELS, ExrError, ExrFrame, read_frame_exr, write_frame_exr
from .header import detector_from_attrs, frame_attrs, frame_from_attrs, geometry_attrs

__all__ = [
    "CHANNELS",
    "ExrError",
    "ExrFrame",
    "atomic_output",
    "check_output_dir",
    "detector_from_attrs",
    "frame_attrs",
    "frame_from_attrs",
    "geometry_attrs",
    "read_frame_exr",
    "write_frame_exr",
    "write_json_atomic",
]
