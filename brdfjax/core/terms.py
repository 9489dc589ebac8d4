"""BRDF terms and models (seed Eq 70, 112-115; Chapter VI).

A term is a small ``equinox`` module whose fields are its parameters and whose
call ``term(dirs, wavelength) -> sr^-1`` evaluates it on
:class:`~brdfjax.core.geometry.Directions` expressed in the **sample frame** (the
frame is rotated by ``-phi_ref`` about the normal before any term sees it, see
:func:`brdfjax.core.render.pixel_directions`).  A :class:`Model` is a named sum of
terms; wrappers (:class:`OffsetNormal`) wrap any term.

Parameters are addressed by flat names ``"<term>.<parameter>"`` (the
distribution's parameters and a wrapped term's parameters are lifted into the
term's namespace, e.g. ``"offset.m"``), or by aliases a model declares (the
solar-cell preset exposes the seed's names ``m1, rho_s1, ...``).
"""

from __future__ import annotations

import abc
import dataclasses
import re
from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .distributions import AbstractDistribution, Beckmann
from .fields import check_param, param
from .fresnel import fresnel_microfacet, q_factor_parts
from .geometry import Directions, Ry, Rz, fast_cos, fast_sinc
from .shadowing import SHADOWING, shadowing_factor, shadowing_parts, smith_mixture_g2_parts

__all__ = [
    "AbstractTerm",
    "Specular",
    "NORMALISATIONS",
    "FRESNELS",
    "Lambertian",
    "Lobe",
    "MultiLobeSpecular",
    "ABg",
    "Phong",
    "Binomial",
    "OffsetNormal",
    "Oriented",
    "Diffraction",
    "Model",
    "solar_cell",
    "SOLAR_CELL_SEED",
]


class AbstractTerm(eqx.Module):
    """One additive BRDF contribution, in sr^-1."""

    kind: ClassVar[str]
    #: the equation it implements: the seed dissertation's number ("Eq 70"), or the source it follows
    equation: ClassVar[str] = ""

    @abc.abstractmethod
    def __call__(self, dirs: Directions, wavelength: ArrayLike) -> Array:
        raise NotImplementedError


def _both_above(dirs: Directions) -> Array:
    return (dirs.cos_theta_i > 0) & (dirs.cos_theta_s > 0)


#: Normalisations of the specular term: the seed's Eq 70 form and Torrance-Sparrow's.
NORMALISATIONS = ("seed", "torrance_sparrow")


#: Fresnel factors of the specular term: the seed's Q polarization factor (Eq 69) at the macro angles, or
#: the Fresnel reflectance at each microfacet's own angle (Cook-Torrance / Walter et al. 2007).
FRESNELS = ("q_factor", "microfacet")


def _check_options(owner: str, shadowing: str, normalisation: str, fresnel: str = "q_factor") -> None:
    if fresnel not in FRESNELS:
        raise ValueError(f"{owner}: unknown fresnel '{fresnel}'; known: {', '.join(FRESNELS)}")
    if shadowing not in SHADOWING:
        raise ValueError(f"{owner}: unknown shadowing '{shadowing}'; known: {', '.join(SHADOWING)}")
    if normalisation not in NORMALISATIONS:
        raise ValueError(f"{owner}: unknown normalisation '{normalisation}'; known: {', '.join(NORMALISATIONS)}")


def _specular_geometry(dirs: Directions, normalisation: str) -> Array:
    """The geometric factor multiplying ``rho_s D G Q``: Eq 70's or Torrance-Sparrow's (``Q/2`` as F)."""
    num, den = _specular_geometry_parts(dirs, normalisation)
    return num / den


def _specular_geometry_parts(dirs: Directions, normalisation: str) -> tuple[float, Array]:
    """``(numerator, denominator)`` of :func:`_specular_geometry`."""
    ci, cs = dirs.cos_theta_i, dirs.cos_theta_s
    if normalisation == "seed":
        return 0.5, jnp.square(ci + cs)
    prod = ci * cs
    return 0.125, jnp.where(prod > 0, prod, 1.0)


