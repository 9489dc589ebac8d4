"""The light-curve forward model in JAX: facets, attitude, the solar disk, flux at the observer.

A satellite is a set of flat facets (:class:`Facets`: area, body-frame normal,
in-plane x axis and ``phi_ref``), each with a brdfjax model (facets that share
a model are evaluated together), and an :class:`Attitude` (nadir-pointing
LVLH with roll/pitch/yaw offsets, or fixed inertial).  Facets flagged as
tracking turn about their x axis so that their normal follows the Sun as
closely as one axis allows (solar arrays of broadband constellations).

For every time step the Sun is a disk of angular radius 4.65e-3 rad
(:class:`SunDisk`: a fixed quadrature over the disk, optionally limb
darkened; ``SunDisk.point()`` is the point-Sun limit).  Each quadrature node
is a direction to part of the Sun; a node whose ray from the satellite hits
the Earth is in shadow (umbra and penumbra follow).  The facet-frame
incident directions ``w_i`` (one per node) and the scattered direction
``w_s`` (to the observer) go to the model as
:class:`~brdfjax.core.geometry.Directions` (the public way to evaluate any model
on arbitrary direction pairs).  The irradiance at the observer from facet j
is::

    E_j / E_sun(1 AU) = (AU / d_sun)^2  A_j  sum_k w_k v_k f_j(w_i,k, w_s) max(cos theta_i,k, 0) max(cos theta_s, 0) / d_obs^2

with quadrature weights ``w_k`` (sum 1) and shadow flags ``v_k``.  The
apparent magnitude is ``m_sun - 2.5 log10(E / E_sun(1 AU))``.  Facets do not
shadow or hide one another (a convex-body approximation, as in lumos-sat).

Everything is jit-compiled and differentiable with respect to the models'
parameters and the attitude offsets (``eqx.filter_grad`` of a loss of
:func:`facet_flux`); time steps are processed in chunks with ``lax.map``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..core.geometry import Directions, Rx, Ry, Rz, safe_sqrt
from ..core.terms import AbstractTerm
from .ephemeris import AU_M, EARTH_RADIUS_M
from .sharp import DEFAULT_TOL, flag_features, term_features

__all__ = [
    "SUN_RADIUS_RAD",
    "SUN_MAGNITUDE_V",
    "SunDisk",
    "AdaptiveDisk",
    "light_curve",
    "Facets",
    "Attitude",
    "Satellite",
    "Geometry",
    "facet_flux",
    "magnitude",
]

#: Mean angular radius of the Sun seen from 1 AU (rad): 959.6 arcsec (0.533 deg diameter).
SUN_RADIUS_RAD = float(np.deg2rad(959.63 / 3600.0))
#: Apparent V magnitude of the Sun at 1 AU (Willmer 2018: -26.76; -26.74 is also quoted).
SUN_MAGNITUDE_V = -26.76


def _unit(v: Array) -> Array:
    n = safe_sqrt(jnp.sum(v * v, -1, keepdims=True))
    return v / jnp.where(n > 0, n, 1.0)


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, -1)


class SunDisk(eqx.Module):
    """A fixed quadrature over the solar disk: node offsets in the unit disk and weights summing to 1.

    :meth:`rings` takes the nodes of a hexagonal lattice of spacing
    ``radius / (n + 1/2)`` that fall inside the disk (one at the centre;
    about ``3.6 n^2`` in all), with equal cell weights times a linear
    limb-darkening law ``1 - u (1 - mu)``; the
    offsets are then scaled so that the weighted mean of ``rho^2`` equals the
    continuous disk's, which makes the quadrature integrate ``cos`` of the
    angle to any direction exactly to O(radius^4) (the Lambertian plate).  A
    narrow lobe (Gaussian of standard deviation sigma in direction) is
    integrated to ~``exp(-2 pi^2 sigma^2 / h^2)`` relative, h the spacing:
    the seed's m = 2e-4 Beckmann peak (sigma ~ 2.8e-4 rad) needs ``n >= 12``.
    """

    offsets: Array  # (K, 2), in units of the angular radius
    weights: Array  # (K,)
    radius: float = eqx.field(static=True, default=SUN_RADIUS_RAD)

    @classmethod
    def point(cls) -> "SunDisk":
        """The point-Sun limit: one node at the centre."""
        return cls(np.zeros((1, 2)), np.ones(1), 0.0)

    @classmethod
    def rings(cls, n: int, radius: float = SUN_RADIUS_RAD, limb_darkening: float = 0.0) -> "SunDisk":
        if n < 0:
            raise ValueError(f"SunDisk.rings: n = {n}; expected n >= 0 rings (0: the centre only)")
        if not 0.0 <= limb_darkening <= 1.0:
            raise ValueError(f"SunDisk.rings: limb_darkening = {limb_darkening}; expected 0 <= u <= 1")
        if n == 0:
            return cls.point()
        step = 1.0 / (n + 0.5)
        k = np.arange(-2 * n - 2, 2 * n + 3)
        i, j = np.meshgrid(k, k, indexing="ij")
        pts = np.stack([(i + 0.5 * j) * step, j * (np.sqrt(3) / 2) * step], -1).reshape(-1, 2)
        xy = pts[np.sum(pts**2, -1) <= 1.0 + 1e-12]
        w = np.ones(len(xy))
        xy, w = np.asarray(xy), np.asarray(w)
        rho2 = np.sum(xy**2, -1)
        u = float(limb_darkening)
        w = w * (1 - u * (1 - np.sqrt(np.clip(1 - rho2, 0, 1))))
        w = w / w.sum()
        target = ((1 - u) / 4 + 2 * u / 15) / ((1 - u) / 2 + u / 3)  # <rho^2> of the limb-darkened disk
        xy = xy * np.sqrt(target / np.sum(w * rho2))
        return cls(xy, w, float(radius))

    @property
    def n_nodes(self) -> int:
        return int(np.shape(self.weights)[0])

    def mean_cos(self) -> Array:
        """``sum_k w_k cos(radius rho_k)``: the rule's mean of the cosine of each node's angle from the centre.

        A centre node with this weight integrates ``f cos(theta_i)`` exactly as the
        full rule does when ``f`` is constant over the disk (the rule is centrally
        symmetric: the nodes' tangential offsets cancel).
        """
        off = jnp.asarray(self.offsets)
        rho = jnp.sqrt(jnp.sum(off**2, -1))
        return jnp.sum(jnp.asarray(self.weights) * jnp.cos(self.radius * rho))

    def directions(self, s: Array) -> Array:
        """Node directions (..., K, 3) around the unit centre directions ``s`` (..., 3)."""
        # Any axis not parallel to s spans the tangent plane; the Sun's declination is within
        # +-23.5 deg, so TEME +z is never closer than 66 deg to it.
        e1 = _unit(jnp.cross(s, jnp.array([0.0, 0.0, 1.0], s.dtype)))
        e2 = jnp.cross(s, e1)
        off = jnp.asarray(self.offsets, s.dtype)
        rho = jnp.sqrt(jnp.sum(off**2, -1))  # constant: no gradient flows through it
        ang = self.radius * rho
        scale = self.radius * jnp.sinc(ang / np.pi)  # sin(radius rho) / rho
        return (
            jnp.cos(ang)[:, None] * s[..., None, :]
            + (scale * off[:, 0])[:, None] * e1[..., None, :]
            + (scale * off[:, 1])[:, None] * e2[..., None, :]
        )


class Facets(eqx.Module):
    """Flat facets of a satellite, all arrays over facets (J,).

    ``normal`` and ``x_axis`` are body-frame unit vectors (``x_axis`` in the
    facet plane); the facet frame is ``(x, y, n)`` with ``x`` the x axis
    turned by ``phi_ref`` about the normal (the model's sample frame: a
    diffraction grating's bars or an anisotropic lobe's axes follow it).  A
    tracking facet turns about ``x_axis`` to face the Sun (``normal`` then
    only gives the side: ``+`` the lit face, the back face has
    ``normal . sun < 0``).
    """

    area: Array  # m^2
    normal: Array  # (J, 3)
    x_axis: Array  # (J, 3)
    phi_ref: Array  # rad
    tracking: Array  # (J,) 1.0 for a Sun-tracking facet, else 0.0
    side: Array  # (J,) +1 front (faces the Sun when tracking), -1 back
    names: tuple[str, ...] = eqx.field(static=True, default=())

    @classmethod
    def build(
        cls,
        names: Sequence[str],
        area: Sequence[float],
        normal: Sequence[Sequence[float]],
        x_axis: Sequence[Sequence[float] | None] | None = None,
        phi_ref: Sequence[float] | None = None,
        tracking: Sequence[bool] | None = None,
        side: Sequence[float] | None = None,
    ) -> "Facets":
        """Checked facets; ``x_axis`` defaults to a perpendicular of the normal; raises ValueError naming the facet."""
        J = len(names)
        normal = np.asarray(normal, np.float64).reshape(J, 3)
        xs = []
        for j, name in enumerate(names):
            nn = np.linalg.norm(normal[j])
            if not np.isfinite(nn) or nn < 1e-12:
                raise ValueError(f"facet '{name}': normal {normal[j].tolist()} has zero length; expected a nonzero vector")
            n = normal[j] / nn
            normal[j] = n
            x = None if x_axis is None else x_axis[j]
            if x is None:
                helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
                x = helper - helper.dot(n) * n
            else:
                x = np.asarray(x, np.float64)
                if not tracking or not tracking[j]:
                    x = x - x.dot(n) * n
            xn = np.linalg.norm(x)
            if xn < 1e-9:
                raise ValueError(f"facet '{name}': x_axis is parallel to the normal; expected a direction in the facet plane")
            xs.append(x / xn)
        area = np.asarray(area, np.float64)
        if np.any(~np.isfinite(area)) or np.any(area <= 0):
            bad = names[int(np.flatnonzero(~(area > 0))[0])]
            raise ValueError(f"facet '{bad}': area must be > 0 (m^2)")
        tr = np.zeros(J) if tracking is None else np.asarray(tracking, np.float64)
        sd = np.ones(J) if side is None else np.asarray(side, np.float64)
        pr = np.zeros(J) if phi_ref is None else np.asarray(phi_ref, np.float64)
        return cls(area, normal, np.asarray(xs), pr, tr, sd, tuple(names))

    def frames(self, sun_body: Array) -> tuple[Array, Array, Array]:
        """Facet axes ``(x, y, n)`` in the body frame at each time, each (T, J, 3), given the body-frame Sun (T, 3)."""
        return _frames(self.x_axis, self.normal, self.phi_ref, self.tracking, self.side, sun_body[:, None, :])

    def take(self, j: Array) -> tuple[Array, Array, Array, Array, Array]:
        """The facet parameters ``(x_axis, normal, phi_ref, tracking, side)`` of facets ``j`` (any shape)."""
        return self.x_axis[j], self.normal[j], self.phi_ref[j], self.tracking[j], self.side[j]


def _frames(x_axis: Array, normal: Array, phi_ref: Array, tracking: Array, side: Array, s: Array
            ) -> tuple[Array, Array, Array]:
    """Facet axes ``(x, y, n)`` in the body frame; vectors (..., 3) and scalars (...) broadcast against ``s`` (..., 3)."""
    a = x_axis
    n_track = _unit(s - _dot(s, a)[..., None] * a) * side[..., None]
    t = tracking[..., None]
    n = t * n_track + (1 - t) * jnp.broadcast_to(normal, n_track.shape)
    a = _unit(a - _dot(a, n)[..., None] * n)
    c, sn = jnp.cos(phi_ref)[..., None], jnp.sin(phi_ref)[..., None]
    x = c * a + sn * jnp.cross(n, a)
    y = jnp.cross(n, x)
    return x, y, n


class Attitude(eqx.Module):
    """Body frame -> TEME.  ``nadir``: LVLH (x along the velocity, z to the Earth's centre, y = z x x) then
    the offsets ``Rz(yaw) Ry(pitch) Rx(roll)``; ``inertial``: ``base`` (columns: body axes in TEME) then the
    offsets.  Offsets in radians, differentiable."""

    roll: Array
    pitch: Array
    yaw: Array
    base: Array  # (3, 3), used by 'inertial'
    kind: str = eqx.field(static=True, default="nadir")

    @classmethod
    def nadir(cls, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> "Attitude":
        return cls(np.float64(roll), np.float64(pitch), np.float64(yaw), np.eye(3), "nadir")

    @classmethod
    def inertial(cls, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> "Attitude":
        """Body axes fixed in TEME, turned from TEME's axes by ``Rz(yaw) Ry(pitch) Rx(roll)``."""
        return cls(np.float64(0.0), np.float64(0.0), np.float64(0.0),
                   np.asarray(Rz(yaw) @ Ry(pitch) @ Rx(roll), np.float64), "inertial")

    def matrix(self, r_hat: Array, v_hat: Array) -> Array:
        """(T, 3, 3) body -> TEME (columns are the body axes)."""
        off = Rz(self.yaw) @ Ry(self.pitch) @ Rx(self.roll)
        if self.kind == "nadir":
            z = -r_hat
            y = _unit(jnp.cross(z, v_hat))
            x = jnp.cross(y, z)
            lvlh = jnp.stack([x, y, z], -1)
            return lvlh @ off
        return jnp.broadcast_to(jnp.asarray(self.base, r_hat.dtype) @ off, r_hat.shape[:-1] + (3, 3))


class Satellite(eqx.Module):
    """Facets, their models (``model_of[j]`` indexes ``models``) and the attitude: everything differentiable."""

    facets: Facets
    models: tuple[AbstractTerm, ...]
    attitude: Attitude
    model_of: tuple[int, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if len(self.model_of) != len(self.facets.names):
            raise ValueError(f"Satellite: {len(self.facets.names)} facets but {len(self.model_of)} model indices")

    def with_models(self, models: Sequence[AbstractTerm]) -> "Satellite":
        return eqx.tree_at(lambda s: s.models, self, tuple(models))

    def subset(self, idx: Sequence[int]) -> "Satellite":
        """The satellite reduced to the facets ``idx`` (and the models they use)."""
        idx = list(idx)
        f = self.facets
        used = sorted({self.model_of[j] for j in idx})
        facets = Facets(f.area[idx], f.normal[idx], f.x_axis[idx], f.phi_ref[idx], f.tracking[idx], f.side[idx],
                        tuple(f.names[j] for j in idx))
        return Satellite(facets, tuple(self.models[m] for m in used), self.attitude,
                         tuple(used.index(self.model_of[j]) for j in idx))


class Geometry(eqx.Module):
    """Per-time-step geometry for the JAX code (host-computed in float64, cast to the working dtype).

    Unit vectors satellite -> Sun ``s`` and satellite -> observer ``o``, the
    distances ``d_sun`` and ``d_obs`` (m), the satellite's unit position and
    velocity, and its radius ``r`` (m); all (T, 3) or (T,).
    """

    s: Array
    o: Array
    d_sun: Array
    d_obs: Array
    r_hat: Array
    v_hat: Array
    r: Array

    @classmethod
    def from_positions(cls, r_sat, v_sat, r_sun, r_obs, dtype=np.float64) -> "Geometry":
        r_sat, v_sat, r_sun, r_obs = (np.asarray(x, np.float64) for x in (r_sat, v_sat, r_sun, r_obs))
        ds, do = r_sun - r_sat, r_obs - r_sat
        d_sun, d_obs, r = (np.linalg.norm(x, axis=-1) for x in (ds, do, r_sat))
        f = [ds / d_sun[:, None], do / d_obs[:, None], d_sun, d_obs, r_sat / r[:, None],
             v_sat / np.linalg.norm(v_sat, axis=-1, keepdims=True), r]
        return cls(*(jnp.asarray(x, dtype) for x in f))

    def __len__(self) -> int:
        return int(self.d_obs.shape[0])

    def chunks(self, size: int) -> tuple["Geometry", int]:
        """The geometry padded to a multiple of ``size`` and reshaped (n_chunks, size, ...); and the padding."""
        T = len(self)
        n = -(-T // size)
        pad = n * size - T

        def f(x):
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x
            return x.reshape((n, size) + x.shape[1:])

        return jax.tree_util.tree_map(f, self), pad


def shadow_mask(r_sat: Array, r_norm: Array, dirs: Array, earth_radius: float = EARTH_RADIUS_M) -> Array:
    """1.0 where the ray from the satellite along ``dirs`` (..., K, 3) misses the Earth sphere, else 0.0."""
    b = jnp.sum(r_sat[..., None, :] * dirs, -1)  # r . d (m)
    miss_sq = jnp.square(r_norm)[..., None] - jnp.square(b)  # squared distance of the ray's line from the centre
    return jnp.where((b < 0) & (miss_sq < earth_radius**2), 0.0, 1.0)


def to_facet_frames(v: Array, x: Array, y: Array, n: Array) -> Array:
    """Body-frame vectors ``v`` (T, ..., 3) in each facet's frame (axes ``x, y, n``: (T, J, 3)): (T, J, ..., 3)."""
    ex = (slice(None), slice(None)) + (None,) * (v.ndim - 2)
    vv = v[:, None]
    return jnp.stack([_dot(vv, x[ex]), _dot(vv, y[ex]), _dot(vv, n[ex])], -1)


def facet_brdf(sat: Satellite, w_i: Array, w_s: Array, wavelength: float) -> Array:
    """Each facet's BRDF (T, J, K) at incident directions ``w_i`` (T, J, K, 3) and the scattered ``w_s`` (T, J, 3),
    in facet frames; the facets sharing a model are evaluated in one call."""
    J = len(sat.facets.names)
    f = [None] * J
    for m, model in enumerate(sat.models):
        idx = [j for j in range(J) if sat.model_of[j] == m]
        if not idx:
            continue
        ii = np.asarray(idx)
        vals = model(Directions.from_vectors(w_i[:, ii], w_s[:, ii][:, :, None, :]), wavelength)  # (T, Jm, K)
        for q, j in enumerate(idx):
            f[j] = vals[:, q]
    return jnp.stack(f, 1)


def _facet_terms(sat: Satellite, g: Geometry, disk: SunDisk, wavelength: float, earth_radius: float):
    """Per-facet flux (T, J) in units of E_sun(1 AU) and the centre-ray angles (T, J) for one chunk."""
    nodes = disk.directions(g.s)  # (T, K, 3)
    vis = shadow_mask(g.r_hat * g.r[:, None], g.r, nodes, earth_radius)  # (T, K)
    M = sat.attitude.matrix(g.r_hat, g.v_hat)  # (T, 3, 3) body -> TEME
    nodes_b = jnp.einsum("tij,tki->tkj", M, nodes)  # body frame
    s_b = jnp.einsum("tij,ti->tj", M, g.s)
    o_b = jnp.einsum("tij,ti->tj", M, g.o)
    x, y, n = sat.facets.frames(s_b)  # (T, J, 3)

    w_i = to_facet_frames(nodes_b, x, y, n)  # (T, J, K, 3)
    w_s = to_facet_frames(o_b, x, y, n)  # (T, J, 3)
    w_c = to_facet_frames(s_b, x, y, n)
    fv = facet_brdf(sat, w_i, w_s, wavelength)  # (T, J, K)
    cos_i = jnp.maximum(w_i[..., 2], 0.0)
    cos_s = jnp.maximum(w_s[..., 2], 0.0)
    wts = jnp.asarray(disk.weights, fv.dtype)
    integral = jnp.sum(wts * vis[:, None, :] * fv * cos_i, -1)  # (T, J)
    scale = jnp.square(AU_M / g.d_sun) / jnp.square(g.d_obs)
    flux = sat.facets.area * integral * cos_s * scale[:, None]
    theta_i = jnp.arctan2(safe_sqrt(w_c[..., 0] ** 2 + w_c[..., 1] ** 2), w_c[..., 2])
    theta_s = jnp.arctan2(safe_sqrt(w_s[..., 0] ** 2 + w_s[..., 1] ** 2), w_s[..., 2])
    lit = jnp.sum(wts * vis, -1)
    return flux, theta_i, theta_s, lit


@eqx.filter_jit
def facet_flux(
    sat: Satellite,
    geometry: Geometry,
    disk: "SunDisk | AdaptiveDisk",
    wavelength: float = 550e-9,
    *,
    chunk: int = 512,
    earth_radius: float = EARTH_RADIUS_M,
) -> dict[str, Array]:
    """Light curve of ``sat`` along ``geometry``: a dict of arrays over time steps (T,).

    ``flux`` (T, J): each facet's irradiance at the observer in units of the
    solar irradiance at 1 AU; ``theta_i``/``theta_s`` (T, J): the angles of
    the Sun's centre and of the observer from each facet's normal (rad);
    ``sunlit`` (T,): the fraction of the solar disk seen from the satellite.
    Time steps run in chunks of ``chunk`` (bounded memory).

    With an :class:`AdaptiveDisk` the full rule is used only where a term is
    sharp over the disk (see there); the dict then also holds ``disk_full``
    (T,): the (facet, term) pairs integrated with the full rule at each step,
    ``disk_overflow`` (T,): pairs that needed it but exceeded the capacity
    (they got the cheap rule; :func:`light_curve` replans and reruns), and
    ``disk_flagged`` (U,): the flagged pairs of each unit (model term), and
    ``sunlit`` is the centre's visibility except in the penumbra.
    """
    if isinstance(disk, AdaptiveDisk):
        return _adaptive_flux(sat, geometry, disk, wavelength, chunk, earth_radius)
    T = len(geometry)
    size = max(1, min(chunk, T))
    chunks, _ = geometry.chunks(size)
    flux, ti, ts, lit = jax.lax.map(lambda g: _facet_terms(sat, g, disk, wavelength, earth_radius), chunks)

    def flat(a):
        return a.reshape((-1,) + a.shape[2:])[:T]

    return {"flux": flat(flux), "theta_i": flat(ti), "theta_s": flat(ts), "sunlit": flat(lit)}


# --- the adaptive solar disk ------------------------------------------------------------------------------


class AdaptiveDisk(eqx.Module):
    """The full disk rule only where it matters: the centre node elsewhere.

    Every (time step, facet, unit) is first integrated by the cheap rule: the
    disk's centre with weight :meth:`SunDisk.mean_cos` (exact for a term that
    is constant over the disk, e.g. Lambertian, to rounding).  A unit is one
    top-level term of a facet's model (the model itself if it is not a
    :class:`~brdfjax.core.terms.Model`).  A pair is flagged (:mod:`.sharp`) when
    the centre half vector is within reach of one of the unit's sharp
    features (narrow lobes, the diffraction streak), when the facet is within
    the Sun's radius of its terminator, or when the step is in the penumbra;
    facets turned from the observer or in full shadow are never flagged.
    Flagged pairs (at most ``capacity[u]`` per unit: JAX needs static shapes)
    are gathered over the whole pass, integrated with the ``full`` rule in
    slices of ``slot_chunk`` pairs, and their cheap value is replaced.  Flags
    choose the rule and carry no gradient; the values are differentiable in
    every parameter and the attitude, like the full rule's.

    ``capacity=None``: call :meth:`plan` (or use :func:`light_curve`, which
    plans, checks ``disk_overflow`` and replans).
    """

    full: SunDisk
    capacity: tuple[int, ...] | None = eqx.field(static=True, default=None)
    tol: float = eqx.field(static=True, default=DEFAULT_TOL)
    slot_chunk: int = eqx.field(static=True, default=32)

    @property
    def radius(self) -> float:
        return self.full.radius

    @property
    def n_nodes(self) -> int:
        return self.full.n_nodes

    def unplanned(self) -> "AdaptiveDisk":
        return AdaptiveDisk(self.full, None, self.tol, self.slot_chunk)

    def with_capacity(self, capacity: Sequence[int]) -> "AdaptiveDisk":
        return AdaptiveDisk(self.full, tuple(int(c) for c in capacity), self.tol, self.slot_chunk)

    def capacity_for(self, counts: Sequence[int], margin: float = 1.25) -> "AdaptiveDisk":
        """Capacities covering ``counts`` flagged pairs per unit with a margin, in whole ``slot_chunk`` slices."""
        sc = self.slot_chunk
        cap = [0 if c <= 0 else sc * math.ceil((c * margin + 4) / sc) for c in counts]
        return self.with_capacity(cap)

    def plan(self, sat: Satellite, geometry: Geometry, *, chunk: int = 512, margin: float = 1.25,
             earth_radius: float = EARTH_RADIUS_M) -> "AdaptiveDisk":
        """Capacities from the flags of ``sat`` along ``geometry`` (with ``margin`` for parameter changes)."""
        counts = np.asarray(_flag_counts(sat, geometry, self, chunk, earth_radius))
        return self.capacity_for(counts.tolist(), margin)


def _units(sat: Satellite) -> list[tuple[int, str | None, AbstractTerm]]:
    """(model index, term name or None, term) of every unit, in a fixed order."""
    out: list[tuple[int, str | None, AbstractTerm]] = []
    for m, model in enumerate(sat.models):
        terms = getattr(model, "terms", None)
        if isinstance(terms, dict):  # sorted, as jax orders a dict's leaves: the same order inside and outside jit
            out += [(m, name, terms[name]) for name in sorted(terms)]
        else:
            out.append((m, None, model))
    return out


def _model_facets(sat: Satellite, m: int) -> np.ndarray:
    return np.asarray([j for j in range(len(sat.facets.names)) if sat.model_of[j] == m], int)


def _unit_features(sat: Satellite, disk: AdaptiveDisk) -> list:
    """The sharp features of every unit (computed once per call, outside the loops over time steps)."""
    return [term_features(term, disk.radius, disk.tol) for _, _, term in _units(sat)]


def _cheap_terms(sat: Satellite, g: Geometry, disk: AdaptiveDisk, wavelength: float, earth_radius: float, features: list):
    """One chunk with the cheap rule: integral (T, J), cos_s (T, J), scale (T,), angles, lit (T,), flags per unit."""
    s = g.s
    r_sat = g.r_hat * g.r[:, None]
    vis_c = shadow_mask(r_sat, g.r, s[:, None, :], earth_radius)[:, 0]  # (T,)
    # penumbra: the Earth's limb within the Sun's radius of its centre, seen from the satellite
    alpha_e = jnp.arcsin(jnp.clip(earth_radius / g.r, -1.0, 1.0))
    beta = jnp.arctan2(safe_sqrt(jnp.sum(jnp.square(jnp.cross(s, -g.r_hat)), -1)), _dot(s, -g.r_hat))
    penumbra = jnp.abs(beta - alpha_e) <= disk.radius * 1.001 + 1e-12
    M = sat.attitude.matrix(g.r_hat, g.v_hat)
    s_b = jnp.einsum("tij,ti->tj", M, s)
    o_b = jnp.einsum("tij,ti->tj", M, g.o)
    x, y, n = sat.facets.frames(s_b)

    def to_facet(v):  # (T, 3) -> (T, J, 3)
        vv = v[:, None]
        return jnp.stack([_dot(vv, x), _dot(vv, y), _dot(vv, n)], -1)

    w_c, w_s = to_facet(s_b), to_facet(o_b)
    J = len(sat.facets.names)
    dtype = w_c.dtype
    f = [None] * J
    for m, model in enumerate(sat.models):
        idx = _model_facets(sat, m)
        if len(idx) == 0:
            continue
        vals = model(Directions.from_vectors(w_c[:, idx], w_s[:, idx]), wavelength)  # (T, Jm)
        for q, j in enumerate(idx):
            f[j] = vals[:, q]
    fv = jnp.stack(f, 1)
    cos_c = jnp.maximum(w_c[..., 2], 0.0)
    cos_s = jnp.maximum(w_s[..., 2], 0.0)
    integral = disk.full.mean_cos().astype(dtype) * vis_c[:, None] * fv * cos_c
    scale = jnp.square(AU_M / g.d_sun) / jnp.square(g.d_obs)
    theta_i = jnp.arctan2(safe_sqrt(w_c[..., 0] ** 2 + w_c[..., 1] ** 2), w_c[..., 2])
    theta_s = jnp.arctan2(safe_sqrt(w_s[..., 0] ** 2 + w_s[..., 1] ** 2), w_s[..., 2])
    # flags: only where the facet faces the observer and part of the Sun
    sin_r = np.sin(disk.radius)
    matters = (w_s[..., 2] > 0) & (w_c[..., 2] > -sin_r) & ((vis_c > 0) | penumbra)[:, None]
    always = (penumbra[:, None] | (jnp.abs(w_c[..., 2]) <= sin_r * 1.001)) & matters
    wsum = w_c + w_s
    norm = safe_sqrt(jnp.sum(wsum * wsum, -1))
    h = wsum / jnp.where(norm > 0, norm, 1.0)[..., None]
    delta_h = disk.radius / jnp.maximum(norm, 1e-9)  # r / (2 cos theta_d)
    flags = []
    for (m, _, _), feats in zip(_units(sat), features):
        idx = _model_facets(sat, m)
        hit = flag_features(feats, jax.lax.stop_gradient(h[:, idx]), jax.lax.stop_gradient(delta_h[:, idx]), disk.radius)
        flags.append((hit & matters[:, idx]) | always[:, idx])
    return integral, cos_s, scale, theta_i, theta_s, vis_c, penumbra, tuple(flags)


def _cheap_pass(sat: Satellite, geometry: Geometry, disk: AdaptiveDisk, wavelength: float, chunk: int, earth_radius: float):
    T = len(geometry)
    size = max(1, min(chunk, T))
    chunks, _ = geometry.chunks(size)
    features = _unit_features(sat, disk)
    out = jax.lax.map(lambda g: _cheap_terms(sat, g, disk, wavelength, earth_radius, features), chunks)
    return jax.tree_util.tree_map(lambda a: a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:])[:T], out)


@eqx.filter_jit
def _flag_counts(sat: Satellite, geometry: Geometry, disk: AdaptiveDisk, chunk: int, earth_radius: float) -> Array:
    flags = _cheap_pass(sat, geometry, disk, 550e-9, chunk, earth_radius)[-1]
    return jnp.stack([jnp.sum(f) for f in flags]) if flags else jnp.zeros(0, int)


def _full_minus_cheap(sat: Satellite, g: Geometry, j: Array, term: AbstractTerm, disk: AdaptiveDisk,
                      wavelength: float, earth_radius: float) -> Array:
    """For slots (S,): step rows ``g`` and facets ``j``, the full rule's integral of ``term`` minus the cheap one."""
    full = disk.full
    r_sat = g.r_hat * g.r[:, None]
    nodes = full.directions(g.s)  # (S, K, 3)
    vis = shadow_mask(r_sat, g.r, nodes, earth_radius)
    vis_c = shadow_mask(r_sat, g.r, g.s[:, None, :], earth_radius)[:, 0]
    M = sat.attitude.matrix(g.r_hat, g.v_hat)
    nodes_b = jnp.einsum("sij,ski->skj", M, nodes)
    s_b = jnp.einsum("sij,si->sj", M, g.s)
    o_b = jnp.einsum("sij,si->sj", M, g.o)
    x, y, n = _frames(*sat.facets.take(j), s_b)  # (S, 3)
    w_i = jnp.stack([_dot(nodes_b, x[:, None]), _dot(nodes_b, y[:, None]), _dot(nodes_b, n[:, None])], -1)
    w_c = jnp.stack([_dot(s_b, x), _dot(s_b, y), _dot(s_b, n)], -1)
    w_s = jnp.stack([_dot(o_b, x), _dot(o_b, y), _dot(o_b, n)], -1)
    K = w_i.shape[1]
    f_all = term(Directions.from_vectors(jnp.concatenate([w_i, w_c[:, None]], 1), w_s[:, None, :]), wavelength)
    f, fc = f_all[:, :K], f_all[:, K]  # the K nodes and the centre, in one evaluation (one compiled term)
    wts = jnp.asarray(full.weights, f.dtype)
    whole = jnp.sum(wts * vis * f * jnp.maximum(w_i[..., 2], 0.0), -1)
    cheap = full.mean_cos().astype(f.dtype) * vis_c * fc * jnp.maximum(w_c[..., 2], 0.0)
    return whole - cheap


def _ranks(flat: Array, block: int = 512) -> Array:
    """``cumsum(flat) - 1`` (int32) in two levels: XLA's one-level cumsum of 10^5 flags costs as much as the light curve."""
    n = flat.shape[0]
    pad = (-n) % block
    b = jnp.concatenate([flat.astype(jnp.int32), jnp.zeros(pad, jnp.int32)]).reshape(-1, block)
    inner = jnp.cumsum(b, 1)
    offset = jnp.cumsum(inner[:, -1]) - inner[:, -1]
    return (inner + offset[:, None]).reshape(-1)[:n] - 1


def _adaptive_flux(sat: Satellite, geometry: Geometry, disk: AdaptiveDisk, wavelength: float, chunk: int,
                   earth_radius: float) -> dict[str, Array]:
    units = _units(sat)
    if disk.capacity is None:
        raise ValueError("AdaptiveDisk: no capacity; plan it first (disk.plan(satellite, geometry)) or call light_curve()")
    if len(disk.capacity) != len(units):
        raise ValueError(f"AdaptiveDisk: {len(disk.capacity)} capacities for {len(units)} units (model terms); "
                         "plan it for this satellite")
    integral, cos_s, scale, ti, ts, vis_c, penumbra, flags = _cheap_pass(sat, geometry, disk, wavelength, chunk, earth_radius)
    T, J = integral.shape
    n_full = jnp.zeros(T, jnp.int32)
    n_over = jnp.zeros(T, jnp.int32)
    counts = []
    for (m, _, term), cap, fl in zip(units, disk.capacity, flags):
        idx = _model_facets(sat, m)
        Jm = len(idx)
        sc = disk.slot_chunk
        cap = sc * math.ceil(cap / sc)
        flat = fl.reshape(-1)
        counts.append(jnp.sum(flat))
        if cap == 0:
            n_over = n_over + jnp.sum(fl, -1).astype(jnp.int32)
            continue
        rank = _ranks(flat)
        fitted = flat & (rank < cap)
        n_full = n_full + jnp.sum(fitted.reshape(T, Jm), -1).astype(jnp.int32)
        n_over = n_over + jnp.sum((flat & ~fitted).reshape(T, Jm), -1).astype(jnp.int32)
        N = T * Jm
        # the flagged pairs' flat indices in order, N where fewer than cap are flagged
        slots = jnp.full(cap, N, jnp.int32).at[jnp.where(fitted, rank, cap)].set(jnp.arange(N, dtype=jnp.int32), mode="drop")
        valid = slots < N
        t_idx = jnp.where(valid, slots // Jm, 0)
        jj = jnp.where(valid, slots % Jm, 0)
        j_idx = jnp.asarray(idx)[jj]
        g_rows = jax.tree_util.tree_map(lambda a, t=t_idx: a[t], geometry)

        def one(args, term=term):
            g, j = args
            return _full_minus_cheap(sat, g, j, term, disk, wavelength, earth_radius)

        shaped = jax.tree_util.tree_map(lambda a, n=cap // sc, c=sc: a.reshape((n, c) + a.shape[1:]), (g_rows, j_idx))
        delta = jax.lax.map(one, shaped).reshape(cap)
        integral = integral.at[jnp.where(valid, t_idx, T), j_idx].add(delta, mode="drop")
    flux = sat.facets.area * integral * cos_s * scale[:, None]
    lit = jnp.where(penumbra, _lit_fraction(geometry, disk.full, earth_radius, penumbra), vis_c)
    return {"flux": flux, "theta_i": ti, "theta_s": ts, "sunlit": lit, "disk_full": n_full, "disk_overflow": n_over,
            "disk_flagged": jnp.stack(counts) if counts else jnp.zeros(0, jnp.int32)}


def _lit_fraction(geometry: Geometry, full: SunDisk, earth_radius: float, where: Array, chunk: int = 256) -> Array:
    """Fraction of the full rule's nodes that see the Sun, at the steps ``where`` (elsewhere 0; chunked)."""
    T = len(geometry)
    size = max(1, min(chunk, T))
    chunks, _ = geometry.chunks(size)
    pad = (-T) % size
    w_chunks = jnp.concatenate([where, jnp.zeros(pad, bool)]).reshape(-1, size)

    def f(args):
        g, w = args

        def compute(_):
            nodes = full.directions(g.s)
            vis = shadow_mask(g.r_hat * g.r[:, None], g.r, nodes, earth_radius)
            return jnp.sum(jnp.asarray(full.weights, vis.dtype) * vis, -1)

        return jax.lax.cond(jnp.any(w), compute, lambda _: jnp.zeros(size, g.s.dtype), None)

    return jax.lax.map(f, (chunks, w_chunks)).reshape(-1)[:T]


def light_curve(sat: Satellite, geometry: Geometry, disk: "SunDisk | AdaptiveDisk", wavelength: float = 550e-9, *,
                chunk: int = 512, earth_radius: float = EARTH_RADIUS_M, margin: float = 1.25) -> dict[str, Array]:
    """:func:`facet_flux`, planning an unplanned :class:`AdaptiveDisk` and replanning once if it overflows.

    Not for use under ``jit``/``grad`` (it reads the overflow count); there, plan
    the disk first and check ``disk_overflow`` yourself.
    """
    if not isinstance(disk, AdaptiveDisk):
        return facet_flux(sat, geometry, disk, wavelength, chunk=chunk, earth_radius=earth_radius)
    if disk.capacity is None:
        disk = disk.plan(sat, geometry, chunk=chunk, margin=margin, earth_radius=earth_radius)
    out = facet_flux(sat, geometry, disk, wavelength, chunk=chunk, earth_radius=earth_radius)
    over = int(jnp.sum(out["disk_overflow"]))
    if over:
        warnings.warn(f"adaptive solar disk: {over} flagged (step, facet, term) pairs exceeded the capacity "
                      f"{disk.capacity}; replanning with the counts {np.asarray(out['disk_flagged']).tolist()}",
                      RuntimeWarning, stacklevel=2)
        disk = disk.capacity_for(np.asarray(out["disk_flagged"]).tolist(), margin)
        out = facet_flux(sat, geometry, disk, wavelength, chunk=chunk, earth_radius=earth_radius)
    return out


def phase_angle(geometry: Geometry) -> Array:
    """Sun-satellite-observer angle (rad) at each step."""
    c = _dot(geometry.s, geometry.o)
    sn = safe_sqrt(jnp.sum(jnp.square(jnp.cross(geometry.s, geometry.o)), -1))
    return jnp.arctan2(sn, c)


def magnitude(flux: Array, sun_magnitude: float = SUN_MAGNITUDE_V) -> Array:
    """Apparent magnitude of an irradiance given in units of the solar irradiance at 1 AU (inf where 0)."""
    return sun_magnitude - 2.5 * jnp.log10(flux)
