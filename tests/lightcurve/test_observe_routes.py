"""brdfjax observe: observation rows positioned by a TLE, facet cant/yaw in the config, model averaging, bands."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from brdfjax.core.terms import ABg, Model
from brdfjax.io.observations import ObservationError, read_observations
from brdfjax.lightcurve.ephemeris import TLEError, julian_date, parse_tle, pass_geometry, sun_position_teme
from brdfjax.lightcurve.observe import FacetSpec, predict_set
from brdfjax.lightcurve.observe_config import load_observe_config, predict_all
from brdfjax.lightcurve.photometry import BANDS, band
from brdfjax.lightcurve.skygeometry import LUMOS_EARTH_RADIUS_M, positions_from_tle, sky_geometry

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[2]
SLINGSHOT = ROOT / "tests" / "data" / "satellites" / "observations" / "slingshot_v2mini.csv"
# the synthetic TLE of configs/lightcurve_box_wing.toml (epoch 2026-12-01 00:00 UTC)
TLE = ("1 99001U 26001A   26335.00000000  .00000000  00000-0  00000-0 0  9997",
       "2 99001  53.0000 160.0000 0001000  90.0000   0.0000 15.05490646    17")
SITE = (-30.2446, -70.7494, 2663.0)  # the box-wing example's observer (summer in the south: visible passes)


class _Built:
    def __init__(self, model, draws=None):
        self.model, self.draws = model, draws


def _visible_times(n: int = 12) -> tuple[np.ndarray, object]:
    """Times within two days of the epoch when the satellite is > 15 deg up, sunlit, and the site's Sun below -8 deg."""
    t0 = np.datetime64("2026-12-01T00:00:00", "us")
    times = t0 + (np.arange(0, 2 * 86400, 10) * 1e6).astype("timedelta64[us]")
    pg = pass_geometry(parse_tle(*TLE), times, *SITE)
    el, sun_el = np.rad2deg(pg.elevation()), np.rad2deg(pg.sun_elevation())
    s = pg.r_sun - pg.r_sat
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    b = np.sum(pg.r_sat * s, -1)
    lit = ~((b < 0) & (np.sum(pg.r_sat**2, -1) - b * b < 6378137.0**2))
    ok = np.flatnonzero((el > 15) & (sun_el < -8) & lit)
    assert ok.size >= n
    idx = ok[np.linspace(0, ok.size - 1, n).astype(int)]
    return times[idx], pg.take(idx)


def _write_rows(path: Path, times, mags=None) -> Path:
    lines = ["utc,lat,lon,h,mag"]
    for i, t in enumerate(times):
        lines.append(f"{str(t)[:19]}Z,{SITE[0]},{SITE[1]},{SITE[2]},{6.0 + 0.1 * i if mags is None else mags[i]}")
    path.write_text("\n".join(lines) + "\n")
    return path


COLS = {"time": "utc", "lat": "lat", "lon": "lon", "height": "h", "mag": "mag"}


def test_tle_positions_match_sgp4_in_teme(tmp_path):
    """Alt/az/range from a TLE, put back through the alt/az geometry, give SGP4's satellite: its elevation (TEME),
    distance from the Earth's centre and the solar phase angle agree."""
    times, pg = _visible_times()
    f = _write_rows(tmp_path / "rows.csv", times)
    with pytest.raises(ObservationError, match="need the satellite's altitude, the satellite's azimuth"):
        read_observations(f, "absolute", COLS, band="V")
    obs = positions_from_tle(read_observations(f, "absolute", COLS, band="V", positions="tle"), *TLE)
    np.testing.assert_allclose(obs.alt_deg, np.rad2deg(pg.elevation()), atol=1e-7)
    np.testing.assert_allclose(obs.range_m, np.linalg.norm(pg.r_sat - pg.r_obs, axis=-1), rtol=1e-12)
    geo = sky_geometry(obs)
    assert geo.keep.size == len(times)
    np.testing.assert_allclose(np.linalg.norm(geo.r_sat, axis=-1), np.linalg.norm(pg.r_sat, axis=-1), rtol=1e-12)
    jd, fr = julian_date(times)
    sun = sun_position_teme(jd, fr)
    s, o = sun - pg.r_sat, pg.r_obs - pg.r_sat
    phase = np.rad2deg(np.arccos(np.sum(s * o, -1) / np.linalg.norm(s, axis=-1) / np.linalg.norm(o, axis=-1)))
    np.testing.assert_allclose(geo.phase_angle_deg(), phase, atol=1e-6)


def test_tle_far_from_its_epoch_is_refused(tmp_path):
    times, _ = _visible_times(3)
    late = times + np.timedelta64(20, "D")
    f = _write_rows(tmp_path / "late.csv", late)
    obs = read_observations(f, "absolute", COLS, band="V", positions="tle")
    with pytest.raises(TLEError, match=r"late.csv: line \d: time 2026-12-2\dT[0-9:]{8} is \+2\d\.\d days from the "
                                       r"TLE's epoch 2026-12-01T00:00:00 \(tle\); 3 row\(s\) are more than 7 days"):
        positions_from_tle(obs, *TLE)
    assert positions_from_tle(obs, *TLE, max_age_days=30).alt_deg.shape == (3,)
    with pytest.raises(ObservationError, match="only to absolute rows"):
        read_observations(SLINGSHOT, "slingshot", positions="tle")