def _q_times_geometry(n, k, dirs: Directions, normalisation: str, extra: tuple = (1.0, 1.0),
                      fresnel: str = "q_factor") -> Array:
    """``Q * geometry`` (times ``extra[0] / extra[1]``, e.g. the shadowing) with a single per-pixel division.

    ``fresnel="microfacet"``: ``F_s + F_p`` at the microfacet angle instead of ``Q``.
    """
    if fresnel == "microfacet":
        q_num, q_den = fresnel_microfacet(n, dirs, k), 1.0
    else:
        q_num, q_den = q_factor_parts(n, dirs, k)
    g_num, g_den = _specular_geometry_parts(dirs, normalisation)
    e_num, e_den = extra
    den = q_den * g_den if isinstance(e_den, float) and e_den == 1.0 else q_den * g_den * e_den
    return (g_num * q_num * e_num) / den


class Specular(AbstractTerm):
    """Microfacet specular term with any distribution D and the Q factor of Eq 69.

    ``normalisation="seed"`` (the default) is the seed's Eq 70,
    ``f = rho_s D(w_h) G Q(n + i k, w_i, w_s) / (2 (cos theta_i + cos theta_s)^2)``;
    ``normalisation="torrance_sparrow"`` is the microfacet form of Torrance and
    Sparrow (1967) / Walter et al. (2007), ``f = rho_s D G (Q / 2) / (4 cos theta_i cos theta_s)``,
    where ``Q / 2`` is the unpolarised Fresnel reflectance in the specular
    direction (``Q = F_s + F_p`` there).  In the specular direction the two forms
    agree; elsewhere ``(cos ti + cos ts)^2 >= 4 cos ti cos ts`` so the seed's
    form is never larger.  ``G`` is the masking-shadowing factor
    (:mod:`brdfjax.core.shadowing`): ``"none"`` (G = 1, the seed), ``"smith"``
    (height-correlated Smith G2 with the distribution's Lambda) or
    ``"v_cavity"`` (Cook-Torrance); ``"smith_mixture"`` is ``"smith"`` for one
    distribution (it differs for :class:`MultiLobeSpecular`).  ``fresnel="q_factor"`` (the default) is the
    seed's polarization factor ``Q`` of Eq 69, evaluated at the macro angles
    ``theta_i, theta_s``; ``fresnel="microfacet"`` replaces it with ``F_s + F_p``
    at the microfacet angle ``theta_d`` (``cos theta_d = w_i . w_h``;
    :func:`brdfjax.core.fresnel.fresnel_microfacet`), the Fresnel factor of
    Cook-Torrance and Walter et al. (2007): the two agree in the specular
    direction and differ off it, most for wide lobes of a conductor.  The
    defaults reproduce the seed exactly.
    """

    kind: ClassVar[str] = "specular"
    equation: ClassVar[str] = "Eq 69-70 (seed form); Walter et al. 2007 (torrance_sparrow)"
    distribution: AbstractDistribution
    rho_s: Array = param("1", "specular weight")
    n: Array = param("1", "real part of the refractive index")
    k: Array = param("1", "imaginary part of the refractive index", default=0.0)
    shadowing: str = eqx.field(static=True, default="none")
    normalisation: str = eqx.field(static=True, default="seed")
    fresnel: str = eqx.field(static=True, default="q_factor")

    def __check_init__(self):
        check_param("specular", "rho_s", self.rho_s, lambda v: v >= 0, "rho_s >= 0")
        check_param("specular", "n", self.n, lambda v: v > 0, "n > 0")
        check_param("specular", "k", self.k, lambda v: v >= 0, "k >= 0")
        _check_options("specular", self.shadowing, self.normalisation, self.fresnel)

    def __call__(self, dirs, wavelength):
        tx2, ty2, upper = dirs.half_slopes()
        D = jnp.where(upper, self.distribution(tx2, ty2), 0.0)
        G = shadowing_parts(self.shadowing, self.distribution, dirs)  # its division folded into Q's
        f = self.rho_s * D * _q_times_geometry(self.n, self.k, dirs, self.normalisation, G, self.fresnel)
        return jnp.where(_both_above(dirs), f, 0.0)


class Lobe(eqx.Module):
    """One lobe of a :class:`MultiLobeSpecular`: a distribution and its weight."""

    distribution: AbstractDistribution
    rho_s: Array = param("1", "weight of this lobe")

    def __check_init__(self):
        check_param("lobe", "rho_s", self.rho_s, lambda v: v >= 0, "rho_s >= 0")


