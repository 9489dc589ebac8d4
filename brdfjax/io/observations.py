"""Ground observations of a satellite's brightness, read from CSV files of documented layouts.

Two kinds of rows:

- **absolute** rows: a UTC time, the observer's WGS84 site (geodetic latitude,
  longitude in degrees east, height above the ellipsoid in metres), the
  satellite's topocentric altitude and azimuth (degrees; azimuth from north
  through east) with its range (km) or its height above the ellipsoid (m),
  a magnitude with its uncertainty and a band.  The SCORE export (IAU CPS
  SatHub) is one such layout (format ``"score"``: SatChecker's altitude,
  azimuth and range columns; ``apparent_magnitude``,
  ``apparent_magnitude_uncertainty``, ``observing_filter``).
- **relative** rows: the geometry relative to the observer, without time or
  site: the Sun's altitude, the satellite's altitude, the azimuth of the Sun
  minus the azimuth of the satellite (degrees), the satellite's height (m), a
  magnitude and a band.  The Slingshot set of Kandula (2025) is one (format
  ``"slingshot"``: ``sun altitude``, ``sat altitude``, ``az diff``,
  ``sat height``, ``measured_ab``, AB magnitudes, no uncertainty column).

A format is a mapping of *roles* to column names (:data:`FORMATS`); a file of
another layout is read with ``format = "absolute"`` or ``"relative"`` and a
``columns`` mapping (role -> column name), which may also override a named
format's columns.  Roles: ``time``, ``lat``, ``lon``, ``height`` (observer),
``alt``, ``az``, ``range_km`` or ``range_m``, ``sat_height`` (m), ``mag``,
``mag_err``, ``band``; relative: ``sun_alt``, ``alt``, ``az_diff``,
``sat_height``, ``mag``, ``mag_err``, ``band``.  Without a band column every
row takes the format's (or the caller's) band; without an uncertainty
column, ``mag_err`` is NaN (unknown).

Every problem raises :class:`ObservationError` (an
:class:`~brdfjax.runtime.errors.InputError`: exit code 2) naming the file,
the line (1 = the header) and the column: a missing time or site column,
text in a numeric column, a time that is not ISO 8601.  Rows with an empty
magnitude are dropped and counted (``dropped``); the geometric checks (below
the horizon, in the Earth's shadow) belong to the geometry
(:mod:`brdfjax.lightcurve.skygeometry`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..runtime.errors import InputError

__all__ = ["FORMATS", "ObservationError", "Observations", "read_observations"]


class ObservationError(InputError):
    """An observation file that cannot be read; the message names the file, line and column."""


#: role -> column name of each named format, and its kind and default band.
FORMATS: dict[str, dict] = {
    "score": {
        "kind": "absolute",
        "band": None,
        "columns": {
            "time": "observation_time_utc", "lat": "observer_latitude_deg", "lon": "observer_longitude_deg",
            "height": "observer_altitude_m", "alt": "alt_deg_satchecker", "az": "az_deg_satchecker",
            "range_km": "range_to_sat_km_satchecker", "mag": "apparent_magnitude",
            "mag_err": "apparent_magnitude_uncertainty", "band": "observing_filter",
            "satellite": "satellite_name", "instrument": "instrument",
        },
    },
    "slingshot": {
        "kind": "relative",
        "band": "AB",
        "columns": {"sun_alt": "sun altitude", "alt": "sat altitude", "az_diff": "az diff", "sat_height": "sat height",
                    "mag": "measured_ab"},
    },
    "absolute": {"kind": "absolute", "band": None, "columns": {}},
    "relative": {"kind": "relative", "band": None, "columns": {}},
}

_NUMERIC = ("lat", "lon", "height", "alt", "az", "range_km", "range_m", "sat_height", "mag", "mag_err", "sun_alt", "az_diff")
_TEXT = ("band", "satellite", "instrument")


@dataclass(frozen=True)
class Observations:
    """Rows of one observation file, arrays over rows (N,); NaN where a file has no such column.

    ``line``: each row's line in the file (1 = the header).  Absolute rows:
    ``time`` (``datetime64[us]`` UTC), ``lat_deg``, ``lon_deg``, ``height_m``,
    ``alt_deg``, ``az_deg``, ``range_m`` and/or ``sat_height_m``.  Relative
    rows: ``sun_alt_deg``, ``alt_deg``, ``az_diff_deg``, ``sat_height_m``.
    """

    source: str
    kind: str
    line: np.ndarray
    mag: np.ndarray
    mag_err: np.ndarray
    band: np.ndarray
    alt_deg: np.ndarray
    sat_height_m: np.ndarray
    time: np.ndarray | None = None
    lat_deg: np.ndarray | None = None
    lon_deg: np.ndarray | None = None
    height_m: np.ndarray | None = None
    az_deg: np.ndarray | None = None
    range_m: np.ndarray | None = None
    sun_alt_deg: np.ndarray | None = None
    az_diff_deg: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.mag.shape[0])

    def take(self, idx) -> "Observations":
        """The rows ``idx`` (an index array or a boolean mask)."""
        def t(a):
            return None if a is None else np.asarray(a)[idx]

        kw = {k: t(getattr(self, k)) for k in ("line", "mag", "mag_err", "band", "alt_deg", "sat_height_m", "time",
                                                "lat_deg", "lon_deg", "height_m", "az_deg", "range_m", "sun_alt_deg",
                                                "az_diff_deg")}
        return Observations(self.source, self.kind, extra={k: v[idx] for k, v in self.extra.items()},
                            dropped=dict(self.dropped), **kw)


def _number(text: str, path: Path, line: int, column: str) -> float:
    t = text.strip()
    if t == "":
        return np.nan
    try:
        return float(t)
    except ValueError:
        raise ObservationError(
            f"{path}: line {line}, column '{column}': '{text}' is not a number"
        ) from None


def _time(text: str, path: Path, line: int, column: str) -> np.datetime64:
    t = text.strip()
    if not t:
        raise ObservationError(f"{path}: line {line}, column '{column}': no time (expected an ISO 8601 UTC time)")
    t = t[:-1] if t.endswith(("Z", "z")) else t.replace("+00:00", "")
    try:
        return np.datetime64(t, "us")
    except ValueError:
        raise ObservationError(
            f"{path}: line {line}, column '{column}': '{text}' is not an ISO 8601 UTC time (e.g. 2024-04-29T10:28:45Z)"
        ) from None


def read_observations(path: str | Path, format: str = "score", columns: dict[str, str] | None = None,
                      band: str | None = None, delimiter: str = ",", positions: str = "observed") -> Observations:
    """Read an observation CSV (see the module docstring for formats, roles and errors).

    ``columns`` maps roles to the file's column names (over the format's);
    ``band`` is the band of rows without a band column (over the format's
    default).  Rows whose magnitude is empty are dropped (counted in
    ``dropped["no_magnitude"]``).  ``positions="tle"``: absolute rows need
    no altitude, azimuth, range or height (a TLE gives them:
    :func:`brdfjax.lightcurve.skygeometry.positions_from_tle`); those
    columns, if mapped, are ignored.
    """
    if positions not in ("observed", "tle"):
        raise ObservationError(f"{path}: positions '{positions}' unknown; known: observed, tle")
    path = Path(path)
    if format not in FORMATS:
        raise ObservationError(f"{path}: unknown observation format '{format}'; known: {', '.join(FORMATS)}")
    spec = FORMATS[format]
    kind = spec["kind"]
    roles = dict(spec["columns"])
    roles.update(columns or {})
    if positions == "tle":
        if kind != "absolute":
            raise ObservationError(f"{path}: a TLE gives positions only to absolute rows (format '{format}' is {kind})")
        for r in ("alt", "az", "range_km", "range_m", "sat_height"):
            roles.pop(r, None)
    default_band = band if band is not None else spec["band"]
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh, delimiter=delimiter))
    except FileNotFoundError:
        raise ObservationError(f"{path}: observation file not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ObservationError(f"{path}: cannot be read as CSV ({type(e).__name__}: {e})") from None
    if not rows:
        raise ObservationError(f"{path}: empty file; expected a header line and observation rows")
    header = [h.strip() for h in rows[0]]
    where = {h: i for i, h in enumerate(header)}

    def col(role: str) -> str | None:
        name = roles.get(role)
        if name is None:
            return None
        if name not in where:
            raise ObservationError(
                f"{path}: no column '{name}' for '{role}' (format '{format}'); the header has: {', '.join(header)}"
            )
        return name

    required = (("time", "lat", "lon", "height", "mag") + (("alt", "az") if positions == "observed" else ())
                if kind == "absolute" else ("sun_alt", "alt", "az_diff", "sat_height", "mag"))
    missing = [r for r in required if roles.get(r) is None]
    if missing:
        what = {"time": "a UTC time", "lat": "the observer's latitude", "lon": "the observer's longitude",
                "height": "the observer's height", "alt": "the satellite's altitude", "az": "the satellite's azimuth",
                "mag": "a magnitude", "sun_alt": "the Sun's altitude", "az_diff": "the Sun-minus-satellite azimuth",
                "sat_height": "the satellite's height"}
        raise ObservationError(
            f"{path}: {kind} observations need {', '.join(what[r] for r in missing)}: no column is mapped to "
            f"{', '.join(repr(r) for r in missing)} (give columns = {{ {missing[0]} = \"<column name>\" }})"
        )
    for r in required:
        col(r)
    if kind == "absolute" and positions == "observed" and roles.get("range_km") is None and roles.get("range_m") is None \
            and roles.get("sat_height") is None:
        raise ObservationError(f"{path}: absolute observations need the satellite's range ('range_km' or 'range_m') "
                               "or height ('sat_height'); none is mapped")
    if default_band is None and roles.get("band") is None:
        raise ObservationError(f"{path}: no band column and no band given (set band = \"V\", \"AB\", ...)")
    body = [(i + 1, r) for i, r in enumerate(rows) if i > 0 and any(x.strip() for x in r)]
    mag_col = col("mag")
    vals: dict[str, list] = {}
    lines, dropped = [], 0
    for line, r in body:
        if len(r) != len(header):
            raise ObservationError(f"{path}: line {line} has {len(r)} fields; the header has {len(header)}")
        m = r[where[mag_col]].strip()
        if m == "":
            dropped += 1
            continue
        lines.append(line)
        for role in roles:
            name = col(role)
            if name is None:
                continue
            text = r[where[name]]
            if role == "time":
                v = _time(text, path, line, name)
            elif role in _NUMERIC:
                v = _number(text, path, line, name)
            else:
                v = text.strip()
            vals.setdefault(role, []).append(v)
    if not lines:
        raise ObservationError(f"{path}: no observation rows (every magnitude in '{mag_col}' is empty)")
    n = len(lines)

    def num(role):
        return np.asarray(vals[role], np.float64) if role in vals else None

    for role in ("lat", "lon", "height") if kind == "absolute" else ():
        a = num(role)
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ObservationError(f"{path}: line {lines[bad[0]]}, column '{roles[role]}': no observer site value")
    bands = np.asarray(vals["band"], object) if "band" in vals else np.full(n, default_band, object)
    if "band" in vals and default_band is not None:
        bands = np.where(bands == "", default_band, bands)
    rng = num("range_m") if "range_m" in vals else (num("range_km") * 1e3 if "range_km" in vals else None)
    err = num("mag_err")
    extra = {k: np.asarray(vals[k], object) for k in ("satellite", "instrument") if k in vals}
    return Observations(
        source=str(path), kind=kind, line=np.asarray(lines), mag=num("mag"),
        mag_err=np.full(n, np.nan) if err is None else err, band=bands,
        alt_deg=num("alt") if "alt" in vals else np.full(n, np.nan),
        sat_height_m=np.full(n, np.nan) if "sat_height" not in vals else num("sat_height"),
        time=np.asarray(vals["time"], "datetime64[us]") if "time" in vals else None,
        lat_deg=num("lat"), lon_deg=num("lon"), height_m=num("height"), az_deg=num("az"), range_m=rng,
        sun_alt_deg=num("sun_alt"), az_diff_deg=num("az_diff"), extra=extra, dropped={"no_magnitude": dropped},
    )