def _tle_config(tmp_path: Path, rows: Path, extra: str = "", facet: str = "") -> Path:
    p = tmp_path / "tle.toml"
    p.write_text(f'''
[[observations]]
name = "tle_rows"
path = "{rows}"
format = "absolute"
columns = {{ time = "utc", lat = "lat", lon = "lon", height = "h", mag = "mag" }}
band = "V"
tle = ["{TLE[0]}", "{TLE[1]}"]
{extra}
[bands]
draws = 0

[facets.plate]
area_m2 = 5.0
normal = [0.0, 0.0, 1.0]
model = "plate"
{facet}
[models.plate]
terms = {{ spec = {{ kind = "abg", params = {{ A = 0.01, B = 1e-3, g = 2.0 }} }} }}
''')
    return p


def test_observe_config_routes_rows_through_the_tle(tmp_path):
    times, _ = _visible_times(6)
    cfg = load_observe_config(_tle_config(tmp_path, _write_rows(tmp_path / "rows.csv", times)))
    pred = predict_all(cfg)[0]
    assert len(pred.mag) == 6 and np.all(np.isfinite(pred.mag))
    # the same rows with the TLE's alt/az/range written out as columns predict the same magnitudes
    obs = positions_from_tle(read_observations(tmp_path / "rows.csv", "absolute", COLS, band="V", positions="tle"), *TLE)
    lines = ["utc,lat,lon,h,mag,alt,az,rng"] + [
        f"{str(t)[:19]}Z,{SITE[0]},{SITE[1]},{SITE[2]},6.0,{float(a)!r},{float(z)!r},{float(r) / 1e3!r}"
        for t, a, z, r in zip(times, obs.alt_deg, obs.az_deg, obs.range_m)]
    (tmp_path / "full.csv").write_text("\n".join(lines) + "\n")
    text = cfg.source and Path(cfg.source).read_text()
    text = text.replace(str(tmp_path / "rows.csv"), str(tmp_path / "full.csv")).replace(
        'mag = "mag" }', 'mag = "mag", alt = "alt", az = "az", range_km = "rng" }')
    text = text.replace(f'tle = ["{TLE[0]}", "{TLE[1]}"]', "")
    (tmp_path / "full.toml").write_text(text)
    full = predict_all(load_observe_config(tmp_path / "full.toml"))[0]
    np.testing.assert_allclose(pred.mag, full.mag, atol=1e-9)