class MultiLobeSpecular(AbstractTerm):
    """Several microfacet lobes (e.g. a narrow spike and a wide halo) sharing one index ``n + i k``.

    ``f = sum_l rho_l D_l(w_h) G_l Q(n + i k) N(theta_i, theta_s)`` with the
    normalisation ``N``, shadowing ``G`` and Fresnel factor (``fresnel``) of
    :class:`Specular`.  With ``shadowing="smith"`` each lobe's G uses its own
    distribution's Lambda; ``shadowing="smith_mixture"`` is Smith's G2 of the
    surface as a whole, whose slope distribution is the mixture of the lobes
    (``Lambda = sum_l w_l Lambda_l``, ``w_l = rho_l / sum rho``;
    :func:`brdfjax.core.shadowing.smith_mixture_g2_parts`), the same G for every lobe.  Each lobe is normalised (Eq 54), so the
    weights ``rho_l`` play the role of :class:`Specular`'s ``rho_s``.  Parameter
    names are ``<lobe>.<name>``: ``spike.m``, ``spike.rho_s``, ``halo.alpha``, ...
    and the shared ``n``, ``k``.
    """

    kind: ClassVar[str] = "multi_lobe"
    equation: ClassVar[str] = "Eq 54, 69-70, lobes summed; Heitz 2014 Eq 72 (smith_mixture)"
    lobes: dict[str, Lobe]
    n: Array = param("1", "real part of the refractive index (shared by every lobe)")
    k: Array = param("1", "imaginary part of the refractive index", default=0.0)
    shadowing: str = eqx.field(static=True, default="none")
    normalisation: str = eqx.field(static=True, default="seed")
    fresnel: str = eqx.field(static=True, default="q_factor")

    def __check_init__(self):
        if not self.lobes:
            raise ValueError("multi_lobe: needs at least one lobe")
        for name, lobe in self.lobes.items():
            if not isinstance(lobe, Lobe):
                raise TypeError(f"multi_lobe: lobe '{name}' is a {type(lobe).__name__}, not a Lobe")
            if "." in name:
                raise ValueError(f"multi_lobe: lobe name '{name}' must not contain '.'")
        check_param("multi_lobe", "n", self.n, lambda v: v > 0, "n > 0")
        check_param("multi_lobe", "k", self.k, lambda v: v >= 0, "k >= 0")
        _check_options("multi_lobe", self.shadowing, self.normalisation, self.fresnel)

    def __call__(self, dirs, wavelength):
        tx2, ty2, upper = dirs.half_slopes()
        mixture = self.shadowing == "smith_mixture"
        extra = (smith_mixture_g2_parts([lb.distribution for lb in self.lobes.values()],
                                        [lb.rho_s for lb in self.lobes.values()], dirs) if mixture else (1.0, 1.0))
        common = _q_times_geometry(self.n, self.k, dirs, self.normalisation, extra, self.fresnel)
        total = 0.0
        for lobe in self.lobes.values():
            D = jnp.where(upper, lobe.distribution(tx2, ty2), 0.0)
            G = 1.0 if mixture else shadowing_factor(self.shadowing, lobe.distribution, dirs)
            total = total + lobe.rho_s * D * G
        return jnp.where(_both_above(dirs), total * common, 0.0)


def _sq_distance_from_mirror(dirs: Directions) -> tuple[Array, Array]:
    """``|beta - beta0|^2`` (projected distance from the mirror direction) and ``|w_r - w_s|^2``.

    With the mirror direction ``w_r = (-w_ix, -w_iy, w_iz)``, ``beta - beta0``
    is the in-plane part of ``w_i + w_s`` (no cancellation: ``w_sum``).
    """
    sx, sy, _ = dirs.t
    b2 = jnp.square(sx) + jnp.square(sy)
    return b2, b2 + jnp.square(dirs.cos_theta_i - dirs.cos_theta_s)


