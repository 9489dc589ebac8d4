"""Raw CCD exposure stacks: the multi-part OpenEXR measurement file and the measurement-set manifest.

This module is the contract between brdfjax and the tools that write raw
scatterometer data (the camera software, :mod:`brdfjax.instrument.synthetic`,
anything else).  It is at the edge: file I/O and validation only, no physics.

One measurement = one multi-part OpenEXR file
=============================================

One **part per exposure time**, in strictly increasing order of exposure
(shortest first).  Every part is a scanline image of the whole detector array,
``n_v`` rows by ``n_h`` columns (row 0 at the top, i.e. the most negative
``n_v`` of the seed's pixel indexing; see :class:`brdfjax.Detector`), with the
channels

============== ======== ==========================================================
``counts``     float32  mean digital counts over the ``n_frames`` averaged frames,
                        black level included (0 ... ``full_scale``); required
``counts_std`` float32  sample standard deviation of the *per-frame* counts over
                        the ``n_frames`` frames (so the standard error of
                        ``counts`` is ``counts_std / sqrt(n_frames)``); optional
============== ======== ==========================================================

Per-part header attributes:

============== ======= ===============================================
``exposure_s`` double  exposure (integration) time, s; > 0
``n_frames``   int     number of frames averaged into ``counts``; >= 1
============== ======= ===============================================

Per-file header attributes (written on every part; a reader takes them from
the first part and checks that any repetition agrees):

================== ======= ===============================================================
``kind``           string  one of ``sample``, ``beam``, ``background``, ``dark``
``optical_density`` double total OD of the stacked ND filters (>= 0)
``nd_filters``     string  the stacked filters' nominal ODs, e.g. ``"4.0+1.0+0.2"``
                           (``""`` for none); must add up to ``optical_density``
``theta_i``        double  incidence angle, rad (0 for a beam signature)
``theta_c``        double  detector arm angle, rad (``theta_i`` when centred on the peak,
                           0 for a beam signature)
``phi_ref``        double  sample rotation about its normal, rad
``wavelength``     double  m
``R``              double  sample-to-array distance, m
``pixel_pitch``    double  horizontal pixel pitch d_h, m
``black_level``    double  the camera's black-level offset, counts
``full_scale``     double  saturation level, counts (16383 for 14 bits)
``roll``           double  CCD rotation misalignment (seed Eq 105), rad
``yaw``            double  rad
``pitch``          double  rad
``m_h``            double  in-plane translational offset, pixels
``m_v``            double  out-of-plane translational offset, pixels
``sample``         string  free text (sample name, notes)
================== ======= ===============================================================

Optional per-file attributes: ``pixel_pitch_v`` (double, m; default
``pixel_pitch``), ``software`` (string).  Per-part ``checksum`` (string,
``"crc32:<hex>"`` over the float32 bytes of ``counts`` then ``counts_std``) is
written by :func:`write_raw_exr` and verified when present.  Other attributes
are kept and returned in :attr:`RawAttrs.extra`.

Angles, lengths and every other number above are stored as OpenEXR
**doubles** (the bindings would store a Python float as a 32-bit float; see
``docs``/dependencies: a float64 array of shape (1,) is written instead).
Compression is lossless ZIP.  Part names are ``exposure_0``, ``exposure_1``,
... (readers must not rely on them; the order and ``exposure_s`` count).

A measurement set: ``manifest.toml``
====================================

A folder holding the measurement files and a ``manifest.toml`` that names the
beam signature and its background, and every sample measurement with its
background; paths are relative to the folder::

    [beam]
    file = "beam.exr"
    background = "beam_background.exr"

    [[sample]]
    name = "solar_cell_20deg"              # output file stem: letters, digits, _ . + -
    file = "solar_cell_20deg.exr"
    background = "solar_cell_20deg_background.exr"

An optional ``[calibration]`` table carries what the reduction needs to know
about the instrument beyond the files::

    [calibration]
    scatter_nonlinearity = 0.0218          # per-pixel non-linearity dNL_s, relative (seed mean)
    nonlinearity_curve = [[0.0, -0.0172], [0.5, 0.0], [1.0, 0.0172]]
    [calibration.nd_tolerances]            # +- OD of ND filters by nominal OD (added to the seed's table)
    "3.0" = 0.15

``nonlinearity_curve`` (optional) is the camera's calibrated response curve:
``[fraction, error]`` pairs, ``fraction`` the signal (counts above the black
level) as a fraction of ``full_scale``, strictly increasing in [0, 1], and
``error`` the relative error of a reading at that level against the linear
response, ``reading / linear - 1`` (seed Eq 91, the array-average curve), in
(-0.5, 0.5); linear in between, constant beyond the first and last points.
The reduction weights (and, if asked, corrects) each exposure by it
(:class:`brdfjax.instrument.reduce.NonlinearityCurve`); without it the
reduction assumes the synthetic instrument's documented curve.  Readers that
predate the key ignore it.

More keys may be added by later versions; :func:`read_manifest` keeps keys it
does not know in ``extra`` rather than rejecting them (unlike brdfjax
configs, a manifest is a data-exchange file that other tools write).

Validation
==========

:func:`read_raw_exr` raises :class:`RawFormatError` (a ``ValueError``) naming
the file and the problem for: a file that is not OpenEXR; a missing or
malformed attribute; a part without a ``counts`` channel; parts of different
shapes; exposure times that do not strictly increase; NaN or infinite pixels;
and a truncated or corrupt file.  The OpenEXR bindings do *not* raise for a
damaged file whose header is intact -- they print a warning and silently drop
the unreadable parts -- so the reader compares the part names in the header
with the parts actually decoded, checks every channel's shape and verifies
the stored checksums.  :func:`write_raw_exr` applies the same checks before
writing and writes atomically (:func:`brdfjax.io.atomic_output`), so readers
see either the old file or the whole new one.

The geometry attributes (``theta_i`` ... ``m_v``, ``pixel_pitch_v``) are the
frame header of :mod:`brdfjax.io.header`: :meth:`RawAttrs.detector` and
:meth:`RawAttrs.frame` read them back through it.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR  # the official bindings (3.x API)

from ..core.detector import Detector
from ..core.render import Conditions
from ..runtime.errors import InputError
from . import atomic_output, toml
from .header import GEOMETRY_ATTRS, detector_from_attrs, frame_from_attrs

#: An ND filter stack: ``"4.0+1.0+0.2"``, a sequence of ODs, or None (no filter).
NDSpec = str | Sequence[float] | None


def parse_nd_filters(spec: NDSpec) -> tuple[float, ...]:
    """The nominal ODs of a stack of ND filters.

    ``"4.0+1.0+0.2"`` -> ``(4.0, 1.0, 0.2)``; ``""``, ``"0"``, ``"none"`` or
    ``None`` -> ``()`` (no filter); a sequence of numbers is taken as the ODs.
    Each OD must be a finite positive number.
    """
    if spec is None:
        return ()
    if isinstance(spec, str):
        text = spec.strip()
        if text.lower() in ("", "0", "0.0", "none"):
            return ()
        tokens = [t.strip() for t in text.split("+")]
        values = []
        for t in tokens:
            try:
                values.append(float(t))
            except ValueError:
                raise ValueError(
                    f"ND filter stack {spec!r}: {t!r} is not an optical density; "
                    "expected ODs joined by '+', e.g. '4.0+1.0+0.2'"
                ) from None
    elif isinstance(spec, Sequence) and not isinstance(spec, bytes):
        values = []
        for v in spec:
            try:
                values.append(float(v))
            except (TypeError, ValueError):
                raise ValueError(f"ND filter stack {spec!r}: {v!r} is not an optical density (a number)") from None
    else:
        raise ValueError(
            f"ND filter stack {spec!r}: expected a string like '4.0+1.0+0.2', a sequence of ODs, or None"
        )
    for v in values:
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"ND filter stack {spec!r}: OD {v!r} must be a finite positive number")
    return tuple(values)


__all__ = [
    "KINDS",
    "FILE_ATTRS",
    "PART_ATTRS",
    "RawFormatError",
    "ManifestError",
    "RawAttrs",
    "Exposure",
    "RawStack",
    "write_raw_exr",
    "read_raw_exr",
    "read_raw_header",
    "Manifest",
    "Calibration",
    "BeamEntry",
    "SpecimenEntry",
    "read_manifest",
    "write_manifest",
]

#: Measurement kinds.
KINDS: tuple[str, ...] = ("sample", "beam", "background", "dark")

#: Per-file attributes: name -> (type, unit).  ``float`` ones are stored as doubles.
FILE_ATTRS: dict[str, tuple[type, str]] = {
    "kind": (str, ""),
    "optical_density": (float, "OD"),
    "nd_filters": (str, ""),
    "theta_i": (float, "rad"),
    "theta_c": (float, "rad"),
    "phi_ref": (float, "rad"),
    "wavelength": (float, "m"),
    "R": (float, "m"),
    "pixel_pitch": (float, "m"),
    "black_level": (float, "counts"),
    "full_scale": (float, "counts"),
    "roll": (float, "rad"),
    "yaw": (float, "rad"),
    "pitch": (float, "rad"),
    "m_h": (float, "px"),
    "m_v": (float, "px"),
    "sample": (str, ""),
}
#: Optional per-file attributes.
OPTIONAL_FILE_ATTRS: dict[str, tuple[type, str]] = {
    "pixel_pitch_v": (float, "m"),
    "software": (str, ""),
}
#: Per-part attributes.
PART_ATTRS: dict[str, tuple[type, str]] = {"exposure_s": (float, "s"), "n_frames": (int, "")}

_STANDARD = {
    "channels",
    "chunkCount",
    "compression",
    "dataWindow",
    "displayWindow",
    "lineOrder",
    "name",
    "pixelAspectRatio",
    "screenWindowCenter",
    "screenWindowWidth",
    "type",
    "version",
}
_RESERVED = _STANDARD | set(PART_ATTRS) | {"checksum"}
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class RawFormatError(InputError):
    """A raw measurement file that cannot be written or read; the message names the file and the problem."""


class ManifestError(InputError):
    """A ``manifest.toml`` that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class RawAttrs:
    """The per-file attributes of a raw measurement (SI units, radians; see the module docstring)."""

    kind: str
    optical_density: float
    nd_filters: str
    theta_i: float
    theta_c: float
    phi_ref: float
    wavelength: float
    R: float
    pixel_pitch: float
    black_level: float
    full_scale: float
    roll: float = 0.0
    yaw: float = 0.0
    pitch: float = 0.0
    m_h: float = 0.0
    m_v: float = 0.0
    sample: str = ""
    pixel_pitch_v: float | None = None
    software: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    def problems(self) -> list[str]:
        """What is wrong with these attributes (empty when valid)."""
        out = []
        if self.kind not in KINDS:
            out.append(f"attribute 'kind' is {self.kind!r}; expected one of {', '.join(KINDS)}")
        for name, (typ, _) in {**FILE_ATTRS, **OPTIONAL_FILE_ATTRS}.items():
            v = getattr(self, name)
            if typ is float and v is not None and not (isinstance(v, int | float) and math.isfinite(v)):
                out.append(f"attribute '{name}' must be a finite number, got {v!r}")
            if typ is str and not isinstance(v, str):
                out.append(f"attribute '{name}' must be a string, got {v!r}")
        if out:
            return out
        for name in ("wavelength", "R", "pixel_pitch"):
            if getattr(self, name) <= 0:
                out.append(f"attribute '{name}' must be a positive length in metres, got {getattr(self, name)!r}")
        if self.pixel_pitch_v is not None and self.pixel_pitch_v <= 0:
            out.append(f"attribute 'pixel_pitch_v' must be a positive length in metres, got {self.pixel_pitch_v!r}")
        for name in ("theta_i", "theta_c"):
            if not 0 <= getattr(self, name) < math.pi / 2:
                out.append(f"attribute '{name}' must be in [0, pi/2) rad, got {getattr(self, name)!r}")
        if self.optical_density < 0:
            out.append(f"attribute 'optical_density' must be >= 0, got {self.optical_density!r}")
        if not self.full_scale > self.black_level:
            out.append(
                f"attribute 'full_scale' ({self.full_scale!r}) must exceed 'black_level' ({self.black_level!r})"
            )
        try:
            filters = parse_nd_filters(self.nd_filters)
        except ValueError as e:
            out.append(f"attribute 'nd_filters': {e}")
        else:
            if abs(sum(filters) - self.optical_density) > 1e-6:
                out.append(
                    f"attribute 'optical_density' = {self.optical_density!r} but 'nd_filters' "
                    f"{self.nd_filters!r} adds up to {sum(filters):g}"
                )
        return out

    @property
    def filters(self) -> tuple[float, ...]:
        """The stacked ND filters' nominal ODs (from ``nd_filters``)."""
        return parse_nd_filters(self.nd_filters)

    def geometry(self) -> dict[str, Any]:
        """The frame-header geometry attributes (:data:`brdfjax.io.header.GEOMETRY_ATTRS`) of this measurement."""
        return {k: getattr(self, k) for k in GEOMETRY_ATTRS}

    def detector(self, shape: tuple[int, int]) -> Detector:
        """The :class:`brdfjax.Detector` of this measurement for an ``(n_v, n_h)`` array (the arm at ``theta_c``)."""
        return detector_from_attrs(self.geometry(), shape, follow_peak=False)

    def frame(self) -> Conditions:
        """The :class:`brdfjax.Conditions` (theta_i, phi_ref, wavelength) of this measurement."""
        return frame_from_attrs(self.geometry())


