"""Where the satellite, the Sun and the observer are: TLE orbits, a solar ephemeris, frames (NumPy, float64).

Positions are in metres in the TEME frame of SGP4 (true equator, mean
equinox), the frame ``sgp4`` returns.  This module is host-side NumPy: the
geometry does not depend on the BRDF or the attitude, so it is computed once
and handed to the JAX light-curve code as arrays.

- Orbit: ``sgp4`` (Vallado's SGP4, the reference implementation) from a TLE,
  vectorised with ``Satrec.sgp4_array``.  A TLE line whose checksum does not
  tally is refused (``sgp4.io.verify_checksum``).
- Earth rotation: TEME -> Earth-fixed by the Greenwich mean sidereal time
  (IAU 1982, ``sgp4.propagation.gstime``), which is exactly the rotation
  TEME -> PEF; polar motion (< 0.5 arcsec, ~15 m on the ground) is
  neglected.  UT1 - UTC (< 0.9 s, < 14 arcsec of Earth rotation) is
  neglected.
- Observer: WGS84 geodetic latitude, longitude, height -> Earth-fixed.
- Sun: the Astronomical Almanac's low-precision formulae (accuracy 0.01 deg
  from 1950 to 2050), in the mean equator and equinox of date, taken as
  TEME (the nutation between them, < 20 arcsec, is neglected).  Why not a
  full ephemeris: 0.01 deg = 1.7e-4 rad is 4 % of the Sun's angular radius
  (4.65e-3 rad), over which the BRDF is integrated anyway, and far below the
  attitude knowledge of any satellite (~0.1 deg and worse); astropy's
  built-in ephemeris would add a large dependency for no visible change in a
  light curve.  No file is downloaded at run time.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
from sgp4.api import WGS72, Satrec
from sgp4.io import verify_checksum

from ..runtime.errors import InputError

__all__ = [
    "AU_M",
    "EARTH_RADIUS_M",
    "TLEError",
    "PassGeometry",
    "parse_tle",
    "julian_date",
    "gmst",
    "sun_position_teme",
    "observer_teme",
    "propagate",
    "pass_geometry",
]

#: Astronomical unit (m, IAU 2012).
AU_M = 1.495978707e11
#: WGS84 equatorial radius (m); the shadow and horizon use a sphere of this radius.
EARTH_RADIUS_M = 6378137.0
_WGS84_F = 1.0 / 298.257223563


class TLEError(InputError):
    """A TLE that cannot be used (bad checksum, malformed line, SGP4 error); the message names where."""


def parse_tle(line1: str, line2: str, where: str = "tle") -> Satrec:
    """An SGP4 ``Satrec`` from two TLE lines; checksums verified.  ``where`` names the source in errors."""
    line1, line2 = line1.rstrip(), line2.rstrip()
    for i, line in enumerate((line1, line2), 1):
        if not line.startswith(f"{i} ") or len(line) != 69:
            raise TLEError(f"{where}: line {i} is not a TLE line {i} (69 characters starting '{i} '): {line!r}")
    try:
        verify_checksum(line1, line2)
    except ValueError as e:
        raise TLEError(f"{where}: bad TLE checksum: {e}") from None
    try:
        sat = Satrec.twoline2rv(line1, line2, WGS72)
    except (ValueError, IndexError) as e:
        raise TLEError(f"{where}: the TLE cannot be parsed: {e}") from None
    if sat.error:
        raise TLEError(f"{where}: SGP4 refuses the TLE (error code {sat.error})")
    return sat


def julian_date(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(jd, fr)`` (integer-ish day and fraction, as SGP4 wants) of ``datetime64`` UTC times."""
    t = np.asarray(times, dtype="datetime64[us]")
    epoch = np.datetime64("2000-01-01T12:00:00", "us")  # JD 2451545.0
    days = (t - epoch).astype(np.int64) / 86400e6
    whole = np.floor(days)
    return 2451545.0 + whole, days - whole


def sun_position_teme(jd: np.ndarray, fr: np.ndarray) -> np.ndarray:
    """Geocentric Sun position (m), shape (..., 3): the Astronomical Almanac's low-precision formulae.

    Accuracy 0.01 deg in direction (1950-2050); distance to ~1e-5 AU.
    """
    n = (jd - 2451545.0) + fr
    L = np.deg2rad(280.460 + 0.9856474 * n)
    g = np.deg2rad(357.528 + 0.9856003 * n)
    lam = L + np.deg2rad(1.915) * np.sin(g) + np.deg2rad(0.020) * np.sin(2 * g)
    eps = np.deg2rad(23.439 - 4e-7 * n)
    r = (1.00014 - 0.01671 * np.cos(g) - 0.00014 * np.cos(2 * g)) * AU_M
    return np.stack([r * np.cos(lam), r * np.cos(eps) * np.sin(lam), r * np.sin(eps) * np.sin(lam)], -1)


def _ecef_to_teme(v: np.ndarray, gmst: np.ndarray) -> np.ndarray:
    c, s = np.cos(gmst), np.sin(gmst)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([c * x - s * y, s * x + c * y, np.broadcast_to(z, c.shape)], -1)