class ABg(AbstractTerm):
    """Harvey-Shack ABg scatter model, the stray-light standard (Harvey 1976; Pfisterer 2011).

    ``f = A / (B + |beta - beta0|^g)`` with ``beta - beta0`` the difference of the
    projections of the scattered and mirror directions on the surface
    (``|beta - beta0| = |(w_i + w_s)_xy|``, in the plane of incidence
    ``|sin theta_s - sin theta_i|``).  Empirical and not normalised: ``A / B``
    is the BRDF in the mirror direction (sr^-1); the total integrated scatter
    depends on A, B, g and the incidence.  Reciprocal: symmetric in w_i, w_s.
    """

    kind: ClassVar[str] = "abg"
    equation: ClassVar[str] = "Harvey 1976"
    A: Array = param("sr^-1", "scale (sr^-1)")
    B: Array = param("1", "roll-off shoulder, in units of |beta - beta0|^g")
    g: Array = param("1", "fall-off exponent")

    def __check_init__(self):
        check_param("abg", "A", self.A, lambda v: v >= 0, "A >= 0 (sr^-1)")
        check_param("abg", "B", self.B, lambda v: v > 0, "B > 0")
        check_param("abg", "g", self.g, lambda v: v >= 0, "g >= 0")

    def __call__(self, dirs, wavelength):
        b2, _ = _sq_distance_from_mirror(dirs)
        pos = b2 > 0
        # |beta - beta0|^g = exp(g/2 ln b2), 0 at the mirror direction (finite gradients there)
        power = jnp.where(pos, jnp.exp(0.5 * self.g * jnp.log(jnp.where(pos, b2, 1.0))), 0.0)
        return jnp.where(_both_above(dirs), self.A / (self.B + power), 0.0)


class Phong(AbstractTerm):
    """Normalised (modified) Phong lobe, the lumos-sat PHONG family's specular part (Lafortune 1994).

    ``f = rho (k + 2) / (2 pi) max(cos alpha, 0)^k`` with ``alpha`` the angle
    between the scattered and the mirror direction
    (``cos alpha = 1 - |w_r - w_s|^2 / 2``).  Reciprocal.  Normalised at normal
    incidence: the directional albedo there is ``rho`` exactly (it falls below
    ``rho`` at oblique incidence, where part of the lobe is below the horizon).
    """

    kind: ClassVar[str] = "phong"
    equation: ClassVar[str] = "Lafortune 1994"
    rho: Array = param("1", "lobe weight (albedo at normal incidence)")
    k: Array = param("1", "exponent, k >= 0")

    def __check_init__(self):
        check_param("phong", "rho", self.rho, lambda v: v >= 0, "rho >= 0")
        check_param("phong", "k", self.k, lambda v: v >= 0, "k >= 0")

    def __call__(self, dirs, wavelength):
        _, d2 = _sq_distance_from_mirror(dirs)
        cos_a = 1.0 - 0.5 * d2
        pos = cos_a > 0
        lobe = jnp.where(pos, jnp.exp(self.k * jnp.log(jnp.where(pos, cos_a, 1.0))), 0.0)
        return jnp.where(_both_above(dirs), self.rho * (self.k + 2.0) / (2.0 * np.pi) * lobe, 0.0)


_BINOMIAL_KEY = re.compile(r"([bc])(\d+)_(\d+)")


def _binomial_coefficients(B: Any, C: Any) -> dict[str, Any]:
    """``{"b<k>_<i>": B[k, i], "c<k>_<i>": C[k, i]}`` from lumos-sat's matrices (rows: powers of V)."""
    out: dict[str, Any] = {}
    for letter, mat in (("b", B), ("c", C)):
        a = np.asarray(mat, dtype=np.float64) if not isinstance(mat, jax.Array | jax.core.Tracer) else mat
        if a.ndim != 2:
            raise ValueError(f"binomial: {letter.upper()} must be a 2-D matrix (powers of V x terms), got shape {a.shape}")
        for k in range(a.shape[0]):
            for i in range(a.shape[1]):
                out[f"{letter}{k}_{i}"] = a[k, i]
    return out


def binomial_shape(names: Any) -> tuple[int, int, int]:
    """``(n, m, j)`` of a binomial term from its coefficient names ``b<k>_<i>`` / ``c<k>_<i>``.

    ``n`` powers of V (``k < n``), ``m`` powers of D (``b``), ``j`` Gaussian terms (``c``).
    Raises ``ValueError`` naming a malformed or missing name.
    """
    got: dict[str, set[tuple[int, int]]] = {"b": set(), "c": set()}
    for name in names:
        hit = _BINOMIAL_KEY.fullmatch(name)
        if not hit:
            raise ValueError(f"binomial: coefficient name '{name}' is not b<k>_<i> or c<k>_<i>")
        got[hit.group(1)].add((int(hit.group(2)), int(hit.group(3))))
    if not got["b"]:
        raise ValueError("binomial: needs at least the coefficient b0_0")
    n = 1 + max(k for s in got.values() for k, _ in s)
    m = 1 + max(i for _, i in got["b"])
    j = 1 + max((i for _, i in got["c"]), default=-1)
    for letter, width in (("b", m), ("c", j)):
        missing = [f"{letter}{k}_{i}" for k in range(n) for i in range(width) if (k, i) not in got[letter]]
        if missing:
            raise ValueError(f"binomial: missing coefficient(s) {', '.join(missing)} (a full {n} x {width} '{letter}' matrix)")
    return n, m, j


