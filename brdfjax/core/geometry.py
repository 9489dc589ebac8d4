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
    "rotate_xyz",
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


def rotate_xyz(matrix: Array, x: ArrayLike, y: ArrayLike, z: ArrayLike) -> tuple[Array, Array, Array]:
    """Apply a (3, 3) rotation to vectors given by their components; returns the three components."""
    return tuple(matrix[i, 0] * x + matrix[i, 1] * y + matrix[i, 2] * z for i in range(3))


def _xyz(v) -> tuple[Array, Array, Array]:
    """Components of a vector given as an array (..., 3) or as a 3-tuple of arrays."""
    if isinstance(v, tuple | list):
        if len(v) != 3:
            raise ValueError(f"Directions: a vector given by components needs 3 of them, got {len(v)}")
        return tuple(jnp.asarray(c) for c in v)
    v = jnp.asarray(v)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise ValueError(f"Directions: vectors must have a last axis of length 3, got shape {v.shape}")
    return v[..., 0], v[..., 1], v[..., 2]


class Directions(eqx.Module):
    """Incident and scattered unit vectors, and their sum.

    Stored component by component (``i = (x, y, z)`` of ``w_i``, ``s`` of
    ``w_s``, ``t`` of ``w_sum``): every term works on the components, so a
    compiled frame evaluation never materialises ``(N, 3)`` arrays (XLA
    would copy and transpose them between fused loops).  ``w_i``, ``w_s``
    and ``w_sum`` give the ``(..., 3)`` arrays; ``Directions(w_i, w_s,
    w_sum)`` accepts arrays ``(..., 3)`` or 3-tuples of component arrays.
    The components of ``w_i`` may have a smaller (broadcastable) shape than
    those of ``w_s``: a frame's single incident direction stays a scalar.

    ``w_sum = w_i + w_s`` is carried separately because near the specular
    direction its x and y components are differences of nearly equal numbers;
    :meth:`brdfjax.Detector.directions` computes it without that cancellation.
    For directions given any other way use :meth:`from_vectors` or
    :meth:`from_angles`.
    """

    i: tuple[Array, Array, Array]
    s: tuple[Array, Array, Array]
    t: tuple[Array, Array, Array]

    def __init__(self, w_i, w_s, w_sum):
        self.i, self.s, self.t = _xyz(w_i), _xyz(w_s), _xyz(w_sum)

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

    @property
    def shape(self) -> tuple[int, ...]:
        """Broadcast shape of the directions (without the vector axis)."""
        return jnp.broadcast_shapes(*(jnp.shape(c) for c in (*self.i, *self.s, *self.t)))

    def _stack(self, comps) -> Array:
        return jnp.stack(jnp.broadcast_arrays(*comps, jnp.zeros(self.shape, jnp.result_type(*comps)))[:3], -1)

    @property
    def w_i(self) -> Array:
        """Incident unit vectors, (..., 3)."""
        return self._stack(self.i)

    @property
    def w_s(self) -> Array:
        """Scattered unit vectors, (..., 3)."""
        return self._stack(self.s)

    @property
    def w_sum(self) -> Array:
        """``w_i + w_s`` (free of cancellation where the producer made it so), (..., 3)."""
        return self._stack(self.t)

    def rotated(self, matrix: Array) -> "Directions":
        """All three vectors expressed in a frame rotated by ``matrix``."""
        return Directions(rotate_xyz(matrix, *self.i), rotate_xyz(matrix, *self.s), rotate_xyz(matrix, *self.t))

    def rotated_z(self, angle: ArrayLike) -> "Directions":
        """The directions expressed in a frame rotated by ``Rz(angle)`` (the matrix applied to the vectors).

        The same as ``rotated(Rz(angle))`` with the z components untouched (no multiplications by 0 and 1).
        """
        c, s = jnp.cos(angle), jnp.sin(angle)

        def turn(v):
            return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])

        return Directions(turn(self.i), turn(self.s), turn(self.t))

    @property
    def cos_theta_i(self) -> Array:
        return self.i[2]

    @property
    def cos_theta_s(self) -> Array:
        return self.s[2]

    def half_vector_xyz(self) -> tuple[Array, Array, Array]:
        """Components of the unit half vector ``w_h`` (Eq 52): one square root and one division."""
        sx, sy, sz = self.t
        n2 = sx * sx + sy * sy + sz * sz
        pos = n2 > 0
        inv = jnp.where(pos, 1.0 / jnp.sqrt(jnp.where(pos, n2, 1.0)), 1.0)
        return sx * inv, sy * inv, sz * inv

    def half_vector(self) -> Array:
        """Unit half vector ``w_h`` (Eq 52), (..., 3)."""
        return jnp.stack(jnp.broadcast_arrays(*self.half_vector_xyz()), -1)

    def half_slopes(self) -> tuple[Array, Array, Array]:
        """``(tan^2 theta_h cos^2 phi_h, tan^2 theta_h sin^2 phi_h, upper)``.

        The squared microfacet slopes along x and y, ``h_x^2 / h_z^2`` and
        ``h_y^2 / h_z^2``, computed from ``w_sum`` without normalising or
        taking an arccos (``physics.md``, numerical pitfalls).  ``upper`` is
        True where the half vector lies in the upper hemisphere; elsewhere the
        slopes are set to 0 and callers must zero the distribution.
        """
        sx, sy, sz = self.t
        upper = sz > 0
        inv = jnp.where(upper, 1.0 / jnp.where(upper, sz, 1.0), 0.0)
        return jnp.square(sx * inv), jnp.square(sy * inv), upper


