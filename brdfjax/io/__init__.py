"""Every file format of brdfjax, and the data blocks files are read into (the core never does I/O).

:mod:`brdfjax.io.blocks`: :class:`~brdfjax.io.blocks.FrameData` and
:class:`~brdfjax.io.blocks.TableData`, the data blocks a fit, a posterior and a
diagnosis take (re-exported by :mod:`brdfjax.fit`).
:mod:`brdfjax.io.tables`: goniometer tables (every reader: CSV/whitespace with
column mapping, MERL in-plane, Cornell ``.brdf``, ASTM E1392, lumos-sat), their
row screening and the export of a table.
:mod:`brdfjax.io.raw`: raw exposure stacks (one OpenEXR file per exposure) and
the measurement-set manifest, with the format's specification.

:mod:`brdfjax.io.header`: the frame header -- the one mapping of a Detector
and a Conditions to file attributes and back (simulated, reduced and raw frames).
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
