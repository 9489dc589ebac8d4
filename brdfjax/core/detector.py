"""CCD pixel to scatter-direction mapping (seed §3.5, §4.4-4.5; Eq 75-86, 105, 109).

Pixel index ``(n_h, n_v)``: the alignment pixel is ``(0, 0)``; on the seed's
3296 x 2472 array the top-left pixel is ``(-1647, -1235)`` and the
bottom-right ``(1648, 1236)``.  Frames are arrays of ``n_v`` rows by ``n_h``
columns, row 0 at the top (most negative ``n_v``).

The detector arm sits at ``theta_c`` from the normal in the plane of
incidence.  With rotational misalignment ``R_CCD = Rz(roll) Ry(yaw) Rx(pitch)``
and translational offsets ``m_h, m_v`` (pixels), Eq 105 gives the vector from
the illuminated spot to a pixel::

    r_s = Ry(theta_c + m_h d_h / R) (R_CCD (n_h d_h, n_v d_v, 0) + R z) + m_v d_v y

which reduces to Eq 78 when aligned.  The scatter direction is computed as
``w_s = Ry(alpha)(z + e)`` with the small vector ``e`` formed without
cancellation, so that ``w_i + w_s`` near the specular direction keeps its
digits in float32 (see :class:`brdfjax.core.geometry.Directions`).
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .fields import check_param, param
from .geometry import (
    Directions,
    Rx,
    Ry,
    Rz,
    direction,
    rotate,
    safe_sqrt,
    zenith_azimuth,
)

__all__ = ["Detector", "PixelGrid", "incident_direction"]


def incident_direction(theta_i: ArrayLike) -> Array:
    """``w_i = (-sin theta_i, 0, cos theta_i)`` (phi_i = 0)."""
    theta_i = jnp.asarray(theta_i)
    return jnp.stack([-jnp.sin(theta_i), jnp.zeros_like(theta_i), jnp.cos(theta_i)], -1)


@dataclass(frozen=True)
class PixelGrid:
    """Which pixels to evaluate: every ``step``-th pixel of a region of interest.

    ``roi = (h0, h1, v0, v1)`` are inclusive pixel-index bounds (seed indices,
    not array offsets); ``None`` means the whole array.
    """

    n_h: np.ndarray  # 1-D column indices
    n_v: np.ndarray  # 1-D row indices

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_v.size, self.n_h.size)


class Detector(eqx.Module):
    """A CCD on the scatterometer arm: array shape, pitch, distance, arm angle and misalignment.

    Lengths in metres, angles in radians.  ``theta_c = None`` centres the
    detector on the specular peak of each frame (``theta_c = theta_i``), as in
    every measurement of the seed.
    """

    shape: tuple[int, int] = eqx.field(static=True)  # (n_v rows, n_h columns)
    pixel_pitch: Array = param("m", "horizontal pixel pitch d_h")
    pixel_pitch_v: Array = param("m", "vertical pixel pitch d_v")
    distance: Array = param("m", "sample-to-array distance R")
    theta_c: Array | None = param("rad", "detector arm angle; None: theta_i", default=None)
    roll: Array = param("rad", "rotation about the optical axis (theta_r)", default=0.0)
    yaw: Array = param("rad", "rotation about the vertical axis (theta_y)", default=0.0)
    pitch: Array = param("rad", "rotation about the horizontal axis (theta_p)", default=0.0)
    m_h: Array = param("px", "in-plane peak offset in pixels", default=0.0)
    m_v: Array = param("px", "out-of-plane peak offset in pixels", default=0.0)

    def __check_init__(self):
        n_v, n_h = self.shape
        if not (isinstance(n_v, int) and isinstance(n_h, int) and n_v >= 1 and n_h >= 1):
            raise ValueError(f"Detector: shape must be two positive integers (n_v, n_h), got {self.shape!r}")
        check_param("Detector", "pixel_pitch", self.pixel_pitch, lambda v: v > 0, "a positive length in metres")
        check_param("Detector", "pixel_pitch_v", self.pixel_pitch_v, lambda v: v > 0, "a positive length in metres")
        check_param("Detector", "distance", self.distance, lambda v: v > 0, "a positive length in metres")
        if self.theta_c is not None:
            check_param(
                "Detector", "theta_c", self.theta_c, lambda v: (v >= 0) & (v < np.pi / 2), "0 <= theta_c < 90 deg"
            )

    @classmethod
    def seed(cls, **kwargs) -> "Detector":
        """The seed's camera: 3296 x 2472 pixels of 5.5 um at R = 0.325 m."""
        base = dict(shape=(2472, 3296), pixel_pitch=5.5e-6, pixel_pitch_v=5.5e-6, distance=0.325)
        base.update(kwargs)
        return cls(**base)

    @classmethod
    def seed_misaligned_example(cls, m_h: float = 3.0, m_v: float = 5.0, **kwargs) -> "Detector":
        """The seed's §4.4 alignment example: roll 0.11, yaw 0.062, pitch 0.025 deg."""
        return cls.seed(
            roll=np.deg2rad(0.11), yaw=np.deg2rad(0.062), pitch=np.deg2rad(0.025), m_h=m_h, m_v=m_v, **kwargs
        )

    def at(self, theta_c: ArrayLike | None) -> "Detector":
        """The same detector with the arm at ``theta_c`` (rad)."""
        return eqx.tree_at(lambda d: d.theta_c, self, theta_c, is_leaf=lambda x: x is None)

    def arm_angle(self, theta_i: ArrayLike) -> ArrayLike:
        """The arm angle of a frame at incidence ``theta_i``: ``theta_c``, or ``theta_i`` when ``theta_c`` is None.

        The one place that decides what ``theta_c = None`` ("centred on the
        specular peak") means.  Traceable: ``None`` is part of the pytree
        structure, so the choice is made at trace time and the value returned
        as given (no conversion).
        """
        return theta_i if self.theta_c is None else self.theta_c

    def with_arm(self, theta_i: ArrayLike) -> "Detector":
        """This detector with its arm fixed (:meth:`arm_angle`): itself when ``theta_c`` is set, else at ``theta_i``."""
        return self if self.theta_c is not None else self.at(theta_i)

    # -- pixel selection ------------------------------------------------------------------
    @property
    def index_range(self) -> tuple[int, int, int, int]:
        """``(h_min, h_max, v_min, v_max)`` pixel indices of the full array."""
        n_v, n_h = self.shape
        h0, v0 = _first_index(n_h), _first_index(n_v)
        return (h0, h0 + n_h - 1, v0, v0 + n_v - 1)

    def grid(self, step: int = 1, roi: tuple[int, int, int, int] | None = None) -> PixelGrid:
        """Pixel indices of every ``step``-th pixel in ``roi = (h0, h1, v0, v1)`` (inclusive)."""
        if not (isinstance(step, int | np.integer) and step >= 1):
            raise ValueError(f"grid: step must be a positive integer, got {step!r}")
        h_min, h_max, v_min, v_max = self.index_range
        if roi is None:
            roi = (h_min, h_max, v_min, v_max)
        h0, h1, v0, v1 = (int(x) for x in roi)
        if not (h_min <= h0 <= h1 <= h_max and v_min <= v0 <= v1 <= v_max):
            raise ValueError(
                f"grid: roi {roi!r} is outside the array; expected h_min<=h0<=h1<=h_max and v likewise "
                f"with (h_min, h_max, v_min, v_max) = {(h_min, h_max, v_min, v_max)}"
            )
        return PixelGrid(np.arange(h0, h1 + 1, step), np.arange(v0, v1 + 1, step))

    # -- geometry -------------------------------------------------------------------------
    def _ccd_rotation(self) -> Array:
        return Rz(self.roll) @ Ry(self.yaw) @ Rx(self.pitch)

    def _alpha(self, theta_c: ArrayLike) -> Array:
        return theta_c + self.m_h * self.pixel_pitch / self.distance

    def _offset_xyz(self, n_h: ArrayLike, n_v: ArrayLike) -> tuple[Array, Array, Array]:
        """Components of ``p = R_CCD r_p + m_v d_v y`` (small) for pixels (``u = p + R z``).

        Written component by component (no stacking, scatter-add or axis
        reductions) so that XLA fuses the whole mapping into one loop.
        """
        x = jnp.asarray(n_h) * self.pixel_pitch
        y = jnp.asarray(n_v) * self.pixel_pitch_v
        M = self._ccd_rotation()
        dy = self.m_v * self.pixel_pitch_v
        return jnp.broadcast_arrays(M[0, 0] * x + M[0, 1] * y, M[1, 0] * x + M[1, 1] * y + dy, M[2, 0] * x + M[2, 1] * y)

    def _offset_vector(self, n_h: ArrayLike, n_v: ArrayLike) -> tuple[Array, Array]:
        """``p = R_CCD r_p + m_v d_v y`` (small) and ``u = p + R z`` for pixels, (..., 3)."""
        p = self._offset_xyz(n_h, n_v)
        u = (p[0], p[1], p[2] + self.distance)
        return jnp.stack(p, -1), jnp.stack(u, -1)

    def _unit_offset_xyz(self, n_h, n_v) -> tuple[Array, Array, Array]:
        """Components of ``e = u / |u| - z`` without cancellation: one square root, one division."""
        px, py, pz = self._offset_xyz(n_h, n_v)
        R = self.distance
        q = px * px + py * py + pz * pz + 2.0 * R * pz  # |u|^2 - R^2
        norm_u = safe_sqrt(R * R + q)
        inv = 1.0 / (norm_u * (norm_u + R))
        # 1/|u| = (|u| + R) inv and R/|u| - 1 = -q inv
        inv_u = (norm_u + R) * inv
        return px * inv_u, py * inv_u, pz * inv_u - q * inv

    def _unit_offset(self, n_h, n_v) -> Array:
        """``e = u / |u| - z`` without cancellation, (..., 3)."""
        return jnp.stack(self._unit_offset_xyz(n_h, n_v), -1)

    def _arm(self, theta_c: ArrayLike | None, theta_i: ArrayLike | None) -> Array:
        if theta_c is not None:
            return jnp.asarray(theta_c)
        if self.theta_c is None and theta_i is None:
            raise ValueError("Detector: theta_c is None (centred on the peak) so theta_i must be given")
        return jnp.asarray(self.arm_angle(theta_i))

    @eqx.filter_jit
    def scatter_directions(self, n_h: ArrayLike, n_v: ArrayLike, theta_c: ArrayLike | None = None) -> Array:
        """Unit scatter directions ``w_s`` of pixels (Eq 78/105 normalised), (..., 3)."""
        alpha = self._alpha(self._arm(theta_c, None))
        e = self._unit_offset(n_h, n_v)
        base = jnp.stack([jnp.sin(alpha), jnp.zeros_like(alpha), jnp.cos(alpha)], -1)
        return base + rotate(Ry(alpha), e)

    @eqx.filter_jit
    def directions(self, n_h: ArrayLike, n_v: ArrayLike, theta_i: ArrayLike) -> Directions:
        """Incident and scattered directions for pixels, with ``w_i + w_s`` free of cancellation.

        Component by component; the incident direction's components keep the
        shape of ``theta_i`` (one direction per frame, not one per pixel).
        """
        theta_i = jnp.asarray(theta_i)
        alpha = self._alpha(self._arm(None, theta_i))
        ex, ey, ez = self._unit_offset_xyz(n_h, n_v)
        ca, sa = jnp.cos(alpha), jnp.sin(alpha)
        # Ry(alpha) e
        erx, erz = ca * ex + sa * ez, ca * ez - sa * ex
        w_s = (sa + erx, ey, ca + erz)
        w_i = (-jnp.sin(theta_i), jnp.zeros_like(theta_i), jnp.cos(theta_i))
        half_sum, half_diff = 0.5 * (alpha + theta_i), 0.5 * (alpha - theta_i)
        # sin(alpha) - sin(theta_i) and cos(alpha) + cos(theta_i) as products (no cancellation).
        c2 = 2.0 * jnp.cos(half_sum)
        w_sum = (c2 * jnp.sin(half_diff) + erx, ey, c2 * jnp.cos(half_diff) + erz)
        return Directions(w_i, w_s, w_sum)

    @eqx.filter_jit
    def angles(self, n_h: ArrayLike, n_v: ArrayLike, theta_c: ArrayLike | None = None) -> tuple[Array, Array]:
        """``(theta_s, phi_s)`` in radians (Eq 80; azimuth from -x, in [0, 2 pi))."""
        return zenith_azimuth(self.scatter_directions(n_h, n_v, theta_c))

    @eqx.filter_jit
    def solid_angle(self, n_h: ArrayLike, n_v: ArrayLike) -> Array:
        """Solid angle of each pixel, sr (Eq 86 aligned; Eq 109 with misalignment).

        ``Omega_d = d_h d_v (u . R_CCD z) / |u|^3`` with ``u`` the pixel vector in
        the arm frame: the pixel's projected area over the squared distance.
        It does not depend on the arm angle.
        """
        _, u = self._offset_vector(n_h, n_v)
        normal = self._ccd_rotation()[:, 2]
        ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
        norm_u = safe_sqrt(ux * ux + uy * uy + uz * uz)
        return self.pixel_pitch * self.pixel_pitch_v * (ux * normal[0] + uy * normal[1] + uz * normal[2]) / norm_u**3

    @eqx.filter_jit
    def pixel_of(
        self, theta_s: ArrayLike, phi_s: ArrayLike, theta_c: ArrayLike | None = None
    ) -> tuple[Array, Array]:
        """Inverse map (Eq 82): fractional pixel indices ``(n_h, n_v)`` hit by a direction.

        The ray along ``(theta_s, phi_s)`` is intersected with the (possibly
        misaligned) array plane.  With perfect alignment this is Eq 82 written
        as ``n_h = (R/d_h) x'/z'``, ``n_v = (R/d_v) y'/z'`` with
        ``w' = Ry(-theta_c) w``, which is regular at both limits of Eq 83-84
        (``theta_c -> 0`` and ``theta_c -> 90 deg``).  Directions that miss the
        plane (``z' <= 0``) give NaN.
        """
        alpha = self._alpha(self._arm(theta_c, None))
        w = rotate(Ry(-alpha), direction(theta_s, phi_s))
        Rc = self._ccd_rotation()
        anchor = jnp.stack(
            [jnp.zeros_like(self.distance), self.m_v * self.pixel_pitch_v, jnp.asarray(self.distance)]
        )
        w_c = rotate(Rc.T, w)
        a_c = Rc.T @ anchor
        t = a_c[2] / w_c[..., 2]
        hit = (w_c[..., 2] > 0) & (t > 0)
        x = t * w_c[..., 0] - a_c[0]
        y = t * w_c[..., 1] - a_c[1]
        return (
            jnp.where(hit, x / self.pixel_pitch, jnp.nan),
            jnp.where(hit, y / self.pixel_pitch_v, jnp.nan),
        )

    def contours(
        self,
        theta_s_deg: ArrayLike | None = None,
        phi_s_deg: ArrayLike | None = None,
        theta_c: ArrayLike | None = None,
        n_points: int = 400,
    ) -> list[dict]:
        """Polylines of constant theta_s and phi_s in pixel coordinates, for plot overlays.

        Levels default to ~6 evenly spaced round values across the array.
        Returns ``[{"kind": "theta_s" | "phi_s", "level_deg": float, "n_h": array, "n_v": array}, ...]``
        with each polyline clipped to the array (NaN where it leaves it).
        """
        h_min, h_max, v_min, v_max = self.index_range
        hh, vv = np.meshgrid(np.linspace(h_min, h_max, 33), np.linspace(v_min, v_max, 33))
        th, ph = (np.asarray(a) for a in self.angles(hh, vv, theta_c))
        th_deg = np.rad2deg(th)
        ph_deg = np.rad2deg(ph)
        # azimuths near 0/360 (theta_c ~ 0) wrap: work in (-180, 180] about the array centre's azimuth.
        centre = float(np.rad2deg(np.asarray(self.angles(np.zeros(1), np.zeros(1), theta_c)[1])[0]))
        ph_rel = (ph_deg - centre + 180.0) % 360.0 - 180.0
        if theta_s_deg is None:
            theta_s_deg = _nice_levels(th_deg.min(), th_deg.max())
        if phi_s_deg is None:
            phi_s_deg = (centre + _nice_levels(ph_rel.min(), ph_rel.max())) % 360.0
        s = np.linspace(0.0, 1.0, n_points)
        th_levels = np.atleast_1d(np.asarray(theta_s_deg, dtype=float))
        ph_levels = np.atleast_1d(np.asarray(phi_s_deg, dtype=float))
        phis = centre + ph_rel.min() + s * (ph_rel.max() - ph_rel.min())
        ths = th_deg.min() + s * (th_deg.max() - th_deg.min())
        # One batched call for every level: (levels, points) arrays of angles.
        th_all = np.concatenate([np.repeat(th_levels[:, None], n_points, 1), np.tile(ths, (ph_levels.size, 1))])
        ph_all = np.concatenate([np.tile(phis, (th_levels.size, 1)), np.repeat(ph_levels[:, None], n_points, 1)])
        nh, nv = (np.asarray(a) for a in self.pixel_of(np.deg2rad(th_all), np.deg2rad(ph_all), theta_c))
        kinds = ["theta_s"] * th_levels.size + ["phi_s"] * ph_levels.size
        levels = list(th_levels) + list(ph_levels)
        lines = [self._clip(k, float(lev), nh[i], nv[i]) for i, (k, lev) in enumerate(zip(kinds, levels))]
        return [ln for ln in lines if np.isfinite(ln["n_h"]).sum() >= 2]

    def _clip(self, kind: str, level: float, nh: Array, nv: Array) -> dict:
        h_min, h_max, v_min, v_max = self.index_range
        nh, nv = np.asarray(nh, dtype=float), np.asarray(nv, dtype=float)
        inside = (nh >= h_min) & (nh <= h_max) & (nv >= v_min) & (nv <= v_max)
        return {"kind": kind, "level_deg": level, "n_h": np.where(inside, nh, np.nan), "n_v": np.where(inside, nv, np.nan)}


def _first_index(n: int) -> int:
    # Seed convention for even counts: 3296 -> -1647..1648 (the alignment pixel is
    # left of/above the geometric centre); odd counts are symmetric.
    return -(n // 2 - 1) if n % 2 == 0 else -(n // 2)


def _nice_levels(lo: float, hi: float, target: int = 5) -> np.ndarray:
    span = hi - lo
    if not np.isfinite(span) or span <= 0:
        return np.array([lo])
    raw = span / target
    if raw > 10:  # wide angular spans (the arm near the normal): steps that divide 360 deg
        step = min((m for m in (15, 30, 45, 90, 180) if m >= raw), default=180)
    else:
        mag = 10 ** np.floor(np.log10(raw))
        step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    return np.arange(np.ceil(lo / step) * step, hi + 1e-12, step)
