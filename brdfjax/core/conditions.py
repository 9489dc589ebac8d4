"""Measurement conditions: what belongs to one measurement rather than to the material.

:class:`Conditions` holds the incidence angle ``theta_i``, the sample's rotation about its normal
``phi_ref`` and the wavelength of one detector frame (a frame *image* is
:class:`~brdfjax.io.exr.ExrFrame`; fitted frame *data* are :class:`~brdfjax.io.blocks.FrameData`).
"""

from __future__ import annotations

import warnings
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Array

from .fields import check_param, param

__all__ = ["Conditions"]


class Conditions(eqx.Module):
    """Measurement conditions of one frame: theta_i (rad), phi_ref (rad), wavelength (m)."""

    theta_i: Array = param("rad", "incidence zenith angle")
    phi_ref: Array = param("rad", "sample rotation about its normal (bar orientation)", default=0.0)
    wavelength: Array = param("m", "wavelength", default=632.8e-9)

    def __check_init__(self):
        check_param(
            "Conditions", "theta_i", self.theta_i, lambda v: (v >= 0) & (v < np.pi / 2), "0 <= theta_i < 90 deg (radians)"
        )
        check_param("Conditions", "phi_ref", self.phi_ref, lambda v: np.isfinite(v), "a finite angle in radians")
        check_param("Conditions", "wavelength", self.wavelength, lambda v: v > 0, "a positive wavelength in metres")

    @classmethod
    def from_degrees(cls, theta_i_deg: float, phi_ref_deg: float = 0.0, wavelength_nm: float = 632.8) -> "Conditions":
        return cls(np.deg2rad(theta_i_deg), np.deg2rad(phi_ref_deg), wavelength_nm * 1e-9)


def __getattr__(name: str) -> Any:
    """``Frame``, the old name of :class:`Conditions`: served for one release with a DeprecationWarning."""
    if name == "Frame":
        warnings.warn("brdfjax.core.conditions.Frame is deprecated: use Conditions (the measurement conditions)",
                      DeprecationWarning, stacklevel=2)
        return Conditions
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