@dataclass(frozen=True)
class Exposure:
    """One exposure of a stack: float32 ``counts`` (and optional ``counts_std``), both ``(n_v, n_h)``."""

    exposure_s: float
    n_frames: int
    counts: np.ndarray
    counts_std: np.ndarray | None = None


@dataclass(frozen=True)
class RawStack:
    """A raw measurement read from (or to be written to) one file: attributes and exposures, shortest first."""

    attrs: RawAttrs
    exposures: tuple[Exposure, ...]
    path: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.exposures[0].counts.shape)  # type: ignore[return-value]

    @property
    def exposure_times(self) -> np.ndarray:
        return np.array([e.exposure_s for e in self.exposures])


# --- writing --------------------------------------------------------------------------------------


def _openexr():
    """The OpenEXR bindings (a seam: tests replace it to simulate a failing write)."""
    return OpenEXR


def _checksum(counts: np.ndarray, counts_std: np.ndarray | None) -> str:
    crc = zlib.crc32(np.ascontiguousarray(counts, dtype=np.float32).data)
    if counts_std is not None:
        crc = zlib.crc32(np.ascontiguousarray(counts_std, dtype=np.float32).data, crc)
    return f"crc32:{crc:08x}"


def _double(x: float) -> np.ndarray:
    return np.array([float(x)], dtype=np.float64)  # shape (1,) float64: stored as a double


