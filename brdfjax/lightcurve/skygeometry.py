"""Satellite, Sun and observer from observed rows, without a TLE (NumPy, float64).

Frames and signs (docs/guides/sky.md has the figures):

- **ECEF**: Earth-fixed, metres, x to (lat 0, lon 0), z to the north pole.
  WGS84 ellipsoid (a = 6378137 m, f = 1/298.257223563).
  :func:`geodetic_to_ecef` / :func:`ecef_to_geodetic` convert geodetic
  latitude, longitude (east positive) and height above the ellipsoid.
- **Topocentric ENU** at the observer: east, north, up, ``up`` the ellipsoid
  normal (geodetic vertical).  Altitude is the angle above the plane normal
  to ``up``; azimuth is measured from north through east (0 = N, 90 = E).
  The unit vector to (alt, az) is ``cos(alt) sin(az) E + cos(alt) cos(az) N
  + sin(alt) U``.
- **Absolute rows** (time, site, alt/az): the satellite is at
  ``r_obs + range u`` with the observed range; with a height instead, the
  range is solved so that the point's geodetic height equals it (Newton on
  the range, 1e-4 m).  The Sun is the built-in ephemeris
  (:func:`~brdfjax.lightcurve.ephemeris.sun_position_teme`, 0.01 deg) turned
  to ECEF by the Greenwich mean sidereal time, at its true distance; the
  direction satellite -> Sun includes the parallax.
- **Relative rows** (Sun altitude, satellite altitude, Sun-minus-satellite
  azimuth, satellite height; no time, no site): a local frame on a *sphere*
  of radius ``earth_radius`` (default WGS84 equatorial; 6378000 m to match
  lumos-sat): the observer at ``(0, 0, R)``, x east, y north, z up; the
  satellite at azimuth 0 (north) and the Sun at azimuth ``az_diff`` (east
  of the satellite for positive values), the range solved on the sphere
  (``|r_obs + rho u| = R + h``).  The Sun is at infinity along the observed
  direction (lumos-sat's convention: the same direction from the satellite
  as from the observer) and at 1 AU.
- **Yaw reference** (:data:`YAW_LAWS`): the engine's nadir attitude puts the
  body z axis to the Earth's centre (``-r_hat``) and the body x axis along
  the component of a reference direction ``v`` normal to it.  ``"sun_yaw"``
  takes ``v = r_hat x s``: body +y then points to the Sun's azimuth at the
  satellite and the Sun lies in the body y-z plane (lumos-sat's brightness
  frame, see :mod:`brdfjax.lightcurve.attitude`); ``"north"`` takes ``v`` =
  the local north at the satellite (absolute rows only).

- **TLE rows** (time and site, no alt/az): :func:`positions_from_tle`
  propagates a TLE with SGP4 to each row's time (TEME), turns it to ECEF by
  the same GMST rotation and fills the row's altitude, azimuth and range;
  the rows are then absolute rows.  A row further than ``max_age_days``
  from the TLE's epoch is refused (SGP4's error grows by kilometres a day).

Checks: rows with the satellite at or below the horizon, or with its centre
in the Earth's shadow (a ray from the satellite to the Sun's centre hits the
sphere of ``earth_radius``; a penumbral row counts as lit), are dropped and
counted; when none is left, :class:`SkyGeometryError` names the file.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ..io.observations import ObservationError, Observations
from .engine import Geometry
from .ephemeris import AU_M, EARTH_RADIUS_M, TLEError, gmst, julian_date, parse_tle, propagate, sun_position_teme

__all__ = ["YAW_LAWS", "SkyGeometryError", "SkyGeometry", "geodetic_to_ecef", "ecef_to_geodetic", "enu_basis",
           "altaz_unit", "satellite_position", "sun_ecef", "sky_geometry", "positions_from_tle",
           "LUMOS_EARTH_RADIUS_M"]

_F = 1.0 / 298.257223563
_E2 = _F * (2 - _F)
#: lumos-sat's Earth radius (m): its relative geometry uses a sphere of this radius.
LUMOS_EARTH_RADIUS_M = 6378000.0
YAW_LAWS = ("sun_yaw", "north")


class SkyGeometryError(ObservationError):
    """Observations whose geometry cannot be used (none above the horizon and sunlit, a law that needs what is missing)."""


def geodetic_to_ecef(lat_deg, lon_deg, height_m) -> np.ndarray:
    """WGS84 geodetic (deg, deg east, m) -> ECEF (m), shape (..., 3)."""
    lat, lon = np.deg2rad(np.asarray(lat_deg, float)), np.deg2rad(np.asarray(lon_deg, float))
    h = np.asarray(height_m, float)
    N = EARTH_RADIUS_M / np.sqrt(1 - _E2 * np.sin(lat) ** 2)
    return np.stack([(N + h) * np.cos(lat) * np.cos(lon), (N + h) * np.cos(lat) * np.sin(lon),
                     (N * (1 - _E2) + h) * np.sin(lat)], -1)


def ecef_to_geodetic(xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (m) -> WGS84 geodetic latitude (deg), longitude (deg east), height (m); Bowring's method, 3 iterations
    (sub-millimetre from the ground to GEO)."""
    xyz = np.asarray(xyz, float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    a, b = EARTH_RADIUS_M, EARTH_RADIUS_M * (1 - _F)
    ep2 = (a * a - b * b) / (b * b)
    beta = np.arctan2(a * z, b * p)
    for _ in range(3):
        lat = np.arctan2(z + ep2 * b * np.sin(beta) ** 3, p - _E2 * a * np.cos(beta) ** 3)
        beta = np.arctan2((1 - _F) * np.sin(lat), np.cos(lat))
    N = a / np.sqrt(1 - _E2 * np.sin(lat) ** 2)
    # height along the normal: stable at every latitude
    h = p * np.cos(lat) + z * np.sin(lat) - a * a / N
    return np.rad2deg(lat), np.rad2deg(lon), h


def enu_basis(lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """East, north, up unit vectors (ECEF components, (..., 3)) at geodetic (lat, lon)."""
    lat, lon = np.deg2rad(np.asarray(lat_deg, float)), np.deg2rad(np.asarray(lon_deg, float))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    e = np.stack([-so, co, np.zeros_like(so)], -1)
    n = np.stack([-sl * co, -sl * so, cl], -1)
    u = np.stack([cl * co, cl * so, sl], -1)
    return e, n, u


def altaz_unit(alt_deg, az_deg, e, n, u) -> np.ndarray:
    """Unit vector to (alt, az) (deg; az from north through east) in the basis ``e, n, u``."""
    alt, az = np.deg2rad(np.asarray(alt_deg, float)), np.deg2rad(np.asarray(az_deg, float))
    return (np.cos(alt) * np.sin(az))[..., None] * e + (np.cos(alt) * np.cos(az))[..., None] * n + np.sin(alt)[..., None] * u


def satellite_position(r_obs, u, range_m=None, height_m=None, iterations: int = 8) -> np.ndarray:
    """ECEF position along the unit line of sight ``u`` from ``r_obs``: at ``range_m``, or where the geodetic height
    is ``height_m`` (Newton on the range from the spherical solution)."""
    r_obs, u = np.asarray(r_obs, float), np.asarray(u, float)
    if range_m is not None:
        return r_obs + np.asarray(range_m, float)[..., None] * u
    h = np.asarray(height_m, float)
    R = np.linalg.norm(r_obs, axis=-1)
    b = np.sum(r_obs * u, -1)
    rho = -b + np.sqrt(b * b - R * R + np.square(R + h))  # on the sphere through the observer
    rho = np.where(np.isfinite(rho), rho, h)
    for _ in range(iterations):
        p = r_obs + rho[..., None] * u
        lat, lon, hh = ecef_to_geodetic(p)
        _, _, up = enu_basis(lat, lon)
        dh = np.sum(up * u, -1)  # d(height)/d(range)
        step = (hh - h) / np.where(np.abs(dh) > 1e-6, dh, 1e-6)
        rho = rho - step
        if np.all(np.abs(step) < 1e-4):
            break
    return r_obs + rho[..., None] * u


def sun_ecef(times) -> np.ndarray:
    """Geocentric Sun position (m) in ECEF at ``datetime64`` UTC times: the built-in ephemeris turned by GMST."""
    jd, fr = julian_date(times)
    r = sun_position_teme(jd, fr)
    g = gmst(jd, fr)
    c, s = np.cos(g), np.sin(g)
    return np.stack([c * r[..., 0] + s * r[..., 1], -s * r[..., 0] + c * r[..., 1], r[..., 2]], -1)


def positions_from_tle(obs: Observations, line1: str, line2: str, *, max_age_days: float = 7.0,
                       where: str = "tle") -> Observations:
    """``obs`` (absolute rows: time and site) with each row's satellite altitude, azimuth (deg) and range (m)
    computed from a TLE (SGP4, TEME -> ECEF by GMST, topocentric ENU at the WGS84 site).

    Raises :class:`~brdfjax.lightcurve.ephemeris.TLEError` (an input error) for a bad TLE, or naming the
    file, line and epoch when a row's time is more than ``max_age_days`` from the TLE's epoch.
    """
    if obs.kind != "absolute" or obs.time is None:
        raise SkyGeometryError(f"{obs.source}: a TLE gives positions only to absolute rows (a UTC time and a site)")
    sat = parse_tle(line1, line2, where=where)
    jd, fr = julian_date(obs.time)
    age = (jd - sat.jdsatepoch) + (fr - sat.jdsatepochF)
    far = np.flatnonzero(np.abs(age) > max_age_days)
    if far.size:
        i = int(far[np.argmax(np.abs(age[far]))])
        epoch = np.datetime64("2000-01-01T12:00:00", "us") + np.timedelta64(
            int(round(((sat.jdsatepoch - 2451545.0) + sat.jdsatepochF) * 86400e6)), "us")
        raise TLEError(f"{obs.source}: line {obs.line[i]}: time {str(obs.time[i])[:19]} is {age[i]:+.1f} days from the "
                       f"TLE's epoch {str(epoch)[:19]} ({where}); {far.size} row(s) are more than {max_age_days:g} days from it: use a "
                       "TLE of the observations' dates (or raise tle_max_age_days)")
    r_teme, _ = propagate(sat, jd, fr, where)
    g = gmst(jd, fr)
    c, s_ = np.cos(g), np.sin(g)
    r_sat = np.stack([c * r_teme[:, 0] + s_ * r_teme[:, 1], -s_ * r_teme[:, 0] + c * r_teme[:, 1], r_teme[:, 2]], -1)
    r_obs = geodetic_to_ecef(obs.lat_deg, obs.lon_deg, obs.height_m)
    e, n, u = enu_basis(obs.lat_deg, obs.lon_deg)
    d = r_sat - r_obs
    rng = np.linalg.norm(d, axis=-1)
    alt = np.rad2deg(np.arcsin(np.clip(np.sum(d * u, -1) / rng, -1, 1)))
    az = np.mod(np.rad2deg(np.arctan2(np.sum(d * e, -1), np.sum(d * n, -1))), 360.0)
    return Observations(**{**obs.__dict__, "alt_deg": alt, "az_deg": az, "range_m": rng})


@dataclass(frozen=True)
class SkyGeometry:
    """Positions of the kept rows (m; ECEF for absolute rows, the local frame for relative rows) and what was dropped.

    ``keep``: the kept rows' indices into the observations; ``dropped``:
    counts by reason; ``distance_factor``: ``(AU / d_sun)^2`` per kept row
    (1 for relative rows).
    """

    r_sat: np.ndarray
    r_sun: np.ndarray  # a point 1 AU from the observer (relative rows) or the ephemeris Sun
    r_obs: np.ndarray
    s: np.ndarray  # unit satellite -> Sun
    keep: np.ndarray
    dropped: dict[str, int]
    earth_radius: float
    yaw_ref: np.ndarray
    distance_factor: np.ndarray

    def engine_geometry(self, dtype=np.float64, sun_distance_factor: bool = True) -> Geometry:
        """The light-curve engine's :class:`~brdfjax.lightcurve.engine.Geometry`; without the distance factor
        (lumos-sat's convention) ``d_sun`` is set to 1 AU."""
        do = self.r_obs - self.r_sat
        d_obs = np.linalg.norm(do, axis=-1)
        r = np.linalg.norm(self.r_sat, axis=-1)
        d_sun = AU_M / np.sqrt(self.distance_factor) if sun_distance_factor else np.full(len(r), AU_M)
        f = [self.s, do / d_obs[:, None], d_sun, d_obs, self.r_sat / r[:, None], self.yaw_ref, r]
        return Geometry(*(jnp.asarray(x, dtype) for x in f))

    def phase_angle_deg(self) -> np.ndarray:
        o = self.r_obs - self.r_sat
        o = o / np.linalg.norm(o, axis=-1, keepdims=True)
        return np.rad2deg(np.arccos(np.clip(np.sum(self.s * o, -1), -1, 1)))

    def sun_elevation_at_satellite_deg(self) -> np.ndarray:
        """The Sun's elevation above the satellite's local horizontal (negative: below it; the angle past the terminator
        of lumos-sat is its negative)."""
        rh = self.r_sat / np.linalg.norm(self.r_sat, axis=-1, keepdims=True)
        return np.rad2deg(np.arcsin(np.clip(np.sum(self.s * rh, -1), -1, 1)))


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _yaw_reference(law: str, r_sat: np.ndarray, s: np.ndarray, frame: str, source: str) -> np.ndarray:
    rh = _unit(r_sat)
    if law == "sun_yaw":
        return _unit(np.cross(rh, s))
    if law == "north":
        if frame != "ecef":
            raise SkyGeometryError(f"{source}: attitude yaw law 'north' needs absolute rows (time and site); "
                                   "relative rows have no north at the satellite: use 'sun_yaw'")
        z = np.array([0.0, 0.0, 1.0])
        return _unit(z - np.sum(rh * z, -1, keepdims=True) * rh)
    raise SkyGeometryError(f"{source}: unknown yaw law '{law}'; known: {', '.join(YAW_LAWS)}")


def _shadowed(r_sat: np.ndarray, s: np.ndarray, R: float) -> np.ndarray:
    b = np.sum(r_sat * s, -1)
    miss2 = np.sum(r_sat * r_sat, -1) - b * b
    return (b < 0) & (miss2 < R * R)


def sky_geometry(obs: Observations, yaw_law: str = "sun_yaw", earth_radius: float | None = None,
                 min_altitude_deg: float = 0.0) -> SkyGeometry:
    """The geometry of every usable row of ``obs`` (see the module docstring); :class:`SkyGeometryError` when none is.

    ``earth_radius``: the sphere of the shadow test and of relative rows
    (default WGS84 equatorial, 6378137 m).
    """
    R = EARTH_RADIUS_M if earth_radius is None else float(earth_radius)
    n = len(obs)
    if obs.kind == "absolute":
        r_obs = geodetic_to_ecef(obs.lat_deg, obs.lon_deg, obs.height_m)
        e, nn, up = enu_basis(obs.lat_deg, obs.lon_deg)
        u = altaz_unit(obs.alt_deg, obs.az_deg, e, nn, up)
        if obs.range_m is not None and np.all(np.isfinite(obs.range_m)):
            r_sat = satellite_position(r_obs, u, range_m=obs.range_m)
        elif obs.range_m is not None:
            r_sat = satellite_position(r_obs, u, range_m=np.where(np.isfinite(obs.range_m), obs.range_m, 1.0))
            missing = ~np.isfinite(obs.range_m)
            if missing.any():
                if not np.all(np.isfinite(obs.sat_height_m[missing])):
                    bad = int(np.flatnonzero(missing & ~np.isfinite(obs.sat_height_m))[0])
                    raise SkyGeometryError(f"{obs.source}: line {obs.line[bad]}: no satellite range or height")
                r_sat[missing] = satellite_position(r_obs[missing], u[missing], height_m=obs.sat_height_m[missing])
        else:
            r_sat = satellite_position(r_obs, u, height_m=obs.sat_height_m)
        r_sun = sun_ecef(obs.time)
        ds = r_sun - r_sat
        s = _unit(ds)
        distance_factor = np.square(AU_M / np.linalg.norm(ds, axis=-1))
        frame = "ecef"
    else:
        alt = np.deg2rad(obs.alt_deg)
        r_obs = np.tile(np.array([0.0, 0.0, R]), (n, 1))
        u = np.stack([np.zeros(n), np.cos(alt), np.sin(alt)], -1)  # azimuth 0: north (+y)
        b = R * np.sin(alt)
        h = obs.sat_height_m
        rho = -b + np.sqrt(b * b + (R + h) ** 2 - R * R)
        r_sat = r_obs + rho[:, None] * u
        sa, az = np.deg2rad(obs.sun_alt_deg), np.deg2rad(obs.az_diff_deg)
        s = np.stack([np.cos(sa) * np.sin(az), np.cos(sa) * np.cos(az), np.sin(sa)], -1)
        r_sun = r_obs + AU_M * s
        distance_factor = np.ones(n)
        frame = "local"
    below = ~(obs.alt_deg > min_altitude_deg)
    shadow = _shadowed(r_sat, s, R) & ~below
    bad_geom = ~np.all(np.isfinite(r_sat), -1) & ~below & ~shadow
    keep = np.flatnonzero(~below & ~shadow & ~bad_geom)
    dropped = {"below_horizon": int(below.sum()), "in_shadow": int(shadow.sum()), "no_position": int(bad_geom.sum())}
    if keep.size == 0:
        raise SkyGeometryError(
            f"{obs.source}: no usable observation: of {n} rows, {dropped['below_horizon']} have the satellite at or "
            f"below {min_altitude_deg:g} deg altitude and {dropped['in_shadow']} have it in the Earth's shadow"
            + (f", {dropped['no_position']} have no position" if dropped["no_position"] else "")
        )
    yaw = _yaw_reference(yaw_law, r_sat[keep], s[keep], frame, obs.source)
    return SkyGeometry(r_sat[keep], r_sun[keep], r_obs[keep], s[keep], keep, dropped, R, yaw, distance_factor[keep])
