"""Microfacet distribution functions D (seed §2.3, Eq 54-68).

Every distribution here is normalised per Eq 54,

    integral_0^{2 pi} integral_0^{pi/2} D(theta_h, phi_h) cos(theta_h) sin(theta_h) dtheta_h dphi_h = 1,

and is evaluated from the squared microfacet slopes
``tx2 = tan^2(theta_h) cos^2(phi_h) = h_x^2 / h_z^2`` and
``ty2 = tan^2(theta_h) sin^2(phi_h) = h_y^2 / h_z^2`` rather than from angles:
``cos^2(theta_h) = 1 / (1 + tx2 + ty2)``.  This keeps a 2e-4 rad wide peak
exact in float32 (``physics.md``: ``acos`` near 1 loses every digit).  The
anisotropic forms take x along the sample's in-plane axis (azimuth 0/pi) and
y across it; ``cos^2(phi_h)`` is unchanged by the seed's "azimuth from -x"
convention.

Normalisations that the seed does not print, derived here (u = tan^2 theta_h,
so that ``cos(th) sin(th) dth / cos^4(th) = du / 2``):

* modified Beard-Maxwell (Eq 56), ``D = B / (cos th (s^2 + tan^2 th))``: with
  ``c = cos th`` the condition reads ``2 pi B I(s) = 1`` where
  ``I(s) = integral_0^1 c^2 / (1 - k^2 c^2) dc = (atanh(k)/k - 1) / k^2`` and
  ``k^2 = 1 - s^2`` (``atan`` form for ``s > 1``, series ``1/3 + k^2/5 + ...``
  near ``s = 1``).
* Ashikhmin-Shirley (Eq 58) with the cosine-weighted measure:
  ``integral dphi / (kx cos^2 + ky sin^2 + 2) = 2 pi / sqrt((kx+2)(ky+2))``,
  so the seed's prefactor ``sqrt((kx+2)(ky+2)) / (2 pi)`` is exact.
* anisotropic Student-t (Eq 68): ``integral_0^inf (1 + A u/(g-1))^-g du = 1/A``
  with ``A = cos^2/sx^2 + sin^2/sy^2`` and ``integral dphi / A = 2 pi sx sy``,
  so the seed's ``1/(pi sx sy)`` prefactor is exact (the seed left it open).
* GTR (Eq 60-61) is evaluated as ``(g-1)(1-c^2) / (pi expm1((g-1) ln(1/c^2)))``,
  which is Eq 60 rearranged, tends to Eq 61 as ``g -> 1`` without a branch
  singularity, and does not overflow for large ``g`` or small ``c``.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .fields import check_param, param

__all__ = [
    "AbstractDistribution",
    "Beckmann",
    "BeckmannAniso",
    "GGX",
    "GGXAniso",
    "GTR",
    "HyperCauchy",
    "Ribardiere",
    "StudentT",
    "StudentTAniso",
    "CosineLobe",
    "AshikhminShirley",
    "BeardMaxwell",
]

_PI = np.pi


def _positive(v: np.ndarray) -> np.ndarray:
    return v > 0


class AbstractDistribution(eqx.Module):
    """A normalised microfacet distribution ``D(w_h)`` in sr^-1.

    Call with the squared slopes ``tx2, ty2`` (see the module docstring).
    """

    name: ClassVar[str]
    equation: ClassVar[str]
    #: the main width parameter (the first parameter field): what a width scan or a width-matched swap scales
    width_field: ClassVar[str]
    #: every width parameter (two for an anisotropic distribution: along x, y)
    width_fields: ClassVar[tuple[str, ...]]
    #: the tail/shape exponent's field, or None
    shape_field: ClassVar[str | None] = None
    #: a start value of the shape exponent for a fit that swaps in this family (None: no shape exponent)
    shape_start: ClassVar[float | None] = None
    #: the anisotropic form of an isotropic distribution (widths :attr:`width_fields` along x, y), or None
    anisotropic: ClassVar[type[AbstractDistribution] | None] = None
    #: factor from the Beckmann-equivalent slope width (peak curvature) to this width, where known
    peak_width_factor: ClassVar[float | None] = None

    @abc.abstractmethod
    def __call__(self, tx2: Array, ty2: Array) -> Array:
        raise NotImplementedError

    def of_angles(self, theta_h: Array, phi_h: Array | float = 0.0) -> Array:
        """Evaluate at half-vector angles (rad; azimuth from -x) for plots and checks."""
        t2 = jnp.square(jnp.tan(theta_h))
        return self(t2 * jnp.square(jnp.cos(phi_h)), t2 * jnp.square(jnp.sin(phi_h)))


def _log1p_t2(tx2: Array, ty2: Array) -> Array:
    # log(1 / cos^2 theta_h)
    return jnp.log1p(tx2 + ty2)


class Beckmann(AbstractDistribution):
    """Isotropic Beckmann, Eq 64: ``exp(-tan^2/m^2) / (pi m^2 cos^4)``; m is the rms slope."""

    name: ClassVar[str] = "beckmann"
    equation: ClassVar[str] = "Eq 64"
    width_field: ClassVar[str] = "m"
    width_fields: ClassVar[tuple[str, ...]] = ('m',)
    peak_width_factor: ClassVar[float | None] = 1.0
    m: Array = param("1", "rms microfacet slope")

    def __check_init__(self):
        check_param("beckmann", "m", self.m, _positive, "m > 0 (rms slope)")

    def __call__(self, tx2, ty2):
        inv_m2 = 1.0 / jnp.square(self.m)  # once per call, not per pixel
        t2 = tx2 + ty2
        return jnp.exp(-t2 * inv_m2) * jnp.square(1.0 + t2) * (inv_m2 / _PI)


class BeckmannAniso(AbstractDistribution):
    """Anisotropic Beckmann, Eq 65 (renormalised): slopes mx along x, my along y."""

    name: ClassVar[str] = "beckmann_aniso"
    equation: ClassVar[str] = "Eq 65"
    width_field: ClassVar[str] = "mx"
    width_fields: ClassVar[tuple[str, ...]] = ('mx', 'my')
    peak_width_factor: ClassVar[float | None] = 1.0
    mx: Array = param("1", "rms slope along x")
    my: Array = param("1", "rms slope along y")

    def __check_init__(self):
        for f in ("mx", "my"):
            check_param("beckmann_aniso", f, getattr(self, f), _positive, f"{f} > 0")

    def __call__(self, tx2, ty2):
        e = tx2 / jnp.square(self.mx) + ty2 / jnp.square(self.my)
        return jnp.exp(-e) * jnp.square(1.0 + tx2 + ty2) / (_PI * self.mx * self.my)


class GGX(AbstractDistribution):
    """Trowbridge-Reitz / GGX, Eq 59-60 with gamma = 2: ``a^2 / (pi cos^4 (a^2 + tan^2)^2)``."""

    name: ClassVar[str] = "ggx"
    equation: ClassVar[str] = "Eq 59-60 (gamma = 2)"
    width_field: ClassVar[str] = "alpha"
    width_fields: ClassVar[tuple[str, ...]] = ('alpha',)
    peak_width_factor: ClassVar[float | None] = math.sqrt(2.0)
    alpha: Array = param("1", "width (the c of Eq 59)")

    def __check_init__(self):
        check_param("ggx", "alpha", self.alpha, _positive, "alpha > 0")

    def __call__(self, tx2, ty2):
        a2 = jnp.square(self.alpha)
        t2 = tx2 + ty2
        return a2 * jnp.square((1.0 + t2) / (a2 + t2)) / _PI


class GGXAniso(AbstractDistribution):
    """Anisotropic GGX, Eq 62: widths alpha_x, alpha_y."""

    name: ClassVar[str] = "ggx_aniso"
    equation: ClassVar[str] = "Eq 62"
    width_field: ClassVar[str] = "alpha_x"
    width_fields: ClassVar[tuple[str, ...]] = ('alpha_x', 'alpha_y')
    peak_width_factor: ClassVar[float | None] = math.sqrt(2.0)
    alpha_x: Array = param("1", "width along x")
    alpha_y: Array = param("1", "width along y")

    def __check_init__(self):
        for f in ("alpha_x", "alpha_y"):
            check_param("ggx_aniso", f, getattr(self, f), _positive, f"{f} > 0")

    def __call__(self, tx2, ty2):
        q = 1.0 + tx2 / jnp.square(self.alpha_x) + ty2 / jnp.square(self.alpha_y)
        return jnp.square((1.0 + tx2 + ty2) / q) / (_PI * self.alpha_x * self.alpha_y)


class GTR(AbstractDistribution):
    """Generalized Trowbridge-Reitz (Burley), Eq 60-61: ``1/(c^2 cos^2 + sin^2)^gamma``, 0 < c < 1."""

    name: ClassVar[str] = "gtr"
    equation: ClassVar[str] = "Eq 60-61"
    width_field: ClassVar[str] = "c"
    width_fields: ClassVar[tuple[str, ...]] = ('c',)
    shape_field: ClassVar[str | None] = "gamma"
    c: Array = param("1", "width, 0 < c < 1")
    gamma: Array = param("1", "tail exponent, gamma > 0")

    def __check_init__(self):
        check_param("gtr", "c", self.c, lambda v: (v > 0) & (v < 1), "0 < c < 1")
        check_param("gtr", "gamma", self.gamma, _positive, "gamma > 0")

    def __call__(self, tx2, ty2):
        c2 = jnp.square(self.c)
        g = self.gamma
        t2 = tx2 + ty2
        log_inv_c2 = -jnp.log(c2)  # > 0
        x = (g - 1.0) * log_inv_c2
        # (g - 1) / expm1(x) = (x / expm1(x)) / log(1/c^2); x / expm1(x) -> 1 at x = 0.
        small = jnp.abs(x) < 1e-6
        x_safe = jnp.where(small, 1.0, x)
        ratio = jnp.where(small, 1.0 - 0.5 * x, x_safe / jnp.expm1(x_safe))
        norm = (1.0 - c2) * ratio / (_PI * log_inv_c2)
        # 1 / (c^2 cos^2 + sin^2)^g = ((1 + t2) / (c2 + t2))^g
        return norm * jnp.exp(g * (jnp.log1p(t2) - jnp.log(c2 + t2)))


class Ribardiere(AbstractDistribution):
    """Ribardiere's family, Eq 66: ``(C-1) B / (pi cos^4 (1 + B tan^2)^C)``, C > 1."""

    name: ClassVar[str] = "ribardiere"
    equation: ClassVar[str] = "Eq 66"
    width_field: ClassVar[str] = "B"
    width_fields: ClassVar[tuple[str, ...]] = ('B',)
    B: Array = param("1", "B > 0")
    C: Array = param("1", "C > 1")

    def __check_init__(self):
        check_param("ribardiere", "B", self.B, _positive, "B > 0")
        check_param("ribardiere", "C", self.C, lambda v: v > 1, "C > 1")

    def __call__(self, tx2, ty2):
        t2 = tx2 + ty2
        return (self.C - 1.0) * self.B / _PI * jnp.exp(2.0 * jnp.log1p(t2) - self.C * jnp.log1p(self.B * t2))