def _file_header(attrs: RawAttrs) -> dict[str, Any]:
    h: dict[str, Any] = {}
    for name, (typ, _) in FILE_ATTRS.items():
        v = getattr(attrs, name)
        h[name] = _double(v) if typ is float else str(v)
    if attrs.pixel_pitch_v is not None:
        h["pixel_pitch_v"] = _double(attrs.pixel_pitch_v)
    if attrs.software:
        h["software"] = attrs.software
    for k, v in attrs.extra.items():
        if k in _RESERVED or k in h:
            raise ValueError(f"extra attribute '{k}' clashes with a reserved or standard attribute name")
        if isinstance(v, bool | int | np.integer):
            h[k] = int(v)
        elif isinstance(v, float | np.floating):
            h[k] = _double(v)
        elif isinstance(v, str):
            h[k] = v
        else:
            raise ValueError(f"extra attribute '{k}' has unsupported type {type(v).__name__}; use int, float or str")
    return h


def _check_exposures(path: Path, exposures: Sequence[Exposure]) -> list[str]:
    out: list[str] = []
    if not exposures:
        return ["no exposures; a raw measurement needs at least one part"]
    shape = np.shape(exposures[0].counts)
    for i, e in enumerate(exposures):
        where = f"part {i} (exposure_s={e.exposure_s!r})"
        t = e.exposure_s
        if not (isinstance(t, int | float | np.floating) and math.isfinite(t) and t > 0):
            out.append(f"{where}: 'exposure_s' must be a positive number of seconds")
        if not (isinstance(e.n_frames, int | np.integer) and not isinstance(e.n_frames, bool) and e.n_frames >= 1):
            out.append(f"{where}: 'n_frames' must be a positive integer, got {e.n_frames!r}")
        for name, arr in (("counts", e.counts), ("counts_std", e.counts_std)):
            if arr is None:
                if name == "counts":
                    out.append(f"{where}: has no 'counts' channel")
                continue
            a = np.asarray(arr)
            if a.ndim != 2 or 0 in a.shape:
                out.append(f"{where}: channel '{name}' must be a non-empty 2-D (rows, cols) array, got shape {a.shape}")
            elif a.shape != shape:
                out.append(
                    f"{where}: channel '{name}' has shape {a.shape}, but part 0 has {shape}; all parts must match"
                )
            elif not np.all(np.isfinite(a)):
                n_bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
                out.append(f"{where}: channel '{name}' has {n_bad} NaN or infinite pixel(s)")
    times = [e.exposure_s for e in exposures]
    if not out and any(b <= a for a, b in zip(times, times[1:])):
        out.append(f"exposure times {times} (s) are not strictly increasing; store the parts shortest exposure first")
    return out