# --- float32 trigonometry that vectorises --------------------------------------------------------

# pi/2 split in three float32 parts (Cody-Waite): q * _PIO2_1 is exact for |q| < 2^16.
_PIO2_1, _PIO2_2, _PIO2_3 = 1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8


def _sin_cos_f32(x: Array) -> tuple[Array, Array]:
    """``(sin x, cos x)`` of a float32 array with polynomials that XLA vectorises.

    XLA's CPU backend calls the scalar ``sinf``/``cosf`` of libm element by
    element; this is Cephes' ``sinf``/``cosf`` (reduction by multiples of
    pi/2 in three parts, minimax polynomials on [-pi/4, pi/4]), accurate to
    a few float32 ulp for ``|x| < 6e4`` (beyond, the reduction loses digits).
    """
    q = jnp.round(x * (2.0 / jnp.pi))
    r = ((x - q * _PIO2_1) - q * _PIO2_2) - q * _PIO2_3
    r2 = r * r
    s = r + r * r2 * (-1.6666654611e-1 + r2 * (8.3321608736e-3 + r2 * -1.9515295891e-4))
    c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166664568298827e-2 + r2 * (-1.388731625493765e-3 + r2 * 2.443315711809948e-5))
    quadrant = q.astype(jnp.int32) & 3
    swap = (quadrant & 1) == 1
    sin_x = jnp.where(swap, c, s)
    cos_x = jnp.where(swap, s, c)
    sin_x = jnp.where(quadrant >= 2, -sin_x, sin_x)
    cos_x = jnp.where((quadrant == 1) | (quadrant == 2), -cos_x, cos_x)
    return sin_x, cos_x


def fast_sin(x: ArrayLike) -> Array:
    """``sin(x)``: the vectorising polynomial for float32 (:func:`_sin_cos_f32`), ``jnp.sin`` otherwise."""
    x = jnp.asarray(x)
    return _sin_cos_f32(x)[0] if x.dtype == jnp.float32 else jnp.sin(x)


def fast_cos(x: ArrayLike) -> Array:
    """``cos(x)``: the vectorising polynomial for float32 (:func:`_sin_cos_f32`), ``jnp.cos`` otherwise."""
    x = jnp.asarray(x)
    return _sin_cos_f32(x)[1] if x.dtype == jnp.float32 else jnp.cos(x)


def fast_sinc(x: ArrayLike) -> Array:
    """Normalised ``sinc(x) = sin(pi x) / (pi x)`` (1 at 0, derivative 0 there) with :func:`fast_sin`."""
    x = jnp.asarray(x)
    zero = x == 0
    px = jnp.pi * jnp.where(zero, 1.0, x)
    return jnp.where(zero, 1.0, fast_sin(px) / px)
