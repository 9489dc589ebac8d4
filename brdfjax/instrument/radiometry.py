"""Radiometry: the BRDF from measured fluxes (seed Eq 45), its inverse, and the incident flux (Eq 87).

Every place that turns fluxes into a BRDF or a BRDF into fluxes uses these functions: the reduction and the
uncertainty budget (:mod:`brdfjax.instrument.reduce`, :mod:`brdfjax.instrument.uncertainty`), the synthetic
camera (:mod:`brdfjax.instrument.synthetic`) and the live view (:mod:`brdfjax.devices.liveview`).

The functions work on NumPy and JAX arrays alike: given any JAX array (or a tracer, so :func:`jax.grad` and
:func:`jax.vmap` pass through) they compute with :mod:`jax.numpy`, otherwise with NumPy in the inputs' own
precision (NumPy float64 stays float64 whatever ``jax_enable_x64`` says).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["brdf_from_flux", "flux_from_brdf", "incident_flux"]


def _xp(*xs: Any) -> Any:
    return jnp if any(isinstance(x, jax.Array) for x in xs) else np


def brdf_from_flux(scatter_flux: Any, incident_flux: Any, theta_s: Any, solid_angle: Any) -> Any:
    """Eq 45: ``f_r = Phi_s / (Phi_i cos(theta_s) Omega_d)`` in sr^-1.

    Fluxes in any common unit (the seed uses scaled digital counts), ``theta_s`` in radians, ``solid_angle``
    (the pixel's, ``Omega_d``) in sr; broadcasts.
    """
    xp = _xp(scatter_flux, incident_flux, theta_s, solid_angle)
    return scatter_flux / (incident_flux * xp.cos(theta_s) * solid_angle)


def flux_from_brdf(brdf: Any, incident_flux: Any, theta_s: Any, solid_angle: Any) -> Any:
    """Eq 45 inverted: ``Phi_s = f_r cos(theta_s) Omega_d Phi_i``, in the unit of ``incident_flux``; broadcasts.

    ``flux_from_brdf(brdf_from_flux(p, i, t, o), i, t, o) == p`` to rounding.
    """
    xp = _xp(brdf, incident_flux, theta_s, solid_angle)
    return brdf * xp.cos(theta_s) * solid_angle * incident_flux


def incident_flux(beam_flux: float, od_beam: float, od_sample: float) -> float:
    """Eq 87: ``Phi_i = Phi_b 10^(OD_b - OD_m)`` (units of ``beam_flux``): the beam measured through ND filters
    of optical density ``OD_b``, the sample through ``OD_m``."""
    return float(beam_flux) * 10.0 ** (float(od_beam) - float(od_sample))