def write_raw_exr(path: str | os.PathLike, attrs: RawAttrs, exposures: Sequence[Exposure]) -> Path:
    """Write a raw measurement to ``path`` atomically; returns the path.

    Raises :class:`RawFormatError` naming the file (and writes nothing) when
    the attributes or exposures break the format (see the module docstring).
    """
    OpenEXR = _openexr()
    path = Path(path)
    problems = attrs.problems() + _check_exposures(path, exposures)
    if problems:
        raise RawFormatError(f"{path}: cannot write raw measurement: " + "; ".join(problems))
    try:
        file_header = _file_header(attrs)
    except ValueError as e:
        raise RawFormatError(f"{path}: {e}") from None
    parts = []
    for i, e in enumerate(exposures):
        counts = np.ascontiguousarray(e.counts, dtype=np.float32)
        channels = {"counts": counts}
        std = None
        if e.counts_std is not None:
            std = np.ascontiguousarray(e.counts_std, dtype=np.float32)
            channels["counts_std"] = std
        header = {
            "compression": OpenEXR.ZIP_COMPRESSION,
            "type": OpenEXR.scanlineimage,
            **file_header,
            "exposure_s": _double(e.exposure_s),
            "n_frames": int(e.n_frames),
            "checksum": _checksum(counts, std),
        }
        parts.append(OpenEXR.Part(header, channels, f"exposure_{i}"))
    try:
        with atomic_output(path) as tmp:
            OpenEXR.File(parts).write(str(tmp))
    except OSError:
        raise
    except Exception as e:
        raise RawFormatError(f"{path}: could not write the OpenEXR file: {e}") from e
    return path


