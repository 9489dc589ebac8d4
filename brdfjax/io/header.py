"""The frame header: a :class:`~brdfjax.Detector` and a :class:`~brdfjax.Conditions` <-> EXR attributes, both ways.

This is the one place that knows how a measurement's geometry is written into
a file header and read back.  Every writer goes through
:func:`geometry_attrs` / :func:`frame_attrs` (``brdfjax simulate``, the
reduction, the synthetic instrument and the capture of raw stacks) and every
reader through :func:`detector_from_attrs` / :func:`frame_from_attrs` (the
fit's frame reader, the raw stack reader, the CLI's figures).

The attributes (SI units, radians; stored as doubles by :mod:`brdfjax.io.exr`
and :mod:`brdfjax.io.raw`), in the order they are written:

================= ====== ==============================================================
``theta_i``       rad    incidence angle (:class:`Conditions`)
``theta_c``       rad    the detector arm's angle (:meth:`Detector.arm_angle`: ``theta_i``
                         when the detector is centred on the peak)
``phi_ref``       rad    sample rotation about its normal
``wavelength``    m
``R``             m      sample-to-array distance
``pixel_pitch``   m      horizontal pixel pitch d_h
``pixel_pitch_v`` m      vertical pixel pitch d_v (read: default ``pixel_pitch``)
``roll``, ``yaw``, rad   CCD rotation misalignment (read: default 0)
``pitch``
``m_h``, ``m_v``  px     translational misalignment (read: default 0)
================= ====== ==============================================================

A frame on a pixel grid (:func:`frame_attrs`) adds ``step`` and ``roi =
(h0, h1, v0, v1)`` (inclusive seed pixel indices) and, for a reduced frame,
the raw array's ``detector_n_v`` x ``detector_n_h`` (files without them get
the smallest even-sized array that holds the roi; pixel geometry depends on
the indices only).  Files written before any of the defaults above existed
still read.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from ..core.detector import Detector
from ..core.render import Conditions

__all__ = [
    "GEOMETRY_ATTRS",
    "MISALIGNMENT_ATTRS",
    "geometry_attrs",
    "frame_attrs",
    "detector_from_attrs",
    "frame_from_attrs",
    "shape_from_roi",
]

#: The geometry attributes of every frame header, name -> unit, in file order.
GEOMETRY_ATTRS: dict[str, str] = {
    "theta_i": "rad",
    "theta_c": "rad",
    "phi_ref": "rad",
    "wavelength": "m",
    "R": "m",
    "pixel_pitch": "m",
    "pixel_pitch_v": "m",
    "roll": "rad",
    "yaw": "rad",
    "pitch": "rad",
    "m_h": "px",
    "m_v": "px",
}

#: Misalignment attributes (seed Eq 105); 0 when absent.
MISALIGNMENT_ATTRS: tuple[str, ...] = ("roll", "yaw", "pitch", "m_h", "m_v")


def geometry_attrs(detector: Detector, frame: Conditions, *, theta_c: Any = None) -> dict[str, float]:
    """The geometry attributes of ``detector`` measuring ``frame``, as Python floats (in file order).

    ``theta_c`` (rad) overrides the arm angle, which is otherwise
    ``detector.arm_angle(frame.theta_i)`` (e.g. a beam signature's arm at 0).
    """
    arm = detector.arm_angle(frame.theta_i) if theta_c is None else theta_c
    return {
        "theta_i": float(frame.theta_i),
        "theta_c": float(arm),
        "phi_ref": float(frame.phi_ref),
        "wavelength": float(frame.wavelength),
        "R": float(detector.distance),
        "pixel_pitch": float(detector.pixel_pitch),
        "pixel_pitch_v": float(detector.pixel_pitch_v),
        **{k: float(getattr(detector, k)) for k in MISALIGNMENT_ATTRS},
    }


def frame_attrs(
    detector: Detector,
    frame: Conditions,
    *,
    step: int,
    roi: tuple[int, int, int, int],
    array_shape: bool = False,
) -> dict[str, Any]:
    """The header of a frame on a pixel grid: :func:`geometry_attrs`, ``step``, ``roi`` (and the array's shape).

    ``array_shape`` adds ``detector_n_v``, ``detector_n_h`` (the raw array's
    shape, which the roi indexes; written by the reduction).
    """
    h0, h1, v0, v1 = roi
    out: dict[str, Any] = {
        **geometry_attrs(detector, frame),
        "step": int(step),
        "roi": (int(h0), int(h1), int(v0), int(v1)),
    }
    if array_shape:
        out["detector_n_v"], out["detector_n_h"] = (int(n) for n in detector.shape)
    return out


def shape_from_roi(roi: tuple[int, int, int, int]) -> tuple[int, int]:
    """The smallest even-sized ``(n_v, n_h)`` array whose seed pixel indices hold ``roi = (h0, h1, v0, v1)``."""
    h0, h1, v0, v1 = roi

    def size(lo: int, hi: int) -> int:
        # even n: indices -(n/2 - 1) .. n/2
        n = max(2 * hi, 2 - 2 * lo, 2)
        return n + (n % 2)

    return size(v0, v1), size(h0, h1)


def detector_from_attrs(
    attrs: Mapping[str, Any], shape: tuple[int, int] | None = None, *, follow_peak: bool = True
) -> Detector:
    """The :class:`Detector` a header describes.

    ``shape`` (``(n_v, n_h)``) defaults to ``detector_n_v`` x ``detector_n_h``,
    else :func:`shape_from_roi` of the header's ``roi``.  With
    ``follow_peak`` an arm at ``theta_i`` (within 1e-12 rad) or a missing
    ``theta_c`` gives ``theta_c = None`` ("follows the peak", so frames at
    several incidence angles share one detector); without it the arm stays at
    the stored ``theta_c``.  Raises ``KeyError`` for a missing required
    attribute and ``ValueError`` for values that are no valid detector.
    """
    if shape is None:
        if "detector_n_v" in attrs and "detector_n_h" in attrs:
            shape = (int(attrs["detector_n_v"]), int(attrs["detector_n_h"]))
        else:
            shape = shape_from_roi(tuple(int(x) for x in attrs["roi"]))  # type: ignore[arg-type]
    theta_c = attrs.get("theta_c")
    if follow_peak and (
        theta_c is None
        or math.isclose(float(theta_c), float(attrs["theta_i"]), rel_tol=0.0, abs_tol=1e-12)
    ):
        theta_c = None
    elif theta_c is not None:
        theta_c = float(theta_c)
    pitch = float(attrs["pixel_pitch"])
    return Detector(
        shape=(int(shape[0]), int(shape[1])),
        pixel_pitch=pitch,
        pixel_pitch_v=float(attrs.get("pixel_pitch_v", pitch) or pitch),
        distance=float(attrs["R"]),
        theta_c=theta_c,
        **{k: float(attrs.get(k, 0.0)) for k in MISALIGNMENT_ATTRS},
    )


def frame_from_attrs(attrs: Mapping[str, Any]) -> Conditions:
    """The :class:`Conditions` (``theta_i``, ``phi_ref``, ``wavelength``) a header describes."""
    return Conditions(float(attrs["theta_i"]), float(attrs["phi_ref"]), float(attrs["wavelength"]))