class Binomial(AbstractTerm):
    """Greynolds' binomial empirical BRDF, lumos-sat's ``BINOMIAL`` family (Greynolds 2015).

    ``log10 f = sum_k V^k [ sum_i b_ki D^i + 1/2 sum_i c_ki log10(1 + d^(i + l1) D^2) ]``
    with ``D = |beta - beta0| = |(w_i + w_s)_xy|`` (as :class:`ABg`) and
    ``V = beta . beta0 = -(w_i)_xy . (w_s)_xy`` (the projections of the
    scattered and mirror directions), ``k < n``, ``i < m`` (``b``) or ``< j``
    (``c``).  The coefficients are parameters named ``b<k>_<i>`` and ``c<k>_<i>``
    (``B[k, i]``, ``C[k, i]`` of lumos-sat); ``d > 0`` the specularity constant;
    ``l1`` (an integer, not fitted) the lowest Gaussian index.  Empirical, not
    normalised; reciprocal (``D`` and ``V`` are symmetric in w_i, w_s); zero
    below either horizon.  ``10^(b00)`` is the BRDF in the mirror direction at
    normal incidence.
    """

    kind: ClassVar[str] = "binomial"
    equation: ClassVar[str] = "Greynolds 2015"
    coefficients: dict[str, Array] = eqx.field(metadata={"unit_dict": "log10", "doc": "b<k>_<i>, c<k>_<i>: signed coefficients of log10 f"})
    d: Array = param("1", "specularity constant (> 0)")
    l1: int = eqx.field(static=True, default=0)
    shape: tuple[int, int, int] = eqx.field(static=True, init=False, default=(1, 1, 0))

    def __init__(self, B: Any = None, C: Any = None, d: Any = 1.0, l1: int = 0, *, coefficients: Mapping[str, Any] | None = None):
        if coefficients is None:
            if B is None:
                raise ValueError("binomial: give the matrices B and C (lumos-sat's) or coefficients={'b0_0': ...}")
            coefficients = _binomial_coefficients(B, np.zeros((np.shape(B)[0], 0)) if C is None else C)
        elif B is not None or C is not None:
            raise ValueError("binomial: give either B, C or coefficients, not both")
        self.shape = binomial_shape(coefficients)
        self.coefficients = {k: v if isinstance(v, jax.Array | jax.core.Tracer) else np.asarray(v, dtype=np.float64)
                             for k, v in coefficients.items()}
        self.d = d if isinstance(d, jax.Array | jax.core.Tracer) else np.asarray(d, dtype=np.float64)
        if int(l1) != l1:
            raise ValueError(f"binomial: l1 must be an integer, got {l1!r}")
        self.l1 = int(l1)

    def __check_init__(self):
        check_param("binomial", "d", self.d, lambda v: v > 0, "d > 0")
        for name, v in self.coefficients.items():
            check_param("binomial", name, v, lambda x: np.isfinite(x), "a finite number")

    def __call__(self, dirs, wavelength):
        b2, _ = _sq_distance_from_mirror(dirs)
        pos = b2 > 0
        D = jnp.where(pos, jnp.sqrt(jnp.where(pos, b2, 1.0)), 0.0)
        (ix, iy, _), (sx, sy, _) = dirs.i, dirs.s  # components: no (N, 3) arrays stacked
        V = -(ix * sx + iy * sy)
        n, m, j = self.shape
        c = self.coefficients
        log_f = 0.0
        v_pow = 1.0
        for k in range(n):
            poly = 0.0
            d_pow = 1.0
            for i in range(m):
                poly = poly + c[f"b{k}_{i}"] * d_pow
                d_pow = d_pow * D
            gauss = 0.0
            for i in range(j):
                gauss = gauss + c[f"c{k}_{i}"] * jnp.log10(1.0 + self.d ** (i + self.l1) * b2)
            log_f = log_f + (poly + 0.5 * gauss) * v_pow
            v_pow = v_pow * V
        return jnp.where(_both_above(dirs), jnp.power(10.0, log_f), 0.0)