# --- reading --------------------------------------------------------------------------------------


def _scalar(value: Any) -> Any:
    if isinstance(value, np.ndarray) and value.size == 1:
        return value.reshape(-1)[0].item()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _typed(path: Path, where: str, name: str, typ: type, value: Any) -> Any:
    v = _scalar(value)
    if typ is float:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise RawFormatError(f"{path}: {where}attribute '{name}' must be a finite number, got {value!r}")
        return float(v)
    if typ is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise RawFormatError(f"{path}: {where}attribute '{name}' must be an integer, got {value!r}")
        return int(v)
    if not isinstance(v, str):
        raise RawFormatError(f"{path}: {where}attribute '{name}' must be a string, got {value!r}")
    return v


def _attrs_from_header(path: Path, header: Mapping[str, Any]) -> RawAttrs:
    missing = [k for k in FILE_ATTRS if k not in header]
    if missing:
        raise RawFormatError(
            f"{path}: missing attribute(s) {missing}; a raw measurement file needs: {', '.join(FILE_ATTRS)}"
        )
    kw = {k: _typed(path, "", k, typ, header[k]) for k, (typ, _) in FILE_ATTRS.items()}
    for k, (typ, _) in OPTIONAL_FILE_ATTRS.items():
        if k in header:
            kw[k] = _typed(path, "", k, typ, header[k])
    known = set(FILE_ATTRS) | set(OPTIONAL_FILE_ATTRS) | _RESERVED
    kw["extra"] = {k: _scalar(v) for k, v in header.items() if k not in known}
    attrs = RawAttrs(**kw)
    problems = attrs.problems()
    if problems:
        raise RawFormatError(f"{path}: " + "; ".join(problems))
    return attrs


def _header_shape(header: Mapping[str, Any]) -> tuple[int, int]:
    lo, hi = (np.asarray(x) for x in header["dataWindow"])
    return (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))


def _open_headers(path: Path) -> list[tuple[str, dict[str, Any]]]:
    OpenEXR = _openexr()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such raw measurement file")
    try:
        f = OpenEXR.File(str(path), header_only=True)
        return [(p.name(), dict(p.header)) for p in f.parts]
    except Exception as e:
        raise RawFormatError(f"{path}: not a readable OpenEXR file ({e})") from None


