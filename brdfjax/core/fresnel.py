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

__all__ = ["fresnel", "fresnel_microfacet", "q_factor", "q_factor_parts"]


def _csqrt_abs2(a: Array, b: Array) -> tuple[Array, Array, Array]:
    """:func:`_csqrt` of ``a + i b`` and its squared modulus ``|a + i b|``, sharing the hypot."""
    r = safe_hypot(a, b)
    big = safe_sqrt(0.5 * (r + jnp.abs(a)))
    big_safe = jnp.where(big > 0, big, 1.0)
    small = jnp.where(big > 0, 0.5 * b / big_safe, 0.0)
    nonneg = a >= 0
    re = jnp.where(nonneg, big, jnp.abs(small))
    im = jnp.where(nonneg, small, jnp.where(b < 0, -big, big))
    return re, im, r


def _csqrt(a: Array, b: Array) -> tuple[Array, Array]:
    """Principal square root of ``a + i b`` as (real, imag), stable for either sign of ``a``."""
    re, im, _ = _csqrt_abs2(a, b)
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


def fresnel_microfacet(n: ArrayLike, dirs: Directions, k: ArrayLike = 0.0) -> Array:
    """``F_s + F_p`` at the microfacet angle ``theta_d`` (``cos theta_d = w_i . w_h = w_s . w_h``).

    The Fresnel factor of the standard microfacet BRDF (Cook and Torrance
    1982; Walter et al. 2007): each facet reflects with its own local
    incidence angle.  It is twice the unpolarised reflectance, so that it
    equals :func:`q_factor` in the specular direction (``theta_d = theta_i``
    there) and replaces ``Q`` in Eq 70 or in the Torrance-Sparrow form
    without changing either normalisation.  Symmetric in ``w_i``, ``w_s``
    (reciprocal).  ``sin^2 theta_d`` is ``|w_i x w_sum|^2 / |w_sum|^2``
    (no cancellation near ``theta_d = 0``).
    """
    (ix, iy, iz), (sx, sy, sz) = dirs.i, dirs.t
    n2 = sx * sx + sy * sy + sz * sz
    pos = n2 > 0
    inv = jnp.where(pos, 1.0 / jnp.where(pos, n2, 1.0), 0.0)
    dot = ix * sx + iy * sy + iz * sz
    cos_d = jnp.where(pos, dot * safe_sqrt(inv), 1.0)
    cx, cy, cz = iy * sz - iz * sy, iz * sx - ix * sz, ix * sy - iy * sx
    sin2_d = jnp.where(pos, (cx * cx + cy * cy + cz * cz) * inv, 0.0)
    n2r, n2i = _index_squared(n, k)
    Ar, Ai = _csqrt(n2r - sin2_d, n2i)
    rs = _abs2(cos_d - Ar, -Ai) / _abs2(cos_d + Ar, Ai)
    rp = _abs2(n2r * cos_d - Ar, n2i * cos_d - Ai) / _abs2(n2r * cos_d + Ar, n2i * cos_d + Ai)
    return rs + rp


def q_factor(n: ArrayLike, dirs: Directions, k: ArrayLike = 0.0) -> Array:
    """Q polarization factor of Eq 69 for unpolarised light (sum of the four terms).

    ``dphi - pi`` of Eq 69 is taken from the vectors' projections on the
    surface; where either direction is along the normal its azimuth is
    undefined, and Q is independent of it (the ss/ps and sp/pp pairs
    combine to ``cos^2 + sin^2``), so ``cos(dphi - pi) = 1`` is used there.
    In the specular direction Q reduces to ``F_s + F_p``.

    Written with the squared projections only (``sin^2 theta``, never
    ``sin theta``: ``|P cos(dphi - pi) - n^2 sin ti sin ts|^2`` is
    ``|P d + n^2 si^2 ss^2|^2 / (si^2 ss^2)`` with ``d`` the projections' dot
    product) and the four terms over one common denominator: two complex
    square roots and three divisions, of which only those of the scattered
    direction are per pixel when the incident direction is one per frame.
    """
    num, den = q_factor_parts(n, dirs, k)
    return num / den


def q_factor_parts(n: ArrayLike, dirs: Directions, k: ArrayLike = 0.0) -> tuple[Array, Array]:
    """``(numerator, denominator)`` of :func:`q_factor`, so that a caller can fold its own divisor in.

    ``Q = numerator / denominator``; the denominator is positive.  See
    :func:`q_factor` for how the terms are combined.
    """
    (ix, iy, ci), (sx, sy, cs) = dirs.i, dirs.s
    si2 = ix * ix + iy * iy
    ss2 = sx * sx + sy * sy
    rr2 = si2 * ss2
    ok = rr2 > 0
    # cos(dphi) and sin(dphi) from the standard-azimuth projections (dphi - pi flips both signs), times
    # rr2 = si^2 ss^2, which goes into the denominator; where either projection vanishes Q does not depend
    # on the azimuth and cos(dphi - pi) = 1 is used.
    dot = ix * sx + iy * sy
    crs = ix * sy - iy * sx
    rr2_safe = jnp.where(ok, rr2, 1.0)
    cos2 = jnp.where(ok, jnp.square(dot), 1.0)
    sin2 = jnp.where(ok, jnp.square(crs), 0.0)

    n2r, n2i = _index_squared(n, k)
    Air, Aii, Ai2 = _csqrt_abs2(n2r - si2, n2i)
    Asr, Asi, As2 = _csqrt_abs2(n2r - ss2, n2i)
    den_s = _abs2(ci + Air, Aii)  # |cos ti + A(ti)|^2
    den_ss = _abs2(cs + Asr, Asi)  # |cos ts + A(ts)|^2
    den_p = _abs2(n2r * ci + Air, n2i * ci + Aii)  # |n^2 cos ti + A(ti)|^2
    den_ps = _abs2(n2r * cs + Asr, n2i * cs + Asi)  # |n^2 cos ts + A(ts)|^2
    num2 = _abs2(n2r - 1.0, n2i)  # |n^2 - 1|^2

    pr, pi = _cmul(Air, Aii, Asr, Asi)  # P = A(ti) A(ts)
    # |P cos(dphi - pi) - n^2 si ss|^2 si^2 ss^2 = |P dot + n^2 si^2 ss^2|^2 (cos(dphi - pi) = -dot / (si ss))
    pp = jnp.where(ok, _abs2(pr * dot + n2r * rr2, pi * dot + n2i * rr2), _abs2(pr, pi))
    # sum of |x / y|^2 = |x|^2 / |y|^2 over the four terms, on the common denominator
    numer = (cos2 * den_p + Ai2 * sin2 * den_s) * den_ps + (As2 * sin2 * den_p + pp * den_s) * den_ss
    # per-frame factors first (one product of scalars when the incident direction is one per frame)
    return (num2 * numer), ((rr2_safe * (den_s * den_p)) * (den_ss * den_ps))
