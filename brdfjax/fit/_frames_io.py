"""Reduced BRDF frames (``brdfjax.instrument.reduce``) as fit data.

A reduced frame (a :class:`~brdfjax.io.ExrFrame` or its EXR file, written by
``brdfjax reduce``) carries the BRDF on a pixel grid
with the extra channels ``sigma_rel`` and ``mask`` and header attributes that
describe the measurement: ``theta_i``, ``theta_c``, ``phi_ref``,
``wavelength`` (rad, m), the detector (``R``, ``pixel_pitch``,
``pixel_pitch_v``, misalignment ``roll``, ``yaw``, ``pitch``, ``m_h``,
``m_v``, the raw array's ``detector_n_v`` x ``detector_n_h``) and the grid
(``step``, ``roi = (h0, h1, v0, v1)`` seed pixel indices): the frame header
of :mod:`brdfjax.io.header`, which reads it back.
:func:`frame_data_from_reduced` turns one into a :class:`FrameData` with the
same :class:`~brdfjax.Detector` and :class:`~brdfjax.PixelGrid`, optionally
decimated further (every ``step``-th row and column of the stored grid) and
cut to a region of interest.

The detector's arm: when ``theta_c`` equals ``theta_i`` (the camera centred on
the specular peak, as in every seed measurement) the detector is built with
``theta_c = None`` ("follows the peak"), so frames at several incidence
angles share one detector (a joint fit needs no
``allow_different_detectors``) and a fit that frees ``theta_i`` moves the
incidence, not the camera.  Otherwise the arm stays at the stored
``theta_c``.

The weights: ``sigma="auto"`` (default, here and in the fit config) takes
``u_scatter_flux`` where the frame carries it (a brdfjax reduction) and
``sigma_rel`` otherwise; ``"total"`` takes the ``sigma_rel`` channel,
the quadrature total of every contribution of the reduction, frame-wide ones
included (the ND filters' tolerance, the incident flux, the geometry: one
scale error shared by every pixel of the frame, which per-pixel weights
would count as independent noise); ``"pixel"`` takes ``u_scatter_flux``
(each pixel's own noise and non-linearity) and ``"noise"`` only
``u_scatter_noise``.  ``sigma_floor`` is added in quadrature (a per-pixel
error the reduction does not carry, e.g. the residual pixel-to-pixel gain
error after a non-linearity correction).

The instrument function: a frame attribute ``footprint_w_px`` (the 1/e^2
radius of a Gaussian beam footprint, Eq 73, in raw detector pixels), or the
``footprint_w_px`` argument, gives the footprint kernel sampled on the
frame's grid (:func:`brdfjax.instrument.synthetic.footprint_kernel` of the
raw pixels, sampled every grid step); ``footprint`` may also be given as
a kernel array directly.  With a footprint, a region of interest is widened
by the kernel's half-width: the margin is evaluated (light from it reaches
the region through the convolution) but masked.  Files written before ``detector_n_v`` /
``detector_n_h`` existed get the smallest even-sized array that holds the roi
(pixel geometry depends on the indices only, not on the array size).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..core.detector import Detector, PixelGrid
from ..instrument.reduce import read_reduced_frame
from ..instrument.synthetic import footprint_kernel
from ..io import ExrError, header
from ..io.blocks import FrameData
from ._common import FitInputError
from ._nuisance import systematics_from_attrs

__all__ = ["frame_data_from_reduced", "read_frame_data", "detector_from_attrs", "SIGMA_CHOICES"]

#: The ``sigma`` choices and the channel each reads; ``"auto"`` (the default of the API and the config) reads
#: ``u_scatter_flux`` where the frame has it (a brdfjax reduction) and ``sigma_rel`` otherwise (frames
#: written by another program need only ``sigma_rel``).
SIGMA_CHOICES = {"auto": "u_scatter_flux", "total": "sigma_rel", "pixel": "u_scatter_flux", "noise": "u_scatter_noise"}

_REQUIRED = ("theta_i", "phi_ref", "wavelength", "R", "pixel_pitch", "step", "roi")


def _owner(name: str | None, source: str | None) -> str:
    return f"frame '{name}'" + (f" ({source})" if source else "")


def detector_from_attrs(attrs: Mapping[str, Any], *, owner: str = "frame") -> Detector:
    """The :class:`Detector` a reduced frame was measured with (arm ``None`` when centred on the peak).

    :func:`brdfjax.io.header.detector_from_attrs`, with the errors of a fit input.
    """
    missing = [k for k in _REQUIRED if k not in attrs]
    if missing:
        raise FitInputError(
            f"{owner}: missing header attribute(s) {missing}; a reduced frame has {', '.join(_REQUIRED)} "
            "(written by brdfjax reduce)"
        )
    try:
        return header.detector_from_attrs(attrs)
    except (ValueError, TypeError) as e:
        raise FitInputError(f"{owner}: the header does not describe a valid detector: {e}") from None


def _stored_grid(attrs: Mapping[str, Any], shape: tuple[int, int], owner: str) -> PixelGrid:
    h0, h1, v0, v1 = (int(x) for x in attrs["roi"])
    step = int(attrs["step"])
    grid = PixelGrid(np.arange(h0, h1 + 1, step), np.arange(v0, v1 + 1, step))
    if grid.shape != tuple(shape):
        raise FitInputError(
            f"{owner}: the header's roi {(h0, h1, v0, v1)} with step {step} gives a {grid.shape} grid, "
            f"but the channels are {tuple(shape)}"
        )
    return grid


def _footprint_for(w_px: float | None, pixel_step: int):
    if w_px is None:
        return None
    return footprint_kernel(float(w_px), tail=1e-6, step=int(pixel_step))


def frame_data_from_reduced(
    reduced: Any,
    *,
    name: str | None = None,
    step: int = 1,
    mask: Any = None,
    roi: tuple[int, int, int, int] | None = None,
    footprint: Any = "auto",
    footprint_w_px: float | None = None,
    sigma: str = "auto",
    sigma_floor: float = 0.0,
    source: str | None = None,
) -> FrameData:
    """A :class:`FrameData` from a reduced frame (an :class:`~brdfjax.io.ExrFrame` or anything with ``brdf``, ``extra``, ``attrs``).

    ``step`` keeps every ``step``-th row and column of the stored grid;
    ``roi = (h0, h1, v0, v1)`` (inclusive seed pixel indices) keeps the part
    of the grid inside it; ``mask`` (boolean, the stored grid's shape, or
    the decimated one) is AND-ed with the frame's ``mask`` channel.
    ``footprint``: ``"auto"`` (from the ``footprint_w_px`` argument or
    header attribute, else none), ``None`` (none) or a kernel on the
    output grid's spacing.  ``sigma`` (``"total"``, ``"pixel"``, ``"noise"``) and
    ``sigma_floor``: the weights (module docstring).  ``name`` defaults to the header's
    ``sample_file`` stem or ``"frame"``.
    """
    attrs = dict(getattr(reduced, "attrs", {}) or {})
    extra = dict(getattr(reduced, "extra", {}) or {})
    if name is None:
        stem = Path(str(attrs.get("sample_file", "") or "")).stem
        name = stem or "frame"
    owner = _owner(name, source)
    if not (isinstance(step, int | np.integer) and not isinstance(step, bool) and step >= 1):
        raise FitInputError(f"{owner}: step must be a positive integer, got {step!r}")
    brdf = np.asarray(reduced.brdf, dtype=np.float64)
    if brdf.ndim != 2:
        raise FitInputError(f"{owner}: 'brdf' must be a 2-D frame, got shape {brdf.shape}")
    if sigma not in SIGMA_CHOICES:
        raise FitInputError(f"{owner}: sigma must be one of {', '.join(SIGMA_CHOICES)}, got {sigma!r}")
    channel = SIGMA_CHOICES[sigma]
    if sigma == "auto" and channel not in extra:
        channel = "sigma_rel"
    if channel not in extra:
        have = [f"sigma = {k!r} ({c})" for k, c in SIGMA_CHOICES.items() if k != "auto" and c in extra]
        raise FitInputError(
            f"{owner}: no '{channel}' channel (sigma = {sigma!r}); a fit needs each pixel's relative uncertainty. "
            + (f"This frame has: {', '.join(have)}; pass that sigma (config: [data] sigma)." if have else
               "This frame has no uncertainty channel at all: write 'sigma_rel' (relative, 1-sigma, per pixel) "
               "with the frame (README: Conditions files).")
        )
    if not (np.isfinite(sigma_floor) and sigma_floor >= 0):
        raise FitInputError(f"{owner}: sigma_floor must be a non-negative number, got {sigma_floor!r}")
    detector = detector_from_attrs(attrs, owner=owner)
    grid = _stored_grid(attrs, brdf.shape, owner)
    sig = np.asarray(extra[channel], dtype=np.float64)
    if sigma_floor > 0:
        sig = np.hypot(sig, float(sigma_floor))
    keep = np.ones(brdf.shape, bool) if "mask" not in extra else np.asarray(extra["mask"]) > 0.5
    pixel_step = int(attrs["step"]) * int(step)
    if isinstance(footprint, str):
        if footprint != "auto":
            raise FitInputError(f"{owner}: footprint must be 'auto', None or a kernel array, got {footprint!r}")
        w = footprint_w_px if footprint_w_px is not None else attrs.get("footprint_w_px")
        kernel = _footprint_for(None if w is None or float(w) <= 0 else float(w), pixel_step)
    else:
        kernel = footprint
    rows = np.arange(brdf.shape[0])[::step]
    cols = np.arange(brdf.shape[1])[::step]
    inside = None
    if roi is not None:
        h0, h1, v0, v1 = (int(x) for x in roi)
        in_c = (grid.n_h[cols] >= h0) & (grid.n_h[cols] <= h1)
        in_r = (grid.n_v[rows] >= v0) & (grid.n_v[rows] <= v1)
        if not in_r.any() or not in_c.any():
            raise FitInputError(
                f"{owner}: the region of interest {tuple(roi)} holds no pixel of the frame's grid "
                f"(n_h {grid.n_h[0]}..{grid.n_h[-1]}, n_v {grid.n_v[0]}..{grid.n_v[-1]})"
            )
        mr = mc = 0
        if kernel is not None:
            mr, mc = (int(n) // 2 for n in np.shape(kernel))
        ir, ic = np.flatnonzero(in_r), np.flatnonzero(in_c)
        r_sel = np.arange(max(0, ir[0] - mr), min(rows.size, ir[-1] + mr + 1))
        c_sel = np.arange(max(0, ic[0] - mc), min(cols.size, ic[-1] + mc + 1))
        inside = np.outer(in_r[r_sel], in_c[c_sel])
        rows, cols = rows[r_sel], cols[c_sel]
    ix = np.ix_(rows, cols)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape == brdf.shape:
            m = m[ix]
        elif m.shape != (rows.size, cols.size):
            raise FitInputError(
                f"{owner}: mask has shape {m.shape}; expected the stored grid's {brdf.shape} "
                f"or the decimated grid's {(rows.size, cols.size)}"
            )
        keep_out = keep[ix] & m
    else:
        keep_out = keep[ix]
    if inside is not None:
        keep_out = keep_out & inside
    out_grid = PixelGrid(grid.n_h[cols], grid.n_v[rows])
    return FrameData(
        brdf=brdf[ix],
        sigma_rel=sig[ix],
        theta_i=float(attrs["theta_i"]),
        detector=detector,
        grid=out_grid,
        mask=keep_out,
        phi_ref=float(attrs["phi_ref"]),
        wavelength=float(attrs["wavelength"]),
        footprint=kernel,
        name=name,
        systematics=systematics_from_attrs(attrs),
    )


def read_frame_data(
    path: str | os.PathLike,
    *,
    name: str | None = None,
    step: int = 1,
    mask: Any = None,
    roi: tuple[int, int, int, int] | None = None,
    footprint: Any = "auto",
    footprint_w_px: float | None = None,
    sigma: str = "auto",
    sigma_floor: float = 0.0,
) -> FrameData:
    """A :class:`FrameData` from a reduced frame EXR (``brdfjax reduce`` output); ``name`` defaults to the file stem.

    Raises :class:`FitInputError` naming the file when it is missing, not a
    frame file, or lacks ``sigma_rel`` or a header attribute.
    """
    path = Path(path)
    try:
        reduced = read_reduced_frame(path)
    except FileNotFoundError:
        raise FitInputError(f"{path}: no such frame file") from None
    except ExrError as e:
        raise FitInputError(str(e)) from None
    return frame_data_from_reduced(
        reduced, name=name or path.stem, step=step, mask=mask, roi=roi, footprint=footprint,
        footprint_w_px=footprint_w_px, sigma=sigma, sigma_floor=sigma_floor, source=str(path),
    )