class Lambertian(AbstractTerm):
    """Perfectly diffuse term ``rho_d / pi`` (Eq 50, 70)."""

    kind: ClassVar[str] = "lambertian"
    equation: ClassVar[str] = "Eq 50, 70"
    rho_d: Array = param("1", "diffuse reflectance")

    def __check_init__(self):
        check_param("lambertian", "rho_d", self.rho_d, lambda v: v >= 0, "rho_d >= 0")

    def __call__(self, dirs, wavelength):
        return jnp.where(_both_above(dirs), self.rho_d / np.pi, 0.0)


class OffsetNormal(AbstractTerm):
    """A term evaluated about a tilted surface normal (Eq 112-113).

    Both directions (and their sum) are rotated by ``Ry(-dtheta) Rz(-dphi0)``
    in the sample frame, i.e. ``Ry(-dtheta) Rz(-dphi0 - phi_ref)`` in the
    scatter frame, and the wrapped term is evaluated there.  ``dphi0`` is
    measured from +x toward +y.
    """

    kind: ClassVar[str] = "offset_normal"
    equation: ClassVar[str] = "Eq 112-113"
    term: AbstractTerm
    dtheta: Array = param("rad", "zenith tilt of the second normal")
    dphi0: Array = param("rad", "azimuth of the tilt, from +x toward +y")

    def rotation(self) -> Array:
        return Ry(-self.dtheta) @ Rz(-self.dphi0)

    def __call__(self, dirs, wavelength):
        return jnp.where(_both_above(dirs), self.term(dirs.rotated(self.rotation()), wavelength), 0.0)


class Oriented(AbstractTerm):
    """A term turned about the sample normal by ``psi`` (rad): evaluated on directions rotated by ``Rz(-psi)``.

    The wrapped term's x axis lies at azimuth ``psi`` from +x toward +y: the
    orientation of an anisotropic distribution's axes (a groove pattern) or of
    a bar grating.  Fresnel and Q do not depend on the azimuth, so turning a
    specular term is exactly turning its microfacet distribution.
    """

    kind: ClassVar[str] = "oriented"
    equation: ClassVar[str] = "rotation of any term about the normal by psi"
    term: AbstractTerm
    psi: Array = param("rad", "orientation of the wrapped term's x axis, from +x toward +y")

    def __check_init__(self):
        check_param("oriented", "psi", self.psi, np.isfinite, "a finite angle (rad)")

    def __call__(self, dirs, wavelength):
        return self.term(dirs.rotated(Rz(-self.psi)), wavelength)


class Diffraction(AbstractTerm):
    """Fraunhofer diffraction by two bars of spacing a and width b (Eq 114-115).

    With the unit half vector h in the sample frame, ``ybar/zbar = h_y`` and
    ``xbar = distance * h_x``::

        f = rho cos^2(2 pi a h_y cos(theta_i) / lambda)
                sinc^2(2 b h_y cos(theta_i) / lambda) exp(-(distance h_x)^2 / c^2)

    ``sinc`` is the normalised sinc.  ``distance`` is the nominal 0.325 m of
    the seed (it does not cancel in the Gaussian, where c is in metres); it is
    a fixed constant, not a fitted parameter.  ``grating_factor=False`` drops
    the seed's ``2 cos(theta_i)`` factor (then the plain two-slit pattern
    ``cos^2(pi a ybar / (lambda zbar)) sinc^2(b ybar / (lambda zbar))``).
    """

    kind: ClassVar[str] = "diffraction"
    equation: ClassVar[str] = "Eq 114-115"
    rho: Array = param("sr^-1", "peak magnitude (rho_s3)")
    a: Array = param("m", "bar spacing")
    b: Array = param("m", "bar width")
    c: Array = param("m", "Gaussian half-width of the band along the bars")
    distance: float = eqx.field(static=True, default=0.325)
    grating_factor: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_param("diffraction", "rho", self.rho, lambda v: v >= 0, "rho >= 0 (sr^-1)")
        for f in ("a", "b", "c"):
            check_param("diffraction", f, getattr(self, f), lambda v: v > 0, f"{f} > 0 (metres)")

    def __call__(self, dirs, wavelength):
        hx, hy, _ = dirs.half_vector_xyz()
        scale = 2.0 * dirs.cos_theta_i if self.grating_factor else 1.0
        # u = 2 ybar cos(theta_i) / (lambda zbar) = hy * scale / lambda (with the grating factor); the
        # per-frame factors are combined first so that each pixel does multiplications only.
        k = scale / wavelength
        f = (
            self.rho
            * jnp.square(fast_cos(hy * (np.pi * self.a * k)))
            * jnp.square(fast_sinc(hy * (self.b * k)))
            * jnp.exp(-jnp.square(hx * (self.distance / self.c)))
        )
        return jnp.where(_both_above(dirs), f, 0.0)


