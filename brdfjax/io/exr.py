"""One rendered frame as a single-part OpenEXR file (lossless ZIP, float32 channels).

Channels (rows = n_v, top row = most negative n_v; columns = n_h):

========== ======= ====================================================
``brdf``   sr^-1   the BRDF of every pixel of the grid
``theta_s`` rad    scatter zenith angle of the pixel
``phi_s``  rad     scatter azimuth, measured from -x (seed §3.5)
``omega``  sr      solid angle of the pixel (Eq 86 / 109)
========== ======= ====================================================

Header attributes (the geometry ones are the frame header of
:mod:`brdfjax.io.header`, the one place that maps a Detector and a Conditions to
them and back): the angles ``theta_i``, ``theta_c``, ``phi_ref``, ``roll``,
``yaw``, ``pitch`` (rad), the lengths ``wavelength``, ``R``, ``pixel_pitch``,
``pixel_pitch_v`` (m) and the offsets ``m_h``, ``m_v`` (pixels) are stored as
**doubles** (the OpenEXR bindings store a Python float as a 32-bit float, so
each is written as a float64 array of shape (1,)); ``step`` is an int,
``roi`` a box ``(h0, v0)-(h1, v1)`` of inclusive seed pixel indices; ``model``,
``brdfjax_version``, ``precision`` and ``frame`` are strings, and ``checksum``
is a CRC-32 of the four channels' float32 pixels.

Files are written atomically (:func:`brdfjax.io.atomic_output`), so a reader
never sees half a frame.  A damaged file whose
header is intact does not make the OpenEXR bindings raise (they warn and drop
the pixel data): :func:`read_frame_exr` checks that every expected channel
came back with the header's shape, and that the pixels match the stored
checksum (small or incompressible chunks are stored raw, so damage there
decodes without any complaint), and raises :class:`ExrError` naming the file.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR  # the official bindings (3.x API)

from ..runtime.atomic import atomic_output
from ..runtime.errors import InputError
from .header import GEOMETRY_ATTRS

# OpenEXR compresses and decompresses a file's line blocks in a thread pool only when one is set (its
# default is none).  With one thread per core a full frame's four float32 channels are written in 0.56 s
# instead of 0.96 s (ZIP, 2 cores), byte for byte the same file.  A pool the process chose is left alone.
if OpenEXR.global_thread_count() == 0:
    OpenEXR.set_global_thread_count(min(os.cpu_count() or 1, 8))

__all__ = [
    "CHANNELS",
    "CHANNEL_UNITS",
    "DOUBLE_ATTRS",
    "REQUIRED_ATTRS",
    "ExrError",
    "ExrFrame",
    "pixel_checksum",
    "write_frame_exr",
    "read_frame_exr",
]

#: Channel name -> unit, in file order.
CHANNEL_UNITS: dict[str, str] = {"brdf": "sr^-1", "theta_s": "rad", "phi_s": "rad", "omega": "sr"}
CHANNELS: tuple[str, ...] = tuple(CHANNEL_UNITS)

#: Attributes stored as doubles, with their units: the frame header's geometry (:mod:`brdfjax.io.header`).
DOUBLE_ATTRS: dict[str, str] = GEOMETRY_ATTRS

#: Attributes every frame file carries.
REQUIRED_ATTRS: tuple[str, ...] = (
    "theta_i",
    "theta_c",
    "phi_ref",
    "wavelength",
    "R",
    "pixel_pitch",
    "step",
    "roi",
    "model",
    "brdfjax_version",
)

# Attributes OpenEXR itself manages; not returned in ``attrs``.
_STANDARD = {
    "channels",
    "compression",
    "dataWindow",
    "displayWindow",
    "lineOrder",
    "pixelAspectRatio",
    "screenWindowCenter",
    "screenWindowWidth",
    "type",
}


class ExrError(InputError):
    """A frame file that cannot be written or read as expected; the message names the file."""


@dataclass(frozen=True)
class ExrFrame:
    """A frame on a pixel grid: float32 ``(rows, cols)`` channels, the header attributes and any extra channels.

    What :func:`read_frame_exr` returns and what the reduction produces
    (:func:`brdfjax.instrument.reduce.reduce_measurement`).  ``extra`` holds
    the channels beyond :data:`CHANNELS` by name (e.g. a reduced frame's
    ``sigma_rel``, ``mask`` and uncertainty contributions).  Not to be
    confused with :class:`brdfjax.fit.FrameData`, the fit's data block.
    """

    brdf: np.ndarray
    theta_s: np.ndarray
    phi_s: np.ndarray
    omega: np.ndarray
    attrs: Mapping[str, Any]
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)


def pixel_checksum(channels: Mapping[str, np.ndarray]) -> str:
    """``"crc32:<hex>"`` over the float32 pixels of :data:`CHANNELS`, then any extra channels sorted by name."""
    crc = 0
    for name in (*CHANNELS, *sorted(set(channels) - set(CHANNELS))):
        crc = zlib.crc32(np.ascontiguousarray(channels[name], dtype=np.float32).data, crc)
    return f"crc32:{crc:08x}"


def _openexr():
    """The OpenEXR bindings (a seam: tests replace it to simulate a failing write)."""
    return OpenEXR


def _header_value(path: Path, key: str, value: Any) -> Any:
    if key in DOUBLE_ATTRS:
        v = np.asarray(value, dtype=np.float64).reshape(-1)
        if v.size != 1 or not np.isfinite(v[0]):
            raise ExrError(f"{path}: attribute '{key}' must be one finite number, got {value!r}")
        return v  # shape (1,) float64: stored as a double
    if key == "roi":
        h0, h1, v0, v1 = (int(x) for x in value)
        return (np.array([h0, v0], np.int32), np.array([h1, v1], np.int32))
    if isinstance(value, bool | np.bool_):
        return int(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return np.array([value], np.float64)
    if isinstance(value, str):
        return value
    raise ExrError(
        f"{path}: attribute '{key}' has unsupported type {type(value).__name__}; use a number, an int or a str"
    )


def write_frame_exr(
    path: str | os.PathLike,
    brdf: Any,
    theta_s: Any,
    phi_s: Any,
    omega: Any,
    attrs: Mapping[str, Any],
    *,
    extra_channels: Mapping[str, Any] | None = None,
) -> Path:
    """Write one frame to ``path`` atomically; returns the path.

    The four arrays (and any ``extra_channels``, e.g. ``sigma_rel`` and
    ``mask`` of a reduced frame) must share one 2-D shape ``(rows, cols)``
    and are stored as float32 in the same part, all covered by the checksum.  ``attrs`` must hold :data:`REQUIRED_ATTRS` (``roi`` as
    ``(h0, h1, v0, v1)``); floats in :data:`DOUBLE_ATTRS` are stored as doubles,
    other extra attributes may be ints, floats (stored as doubles) or strings.
    """
    OpenEXR = _openexr()
    path = Path(path)
    arrays = {"brdf": brdf, "theta_s": theta_s, "phi_s": phi_s, "omega": omega}
    extra_channels = dict(extra_channels or {})
    clash = sorted(set(extra_channels) & set(CHANNELS))
    if clash:
        raise ExrError(f"{path}: extra channel name(s) {clash} clash with the frame channels {', '.join(CHANNELS)}")
    arrays.update(extra_channels)
    channels = {k: np.ascontiguousarray(np.asarray(v, dtype=np.float32)) for k, v in arrays.items()}
    shape = channels["brdf"].shape
    if len(shape) != 2 or 0 in shape:
        raise ExrError(f"{path}: channel 'brdf' must be a non-empty 2-D (rows, cols) array, got shape {shape}")
    for k, v in channels.items():
        if v.shape != shape:
            raise ExrError(f"{path}: channel '{k}' has shape {v.shape}, expected {shape} like 'brdf'")
    missing = [k for k in REQUIRED_ATTRS if k not in attrs]
    if missing:
        raise ExrError(f"{path}: missing attribute(s) {missing}; a frame file needs: {', '.join(REQUIRED_ATTRS)}")
    clash = sorted(set(attrs) & _STANDARD)
    if clash:
        raise ExrError(f"{path}: attribute name(s) {clash} are reserved by OpenEXR")
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update({k: _header_value(path, k, v) for k, v in attrs.items()})
    header.setdefault("channel_units", ", ".join(f"{k}: {u}" for k, u in CHANNEL_UNITS.items()))
    header["checksum"] = pixel_checksum(channels)

    try:
        with atomic_output(path) as tmp:
            OpenEXR.File(header, channels).write(str(tmp))
    except (ExrError, OSError):
        raise
    except Exception as e:
        raise ExrError(f"{path}: could not write the OpenEXR file: {e}") from e
    return path


def _attr_value(key: str, value: Any) -> Any:
    if key == "roi" and isinstance(value, tuple) and len(value) == 2:
        (h0, v0), (h1, v1) = (np.asarray(x).tolist() for x in value)
        return (int(h0), int(h1), int(v0), int(v1))
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "f" and value.size == 1:
            return float(value.reshape(-1)[0])
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def read_frame_exr(path: str | os.PathLike) -> ExrFrame:
    """Read a frame written by :func:`write_frame_exr`.

    Float attributes come back as Python floats (the doubles exactly), ``roi``
    as ``(h0, h1, v0, v1)``.  Raises ``FileNotFoundError`` for a missing file
    and :class:`ExrError` naming the file when it is not OpenEXR, damaged or
    truncated, or lacks an expected channel or attribute.
    """
    OpenEXR = _openexr()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such frame file")
    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except Exception as e:
        raise ExrError(f"{path}: not a readable OpenEXR file ({e})") from None
    declared = [c.name for c in header.get("channels", [])]
    missing = [c for c in CHANNELS if c not in declared]
    if missing:
        raise ExrError(
            f"{path}: missing channel(s) {missing}; a frame file has: {', '.join(CHANNELS)} (found: {declared})"
        )
    missing_attrs = [k for k in REQUIRED_ATTRS if k not in header]
    if missing_attrs:
        raise ExrError(f"{path}: missing attribute(s) {missing_attrs}; a frame file has: {', '.join(REQUIRED_ATTRS)}")
    lo, hi = (np.asarray(x) for x in header["dataWindow"])
    shape = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        parts = f.parts
        got = dict(parts[0].channels) if len(parts) == 1 else {}
    except Exception as e:
        raise ExrError(f"{path}: the pixel data cannot be read; the file is damaged or truncated ({e})") from None
    lost = [c for c in CHANNELS if c not in got]
    if lost:
        raise ExrError(
            f"{path}: the pixel data of channel(s) {lost} could not be read; the file is damaged or truncated"
        )
    arrays = {}
    for c in (*CHANNELS, *sorted(set(got) - set(CHANNELS))):
        px = np.asarray(got[c].pixels)
        if px.dtype != np.float32 or px.shape != shape:
            raise ExrError(
                f"{path}: channel '{c}' is {px.dtype} {px.shape}, expected float32 {shape}; "
                "the file is damaged or was not written by brdfjax"
            )
        arrays[c] = px
    stored = header.get("checksum")
    if isinstance(stored, str) and stored.startswith("crc32:") and stored != pixel_checksum(arrays):
        raise ExrError(f"{path}: the pixel data does not match its checksum; the file is damaged")
    attrs = {k: _attr_value(k, v) for k, v in header.items() if k not in _STANDARD}
    extra = {k: arrays.pop(k) for k in list(arrays) if k not in CHANNELS}
    return ExrFrame(attrs=attrs, extra=extra, **arrays)
