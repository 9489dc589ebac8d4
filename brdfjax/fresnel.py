"""Fresnel reflectance (Eq 24-27) and the Q polarization factor (Eq 69)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .geometry import Directions, safe_hypot

__all__ = ["complex_index", "fresnel", "q_factor"]


def complex_index(n: ArrayLike, k: ArrayLike = 0.0) -> Array:
    """``n + i k`` as complex64 or complex128 to match the real dtype."""
    n, k = jnp.broadcast_arrays(jnp.asarray(n), jnp.asarray(k))
    dtype = jnp.promote_types(jnp.result_type(n, k), jnp.float32)
    return jax.lax.complex(n.astype(dtype), k.astype(dtype))


def _fresnel_from_cos_sin(nc: Array, cos_t: Array, sin_t: Array) -> tuple[Array, Array]:
    n2 = nc * nc
    A = jnp.sqrt(n2 - jnp.square(sin_t).astype(nc.dtype))
    rs = (cos_t - A) / (cos_t + A)
    rp = (n2 * cos_t - A) / (n2 * cos_t + A)
    return jnp.square(jnp.abs(rs)), jnp.square(jnp.abs(rp))


def fresnel(n: ArrayLike, theta: ArrayLike, k: ArrayLike = 0.0) -> tuple[Array, Array]:
    """Fresnel power reflectances ``(F_s, F_p)`` for index ``n + i k`` at incidence ``theta`` (rad)."""
    theta = jnp.asarray(theta)
    return _fresnel_from_cos_sin(complex_index(n, k), jnp.cos(theta), jnp.sin(theta))


def q_factor(n: ArrayLike, dirs: Directions, k: ArrayLike = 0.0) -> Array:
    """Q polarization factor of Eq 69 for unpolarised light (sum of the four terms).

    ``dphi - pi`` of Eq 69 is taken from the vectors' projections on the
    surface; where either direction is along the normal its azimuth is
    undefined, and Q is independent of it (the ss/ps and sp/pp pairs
    combine to ``cos^2 + sin^2``), so ``cos(dphi - pi) = 1`` is used there.
    In the specular direction Q reduces to ``F_s + F_p``.
    """
    nc = complex_index(n, k)
    w_i, w_s = dirs.w_i, dirs.w_s
    ci, cs = w_i[..., 2], w_s[..., 2]
    si = safe_hypot(w_i[..., 0], w_i[..., 1])
    ss = safe_hypot(w_s[..., 0], w_s[..., 1])
    rr = si * ss
    ok = rr > 0
    rr_safe = jnp.where(ok, rr, 1.0)
    # cos(dphi) and sin(dphi) from the standard-azimuth projections; dphi - pi flips both signs.
    dot = w_i[..., 0] * w_s[..., 0] + w_i[..., 1] * w_s[..., 1]
    crs = w_i[..., 0] * w_s[..., 1] - w_i[..., 1] * w_s[..., 0]
    cosd = jnp.where(ok, -dot / rr_safe, 1.0)
    sind = jnp.where(ok, -crs / rr_safe, 0.0)

    n2 = nc * nc
    Ai = jnp.sqrt(n2 - jnp.square(si).astype(nc.dtype))
    As = jnp.sqrt(n2 - jnp.square(ss).astype(nc.dtype))
    d_si = ci + Ai
    d_ss = cs + As
    d_pi = n2 * ci + Ai
    d_ps = n2 * cs + As

    def a2(z):
        return jnp.square(jnp.real(z)) + jnp.square(jnp.imag(z))

    # |x / y|^2 = |x|^2 / |y|^2: no complex division (the costly part on CPU).
    num2 = a2(n2 - 1.0)
    den_s = a2(d_si)
    den_p = a2(d_pi)
    q_ss = num2 * jnp.square(cosd) / (den_s * a2(d_ss))
    q_sp = num2 * a2(As) * jnp.square(sind) / (den_s * a2(d_ps))
    q_ps = num2 * a2(Ai) * jnp.square(sind) / (den_p * a2(d_ss))
    q_pp = num2 * a2(Ai * As * cosd - n2 * (si * ss)) / (den_p * a2(d_ps))
    return q_ss + q_sp + q_ps + q_pp