class HyperCauchy(AbstractDistribution):
    """Hyper-Cauchy (Wellems), Eq 63: ``(g-1) s^(2g-2) / (pi cos^4 (s^2 + tan^2)^g)``, g > 1."""

    name: ClassVar[str] = "hyper_cauchy"
    equation: ClassVar[str] = "Eq 63"
    width_field: ClassVar[str] = "sigma"
    width_fields: ClassVar[tuple[str, ...]] = ('sigma',)
    shape_field: ClassVar[str | None] = "gamma"
    shape_start: ClassVar[float | None] = 2.0
    sigma: Array = param("1", "width")
    gamma: Array = param("1", "tail exponent, > 1")

    def __check_init__(self):
        check_param("hyper_cauchy", "sigma", self.sigma, _positive, "sigma > 0")
        check_param("hyper_cauchy", "gamma", self.gamma, lambda v: v > 1, "gamma > 1")

    def __call__(self, tx2, ty2):
        s2 = jnp.square(self.sigma)
        g = self.gamma
        t2 = tx2 + ty2
        log_d = jnp.log(g - 1.0) + (g - 1.0) * jnp.log(s2) + 2.0 * jnp.log1p(t2) - g * jnp.log(s2 + t2)
        return jnp.exp(log_d) / _PI


class StudentT(AbstractDistribution):
    """Ribardiere's Student-t, Eq 67 (Eq 66 with B = 1/(s^2 (g-1)), C = g); GGX at g = 2, Beckmann as g -> inf."""

    name: ClassVar[str] = "student_t"
    equation: ClassVar[str] = "Eq 67"
    width_field: ClassVar[str] = "sigma"
    width_fields: ClassVar[tuple[str, ...]] = ('sigma',)
    shape_field: ClassVar[str | None] = "gamma"
    shape_start: ClassVar[float | None] = 3.0
    sigma: Array = param("1", "width (rms slope in the Beckmann limit)")
    gamma: Array = param("1", "shape, > 1")

    def __check_init__(self):
        check_param("student_t", "sigma", self.sigma, _positive, "sigma > 0")
        check_param("student_t", "gamma", self.gamma, lambda v: v > 1, "gamma > 1")

    def __call__(self, tx2, ty2):
        s2 = jnp.square(self.sigma)
        g = self.gamma
        t2 = tx2 + ty2
        return jnp.exp(2.0 * jnp.log1p(t2) - g * jnp.log1p(t2 / ((g - 1.0) * s2))) / (_PI * s2)


