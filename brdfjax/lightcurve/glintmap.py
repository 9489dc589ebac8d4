"""Glint maps: the observer directions where a facet model outshines a baseline, with the solar disk.

For one facet and one Sun direction ``w_c`` (incidence ``theta_i``, in the
facet's plane of incidence, azimuth 0), :func:`glint_map` evaluates the model
on a fine grid of observer directions ``w_s = (u, v, sqrt(1 - u^2 - v^2))``
and averages it over the solar disk by a convolution of the grid with the
disk: every narrow feature of these models depends on the directions through
the half vector, and moving the Sun by ``(d1, d2)`` (along and across the
plane of incidence) turns the half vector as moving the observer by
``(d1 cos theta_i, d2)`` in ``(u, v)`` (exact at the mirror direction), so
the disk becomes an ellipse in ``(u, v)``; the slowly varying factors
(``cos theta_i``, Fresnel) change by the disk's 0.5 % at most.  The grid is a
strip around the mirror line ``u = -u_i`` (where the specular peaks and the
diffraction streak of a grating whose bars lie along x lie), wide enough for
the offset peak and the disk; the model is taken as no brighter than the
baseline outside it (checked on the strip's border, see ``edge_excess``).

A geometry glints when the disk-averaged model exceeds the baseline by more
than ``threshold_mag`` magnitudes.  The result carries the solid angle of the
glinting observer directions (sr), so that models can be compared by a number.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..core.geometry import Directions
from ..core.terms import AbstractTerm
from .engine import SUN_RADIUS_RAD

__all__ = ["GlintMap", "glint_map"]


@dataclass(frozen=True)
class GlintMap:
    theta_i: float
    u: np.ndarray  # (nu,) observer direction x components
    v: np.ndarray  # (nv,)
    model: np.ndarray  # (nv, nu) disk-averaged BRDF (sr^-1)
    baseline: np.ndarray  # (nv, nu)
    glint: np.ndarray  # (nv, nu) bool
    solid_angle_sr: float  # of the glinting directions
    edge_excess: float  # largest model/baseline ratio on the strip's border (should stay below the threshold)


def _disk_kernel(du: float, dv: float, ru: float, rv: float) -> np.ndarray:
    """The solar disk seen in the observer's (u, v): an ellipse of semi-axes ``ru``, ``rv``, normalised to sum 1."""
    nu, nv = int(np.ceil(ru / du)), int(np.ceil(rv / dv))
    # supersample each cell 4 x 4 so that the kernel's area is right to ~1 % per edge cell
    su = (np.arange(-nu, nu + 1)[:, None] + (np.arange(4) + 0.5)[None, :] / 4 - 0.5) * du
    sv = (np.arange(-nv, nv + 1)[:, None] + (np.arange(4) + 0.5)[None, :] / 4 - 0.5) * dv
    inside = (sv[:, None, :, None] / rv) ** 2 + (su[None, :, None, :] / ru) ** 2 <= 1.0
    k = inside.mean(axis=(2, 3))
    return k / k.sum()


def _convolve_same(img: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``img`` convolved with ``k`` (odd sizes), same shape, zero outside (NumPy FFT)."""
    sh = (img.shape[0] + k.shape[0] - 1, img.shape[1] + k.shape[1] - 1)
    out = np.fft.irfft2(np.fft.rfft2(img, sh) * np.fft.rfft2(k, sh), sh)
    a, b = k.shape[0] // 2, k.shape[1] // 2
    return out[a : a + img.shape[0], b : b + img.shape[1]]


def glint_map(
    model: AbstractTerm,
    baseline: AbstractTerm,
    theta_i: float,
    *,
    wavelength: float = 550e-9,
    threshold_mag: float = 1.0,
    half_width_u: float = 0.03,
    half_width_v: float = 0.35,
    du: float = 4e-5,
    dv: float = 8e-5,
    sun_radius: float = SUN_RADIUS_RAD,
) -> GlintMap:
    """Where ``model`` (disk-averaged) is brighter than ``baseline`` by more than ``threshold_mag`` (see module doc)."""
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    wi = np.array([np.sin(theta_i), 0.0, np.cos(theta_i)])  # Sun toward +x: the mirror direction has u = -sin(theta_i)
    u0 = -wi[0]
    u = u0 + np.arange(-half_width_u, half_width_u + du / 2, du)
    v = np.arange(-half_width_v, half_width_v + dv / 2, dv)

    @jax.jit
    def row(vv):
        uu = jnp.asarray(u, dtype)
        w = jnp.clip(1 - uu**2 - vv**2, 0, None)
        ws = jnp.stack([uu, jnp.broadcast_to(vv, uu.shape), jnp.sqrt(w)], -1)
        d = Directions.from_vectors(jnp.broadcast_to(jnp.asarray(wi, dtype), ws.shape), ws)
        return model(d, wavelength), baseline(d, wavelength)

    fm, fb = (np.asarray(x, np.float64) for x in jax.lax.map(row, jnp.asarray(v, dtype), batch_size=64))
    # moving the Sun by (d1 along the plane of incidence, d2 across) moves the half vector as moving the
    # observer by (d1 cos(theta_i), d2) in (u, v) (exact at the mirror direction): an ellipse
    k = _disk_kernel(du, dv, sun_radius * np.cos(theta_i), sun_radius)
    fm_disk = _convolve_same(fm, k)
    fb_disk = _convolve_same(fb, k)
    ratio = 10 ** (0.4 * threshold_mag)
    above = (1 - u[None, :] ** 2 - v[:, None] ** 2) > 0  # observer directions above the facet's horizon
    glint = above & (fb_disk > 0) & (fm_disk > ratio * np.maximum(fb_disk, 1e-300))
    # keep the border clear of the zero padding's edge effect: judge the interior only
    a, b = k.shape[0] // 2 + 1, k.shape[1] // 2 + 1
    interior = np.zeros_like(glint)
    interior[a:-a, b:-b] = True
    glint &= interior
    W = np.sqrt(np.clip(1 - u[None, :] ** 2 - v[:, None] ** 2, 1e-12, None))
    omega = float(np.sum(glint / W) * du * dv)
    border = np.zeros_like(interior)
    border[a, b:-b] = border[-a - 1, b:-b] = border[a:-a, b] = border[a:-a, -b - 1] = True
    border &= above & (fb_disk > 0)
    edge = float(np.max(fm_disk[border] / fb_disk[border])) if border.any() else 0.0
    return GlintMap(float(theta_i), u, v, fm_disk, fb_disk, glint, omega, edge)