# --- models and parameter naming ---------------------------------------------------------


def param_fields(module: eqx.Module) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(module) if "unit" in f.metadata]


def _child_fields(module: eqx.Module) -> list[dataclasses.Field]:
    return [
        f
        for f in dataclasses.fields(module)
        if not f.metadata.get("static", False) and isinstance(getattr(module, f.name), eqx.Module)
    ]


def _module_dicts(module: eqx.Module) -> list[dataclasses.Field]:
    """Fields holding a dict of named modules (the lobes of a multi-lobe term)."""
    out = []
    for f in dataclasses.fields(module):
        v = getattr(module, f.name)
        if not f.metadata.get("static", False) and isinstance(v, Mapping) and v and all(
            isinstance(x, eqx.Module) for x in v.values()
        ):
            out.append(f)
    return out


def _term_paths(module: eqx.Module, prefix: tuple[str, ...] = ()) -> dict[str, tuple[tuple[str, ...], str]]:
    """Flat parameter name -> (attribute path, unit), lifting nested modules' parameters.

    A dict of named modules (``MultiLobeSpecular.lobes``) lifts each entry's
    parameters as ``<key>.<name>``.
    """
    out: dict[str, tuple[tuple[str, ...], str]] = {}
    for child in _child_fields(module):
        for name, entry in _term_paths(getattr(module, child.name), prefix + (child.name,)).items():
            out[name] = entry
    for field in _module_dicts(module):
        for key, sub in getattr(module, field.name).items():
            for name, entry in _term_paths(sub, prefix + (field.name, key)).items():
                out[f"{key}.{name}"] = entry
    for f in param_fields(module):
        out[f.name] = (prefix + (f.name,), f.metadata["unit"])
    for f in dataclasses.fields(module):
        if "unit_dict" in f.metadata:  # a dict of scalar parameters (Binomial's coefficients): names are the keys
            for key in getattr(module, f.name):
                out[key] = (prefix + (f.name, key), f.metadata["unit_dict"])
    return out


def _get_path(obj: Any, path: tuple[str, ...]) -> Any:
    for p in path:
        obj = obj[p] if isinstance(obj, Mapping) else getattr(obj, p)
    return obj