def _validate_headers(path: Path, headers: list[tuple[str, dict[str, Any]]]):
    if not headers:
        raise RawFormatError(f"{path}: the file has no parts; a raw measurement has one part per exposure")
    attrs = _attrs_from_header(path, headers[0][1])
    first = {k: _scalar(headers[0][1][k]) for k in FILE_ATTRS}
    shape = _header_shape(headers[0][1])
    meta = []
    for i, (name, h) in enumerate(headers):
        where = f"part {i} ('{name}'): "
        declared = [c.name for c in h.get("channels", [])]
        if "counts" not in declared:
            raise RawFormatError(
                f"{path}: {where}has no 'counts' channel (channels: {declared}); every exposure part needs "
                "a float32 'counts' channel"
            )
        missing = [k for k in PART_ATTRS if k not in h]
        if missing:
            raise RawFormatError(
                f"{path}: {where}missing attribute(s) {missing}; every part needs: {', '.join(PART_ATTRS)}"
            )
        t = _typed(path, where, "exposure_s", float, h["exposure_s"])
        n = _typed(path, where, "n_frames", int, h["n_frames"])
        if t <= 0:
            raise RawFormatError(f"{path}: {where}attribute 'exposure_s' must be positive, got {t!r}")
        if n < 1:
            raise RawFormatError(f"{path}: {where}attribute 'n_frames' must be >= 1, got {n!r}")
        if _header_shape(h) != shape:
            raise RawFormatError(
                f"{path}: {where}has shape {_header_shape(h)} (rows, cols) but part 0 has {shape}; "
                "all exposures must cover the same pixels"
            )
        for k in FILE_ATTRS:
            if k in h and i > 0 and _scalar(h[k]) != first[k]:
                raise RawFormatError(
                    f"{path}: {where}per-file attribute '{k}' = {_scalar(h[k])!r} differs from part 0's {first[k]!r}"
                )
        meta.append((t, n, "counts_std" in declared, h.get("checksum")))
    times = [m[0] for m in meta]
    if any(b <= a for a, b in zip(times, times[1:])):
        raise RawFormatError(
            f"{path}: exposure times {times} (s) are not strictly increasing; parts must be stored shortest first"
        )
    return attrs, shape, meta


def read_raw_header(path: str | os.PathLike) -> tuple[RawAttrs, tuple[int, int], list[tuple[float, int]]]:
    """Attributes, array shape ``(n_v, n_h)`` and ``[(exposure_s, n_frames), ...]`` without reading pixels."""
    path = Path(path)
    attrs, shape, meta = _validate_headers(path, _open_headers(path))
    return attrs, shape, [(t, n) for t, n, _, _ in meta]


def read_raw_exr(path: str | os.PathLike) -> RawStack:
    """Read and validate a raw measurement file; see the module docstring for what is checked.

    Raises ``FileNotFoundError`` for a missing file and :class:`RawFormatError`
    (naming the file and the problem) for anything else.
    """
    OpenEXR = _openexr()
    path = Path(path)
    headers = _open_headers(path)
    attrs, shape, meta = _validate_headers(path, headers)
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        got = {p.name(): p for p in f.parts}
    except Exception as e:
        raise RawFormatError(f"{path}: the pixel data cannot be read; the file is damaged or truncated ({e})") from None
    lost = [name for name, _ in headers if name not in got]
    if lost:
        raise RawFormatError(
            f"{path}: the pixel data of part(s) {lost} could not be read; the file is damaged or truncated"
        )
    exposures = []
    for (name, _), (t, n, has_std, checksum) in zip(headers, meta):
        part = got[name]
        arrays = {}
        for c in ("counts", "counts_std") if has_std else ("counts",):
            if c not in part.channels:
                raise RawFormatError(
                    f"{path}: part '{name}': channel '{c}' could not be read; the file is damaged or truncated"
                )
            px = np.asarray(part.channels[c].pixels)
            if px.dtype != np.float32 or px.shape != shape:
                raise RawFormatError(
                    f"{path}: part '{name}': channel '{c}' is {px.dtype} {px.shape}, expected float32 {shape}"
                )
            if not np.all(np.isfinite(px)):
                n_bad = int(px.size - np.count_nonzero(np.isfinite(px)))
                raise RawFormatError(
                    f"{path}: part '{name}' (exposure_s={t!r}): channel '{c}' has {n_bad} NaN or infinite pixel(s)"
                )
            arrays[c] = px
        if isinstance(checksum, str) and checksum.startswith("crc32:"):
            if checksum != _checksum(arrays["counts"], arrays.get("counts_std")):
                raise RawFormatError(
                    f"{path}: part '{name}': the pixel data does not match its checksum; the file is damaged"
                )
        exposures.append(Exposure(t, n, arrays["counts"], arrays.get("counts_std")))
    return RawStack(attrs, tuple(exposures), path)


