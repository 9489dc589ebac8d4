"""Where a BRDF term varies over the solar disk: the sharp features that the adaptive disk integrates in full.

Over the Sun's 0.53 deg disk the half vector moves by ``delta_h = r / (2 cos theta_d)``
(``r`` the Sun's angular radius, ``theta_d`` half the angle between the
directions to the Sun and to the observer).  A term whose value changes little
over such a patch is integrated well by the disk's centre (the cheap rule);
near a narrow lobe or a diffraction streak it is not.  :func:`term_features`
lists, for one term, the features that can make the cheap rule wrong:

- ``axis``: a lobe about a direction ``a`` of the half vector (a microfacet
  distribution about the normal, a Phong or ABg lobe about the mirror
  direction, the offset peak about its tilted normal), with a radius ``rho``:
  beyond ``rho`` from ``a`` the cheap rule's error is below ``tol`` of the
  lobe's peak (see :func:`lobe_radius`).  A pair is flagged when the angle of
  the centre half vector from ``a`` is below ``delta_h + rho``.
- ``band``: a diffraction streak ``|h . u| small`` (the bars' Gaussian
  ``exp(-(d h_x / c)^2)`` across it, fringes finer than the disk along it);
  flagged when ``|h . u| < sin(delta_h + rho)``, ``rho = (c / d) sqrt(ln(1/tol))``.
- ``everywhere``: a term kind this module does not know (always flagged: the
  full rule, correct but not cheaper).

Features of wrapped terms (:class:`~brdfjax.core.terms.OffsetNormal`,
:class:`~brdfjax.core.terms.Oriented`) are turned back into the facet frame.
Radii are computed from the term's parameters with JAX (they follow
posterior draws and fits) but carry no gradient: flags only choose the rule.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..core.geometry import Rz
from ..core.terms import (
    ABg,
    AbstractTerm,
    Diffraction,
    Lambertian,
    MultiLobeSpecular,
    OffsetNormal,
    Oriented,
    Phong as CorePhong,
    Specular,
)
from .models import Phong as LCPhong  # the light-curve Phong baseline (kd, ks, exponent)

__all__ = ["Feature", "term_features", "lobe_radius", "DEFAULT_TOL"]

#: Tolerated error of the cheap rule, relative to the larger of a term's local value and its mean level.
DEFAULT_TOL = 1e-3

_THETA = np.geomspace(1e-7, 1.5, 192)  # probe angles from the lobe's axis (rad)
_DX = float(np.log(_THETA[1] / _THETA[0]))


@dataclass(frozen=True)
class Feature:
    """A sharp feature in the facet frame: ``kind`` 'axis' | 'band' | 'everywhere', a unit vector, a radius (rad).

    A radius < 0 means the feature is smooth at these parameters (never flagged).
    """

    kind: str
    vector: Array  # (3,)
    radius: Array  # ()

    def rotated_back(self, matrix: Array) -> "Feature":
        """The feature of a term evaluated on directions rotated by ``matrix`` (``v' = M v``), in the outer frame."""
        return Feature(self.kind, jnp.asarray(matrix).T @ self.vector, self.radius)


def lobe_radius(log_profile: Callable[[Array], Array], deltas: Array, tol: float = DEFAULT_TOL, dim: int = 2) -> Array:
    """Angles from a lobe's axis beyond which the disk's centre integrates it well, one per disk radius (-1: never).

    ``log_profile(theta)`` is ``ln g`` along a ray from the axis; ``deltas``
    (n,) are disk radii in half-vector angle.  With ``x = ln theta``, the
    disk average of a smooth ``g`` differs from its centre value by
    ``eps = delta^2 / (8 theta^2) |L_xx + L_x^2|`` relative (the Laplacian
    term), and by up to ``g`` itself where that expansion fails (``eps > 1``).
    The error is measured against the larger of the local value and the
    lobe's mean level, estimated as ``g(0) w^dim`` with ``w`` the half-maximum
    angle (the level of a Lambertian of the lobe's albedo, for ``dim = 2``;
    ``dim = 1`` for a band).  The radius is the largest probe angle where
    ``min(eps, 1) q / max(q, 1) > tol``, ``q = g / level``, times one probe step.
    """
    th = jnp.asarray(_THETA)
    L = log_profile(th)
    fin = jnp.isfinite(L)
    L0 = jnp.maximum(log_profile(jnp.zeros(1))[0], jnp.max(jnp.where(fin, L, -jnp.inf)))
    p = jnp.where(fin, jnp.exp(L - L0), 0.0)
    half = jnp.min(jnp.where(p < 0.5, th, _THETA[-1]))
    q = p / jnp.minimum(half, 1.0) ** dim
    Lf = jnp.where(fin, L, -1e300)
    Lx = jnp.gradient(Lf, _DX)
    Lxx = jnp.gradient(Lx, _DX)
    curv = jnp.abs(Lxx + Lx**2) / (8 * th**2)
    eps = jnp.asarray(deltas)[:, None] ** 2 * curv
    eps = jnp.where(jnp.isfinite(eps) & fin, eps, 1.0)
    err = jnp.minimum(eps, 1.0) * q / jnp.maximum(q, 1.0)
    bad = err > tol
    r = jnp.max(jnp.where(bad, th, -1.0), -1)
    return jnp.where(r > 0, r * np.exp(_DX), -1.0)


def disk_deltas(radius: float) -> np.ndarray:
    """The disk radii in half-vector angle at which feature radii are tabulated: ``(r / 2) / cos(theta_d)``."""
    return 0.5 * radius * np.array([1.0, 1.25, 1.6, 2.0, 3.0, 5.0, 10.0])


def _stop(tree):
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if isinstance(x, jax.Array) else x, tree)