class Model(AbstractTerm):
    """A named sum of terms: ``f = sum_k terms[k](dirs, wavelength)``.

    ``aliases`` maps user-facing names to flat names, e.g. ``("m1", "center.m")``.
    """

    kind: ClassVar[str] = "model"
    equation: ClassVar[str] = "sum of terms"
    terms: dict[str, AbstractTerm]
    aliases: tuple[tuple[str, str], ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if not self.terms:
            raise ValueError("Model: needs at least one term")
        for name, term in self.terms.items():
            if not isinstance(term, AbstractTerm):
                raise TypeError(f"Model: term '{name}' is a {type(term).__name__}, not a brdfjax term")
            if "." in name:
                raise ValueError(f"Model: term name '{name}' must not contain '.'")

    def __call__(self, dirs, wavelength):
        values = [t(dirs, wavelength) for t in self.terms.values()]
        return sum(values[1:], values[0])

    def term_values(self, dirs: Directions, wavelength: ArrayLike) -> dict[str, Array]:
        """Each term's contribution separately."""
        return {name: t(dirs, wavelength) for name, t in self.terms.items()}

    # parameters -------------------------------------------------------------------------
    def _paths(self) -> dict[str, tuple[tuple[str, ...], str]]:
        out = {}
        for tname, term in self.terms.items():
            for pname, (path, unit) in _term_paths(term).items():
                out[f"{tname}.{pname}"] = (("terms", tname) + path, unit)
        return out

    def _resolve(self, name: str) -> str:
        paths = self._paths()
        alias = dict(self.aliases)
        flat = alias.get(name, name)
        if flat not in paths:
            known = sorted(set(alias) | (set(paths) - set(alias.values())))
            raise KeyError(f"unknown parameter '{name}'; known: {', '.join(known)}")
        return flat

    def parameter_units(self) -> dict[str, str]:
        """Public parameter name -> unit ('rad', 'm', '1', 'sr^-1')."""
        back = {v: k for k, v in self.aliases}
        return {back.get(n, n): unit for n, (_, unit) in self._paths().items()}

    def params(self) -> dict[str, Array]:
        """Public parameter name -> value (aliases where declared, else ``term.param``)."""
        back = {v: k for k, v in self.aliases}
        return {back.get(n, n): _get_path(self, path) for n, (path, _) in self._paths().items()}

    def with_params(self, values: Mapping[str, ArrayLike]) -> "Model":
        """A copy with some parameters replaced (names as in :meth:`params`); differentiable."""
        if not values:
            return self
        paths = self._paths()
        flat = [paths[self._resolve(k)][0] for k in values]
        # Arrays and tracers keep their dtype (so this works under jit/grad); plain numbers become float64.
        new = [v if isinstance(v, np.ndarray | jax.Array | jax.core.Tracer) else np.asarray(v, dtype=np.float64)
               for v in values.values()]

        def where(m):
            return tuple(_get_path(m, p) for p in flat)

        return eqx.tree_at(where, self, tuple(new))


def _deg(x: float) -> float:
    return float(np.deg2rad(x))


#: Seed §6.4 parameters of the solar-cell model (radians and metres).
SOLAR_CELL_SEED: dict[str, float] = {
    "m1": 2e-4,
    "rho_s1": 0.015,
    "n1": 3.6,
    "m2": 2e-4,
    "rho_s2": 0.7,
    "n2": 1.4,
    "dtheta": _deg(0.5),
    "dphi0": _deg(45.0),
    "a": 8e-4,
    "b": 1e-5,
    "c": 4e-5,
    "rho_s3": 300.0,
}

_SOLAR_ALIASES = (
    ("m1", "center.m"),
    ("rho_s1", "center.rho_s"),
    ("n1", "center.n"),
    ("m2", "offset.m"),
    ("rho_s2", "offset.rho_s"),
    ("n2", "offset.n"),
    ("dtheta", "offset.dtheta"),
    ("dphi0", "offset.dphi0"),
    ("a", "bars.a"),
    ("b", "bars.b"),
    ("c", "bars.c"),
    ("rho_s3", "bars.rho"),
)


def solar_cell(**overrides: float) -> Model:
    """The seed's three-term solar-cell model (Chapter VI) with the §6.4 parameters.

    Terms: ``center`` (Beckmann specular, Eq 111), ``offset`` (offset-normal
    Beckmann specular, Eq 112-113) and ``bars`` (diffraction, Eq 114-115).
    Parameters use the seed's names ``m1, rho_s1, n1, m2, rho_s2, n2, dtheta,
    dphi0, a, b, c, rho_s3`` (angles in radians); keyword overrides replace
    the seed values.  ``theta_i`` and ``phi_ref`` belong to the frame.
    """
    unknown = set(overrides) - set(SOLAR_CELL_SEED)
    if unknown:
        raise KeyError(
            f"solar_cell: unknown parameter(s) {sorted(unknown)}; known: {', '.join(SOLAR_CELL_SEED)}"
        )
    p = {**SOLAR_CELL_SEED, **overrides}
    return Model(
        terms={
            "center": Specular(Beckmann(p["m1"]), rho_s=p["rho_s1"], n=p["n1"]),
            "offset": OffsetNormal(
                Specular(Beckmann(p["m2"]), rho_s=p["rho_s2"], n=p["n2"]),
                dtheta=p["dtheta"],
                dphi0=p["dphi0"],
            ),
            "bars": Diffraction(rho=p["rho_s3"], a=p["a"], b=p["b"], c=p["c"]),
        },
        aliases=_SOLAR_ALIASES,
    )