# --- manifest -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BeamEntry:
    """The beam signature and its background (absolute paths)."""

    file: Path
    background: Path


@dataclass(frozen=True)
class SpecimenEntry:
    """One sample measurement: ``name`` (output stem), its file and its background (absolute paths)."""

    name: str
    file: Path
    background: Path


#: The older name of :class:`SpecimenEntry` ("sample" is also the posterior package).
SampleEntry = SpecimenEntry


@dataclass(frozen=True)
class Calibration:
    """The optional ``[calibration]`` table: ``scatter_nonlinearity`` (relative), ``nd_tolerances`` (OD -> +-OD)
    and ``nonlinearity_curve`` (``((fraction of full scale, relative error), ...)``; see the module docstring)."""

    scatter_nonlinearity: float | None = None
    nd_tolerances: Mapping[float, float] = field(default_factory=dict)
    nonlinearity_curve: tuple[tuple[float, float], ...] | None = None


@dataclass(frozen=True)
class Manifest:
    """A parsed ``manifest.toml``; ``extra`` keeps keys this version does not know."""

    path: Path
    beam: BeamEntry
    samples: tuple[SpecimenEntry, ...]
    calibration: Calibration = Calibration()
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def folder(self) -> Path:
        return self.path.parent

    def files(self) -> list[Path]:
        """Every raw file the manifest names."""
        out = [self.beam.file, self.beam.background]
        for s in self.samples:
            out += [s.file, s.background]
        return out


def _entry_path(mpath: Path, key: str, table: Mapping[str, Any], name: str, check_exists: bool) -> Path:
    if name not in table:
        raise ManifestError(f"{mpath}: {key}: missing key '{name}' (a path relative to the manifest's folder)")
    v = table[name]
    if not isinstance(v, str) or not v:
        raise ManifestError(f"{mpath}: {key}.{name}: must be a non-empty path string, got {v!r}")
    p = (mpath.parent / v).resolve()
    if check_exists and not p.is_file():
        raise ManifestError(f"{mpath}: {key}.{name}: no such file {v!r} (looked for {p})")
    return p


def read_manifest(path: str | os.PathLike, *, check_files: bool = True) -> Manifest:
    """Parse a measurement set's ``manifest.toml``; raises :class:`ManifestError` naming the file and key.

    ``check_files`` also checks that every named file exists.
    """
    path = Path(path).resolve()
    if path.is_dir():
        path = path / "manifest.toml"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such manifest")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ManifestError(f"{path}: not valid TOML ({e})") from None
    beam = data.get("beam")
    if not isinstance(beam, dict):
        raise ManifestError(f"{path}: missing [beam] table with 'file' and 'background'")
    beam_entry = BeamEntry(
        _entry_path(path, "beam", beam, "file", check_files),
        _entry_path(path, "beam", beam, "background", check_files),
    )
    samples = data.get("sample")
    if not isinstance(samples, list) or not samples or not all(isinstance(s, dict) for s in samples):
        raise ManifestError(
            f"{path}: missing [[sample]] tables; each needs 'name', 'file' and 'background' (at least one sample)"
        )
    entries, seen = [], set()
    for i, s in enumerate(samples):
        key = f"sample[{i}]"
        name = s.get("name")
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ManifestError(
                f"{path}: {key}.name: must be a file-name-safe string (letters, digits, _ . + -), got {name!r}"
            )
        if name in seen:
            raise ManifestError(f"{path}: {key}.name: duplicate sample name {name!r}; names must be unique")
        seen.add(name)
        entries.append(
            SpecimenEntry(
                name,
                _entry_path(path, key, s, "file", check_files),
                _entry_path(path, key, s, "background", check_files),
            )
        )
    extra = {k: v for k, v in data.items() if k not in ("beam", "sample", "calibration")}
    return Manifest(path, beam_entry, tuple(entries), _calibration(path, data.get("calibration", {})), extra)


