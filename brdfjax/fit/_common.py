"""Shared small pieces of the fitting package: the input-error type and unit helpers."""

from __future__ import annotations

import numpy as np

from ..runtime.errors import FitInputError

__all__ = ["FitInputError", "natural_unit", "to_natural", "FRAME_PARAMETERS"]

#: Conditions parameters that a fit may free, with their units (per frame by default).
FRAME_PARAMETERS: dict[str, str] = {"theta_i": "rad", "phi_ref": "rad"}


def natural_unit(unit: str) -> str:
    """The unit a parameter is reported in: radians are reported in degrees, the rest as stored."""
    return "deg" if unit == "rad" else unit


def to_natural(unit: str) -> float:
    """Factor from the stored unit to the reported unit (180/pi for radians, else 1)."""
    return float(np.rad2deg(1.0)) if unit == "rad" else 1.0
