"""Directions, rotations and numerically safe angle helpers (pure JAX).

Conventions (``physics.md``, seed §3.5): the scatter frame has +z along the
sample's macro-surface normal, +x in the plane of incidence toward forward
scatter and +y out of plane.  Incident and scattered directions both point away
from the surface.  Azimuths are measured from the **-x** direction, so a
direction with zenith ``theta`` and azimuth ``phi`` is
``(sin(theta) cos(phi - pi), sin(theta) sin(phi - pi), cos(theta))``.

Near a 2e-4 rad wide specular peak ``w_i + w_s`` is a difference of nearly
equal numbers in its x and y components.  :class:`Directions` therefore
carries the sum ``w_sum`` alongside the two unit vectors; producers that can
compute it without cancellation (the detector mapping) do so, and every term
takes the half vector from ``w_sum``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

__all__ = [
    "Directions",
    "Rx",
    "Ry",
    "Rz",
    "direction",
    "zenith_azimuth",
    "safe_sqrt",
    "safe_hypot",
    "rotate",
]


def safe_sqrt(x: ArrayLike) -> Array:
    """``sqrt(x)`` for ``x >= 0`` whose gradient is finite (zero) at ``x = 0``."""
    x = jnp.asarray(x)
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_hypot(x: ArrayLike, y: ArrayLike) -> Array:
    """``hypot(x, y)`` with a finite gradient at the origin."""
    return safe_sqrt(jnp.square(x) + jnp.square(y))


def Rx(a: ArrayLike) -> Array:
    """Right-handed rotation by ``a`` (rad) about +x, shape (..., 3, 3)."""
    a = jnp.asarray(a)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack(
        [jnp.stack([o, z, z], -1), jnp.stack([z, c, -s], -1), jnp.stack([z, s, c], -1)],
        -2,
    )


def Ry(a: ArrayLike) -> Array:
    """Right-handed rotation by ``a`` (rad) about +y, shape (..., 3, 3)."""
    a = jnp.asarray(a)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack(
        [jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1), jnp.stack([-s, z, c], -1)],
        -2,
    )


def Rz(a: ArrayLike) -> Array:
    """Right-handed rotation by ``a`` (rad) about +z, shape (..., 3, 3)."""
    a = jnp.asarray(a)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack(
        [jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)],
        -2,
    )


def rotate(matrix: Array, v: Array) -> Array:
    """Apply a (3, 3) rotation to vectors of shape (..., 3).

    Written as explicit multiply-adds rather than a matmul so that XLA fuses
    it with the surrounding elementwise work (a (N, 3) x (3, 3) dot is a
    separate, memory-bound kernel per call).
    """
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([matrix[i, 0] * x + matrix[i, 1] * y + matrix[i, 2] * z for i in range(3)], -1)


def direction(theta: ArrayLike, phi: ArrayLike) -> Array:
    """Unit vector of zenith ``theta`` and azimuth ``phi`` (from -x), (..., 3)."""
    theta, phi = jnp.asarray(theta), jnp.asarray(phi)
    st = jnp.sin(theta)
    return jnp.stack(
        [-st * jnp.cos(phi), -st * jnp.sin(phi), jnp.cos(theta) * jnp.ones_like(phi)], -1
    )


def zenith_azimuth(v: Array) -> tuple[Array, Array]:
    """Zenith and azimuth (from -x, in [0, 2 pi)) of vectors (..., 3).

    The zenith is ``atan2(hypot(x, y), z)``: ``acos`` of a dot product near 1
    loses every digit in float32 (``physics.md``).  The vectors need not be
    unit length.
    """
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    theta = jnp.arctan2(safe_hypot(x, y), z)
    at_pole = (x == 0) & (y == 0)
    # atan2(0, 0) has a NaN gradient; at the pole the azimuth is a convention (pi, as the seed prints).
    phi = jnp.arctan2(jnp.where(at_pole, 0.0, y), jnp.where(at_pole, 1.0, x)) + jnp.pi
    return theta, jnp.mod(phi, 2 * jnp.pi)


class Directions(eqx.Module):
    """Incident and scattered unit vectors, and their sum, shape (..., 3).

    ``w_sum = w_i + w_s`` is carried separately because near the specular
    direction its x and y components are differences of nearly equal numbers;
    :meth:`brdfjax.Detector.directions` computes it without that cancellation.
    For directions given any other way use :meth:`from_vectors` or
    :meth:`from_angles`.
    """

    w_i: Array
    w_s: Array
    w_sum: Array

    @classmethod
    def from_vectors(cls, w_i: ArrayLike, w_s: ArrayLike) -> "Directions":
        """From unit vectors (broadcast against each other)."""
        w_i, w_s = jnp.broadcast_arrays(jnp.asarray(w_i), jnp.asarray(w_s))
        return cls(w_i, w_s, w_i + w_s)

    @classmethod
    def from_angles(
        cls, theta_i: ArrayLike, phi_i: ArrayLike, theta_s: ArrayLike, phi_s: ArrayLike
    ) -> "Directions":
        """From zenith/azimuth angles in radians (azimuth from -x)."""
        return cls.from_vectors(direction(theta_i, phi_i), direction(theta_s, phi_s))

    def rotated(self, matrix: Array) -> "Directions":
        """All three vectors expressed in a frame rotated by ``matrix``."""
        return Directions(rotate(matrix, self.w_i), rotate(matrix, self.w_s), rotate(matrix, self.w_sum))

    @property
    def cos_theta_i(self) -> Array:
        return self.w_i[..., 2]

    @property
    def cos_theta_s(self) -> Array:
        return self.w_s[..., 2]

    def half_vector(self) -> Array:
        """Unit half vector ``w_h`` (Eq 52), (..., 3)."""
        sx, sy, sz = self.w_sum[..., 0], self.w_sum[..., 1], self.w_sum[..., 2]
        norm = safe_sqrt(sx * sx + sy * sy + sz * sz)
        return self.w_sum / jnp.where(norm > 0, norm, 1.0)[..., None]

    def half_slopes(self) -> tuple[Array, Array, Array]:
        """``(tan^2 theta_h cos^2 phi_h, tan^2 theta_h sin^2 phi_h, upper)``.

        The squared microfacet slopes along x and y, ``h_x^2 / h_z^2`` and
        ``h_y^2 / h_z^2``, computed from ``w_sum`` without normalising or
        taking an arccos (``physics.md``, numerical pitfalls).  ``upper`` is
        True where the half vector lies in the upper hemisphere; elsewhere the
        slopes are set to 0 and callers must zero the distribution.
        """
        sx, sy, sz = self.w_sum[..., 0], self.w_sum[..., 1], self.w_sum[..., 2]
        upper = sz > 0
        sz_safe = jnp.where(upper, sz, 1.0)
        tx2 = jnp.where(upper, jnp.square(sx / sz_safe), 0.0)
        ty2 = jnp.where(upper, jnp.square(sy / sz_safe), 0.0)
        return tx2, ty2, upper