class StudentTAniso(AbstractDistribution):
    """Anisotropic Student-t, Eq 68 (normalisation derived in the module docstring)."""

    name: ClassVar[str] = "student_t_aniso"
    equation: ClassVar[str] = "Eq 68"
    width_field: ClassVar[str] = "sigma_x"
    width_fields: ClassVar[tuple[str, ...]] = ('sigma_x', 'sigma_y')
    shape_field: ClassVar[str | None] = "gamma"
    sigma_x: Array = param("1", "width along x")
    sigma_y: Array = param("1", "width along y")
    gamma: Array = param("1", "shape, > 1")

    def __check_init__(self):
        for f in ("sigma_x", "sigma_y"):
            check_param("student_t_aniso", f, getattr(self, f), _positive, f"{f} > 0")
        check_param("student_t_aniso", "gamma", self.gamma, lambda v: v > 1, "gamma > 1")

    def __call__(self, tx2, ty2):
        g = self.gamma
        e = (tx2 / jnp.square(self.sigma_x) + ty2 / jnp.square(self.sigma_y)) / (g - 1.0)
        return jnp.exp(2.0 * jnp.log1p(tx2 + ty2) - g * jnp.log1p(e)) / (_PI * self.sigma_x * self.sigma_y)


class CosineLobe(AbstractDistribution):
    """Normalised cosine lobe / Blinn-Phong, Eq 57: ``(k+2)/(2 pi) cos^k``."""

    name: ClassVar[str] = "cosine_lobe"
    equation: ClassVar[str] = "Eq 57"
    width_field: ClassVar[str] = "k"
    width_fields: ClassVar[tuple[str, ...]] = ('k',)
    k: Array = param("1", "exponent, k >= 0")

    def __check_init__(self):
        check_param("cosine_lobe", "k", self.k, lambda v: v >= 0, "k >= 0")

    def __call__(self, tx2, ty2):
        return (self.k + 2.0) / (2.0 * _PI) * jnp.exp(-0.5 * self.k * jnp.log1p(tx2 + ty2))


