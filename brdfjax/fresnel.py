"""Fresnel reflectance (Eq 24-27) and the Q polarization factor (Eq 69).

Complex arithmetic is written out in real and imaginary parts: XLA lowers
``complex64`` square roots and divisions into several unfused kernels on CPU,
and the real-arithmetic form fuses with the rest of a frame evaluation (about
twice as fast for the solar-cell model).  The complex refractive index is
``n + i k``; the principal square root is taken, as in Eq 24-27.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .geometry import Directions, safe_hypot, safe_sqrt

__all__ = ["fresnel", "q_factor"]


def _csqrt(a: Array, b: Array) -> tuple[Array, Array]:
    """Principal square root of ``a + i b`` as (real, imag), stable for either sign of ``a``."""
    r = safe_hypot(a, b)
    big = safe_sqrt(0.5 * (r + jnp.abs(a)))  # the larger of |re|, |im| of the root
    big_safe = jnp.where(big > 0, big, 1.0)
    small = jnp.where(big > 0, 0.5 * b / big_safe, 0.0)
    nonneg = a >= 0
    re = jnp.where(nonneg, big, jnp.abs(small))
    im = jnp.where(nonneg, small, jnp.where(b < 0, -big, big))
    return re, im


def _cmul(a, b, c, d):
    return a * c - b * d, a * d + b * c


def _abs2(a, b):
    return jnp.square(a) + jnp.square(b)


def _index_squared(n: ArrayLike, k: ArrayLike) -> tuple[Array, Array]:
    n, k = jnp.asarray(n), jnp.asarray(k)
    return jnp.square(n) - jnp.square(k), 2.0 * n * k


def _fresnel_cs(n2r, n2i, cos_t, sin_t):
    Ar, Ai = _csqrt(n2r - jnp.square(sin_t), n2i)
    rs = _abs2(cos_t - Ar, -Ai) / _abs2(cos_t + Ar, Ai)
    rp = _abs2(n2r * cos_t - Ar, n2i * cos_t - Ai) / _abs2(n2r * cos_t + Ar, n2i * cos_t + Ai)
    return rs, rp


def fresnel(n: ArrayLike, theta: ArrayLike, k: ArrayLike = 0.0) -> tuple[Array, Array]:
    """Fresnel power reflectances ``(F_s, F_p)`` for index ``n + i k`` at incidence ``theta`` (rad)."""
    theta = jnp.asarray(theta)
    n2r, n2i = _index_squared(n, k)
    return _fresnel_cs(n2r, n2i, jnp.cos(theta), jnp.sin(theta))


def q_factor(n: ArrayLike, dirs: Directions, k: ArrayLike = 0.0) -> Array:
    """Q polarization factor of Eq 69 for unpolarised light (sum of the four terms).

    ``dphi - pi`` of Eq 69 is taken from the vectors' projections on the
    surface; where either direction is along the normal its azimuth is
    undefined, and Q is independent of it (the ss/ps and sp/pp pairs
    combine to ``cos^2 + sin^2``), so ``cos(dphi - pi) = 1`` is used there.
    In the specular direction Q reduces to ``F_s + F_p``.
    """
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
    sind2 = jnp.where(ok, jnp.square(crs / rr_safe), 0.0)

    n2r, n2i = _index_squared(n, k)
    Air, Aii = _csqrt(n2r - jnp.square(si), n2i)
    Asr, Asi = _csqrt(n2r - jnp.square(ss), n2i)
    den_s = _abs2(ci + Air, Aii)  # |cos ti + A(ti)|^2
    den_ss = _abs2(cs + Asr, Asi)  # |cos ts + A(ts)|^2
    den_p = _abs2(n2r * ci + Air, n2i * ci + Aii)  # |n^2 cos ti + A(ti)|^2
    den_ps = _abs2(n2r * cs + Asr, n2i * cs + Asi)  # |n^2 cos ts + A(ts)|^2
    num2 = _abs2(n2r - 1.0, n2i)  # |n^2 - 1|^2

    # |x / y|^2 = |x|^2 / |y|^2
    q_ss = num2 * jnp.square(cosd) / (den_s * den_ss)
    q_sp = num2 * _abs2(Asr, Asi) * sind2 / (den_s * den_ps)
    q_ps = num2 * _abs2(Air, Aii) * sind2 / (den_p * den_ss)
    pr, pi = _cmul(Air, Aii, Asr, Asi)
    sis = si * ss
    q_pp = num2 * _abs2(pr * cosd - n2r * sis, pi * cosd - n2i * sis) / (den_p * den_ps)
    return q_ss + q_sp + q_ps + q_pp