def test_cli_exit_2_when_the_tle_is_far_from_the_rows(tmp_path):
    times, _ = _visible_times(3)
    rows = _write_rows(tmp_path / "late.csv", times + np.timedelta64(10, "D"))
    r = subprocess.run([sys.executable, "-m", "brdfjax", "observe", str(_tle_config(tmp_path, rows)), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert re.search(r"late.csv: line \d: time 2026-12-1\dT[0-9:]{8} is \+1\d\.\d days from the TLE's epoch", r.stderr)


def test_cli_exit_2_unknown_band_and_missing_time(tmp_path):
    times, _ = _visible_times(3)
    rows = _write_rows(tmp_path / "rows.csv", times)
    cfg = _tle_config(tmp_path, rows)
    cfg.write_text(cfg.read_text().replace('band = "V"', 'band = "Hbeta"'))
    r = subprocess.run([sys.executable, "-m", "brdfjax", "observe", str(cfg), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "rows.csv: line 2: unknown band 'Hbeta'" in r.stderr, r.stderr
    cfg.write_text(cfg.read_text().replace('band = "Hbeta"', 'band = "V"').replace('time = "utc", ', ""))
    r = subprocess.run([sys.executable, "-m", "brdfjax", "observe", str(cfg), "--out", str(tmp_path / "o2")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "rows.csv: absolute observations need a UTC time" in r.stderr, r.stderr


def test_facet_yaw_and_cant_in_the_config(tmp_path):
    """yaw_deg turns a facet about body z, cant_deg tilts its normal about the facet's x axis (both right-handed): the
    same magnitudes as the turned normal written out."""
    times, _ = _visible_times(6)
    rows = _write_rows(tmp_path / "rows.csv", times)
    c, s = float(np.cos(np.deg2rad(30.0))), float(np.sin(np.deg2rad(30.0)))
    base = predict_all(load_observe_config(_tle_config(tmp_path, rows)))[0].mag
    cfg = _tle_config(tmp_path, rows).read_text()

    def run(normal, extra=""):
        p = tmp_path / "f.toml"
        p.write_text(cfg.replace("normal = [0.0, 0.0, 1.0]", f"normal = {normal}\n{extra}"))
        return predict_all(load_observe_config(p))[0].mag

    sn, cn = float(np.sin(np.deg2rad(40.0))), float(np.cos(np.deg2rad(40.0)))
    side = run(f"[{sn!r}, 0.0, {cn!r}]", "yaw_deg = 30.0")
    assert np.sum(np.isfinite(side)) >= 4
    np.testing.assert_allclose(side, run(f"[{sn * c!r}, {sn * s!r}, {cn!r}]"), atol=1e-9)
    assert np.nanmax(np.abs(side - run(f"[{sn!r}, 0.0, {cn!r}]"))) > 0.01
    # cant: right-handed about the facet's x axis (body x for this normal): -20 deg tips (0, 0, 1) toward +y (the Sun's
    # side in the nadir_sun_yaw frame)
    canted = run("[0.0, 0.0, 1.0]", "cant_deg = -20.0")
    assert np.all(np.isfinite(canted)) and np.max(np.abs(canted - base)) > 0.01
    c2, s2 = float(np.cos(np.deg2rad(20.0))), float(np.sin(np.deg2rad(20.0)))
    np.testing.assert_allclose(canted, run(f"[0.0, {s2!r}, {c2!r}]"), atol=1e-9)


def test_model_averaging_weights_the_fluxes_and_the_draws():
    """weights: the prediction is the weighted mean flux of the families; the band draws each with its weight."""
    obs = read_observations(SLINGSHOT, "slingshot").take(np.arange(0, 1584, 60))
    A0 = 9.737e-5
    models = {"a": _Built(Model({"t": ABg(A0, 8.448e-6, 2.686)})), "b": _Built(Model({"t": ABg(3 * A0, 8.448e-6, 2.686)}))}
    kw = dict(normals="lumos", convention="lumos", earth_radius=LUMOS_EARTH_RADIUS_M, earthshine_albedo=0.3)
    pa = predict_set("s", obs, [FacetSpec("p", 10.0, (0, 0, -1), ["a", "b"])], models, **kw)
    pw = predict_set("s", obs, [FacetSpec("p", 10.0, (0, 0, -1), ["a", "b"], weights=(0.25, 0.75))], models,
                     draws=4000, seed=3, **kw)
    # ABg is linear in A: 0.25 F + 0.75 (3 F) = 2.5 F (direct and earthshine alike)
    np.testing.assert_allclose(pw.mag, pa.mag - 2.5 * np.log10(2.5), atol=1e-9)
    n = pw.families_drawn["p"]
    assert n["b"] / 4000 == pytest.approx(0.75, abs=0.03)
    # the band is the mixture of the two (no other uncertainty here): 2.5 % at family b, 97.5 % at family a
    np.testing.assert_allclose(pw.band[:, 4], pa.mag, atol=1e-9)
    np.testing.assert_allclose(pw.band[:, 0], pa.mag - 2.5 * np.log10(3.0), atol=1e-9)
    with pytest.raises(Exception, match="weights: 3 given, expected 2"):
        from brdfjax.lightcurve.observe_config import ObserveFacetConfig

        ObserveFacetConfig(area_m2=1.0, normal=(0, 0, 1), model="a", alternatives=["b"], weights=[1, 1, 1])


def test_band_solar_magnitudes():
    """The Sun's magnitude per band (Willmer 2018; lumos-sat's AB): V -26.76, G -26.90, SDSS g/r/i -26.52/-26.96/-27.05,
    AB (lumos-sat) -27.056; CLEAR and VISUAL as V."""
    want = {"V": -26.76, "G": -26.90, "g": -26.52, "r": -26.96, "i": -27.05, "CLEAR": -26.76, "VISUAL": -26.76}
    for k, v in want.items():
        assert band(k).sun_magnitude == pytest.approx(v, abs=0.005), k
    assert band("AB").sun_magnitude == pytest.approx(-27.056, abs=0.001)
    assert {"V", "AB", "CLEAR"} <= set(BANDS)


def test_sky_fit_recovers_a_facet_yaw():
    """A facet's yaw offset is a parameter of the sky fit (brdfjax.lightcurve.skyfit): simulated magnitudes with the
    side facet turned 15 deg about body z, 0.05 mag noise: the fit finds the yaw within 1 deg."""
    from brdfjax.lightcurve.models import lumos_phong
    from brdfjax.lightcurve.skyfit import SkyProblem, sky_data

    obs = read_observations(SLINGSHOT, "slingshot")
    obs = obs.take(np.arange(0, len(obs), 8))
    d = sky_data("s", obs, convention="lumos", earth_radius=LUMOS_EARTH_RADIUS_M)
    models = {"chassis": lumos_phong(0.1, 0.5, 10.0), "side": lumos_phong(0.2, 0.3, 5.0)}
    facets = [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"]),
              FacetSpec("side", 3.0, (0, 0.7071, -0.7071), ["side"])]
    P = SkyProblem.build(d, facets, models, normals="lumos", yaw=["side"])
    truth = P.u0()
    truth[P.index("yaw.side")] = P.params[P.index("yaw.side")].to_u(np.deg2rad(15.0))
    rng = np.random.default_rng(11)
    P.data = d.with_mag(P.predict(truth) + 0.05 * rng.standard_normal(len(d)))
    P._fns.clear()
    f = P.fit(P.default_free("yaw.side"))
    assert abs(np.rad2deg(f.values()["yaw.side"]) - 15.0) < 1.0
