"""Additive light terms a facet model may lack, as pure JAX functions of named parameters.

One implementation serves two callers: the sky gap diagnosis
(:mod:`.skygap`) fits these terms' parameters, and ``brdfjax observe``
(:mod:`.observe_config`, its ``[effects]`` table) predicts with the fitted
values, so that a diagnosed model written as an observe config reruns to the
same magnitudes.  Every term is a flux in units of the solar irradiance at
1 AU (as :func:`~.engine.facet_flux`), evaluated at the centre of the Sun.

Parameter keys (natural units: radians, sr^-1, m^2):

``miss.arho``, ``miss.tilt``, ``miss.az``
    a Lambertian plate the model lacks: area times albedo ``A rho`` (m^2),
    its body-frame normal at ``tilt`` from body +z and azimuth ``az`` about z
    (``(sin t cos a, sin t sin a, cos t)``); flux ``A rho / pi cos_i cos_s
    scale``.
``wide.<facet>.k``, ``wide.<facet>.w``
    a lobe beyond the facet's lab-measured incidence: ``k exp(-(1 - h_z) /
    w^2)`` (``h`` the half vector in the facet frame) switched on by
    ``sigmoid((theta_i - theta_max) / 2 deg)``, ``theta_max`` the facet's
    largest measured incidence.
``oop.<facet>.k``, ``oop.<facet>.delta``
    an offset peak out of the plane of incidence: ``k/2 sum_+- exp(-(1 - h .
    h0) / w0^2)`` about ``h0 = cos(delta) z +- sin(delta) p`` (``p`` the unit
    normal of the plane of incidence), ``w0`` = 6 deg.
``diff.<facet>.k``, ``diff.<facet>.s``
    the first diffraction orders of a grating whose grooves run along the
    facet's x axis (a material anisotropy that an in-plane lab scan along x
    does not see): ``k/2 sum_+- exp(-|t_s + t_i -+ s y|^2 / w1^2)`` with
    ``t`` the tangential (x, y) components of the unit directions (the
    grating equation: order m leaves where ``t_s = -t_i + m (lambda /
    Lambda) y``), ``s = lambda / Lambda`` the order spacing, ``w1`` = 0.035
    (2 deg).

Each facet term is multiplied by ``cos_i cos_s A_j scale`` (the facet's
fitted area), as a BRDF term would be.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["OOP_WIDTH", "DIFF_WIDTH", "GATE", "effects_flux"]

OOP_WIDTH = float(np.deg2rad(6.0))
DIFF_WIDTH = 0.035
GATE = float(np.deg2rad(2.0))


def effects_flux(vals: dict, facet_names, w_c, w_s, s_b, o_b, scale, area, theta_max):
    """The effects' flux (N,): ``vals`` maps the keys above to values (absent keys: the term is off).

    ``w_c``, ``w_s``: Sun-centre and observer directions in each facet's frame
    (N, J, 3); ``s_b``, ``o_b``: the same in the body frame (N, 3); ``scale``
    (N,): ``(AU / d_sun)^2 / d_obs^2``; ``area`` (J,): facet areas (m^2);
    ``theta_max`` (J,): each facet's largest measured incidence (rad).
    """
    scale = jnp.asarray(scale)
    total = jnp.zeros(scale.shape[0])
    if "miss.arho" in vals:
        t, a = vals["miss.tilt"], vals["miss.az"]
        n = jnp.stack([jnp.sin(t) * jnp.cos(a), jnp.sin(t) * jnp.sin(a), jnp.cos(t)])
        cs = jnp.maximum(jnp.asarray(s_b) @ n, 0.0)
        co = jnp.maximum(jnp.asarray(o_b) @ n, 0.0)
        total = total + vals["miss.arho"] / np.pi * cs * co * scale
    keys = [f"{p}.{f}.k" for f in facet_names for p in ("wide", "oop", "diff")]
    if not any(k in vals for k in keys):
        return total
    cos = jnp.maximum(w_c[..., 2], 0.0) * jnp.maximum(w_s[..., 2], 0.0)  # (N, J)
    h = w_c + w_s
    h = h / jnp.maximum(jnp.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    ti = jnp.arctan2(jnp.hypot(w_c[..., 0], w_c[..., 1]), w_c[..., 2])
    pn = jnp.stack([w_c[..., 1], -w_c[..., 0], jnp.zeros_like(w_c[..., 0])], -1)
    pn = pn / jnp.maximum(jnp.linalg.norm(pn, axis=-1, keepdims=True), 1e-12)
    for j, f in enumerate(facet_names):
        geo = cos[:, j] * area[j] * scale
        if f"wide.{f}.k" in vals:
            k, w = vals[f"wide.{f}.k"], vals[f"wide.{f}.w"]
            gate = 1.0 / (1.0 + jnp.exp(-(ti[:, j] - theta_max[j]) / GATE))
            total = total + k * jnp.exp(-(1.0 - h[:, j, 2]) / jnp.square(w)) * gate * geo
        if f"oop.{f}.k" in vals:
            k, dl = vals[f"oop.{f}.k"], vals[f"oop.{f}.delta"]
            hz, hp = h[:, j, 2], jnp.sum(h[:, j] * pn[:, j], -1)
            lobe = 0.0
            for sgn in (1.0, -1.0):
                c = jnp.cos(dl) * hz + sgn * jnp.sin(dl) * hp
                lobe = lobe + 0.5 * jnp.exp(-(1.0 - c) / OOP_WIDTH**2)
            total = total + k * lobe * geo
        if f"diff.{f}.k" in vals:
            k, s = vals[f"diff.{f}.k"], vals[f"diff.{f}.s"]
            tx = w_c[:, j, 0] + w_s[:, j, 0]
            ty = w_c[:, j, 1] + w_s[:, j, 1]
            lobe = 0.0
            for sgn in (1.0, -1.0):
                lobe = lobe + 0.5 * jnp.exp(-(jnp.square(tx) + jnp.square(ty - sgn * s)) / DIFF_WIDTH**2)
            total = total + k * lobe * geo
    return total
