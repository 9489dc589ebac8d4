"""Instrument layer: raw exposure stacks, synthetic CCD frames, reduction and uncertainty (seed Ch. III-IV)."""

from .uncertainty import (
    brdf_uncertainty as brdf_uncertainty,
    geometry_uncertainty as geometry_uncertainty,
    optical_density_uncertainty as optical_density_uncertainty,
)