def _safe_log(x: Array) -> Array:
    return jnp.where(x > 0, jnp.log(jnp.where(x > 0, x, 1.0)), -jnp.inf)


def _distribution_radius(dist, deltas: Array, tol: float) -> Array:
    """Largest :func:`lobe_radius` of a microfacet distribution along its x and y slope axes."""

    def along(axis):
        def lp(th):
            t2 = jnp.square(jnp.tan(th))
            z = jnp.zeros_like(t2)
            return _safe_log(dist(t2, z) if axis == 0 else dist(z, t2))

        return lobe_radius(lp, deltas, tol)

    return jnp.maximum(along(0), along(1))


_Z = np.array([0.0, 0.0, 1.0])


def term_features(term: AbstractTerm, radius: float, tol: float = DEFAULT_TOL) -> list[Feature]:
    """The sharp features of one term (facet frame) for a Sun of angular ``radius`` (rad)."""
    term = _stop(term)
    return _features(term, jnp.asarray(disk_deltas(radius)), tol)


def _features(term: AbstractTerm, delta: Array, tol: float) -> list[Feature]:
    if isinstance(term, Lambertian):
        return []
    if isinstance(term, Specular):
        return [Feature("axis", jnp.asarray(_Z), _distribution_radius(term.distribution, delta, tol))]
    if isinstance(term, MultiLobeSpecular):
        # one radius per disk radius (the feature's table): the widest reach of any lobe at each
        r = jnp.max(jnp.stack([_distribution_radius(lobe.distribution, delta, tol) for lobe in term.lobes.values()]), axis=0)
        return [Feature("axis", jnp.asarray(_Z), r)]
    if isinstance(term, CorePhong | LCPhong):
        k = term.k if isinstance(term, CorePhong) else term.exponent
        # cos(alpha)^k about the mirror direction; alpha ~ 2 theta_h

        def lp(th):
            c = jnp.cos(jnp.minimum(2 * th, np.pi / 2))
            return k * _safe_log(c)

        return [Feature("axis", jnp.asarray(_Z), lobe_radius(lp, delta, tol))]
    if isinstance(term, ABg):

        def lp(th):
            return -jnp.log(term.B + jnp.exp(term.g * jnp.log(2 * jnp.sin(th) + 1e-300)))

        return [Feature("axis", jnp.asarray(_Z), lobe_radius(lp, delta, tol))]
    if isinstance(term, Diffraction):
        w = term.c / term.distance  # exp(-(h_x / w)^2) across the streak; fringes along it are finer than the disk

        def lp(th):
            return -jnp.square(th / w)

        return [Feature("band", jnp.asarray([1.0, 0.0, 0.0]), lobe_radius(lp, delta, tol, dim=1))]
    if isinstance(term, OffsetNormal):
        R = term.rotation()
        return [f.rotated_back(R) for f in _features(term.term, delta, tol)]
    if isinstance(term, Oriented):
        R = Rz(-term.psi)
        return [f.rotated_back(R) for f in _features(term.term, delta, tol)]
    if isinstance(getattr(term, "terms", None), dict):  # a nested Model
        return [f for t in term.terms.values() for f in _features(t, delta, tol)]
    return [Feature("everywhere", jnp.asarray(_Z), jnp.full(delta.shape, np.inf))]


def flag_features(features: list[Feature], h: Array, delta_h: Array, radius: float) -> Array:
    """Boolean (...) where centre half vectors ``h`` (..., 3), with disk radii ``delta_h`` (...), reach a feature.

    Each feature's radius is taken at the first tabulated disk radius
    (:func:`disk_deltas`) at or above ``delta_h``; beyond the table every
    feature that is sharp anywhere flags the pair.
    """
    table = jnp.asarray(disk_deltas(radius), h.dtype)
    idx = jnp.sum(delta_h[..., None] > table, -1)  # searchsorted (left) without a loop
    flag = jnp.zeros(h.shape[:-1], bool)
    for f in features:
        radii = jnp.asarray(f.radius, h.dtype)
        ext = jnp.concatenate([radii, jnp.where(jnp.max(radii) >= 0, np.inf, -1.0)[None]])
        rad = ext[idx]
        if f.kind == "everywhere":
            flag = flag | True
            continue
        v = jnp.asarray(f.vector, h.dtype)
        c = jnp.sum(h * v, -1)
        reach = jnp.minimum(delta_h + rad, np.pi / 2)
        if f.kind == "axis":
            hit = c > jnp.cos(reach)  # angle(h, v) < reach, both unit vectors
        else:  # band
            hit = jnp.abs(c) < jnp.sin(reach)
        flag = flag | ((rad >= 0) & hit)
    return flag