def geodetic_to_ecef(lat_deg: float, lon_deg: float, height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Earth-fixed position (m) and the local geodetic up unit vector of a WGS84 site."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    e2 = _WGS84_F * (2 - _WGS84_F)
    N = EARTH_RADIUS_M / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    pos = np.array(
        [(N + height_m) * np.cos(lat) * np.cos(lon), (N + height_m) * np.cos(lat) * np.sin(lon),
         (N * (1 - e2) + height_m) * np.sin(lat)]
    )
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    return pos, up


def gmst(jd: np.ndarray, fr: np.ndarray) -> np.ndarray:
    """Greenwich mean sidereal time (rad), IAU 1982: ``sgp4.propagation.gstime``'s formula, vectorised.

    (sgp4's own function takes one scalar; this is the same polynomial, with the
    day split as ``jd + fr`` for precision; tests check they agree.)
    """
    tut1 = ((np.asarray(jd, np.float64) - 2451545.0) + np.asarray(fr, np.float64)) / 36525.0
    sec = -6.2e-6 * tut1**3 + 0.093104 * tut1**2 + (876600.0 * 3600 + 8640184.812866) * tut1 + 67310.54841
    return np.mod(np.deg2rad(sec / 240.0), 2 * np.pi)


def observer_teme(lat_deg: float, lon_deg: float, height_m: float, jd: np.ndarray, fr: np.ndarray):
    """Observer position (m) and local up vector in TEME at each time, shapes (n, 3)."""
    pos, up = geodetic_to_ecef(lat_deg, lon_deg, height_m)
    g = gmst(jd, fr)
    return _ecef_to_teme(pos, g), _ecef_to_teme(up, g)


def propagate(sat: Satrec, jd: np.ndarray, fr: np.ndarray, where: str = "tle") -> tuple[np.ndarray, np.ndarray]:
    """TEME position (m) and velocity (m/s) at each time, shapes (n, 3)."""
    err, r, v = sat.sgp4_array(np.ascontiguousarray(jd, np.float64), np.ascontiguousarray(fr, np.float64))
    bad = np.flatnonzero(err)
    if bad.size:
        raise TLEError(f"{where}: SGP4 fails at {bad.size} time step(s) (first error code {int(err[bad[0]])}): "
                       "the TLE is too far from its epoch or decayed")
    return r * 1e3, v * 1e3


@dataclass(frozen=True)
class PassGeometry:
    """Positions along a time span, TEME metres, each (n, 3); ``times`` are ``datetime64[us]`` UTC."""

    times: np.ndarray
    r_sat: np.ndarray
    v_sat: np.ndarray
    r_sun: np.ndarray
    r_obs: np.ndarray
    up_obs: np.ndarray

    def __len__(self) -> int:
        return len(self.times)

    def take(self, idx: np.ndarray) -> "PassGeometry":
        return PassGeometry(*(getattr(self, f)[idx] for f in ("times", "r_sat", "v_sat", "r_sun", "r_obs", "up_obs")))

    def elevation(self) -> np.ndarray:
        """Satellite elevation above the observer's geodetic horizon (rad)."""
        d = self.r_sat - self.r_obs
        return np.arcsin(np.clip(np.sum(d * self.up_obs, -1) / np.linalg.norm(d, axis=-1), -1, 1))

    def sun_elevation(self) -> np.ndarray:
        """Sun elevation above the observer's horizon (rad), from the observer (parallax included)."""
        d = self.r_sun - self.r_obs
        return np.arcsin(np.clip(np.sum(d * self.up_obs, -1) / np.linalg.norm(d, axis=-1), -1, 1))

    def seconds(self) -> np.ndarray:
        """Seconds since the first time step."""
        return (self.times - self.times[0]).astype(np.int64) / 1e6


def time_grid(start: dt.datetime, stop: dt.datetime, step_s: float) -> np.ndarray:
    """``datetime64[us]`` UTC times from ``start`` to ``stop`` (inclusive when it falls on the grid)."""
    def utc(t: dt.datetime) -> np.datetime64:
        t = t.astimezone(dt.timezone.utc).replace(tzinfo=None) if t.tzinfo is not None else t
        return np.datetime64(t, "us")

    t0, t1 = utc(start), utc(stop)
    n = int(np.floor((t1 - t0).astype(np.int64) / (step_s * 1e6) + 1e-9)) + 1
    return t0 + (np.arange(n) * step_s * 1e6).astype("timedelta64[us]")


def pass_geometry(sat: Satrec, times: np.ndarray, lat_deg: float, lon_deg: float, height_m: float,
                  where: str = "tle") -> PassGeometry:
    """Satellite, Sun and observer along ``times`` (``datetime64`` UTC)."""
    jd, fr = julian_date(times)
    r, v = propagate(sat, jd, fr, where)
    r_obs, up = observer_teme(lat_deg, lon_deg, height_m, jd, fr)
    return PassGeometry(np.asarray(times, "datetime64[us]"), r, v, sun_position_teme(jd, fr), r_obs, up)