def _calibration(path: Path, table: Any) -> Calibration:
    if not isinstance(table, dict):
        raise ManifestError(f"{path}: calibration: must be a table")
    nl = table.get("scatter_nonlinearity")
    if nl is not None and (isinstance(nl, bool) or not isinstance(nl, int | float) or not 0 <= nl < 1):
        raise ManifestError(f"{path}: calibration.scatter_nonlinearity: must be a fraction in [0, 1), got {nl!r}")
    tol_table = table.get("nd_tolerances", {})
    if not isinstance(tol_table, dict):
        raise ManifestError(f"{path}: calibration.nd_tolerances: must be a table of \"OD\" = tolerance")
    tolerances = {}
    for k, v in tol_table.items():
        try:
            od = float(k)
        except ValueError:
            raise ManifestError(
                f"{path}: calibration.nd_tolerances: key {k!r} is not a nominal OD like \"3.0\""
            ) from None
        if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v >= 0):
            raise ManifestError(f"{path}: calibration.nd_tolerances.\"{k}\": must be a number >= 0, got {v!r}")
        tolerances[od] = float(v)
    curve = table.get("nonlinearity_curve")
    if curve is not None:
        curve = _nonlinearity_curve(f"{path}: calibration.nonlinearity_curve", curve)
    return Calibration(None if nl is None else float(nl), tolerances, curve)


def _number(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


def _nonlinearity_curve(where: str, curve: Any) -> tuple[tuple[float, float], ...]:
    """Validate ``[[fraction, error], ...]`` (fractions strictly increasing in [0, 1], errors in (-0.5, 0.5))."""
    if isinstance(curve, str | bytes) or not isinstance(curve, Sequence) or not curve:
        raise ManifestError(f"{where}: must be a non-empty array of [fraction of full scale, relative error] pairs")
    out = []
    for i, pt in enumerate(curve):
        if isinstance(pt, str | bytes) or not isinstance(pt, Sequence) or len(pt) != 2 or not all(map(_number, pt)):
            raise ManifestError(f"{where}[{i}]: must be a pair of numbers [fraction, error], got {pt!r}")
        x, e = float(pt[0]), float(pt[1])
        if not 0.0 <= x <= 1.0:
            raise ManifestError(f"{where}[{i}]: fraction of full scale {x!r} is outside [0, 1]")
        if not -0.5 < e < 0.5:
            raise ManifestError(f"{where}[{i}]: relative error {e!r} is outside (-0.5, 0.5)")
        if out and x <= out[-1][0]:
            raise ManifestError(f"{where}[{i}]: fractions must strictly increase ({out[-1][0]!r} then {x!r})")
        out.append((x, e))
    return tuple(out)


def write_manifest(
    path: str | os.PathLike,
    beam: tuple[str, str],
    samples: Sequence[tuple[str, str, str]],
    calibration: Calibration | None = None,
) -> Path:
    """Write ``manifest.toml`` atomically: ``beam = (file, background)``, ``samples = [(name, file, background)]``.

    Paths are written as given (they should be relative to the manifest's folder).
    """
    path = Path(path)
    doc: dict = {"beam": {"file": beam[0], "background": beam[1]}, "sample": []}
    for name, file, bg in samples:
        if not _NAME_RE.match(name):
            raise ManifestError(f"{path}: sample name {name!r} is not file-name-safe (letters, digits, _ . + -)")
        doc["sample"].append({"name": name, "file": file, "background": bg})
    if not doc["sample"]:
        del doc["sample"]
    if calibration is not None:
        cal: dict = {}
        if calibration.scatter_nonlinearity is not None:
            cal["scatter_nonlinearity"] = float(calibration.scatter_nonlinearity)
        if calibration.nonlinearity_curve is not None:
            curve = _nonlinearity_curve(f"{path}: calibration.nonlinearity_curve", calibration.nonlinearity_curve)
            cal["nonlinearity_curve"] = [[x, e] for x, e in curve]
        if calibration.nd_tolerances:
            cal["nd_tolerances"] = {repr(float(od)): float(t) for od, t in sorted(calibration.nd_tolerances.items())}
        doc["calibration"] = cal
    return toml.write(path, doc)