class AshikhminShirley(AbstractDistribution):
    """Ashikhmin-Shirley anisotropic cosine lobe, Eq 58: exponent kx cos^2 phi + ky sin^2 phi."""

    name: ClassVar[str] = "ashikhmin_shirley"
    equation: ClassVar[str] = "Eq 58"
    width_field: ClassVar[str] = "kx"
    width_fields: ClassVar[tuple[str, ...]] = ('kx', 'ky')
    kx: Array = param("1", "exponent along x, >= 0")
    ky: Array = param("1", "exponent along y, >= 0")

    def __check_init__(self):
        for f in ("kx", "ky"):
            check_param("ashikhmin_shirley", f, getattr(self, f), lambda v: v >= 0, f"{f} >= 0")

    def __call__(self, tx2, ty2):
        t2 = tx2 + ty2
        pos = t2 > 0
        t2_safe = jnp.where(pos, t2, 1.0)
        # At theta_h = 0 the exponent is irrelevant (cos = 1); pick kx there.
        expo = jnp.where(pos, (self.kx * tx2 + self.ky * ty2) / t2_safe, self.kx)
        norm = jnp.sqrt((self.kx + 2.0) * (self.ky + 2.0)) / (2.0 * _PI)
        return norm * jnp.exp(-0.5 * expo * jnp.log1p(t2))


