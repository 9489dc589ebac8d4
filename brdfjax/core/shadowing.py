"""Shadowing-masking of the microfacet specular term (beyond the seed; ``physics.md``).

Smith's uncorrelated-direction model (Smith 1967; Walter et al. 2007; Heitz
2014, "Understanding the masking-shadowing function in microfacet-based
BRDFs", JCGT 3(2)) gives the fraction of microfacets with normal ``w_h`` that
are visible from a direction ``w`` as

    G1(w) = chi+(w . w_h) / (1 + Lambda(w))

and the height-correlated masking-shadowing of the pair (w_i, w_s) as

    G2(w_i, w_s) = chi+(w_i . w_h) chi+(w_s . w_h) / (1 + Lambda(w_i) + Lambda(w_s)).

``Lambda`` depends on the distribution D and on the direction's zenith theta
(and, for an anisotropic D, its azimuth).  With ``t = alpha tan(theta)``,
``alpha`` the distribution's width along the direction's azimuth
(``alpha^2 = alpha_x^2 cos^2 phi + alpha_y^2 sin^2 phi``, i.e.
``t^2 = alpha_x^2 w_x^2 / w_z^2 + alpha_y^2 w_y^2 / w_z^2``) and ``a = 1 / t``:

* Beckmann (Heitz 2014 Eq 80): ``Lambda = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi))``
* GGX (Heitz 2014 Eq 86): ``Lambda = (sqrt(1 + t^2) - 1) / 2``

Every other distribution of :mod:`brdfjax.core.distributions` gets a **tabulated**
Lambda from Heitz 2014 Eq 72 written in slope space.  With the slope
distribution ``P22(x, y) = D cos^4(theta_h)`` (unit integral over the slope
plane: Eq 54), ``mu = cot(theta)`` and the slopes rotated so that x points along
the direction's azimuth,

    Lambda(mu) = I(mu) / mu,   I(mu) = integral integral_{x > mu} (x - mu) P22 dx dy.

How it is computed (:func:`lambda_table`):

* ``I`` is evaluated at ``N_NU = 401`` values of ``nu = mu / c`` spaced
  logarithmically from 1e-3 to 1e3, ``c = 1 / sqrt(pi D(0))`` being the
  distribution's slope scale (``c = m`` for Beckmann).  For an isotropic D the
  inner integral is done in closed form in polar slope coordinates
  (``r > mu``: ``I = integral 2 r P22(r) (sqrt(r^2 - mu^2) - mu acos(mu / r)) dr``);
  the radial integral is a trapezoid rule in ``t = ln((r - mu) / c)`` on
  ``[-30, 17]`` with step 0.08 (the integrand decays exponentially in t at
  both ends, so the rule converges geometrically; the truncation at
  ``r - mu = 2.4e7 c`` matters only for tails slower than ``r^-5`` in P22,
  e.g. Hyper-Cauchy with ``gamma < 2``).  An anisotropic D that is not a
  stretch of an isotropic one (Ashikhmin-Shirley) adds a 24-point
  Gauss-Legendre rule over the angle in the slope plane and a table over the
  direction's azimuth (``N_PHI = 9`` values on ``[0, pi/2]``, linear in
  between; D depends on ``cos^2``, ``sin^2`` only), on a coarser grid
  (97 values of nu, radial step 0.16).  Stretch-invariant anisotropic forms
  (anisotropic Student-t) use their isotropic table with the projected
  width, exactly like Beckmann and GGX.
* Between the nodes ``ln I`` is a cubic Hermite interpolant in ``ln nu`` whose
  slopes are the exact derivatives ``dI/dmu = -integral_{x > mu} P22`` (the
  same quadrature); beyond the ends ``ln I`` continues linearly in ``ln nu``
  (``I -> I(0) = E[x+]`` below, a power law above).
* Accuracy, measured against the closed forms (``tests/core/test_shadowing.py``):
  the tabulated Lambda of Beckmann and GGX agrees with the exact one to a
  relative 2e-6 (or an absolute 1e-9) from normal incidence to 89.9 deg for
  widths 2e-4 to 1.

The table is rebuilt at every call from the current parameters (about 2.4e5
evaluations of D for an isotropic distribution, 6e6 for Ashikhmin-Shirley),
so it is differentiable in the distribution's parameters and costs the same
for a 10-point table and a full frame.

V-cavity (Cook and Torrance 1982): ``G = min(1, 2 (n.h)(n.w_s)/(w_s.h), 2 (n.h)(n.w_i)/(w_s.h))``,
which needs no Lambda.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erfc
from jaxtyping import Array, ArrayLike

from .distributions import (
    GGX,
    AbstractDistribution,
    Beckmann,
    BeckmannAniso,
    GGXAniso,
    StudentT,
    StudentTAniso,
)
from .geometry import Directions, safe_sqrt

__all__ = [
    "SHADOWING",
    "lambda_beckmann",
    "lambda_ggx",
    "smith_lambda",
    "lambda_table",
    "smith_g1",
    "smith_g2",
    "smith_g2_parts",
    "smith_lambda_pair",
    "smith_mixture_g2_parts",
    "v_cavity",
    "shadowing_factor",
    "shadowing_parts",
]

#: Shadowing-masking forms a specular term accepts.  ``smith_mixture``: Smith G2 of the whole surface when
#: it has several lobes (:func:`smith_mixture_g2_parts`); for one distribution it is ``smith``.
SHADOWING = ("none", "smith", "v_cavity", "smith_mixture")

_SQRT_PI = math.sqrt(math.pi)

# --- closed forms -------------------------------------------------------------------------------


def _comps(w) -> tuple[Array, Array, Array]:
    """Components of directions given as an array (..., 3) or as a 3-tuple of arrays."""
    if isinstance(w, tuple | list):
        return tuple(jnp.asarray(c) for c in w)
    w = jnp.asarray(w)
    return w[..., 0], w[..., 1], w[..., 2]


def _slope2(w: Array, ax: ArrayLike, ay: ArrayLike) -> tuple[Array, Array]:
    """``t^2 = alpha(phi)^2 tan^2(theta)`` of directions ``w`` (..., 3, or components), and ``w_z > 0``."""
    wx, wy, wz = _comps(w)
    up = wz > 0
    wz_safe = jnp.where(up, wz, 1.0)
    t2 = (jnp.square(ax * wx) + jnp.square(ay * wy)) / jnp.square(wz_safe)
    return t2, up


def lambda_ggx(t2: ArrayLike) -> Array:
    """GGX Smith Lambda as a function of ``t^2 = alpha^2 tan^2(theta)`` (Heitz 2014 Eq 86).

    Written as ``t^2 / (2 (1 + sqrt(1 + t^2)))`` (no cancellation at small t).
    """
    t2 = jnp.asarray(t2)
    return t2 / (2.0 * (1.0 + jnp.sqrt(1.0 + t2)))


def lambda_beckmann(t2: ArrayLike) -> Array:
    """Beckmann Smith Lambda as a function of ``t^2 = m^2 tan^2(theta)`` (Heitz 2014 Eq 80).

    ``a = 1/t``: ``(exp(-a^2) / (a sqrt(pi)) - erfc(a)) / 2``; 0 at ``t = 0`` (and for
    ``a > 26``, where both terms underflow), with a finite gradient everywhere.
    """
    t2 = jnp.asarray(t2)
    ok = (t2 > 0) & (t2 > 1.0 / 26.0**2)
    a = 1.0 / safe_sqrt(jnp.where(ok, t2, 1.0))
    lam = 0.5 * (jnp.exp(-jnp.square(a)) / (a * _SQRT_PI) - erfc(a))
    return jnp.where(ok, jnp.maximum(lam, 0.0), 0.0)


# --- tabulated Lambda ----------------------------------------------------------------------------

#: Table nodes in ln(nu), nu = mu / c: fine for isotropic D (N_NU), coarser for the 2-D anisotropic table.
N_NU = 481
N_NU_ANISO = 113
_NU_RANGE = (math.log(1e-3), math.log(1e4))
_LOG_NU = np.linspace(*_NU_RANGE, N_NU)
_LOG_NU_ANISO = np.linspace(*_NU_RANGE, N_NU_ANISO)
_T_STEP = 0.08
_T = np.arange(-30.0, 17.0 + 1e-9, _T_STEP)  # ln((r - mu)/c) nodes of the radial trapezoid rule
_T_W = np.full(_T.shape, _T_STEP)
_T_W[[0, -1]] *= 0.5
#: The anisotropic table's radial rule (coarser) and azimuths.
_T_ANISO = _T[::2]
_T_W_ANISO = np.full(_T_ANISO.shape, 2 * _T_STEP)
_T_W_ANISO[[0, -1]] *= 0.5
N_PHI = 9
_PHI = np.linspace(0.0, math.pi / 2, N_PHI)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(24)


def _slope_scale(dist: AbstractDistribution) -> Array:
    """``1 / sqrt(pi D(0))``: the slope width of the distribution (m for Beckmann)."""
    d0 = dist(jnp.zeros(()), jnp.zeros(()))
    return jax.lax.stop_gradient(1.0 / jnp.sqrt(jnp.pi * d0))


def _p22(dist: AbstractDistribution, x: Array, y: Array) -> Array:
    x2, y2 = jnp.square(x), jnp.square(y)
    return dist(x2, y2) / jnp.square(1.0 + x2 + y2)


class LambdaTable:
    """``ln I`` and ``d ln I / d ln nu`` at the nodes ``_LOG_NU`` (and azimuths ``_PHI``), slope scale ``c``."""

    def __init__(self, log_i: Array, slope: Array, c: Array, isotropic: bool):
        self.log_i, self.slope, self.c, self.isotropic = log_i, slope, c, isotropic


def _tail(f: Array, step: float) -> Array:
    """``integral_T^inf f dt`` beyond the last node, for an integrand that decays like ``exp(-p t)`` there.

    ``p`` from the last two nodes (a power-law tail of P22 in r is exponential
    in t = ln r); zero where the integrand has already vanished.
    """
    a, b = f[..., -2], f[..., -1]
    ok = (a > 0) & (b > 0)
    p = jnp.where(ok, (jnp.log(jnp.where(ok, a, 1.0)) - jnp.log(jnp.where(ok, b, 1.0))) / step, 1.0)
    return jnp.where(ok & (p > 0.05), b / jnp.maximum(p, 0.05), 0.0)


def lambda_table(dist: AbstractDistribution) -> LambdaTable:
    """Tabulate ``I(mu) = mu Lambda(mu)`` of any distribution (module docstring).

    Compiled once per distribution class (``equinox.filter_jit``): the table is
    a few hundred thousand element-wise operations that would otherwise be
    dispatched one by one outside a jitted caller.
    """
    log_i, slope, c = _table_arrays(dist)
    return LambdaTable(log_i, slope, c, len(dist.width_fields) == 1)


@eqx.filter_jit
def _table_arrays(dist: AbstractDistribution) -> tuple[Array, Array, Array]:
    c = _slope_scale(dist)
    isotropic = len(dist.width_fields) == 1
    log_nu, t, tw = (_LOG_NU, _T, _T_W) if isotropic else (_LOG_NU_ANISO, _T_ANISO, _T_W_ANISO)
    mu = c * jnp.exp(jnp.asarray(log_nu))  # (N,)
    dx = c * jnp.exp(jnp.asarray(t))  # r - mu
    w = jnp.asarray(tw) * dx  # dr = (r - mu) dt
    r = mu[:, None] + dx[None, :]  # (N, N_T)
    if isotropic:
        p = _p22(dist, r, jnp.zeros_like(r))
        cos_b = mu[:, None] / r
        beta = jnp.arccos(jnp.clip(cos_b, -1.0, 1.0))
        chord = r * safe_sqrt(1.0 - jnp.square(cos_b))  # sqrt(r^2 - mu^2)
        integ_i = 2.0 * r * p * (chord - mu[:, None] * beta)
        integ_s = 2.0 * r * p * beta
        i_val = (jnp.sum(integ_i * w, -1) + _tail(integ_i * dx, _T_STEP))[:, None]  # (N_NU, 1)
        s_val = (jnp.sum(integ_s * w, -1) + _tail(integ_s * dx, _T_STEP))[:, None]
    else:
        # angle psi from the direction's azimuth, |psi| < acos(mu / r): Gauss-Legendre on that interval
        beta = jnp.arccos(jnp.clip(mu[:, None] / r, -1.0, 1.0))  # (N_NU, N_T)
        psi = beta[..., None] * jnp.asarray(_GL_X)  # (N_NU, N_T, N_GL)
        gw = beta[..., None] * jnp.asarray(_GL_W)
        ang = jnp.asarray(_PHI)[:, None, None, None] + psi[None]  # (N_PHI, N_NU, N_T, N_GL)
        rr = r[None, :, :, None]
        p = _p22(dist, rr * jnp.cos(ang), rr * jnp.sin(ang))
        lever = rr * jnp.cos(psi)[None] - mu[None, :, None, None]
        f_i = jnp.sum(p * jnp.maximum(lever, 0.0) * gw[None], -1) * r[None]  # per unit r, (N_PHI, N, N_T)
        # dI/dmu = -integral_{x > mu} P22: the same rule without the lever arm
        f_s = jnp.sum(p * gw[None], -1) * r[None]
        i_val = (jnp.sum(f_i * w, -1) + _tail(f_i * dx, 2 * _T_STEP)).T  # (N, N_PHI)
        s_val = (jnp.sum(f_s * w, -1) + _tail(f_s * dx, 2 * _T_STEP)).T
    tiny = 1e-300 if mu.dtype == jnp.float64 else 1e-37
    ok = i_val > tiny
    log_i = jnp.where(ok, jnp.log(jnp.where(ok, i_val, 1.0)), math.log(tiny))
    # d ln I / d ln nu = mu I'(mu) / I = -mu S / I; where I underflowed, a steep fall
    slope = jnp.where(ok, -mu[:, None] * s_val / jnp.where(ok, i_val, 1.0), -50.0)
    return log_i, slope, c


def _hermite(x: Array, xs: np.ndarray, ys: Array, ds: Array) -> Array:
    """Cubic Hermite interpolation on the uniform grid ``xs`` (values ys, slopes ds), linear beyond the ends."""
    h = float(xs[1] - xs[0])
    n = xs.size
    xc = jnp.clip(x, xs[0], xs[-1])
    k = jnp.clip(jnp.floor((xc - xs[0]) / h).astype(jnp.int32), 0, n - 2)
    s = (xc - (xs[0] + k * h)) / h
    y0, y1, d0, d1 = ys[k], ys[k + 1], ds[k] * h, ds[k + 1] * h
    s2, s3 = s * s, s * s * s
    val = (2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * d0 + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * d1
    # beyond the ends: ln I continues linearly in ln nu (a power law; I -> I(0) below, since the slope -> 0 there)
    return val + jnp.where(x > xs[-1], (x - xs[-1]) * ds[-1], 0.0) + jnp.where(x < xs[0], (x - xs[0]) * ds[0], 0.0)


def _interp_table(table: LambdaTable, mu: Array, phi_index: Array | None) -> Array:
    """``I(mu)`` from a table (``phi_index``: fractional index into ``_PHI`` for anisotropic tables)."""
    log_nu = jnp.log(jnp.maximum(mu / table.c, 1e-300))
    if table.isotropic:
        return jnp.exp(_hermite(log_nu, _LOG_NU, table.log_i[:, 0], table.slope[:, 0]))
    xs = _LOG_NU_ANISO
    j = jnp.clip(jnp.floor(phi_index).astype(jnp.int32), 0, N_PHI - 2)
    f = phi_index - j
    vals = [jnp.exp(_hermite(log_nu, xs, table.log_i[:, q], table.slope[:, q])) for q in range(N_PHI)]
    stack = jnp.stack(vals, -1)
    i0 = jnp.take_along_axis(stack, j[..., None], -1)[..., 0]
    i1 = jnp.take_along_axis(stack, (j + 1)[..., None], -1)[..., 0]
    return (1.0 - f) * i0 + f * i1


def _lambda_tabulated(table: LambdaTable, w: Array, stretch: tuple[ArrayLike, ArrayLike] | None = None) -> Array:
    """Lambda of directions ``w`` (..., 3) from a table; ``stretch``: widths for a stretched isotropic table."""
    wx, wy, wz = _comps(w)
    if stretch is not None:
        wx, wy = wx * stretch[0], wy * stretch[1]
    rho2 = jnp.square(wx) + jnp.square(wy)
    side = rho2 > 0
    rho = safe_sqrt(rho2)
    up = wz > 0
    rho_safe = jnp.where(side, rho, 1.0)
    mu = jnp.where(up, wz, 0.0) / rho_safe  # cot(theta) in the (stretched) slope frame
    if table.isotropic:
        phi_index = None
    else:
        phi = jnp.arctan2(jnp.abs(jnp.where(side, wy, 0.0)), jnp.abs(jnp.where(side, wx, 1.0)))  # [0, pi/2]
        phi_index = phi / (math.pi / 2) * (N_PHI - 1)
    i_val = _interp_table(table, mu, phi_index)
    # Lambda = I / mu = I rho / w_z; 0 at normal incidence, inf at the horizon
    wz_safe = jnp.where(up, wz, 1.0)
    lam = jnp.where(side, i_val * rho / wz_safe, 0.0)
    return jnp.where(up, lam, jnp.inf)


# --- dispatch ---------------------------------------------------------------------------------


def smith_lambda(dist: AbstractDistribution, w: ArrayLike, method: str = "auto") -> Array:
    """Smith's Lambda of ``dist`` for directions ``w`` (..., 3, in the distribution's frame).

    ``method='auto'`` uses the closed forms of Beckmann and GGX (and of their
    anisotropic forms, via the projected width) and the table for the rest;
    ``'table'`` forces the table (to test it against the closed forms).
    Directions at or below the horizon get ``inf`` (G = 0).
    """
    if method not in ("auto", "table"):
        raise ValueError(f"smith_lambda: unknown method '{method}'; known: auto, table")
    if method == "auto":
        closed = {
            Beckmann: (lambda_beckmann, lambda d: (d.m, d.m)),
            BeckmannAniso: (lambda_beckmann, lambda d: (d.mx, d.my)),
            GGX: (lambda_ggx, lambda d: (d.alpha, d.alpha)),
            GGXAniso: (lambda_ggx, lambda d: (d.alpha_x, d.alpha_y)),
        }
        if type(dist) in closed:
            fn, widths = closed[type(dist)]
            t2, up = _slope2(w, *widths(dist))
            return jnp.where(up, fn(t2), jnp.inf)
        if isinstance(dist, StudentTAniso):
            # a linear stretch of the isotropic Student-t of unit width
            table = lambda_table(StudentT(jnp.ones_like(dist.gamma), dist.gamma))
            return _lambda_tabulated(table, w, (dist.sigma_x, dist.sigma_y))
    return _lambda_tabulated(lambda_table(dist), w)


def _positive_side(w: Array, w_sum: Array) -> Array:
    """``chi+(w . w_h)`` (the sign of ``w . w_sum``)."""
    (x, y, z), (sx, sy, sz) = _comps(w), _comps(w_sum)
    return x * sx + y * sy + z * sz > 0


def smith_g1(dist: AbstractDistribution, w: ArrayLike, w_h: ArrayLike, method: str = "auto") -> Array:
    """Smith masking ``G1(w, w_h) = chi+(w . w_h) / (1 + Lambda(w))``."""
    w, w_h = jnp.asarray(w), jnp.asarray(w_h)
    lam = smith_lambda(dist, w, method)
    return jnp.where(_positive_side(w, w_h) & jnp.isfinite(lam), 1.0 / (1.0 + jnp.where(jnp.isfinite(lam), lam, 0.0)), 0.0)


def smith_g2(dist: AbstractDistribution, dirs: Directions, method: str = "auto") -> Array:
    """Height-correlated Smith masking-shadowing ``G2 = 1 / (1 + Lambda(w_i) + Lambda(w_s))`` (Heitz 2014 Eq 99).

    Evaluated in the directions' frame (the sample frame, or the frame of a
    wrapper that rotated them); the tabulated Lambda is built once for both.
    """
    num, den = smith_g2_parts(dist, dirs, method)
    return num / den


def smith_lambda_pair(dist: AbstractDistribution, dirs: Directions, method: str = "auto") -> tuple[Array, Array]:
    """``(Lambda(w_i), Lambda(w_s))`` of ``dist`` (a tabulated Lambda is built once for both)."""
    if method == "auto" and type(dist) not in (Beckmann, BeckmannAniso, GGX, GGXAniso, StudentTAniso):
        table = lambda_table(dist)
        return _lambda_tabulated(table, dirs.i), _lambda_tabulated(table, dirs.s)
    return smith_lambda(dist, dirs.i, method), smith_lambda(dist, dirs.s, method)


def _g2_from_lambdas(lam_i: Array, lam_s: Array, dirs: Directions) -> tuple[Array, Array]:
    ok = jnp.isfinite(lam_i) & jnp.isfinite(lam_s) & _positive_side(dirs.i, dirs.t) & _positive_side(dirs.s, dirs.t)
    total = jnp.where(ok, lam_i + lam_s, 0.0)
    return jnp.where(ok, 1.0, 0.0), 1.0 + total


def smith_g2_parts(dist: AbstractDistribution, dirs: Directions, method: str = "auto") -> tuple[Array, Array]:
    """:func:`smith_g2` as ``(numerator, denominator)``: a caller can fold the division into its own."""
    return _g2_from_lambdas(*smith_lambda_pair(dist, dirs, method), dirs)


def smith_mixture_g2_parts(dists, weights, dirs: Directions, method: str = "auto") -> tuple[Array, Array]:
    """Height-correlated Smith G2 of a surface whose slope distribution is a mixture of ``dists``.

    A multi-lobe surface is one surface: its slope distribution is the
    normalised mixture ``P22 = sum_l w_l P22_l`` with ``w_l = weights_l /
    sum(weights)`` (each lobe's D is normalised, Eq 54), and Lambda is linear
    in P22 (Heitz 2014 Eq 72), so ``Lambda = sum_l w_l Lambda_l`` exactly;
    ``G2 = 1 / (1 + Lambda(w_i) + Lambda(w_s))`` then masks every lobe's
    microfacets alike (the narrow lobe's facets are masked by the wide
    lobe's slopes).  For one distribution this is :func:`smith_g2_parts`.
    Weights are the lobes' ``rho_s`` (they share the Fresnel factor); where
    they sum to 0 the lobes count equally.
    """
    w = [jnp.asarray(x) for x in weights]
    total = sum(w[1:], w[0])
    pos = total > 0
    inv = jnp.where(pos, 1.0 / jnp.where(pos, total, 1.0), 0.0)
    lam_i = lam_s = 0.0
    for d, wl in zip(dists, w):
        li, ls = smith_lambda_pair(d, dirs, method)
        frac = jnp.where(pos, wl * inv, 1.0 / len(w))
        # inf (below the horizon) stays inf: only finite values are weighted
        lam_i = lam_i + jnp.where(jnp.isfinite(li), frac * jnp.where(jnp.isfinite(li), li, 0.0), jnp.inf)
        lam_s = lam_s + jnp.where(jnp.isfinite(ls), frac * jnp.where(jnp.isfinite(ls), ls, 0.0), jnp.inf)
    return _g2_from_lambdas(lam_i, lam_s, dirs)


def v_cavity(dirs: Directions) -> Array:
    """Cook-Torrance V-cavity masking-shadowing ``min(1, 2 h_z c_s / (w_s.h), 2 h_z c_i / (w_s.h))``."""
    (sx, sy, sz), (wx, wy, wz) = dirs.t, dirs.s
    norm = safe_sqrt(sx * sx + sy * sy + sz * sz)
    norm_safe = jnp.where(norm > 0, norm, 1.0)
    hz = sz / norm_safe
    wh = (wx * sx + wy * sy + wz * sz) / norm_safe  # = w_i . h
    wh_safe = jnp.where(wh > 0, wh, 1.0)
    g = jnp.minimum(1.0, 2.0 * hz * jnp.minimum(dirs.cos_theta_i, dirs.cos_theta_s) / wh_safe)
    return jnp.where((wh > 0) & (norm > 0), jnp.maximum(g, 0.0), 0.0)


def shadowing_factor(kind: str, dist: AbstractDistribution, dirs: Directions) -> Array | float:
    """The masking-shadowing factor of a specular term: 1, Smith G2 or the V-cavity G."""
    num, den = shadowing_parts(kind, dist, dirs)
    return num if isinstance(den, float) else num / den


def shadowing_parts(kind: str, dist: AbstractDistribution, dirs: Directions) -> tuple[Array | float, Array | float]:
    """:func:`shadowing_factor` as ``(numerator, denominator)`` (the denominator a float 1.0 when there is none)."""
    if kind == "none":
        return 1.0, 1.0
    if kind in ("smith", "smith_mixture"):  # a single distribution is its own mixture
        return smith_g2_parts(dist, dirs)
    if kind == "v_cavity":
        return v_cavity(dirs), 1.0
    raise ValueError(f"unknown shadowing '{kind}'; known: {', '.join(SHADOWING)}")
