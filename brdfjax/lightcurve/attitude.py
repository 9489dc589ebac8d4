"""Attitude laws as named conventions with fittable parameters (JAX where it is differentiable).

The body frame of brdfjax's light-curve engine
(:class:`~brdfjax.lightcurve.engine.Attitude`, kind ``"nadir"``): body +z to
the Earth's centre (nadir), body +x along the component normal to z of a
*yaw reference* direction, body +y = z x x.  Roll, pitch and yaw offsets
(``Rz(yaw) Ry(pitch) Rx(roll)``, radians, differentiable) turn the body from
that frame.  The yaw reference is the law (:data:`~brdfjax.lightcurve.skygeometry.YAW_LAWS`):

``nadir_sun_yaw`` (``yaw_law = "sun_yaw"``)
    body +y points to the Sun's azimuth seen from the satellite; the Sun is in
    the body y-z plane.  This is lumos-sat's brightness frame turned by 180
    deg about its y axis: lumos-sat's frame has z *up* (away from the Earth's
    centre), y to the Sun's azimuth, x = y x z.  A normal given in lumos-sat's
    frame ``(nx, ny, nz)`` is ``(-nx, ny, -nz)`` in the body frame
    (:func:`lumos_normal_to_body`): lumos-sat's Earth-facing ``(0, 0, -1)``
    is body ``+z`` (the chassis faces nadir).
``nadir_north`` (``yaw_law = "north"``)
    body +x to the local north at the satellite (absolute rows only): a bus
    that holds a fixed heading.

Facets (:class:`~brdfjax.lightcurve.engine.Facets`) are flat plates with a
body-frame normal.  Per facet offsets (:func:`offset_facets`, radians,
differentiable): ``cant`` tilts the normal about the facet's x axis,
``yaw`` turns the facet about body z.  A **Sun-tracking array** is a facet
with ``tracking = true`` and rotation axis ``x_axis``: its normal turns about
that body axis to face the Sun as closely as the one axis allows.  With the
``sun_yaw`` law and the axis body x, the Sun is always in the plane of
rotation and the array faces it exactly (lumos-sat's Sun-facing array: normal
``(0, cos a, -sin a)`` in its frame, a the angle past the terminator); with
the axis body z the array turns in azimuth only.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .engine import Facets

__all__ = ["ATTITUDE_LAWS", "lumos_normal_to_body", "offset_facets"]

#: Named attitude laws -> the yaw law of the geometry.
ATTITUDE_LAWS = {"nadir_sun_yaw": "sun_yaw", "nadir_north": "north"}


def lumos_normal_to_body(n) -> np.ndarray:
    """A normal in lumos-sat's brightness frame (z up, y to the Sun's azimuth) -> brdfjax's ``nadir_sun_yaw`` body."""
    n = np.asarray(n, float)
    return n * np.array([-1.0, 1.0, -1.0])


def _rodrigues(v, axis, angle):
    """``v`` (..., 3) turned by ``angle`` (...) about unit ``axis`` (..., 3)."""
    c, s = jnp.cos(angle)[..., None], jnp.sin(angle)[..., None]
    return v * c + jnp.cross(axis, v) * s + axis * jnp.sum(axis * v, -1, keepdims=True) * (1 - c)


def offset_facets(facets: Facets, cant, yaw) -> Facets:
    """``facets`` with each normal tilted by ``cant[j]`` about its x axis, then the facet turned by ``yaw[j]`` about
    body z (radians, arrays (J,), differentiable).  Tracking facets keep their rotation axis turned by ``yaw``
    only (cant does not apply to them)."""
    cant = jnp.asarray(cant, facets.normal.dtype) * (1 - facets.tracking)
    yaw = jnp.asarray(yaw, facets.normal.dtype)
    n = _rodrigues(facets.normal, facets.x_axis, cant)
    z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], n.dtype), n.shape)
    n = _rodrigues(n, z, yaw)
    x = _rodrigues(facets.x_axis, z, yaw)
    return Facets(facets.area, n, x, facets.phi_ref, facets.tracking, facets.side, facets.names)