def _beard_maxwell_integral(s: Array) -> Array:
    """I(s) = integral_0^1 c^2 / (s^2 c^2 + 1 - c^2) dc (module docstring)."""
    s2 = jnp.square(s)
    k2 = 1.0 - s2
    near = jnp.abs(k2) < 1e-2
    series = 1.0 / 3 + k2 / 5 + k2**2 / 7 + k2**3 / 9 + k2**4 / 11 + k2**5 / 13
    below = s < 1.0
    k2_lo = jnp.where(near | ~below, 0.5, k2)  # s < 1: k real
    k_lo = jnp.sqrt(k2_lo)
    s_lo = jnp.where(near | ~below, 0.5, s)
    # atanh(k) = log((1 + k) / s) since (1 + k)(1 - k) = s^2; no cancellation for small s.
    i_lo = (jnp.log((1.0 + k_lo) / s_lo) / k_lo - 1.0) / k2_lo
    kap2 = jnp.where(near | below, 0.5, -k2)  # s > 1: k imaginary
    kap = jnp.sqrt(kap2)
    i_hi = (1.0 - jnp.arctan(kap) / kap) / kap2
    return jnp.where(near, series, jnp.where(below, i_lo, i_hi))


class BeardMaxwell(AbstractDistribution):
    """Modified Beard-Maxwell (Cauchy) distribution, Eq 56, with the normalisation B derived here."""

    name: ClassVar[str] = "beard_maxwell"
    equation: ClassVar[str] = "Eq 56"
    width_field: ClassVar[str] = "s"
    width_fields: ClassVar[tuple[str, ...]] = ('s',)
    s: Array = param("1", "width")

    def __check_init__(self):
        check_param("beard_maxwell", "s", self.s, _positive, "s > 0")

    def __call__(self, tx2, ty2):
        t2 = tx2 + ty2
        B = 1.0 / (2.0 * _PI * _beard_maxwell_integral(self.s))
        return B * jnp.sqrt(1.0 + t2) / (jnp.square(self.s) + t2)


# the anisotropic partners (set here: each is defined after its isotropic form)
Beckmann.anisotropic = BeckmannAniso
GGX.anisotropic = GGXAniso
StudentT.anisotropic = StudentTAniso
