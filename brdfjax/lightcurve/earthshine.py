"""Earthshine: sunlight reflected by a Lambertian Earth onto the satellite's facets (JAX), as lumos-sat has it.

The Earth is a sphere of radius ``earth_radius`` with a uniform Lambertian
albedo ``a``; the Sun is at infinity (direction ``s`` from the satellite).
A surface element ``dA`` of the Earth with normal ``n`` is lit by
``E_sun max(n . s, 0)`` and has radiance ``L = (a / pi) E_sun max(n . s,
0)``.  Seen from the satellite at ``r_sat`` (distance ``d``, direction
``-w`` from the element to the satellite, ``cos_e = n . (r_sat - p) / d``),
it adds to facet ``j`` the irradiance at the observer::

    E_j / E_sun = A_j cos_s,j / d_obs^2  sum_elements f_j(w, w_s) max(cos_i,j(w), 0) L/E_sun cos_e dA / d^2

(the same form as the direct term, each Earth element a small source).  The
elements tile the cap visible from the satellite (angle from the
sub-satellite point up to ``acos(R / r)``) on a midpoint grid of ``n_psi``
polar rings by ``n_chi`` azimuths about the sub-satellite point, with area
``R^2 sin(psi) dpsi dchi``; unlit and hidden elements weigh nothing.  Facets
do not shadow one another and the Earth is not shadowed by the satellite (as
lumos-sat).  lumos-sat integrates the lit part of the same cap on its own
grid; tests/lightcurve/test_observe.py compares the two.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .engine import Geometry, Satellite, facet_brdf, to_facet_frames
from .ephemeris import AU_M, EARTH_RADIUS_M

__all__ = ["earthshine_flux"]


def _unit(v):
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _chunk_terms(sat: Satellite, g: Geometry, albedo, n_psi: int, n_chi: int, earth_radius: float, wavelength: float):
    r = g.r[:, None]
    rh = g.r_hat
    e1 = _unit(g.s - jnp.sum(g.s * rh, -1, keepdims=True) * rh)
    e2 = jnp.cross(rh, e1)
    psi_max = jnp.arccos(jnp.clip(earth_radius / g.r, -1.0, 1.0))  # (T,)
    u = (jnp.arange(n_psi) + 0.5) / n_psi
    psi = psi_max[:, None] * u[None, :]  # (T, P)
    dpsi = psi_max / n_psi
    chi = (jnp.arange(n_chi) + 0.5) * (2 * np.pi / n_chi)
    sp, cp = jnp.sin(psi)[..., None], jnp.cos(psi)[..., None]  # (T, P, 1)
    cc, sc = jnp.cos(chi), jnp.sin(chi)  # (C,)
    n = (cp[..., None] * rh[:, None, None, :]
         + (sp * cc)[..., None] * e1[:, None, None, :] + (sp * sc)[..., None] * e2[:, None, None, :])  # (T, P, C, 3)
    T = n.shape[0]
    n = n.reshape(T, -1, 3)
    dA = (earth_radius**2 * jnp.sin(psi) * dpsi[:, None] * (2 * np.pi / n_chi))  # (T, P)
    dA = jnp.repeat(dA, n_chi, axis=1)  # (T, P*C) in the order of n
    d = (r * rh)[:, None, :] - earth_radius * n  # element -> satellite
    dist = jnp.linalg.norm(d, axis=-1)
    cos_e = jnp.maximum(jnp.sum(n * d, -1) / dist, 0.0)
    cos_sun = jnp.maximum(jnp.sum(n * g.s[:, None, :], -1), 0.0)
    weight = (albedo / np.pi) * cos_sun * cos_e * dA / jnp.square(dist)  # (T, K): L/E_sun cos_e dA / d^2
    w = -d / dist[..., None]  # satellite -> element
    M = sat.attitude.matrix(g.r_hat, g.v_hat)
    w_b = jnp.einsum("tij,tki->tkj", M, w)
    s_b = jnp.einsum("tij,ti->tj", M, g.s)
    o_b = jnp.einsum("tij,ti->tj", M, g.o)
    x, y, nf = sat.facets.frames(s_b)  # (T, J, 3)

    w_i = to_facet_frames(w_b, x, y, nf)  # (T, J, K, 3)
    w_s = to_facet_frames(o_b, x, y, nf)  # (T, J, 3)
    fv = facet_brdf(sat, w_i, w_s, wavelength)  # (T, J, K)
    integral = jnp.sum(fv * jnp.maximum(w_i[..., 2], 0.0) * weight[:, None, :], -1)
    scale = jnp.square(AU_M / g.d_sun) / jnp.square(g.d_obs)
    return sat.facets.area * integral * jnp.maximum(w_s[..., 2], 0.0) * scale[:, None]


def earthshine_flux(sat: Satellite, geometry: Geometry, albedo: float = 0.3, *, n_psi: int = 32, n_chi: int = 64,
                    earth_radius: float = EARTH_RADIUS_M, wavelength: float = 550e-9, chunk: int = 64) -> jax.Array:
    """Each facet's earthshine irradiance at the observer (T, J), in units of the solar irradiance at 1 AU (times
    ``(AU/d_sun)^2`` as the direct term); rows in chunks of ``chunk``."""
    T = len(geometry)
    size = max(1, min(chunk, T))
    chunks, _ = geometry.chunks(size)
    fn = jax.jit(lambda g: _chunk_terms(sat, g, albedo, n_psi, n_chi, earth_radius, wavelength))
    out = jax.lax.map(fn, chunks)
    return out.reshape((-1,) + out.shape[2:])[:T]
