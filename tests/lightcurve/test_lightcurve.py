"""Light curves (brdfjax.lightcurve): closed forms, the solar disk, gradients, lumos-sat, the CLI and bad input."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.cli import main
from brdfjax.lightcurve.config import load_lightcurve_config
from brdfjax.lightcurve.engine import Attitude, Facets, Geometry, Satellite, SunDisk, facet_flux, magnitude
from brdfjax.lightcurve.ephemeris import AU_M, gmst, parse_tle, sun_position_teme
from brdfjax.lightcurve.models import directional_albedo, lumos_phong
from brdfjax.lightcurve.run import build_job

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "configs" / "lightcurve_box_wing.toml"


def _one_step(s, o, r_sat=(0.0, 0.0, 7.0e6), d_obs=1.0e6):
    """Geometry of one time step: Sun along ``s`` at 1 AU from the satellite, observer along ``o`` at ``d_obs``."""
    r = np.array([r_sat], np.float64)
    s, o = np.asarray(s, np.float64), np.asarray(o, np.float64)
    s, o = s / np.linalg.norm(s), o / np.linalg.norm(o)
    return Geometry.from_positions(r, np.array([[7e3, 0, 0]]), r + s * AU_M, r + o * d_obs)


def _plate(model, area=2.0):
    fac = Facets.build(["plate"], [area], [[0.0, 0.0, 1.0]])
    return Satellite(fac, (model,), Attitude.inertial(), (0,))


# --- closed forms --------------------------------------------------------------------------------------


@pytest.mark.parametrize("rings", [0, 8])
def test_lambertian_plate_closed_form(rings):
    ti, ts, rho, area, d = np.deg2rad(35.0), np.deg2rad(62.0), 0.3, 2.0, 1.0e6
    g = _one_step([np.sin(ti), 0, np.cos(ti)], [-np.sin(ts) * np.cos(1.1), np.sin(ts) * np.sin(1.1), np.cos(ts)], d_obs=d)
    disk = SunDisk.rings(rings)
    flux = float(facet_flux(_plate(bj.Model({"d": bj.Lambertian(rho)}), area), g, disk)["flux"][0, 0])
    # the disk-averaged cosine of a uniform disk of angular radius r is cos(theta_i) cos^2(r / 2)
    expected = rho / np.pi * np.cos(ti) * np.cos(ts) * area / d**2 * np.cos(disk.radius / 2) ** 2
    assert flux / expected - 1 == pytest.approx(0.0, abs=1e-6)


def test_lambertian_sphere_phase_function():
    """Facets tiling the lit-and-visible lune of a sphere (Gauss-Legendre) give the diffuse sphere's phase law."""
    alpha, rho, R, d = np.deg2rad(47.0), 0.25, 1.5, 1.0e6
    xb, wb = np.polynomial.legendre.leggauss(16)
    xl, wl = np.polynomial.legendre.leggauss(16)
    b = xb * np.pi / 2
    lo, hi = alpha - np.pi / 2, np.pi / 2
    lon = 0.5 * (hi - lo) * xl + 0.5 * (hi + lo)
    B, L = np.meshgrid(b, lon, indexing="ij")
    W = np.outer(wb * np.pi / 2, wl * 0.5 * (hi - lo))
    normals = np.stack([np.cos(B) * np.cos(L), np.cos(B) * np.sin(L), np.sin(B)], -1).reshape(-1, 3)
    areas = (R**2 * np.cos(B) * W).ravel()
    names = [f"f{i}" for i in range(len(areas))]
    fac = Facets.build(names, areas, normals)
    sat = Satellite(fac, (bj.Model({"d": bj.Lambertian(rho)}),), Attitude.inertial(), (0,) * len(names))
    g = _one_step([1.0, 0, 0], [np.cos(alpha), np.sin(alpha), 0.0], r_sat=(0.0, 0.0, 7e6), d_obs=d)
    flux = float(facet_flux(sat, g, SunDisk.point())["flux"].sum())
    expected = 2 * rho * R**2 / (3 * np.pi * d**2) * (np.sin(alpha) + (np.pi - alpha) * np.cos(alpha))
    assert flux / expected - 1 == pytest.approx(0.0, abs=1e-6)


def test_glint_height_disk_average_vs_analytic_and_point_sun():
    """A mirror-like facet (Beckmann m = 2e-4) in the exact specular geometry: disk-averaged vs analytic."""
    m, rho_s, n, theta = 2e-4, 1.0, 1.5, np.deg2rad(30.0)
    model = bj.Model({"s": bj.Specular(bj.Beckmann(m), rho_s=rho_s, n=n, **bj.SEED_FORM)})
    g = _one_step([np.sin(theta), 0, np.cos(theta)], [-np.sin(theta), 0, np.cos(theta)])
    disk = SunDisk.rings(16)
    flux = float(facet_flux(_plate(model, 1.0), g, disk)["flux"][0, 0])
    point = float(facet_flux(_plate(model, 1.0), g, SunDisk.point())["flux"][0, 0])
    Fs, Fp = bj.fresnel(n, theta)
    omega = 2 * np.pi * (1 - np.cos(disk.radius))
    # narrow lobe inside the disk: (1/Omega) int f cos(theta_i) dw_i = rho_s (F_s + F_p) / (2 Omega)
    analytic = np.cos(theta) * rho_s * float(Fs + Fp) / (2 * omega) / 1e12
    assert flux / analytic - 1 == pytest.approx(0.0, abs=2e-3)
    # the point Sun samples the peak: D(0) / (pi m^2) ... larger by D(0) Omega / (4 cos theta)
    ratio = point / flux
    assert ratio == pytest.approx(omega / (np.pi * m**2) / (4 * np.cos(theta)), rel=2e-3)
    assert ratio > 100


def test_sun_ephemeris_and_gmst():
    # J2000.0: the Sun's apparent longitude 280.37 deg -> RA 281.3 deg, dec -23.03 deg (Astronomical Almanac)
    r = sun_position_teme(np.array([2451545.0]), np.array([0.0]))[0]
    ra, dec = np.rad2deg(np.arctan2(r[1], r[0])) % 360, np.rad2deg(np.arcsin(r[2] / np.linalg.norm(r)))
    assert ra == pytest.approx(281.29, abs=0.02) and dec == pytest.approx(-23.03, abs=0.02)
    assert np.linalg.norm(r) / AU_M == pytest.approx(0.9833, abs=2e-4)
    from sgp4.propagation import gstime  # the library's scalar GMST: the oracle of the vectorised copy

    assert float(gmst(np.array([2461376.5]), np.array([0.3]))[0]) == pytest.approx(gstime(2461376.8), abs=1e-8)


# --- gradients -----------------------------------------------------------------------------------------


def test_gradient_matches_finite_differences():
    """d(loss)/d(BRDF parameters, attitude yaw) of a light-curve loss equals central differences."""
    T = 6
    ang = np.linspace(0.0, 0.3, T)
    r_hat = np.stack([np.cos(ang), np.sin(ang), np.zeros(T)], -1)
    t_hat = np.stack([-np.sin(ang), np.cos(ang), np.zeros(T)], -1)
    r_sat = 6.93e6 * r_hat
    s = -0.3 * r_hat + t_hat + np.array([0.0, 0.0, 0.4])
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    r_obs = 6.37e6 * r_hat - 3e5 * t_hat + np.array([0.0, 0.0, 2e5])
    geo = Geometry.from_positions(r_sat, 7.6e3 * t_hat, r_sat + s * AU_M, r_obs)
    fac = Facets.build(["a", "b"], [1.0, 2.0], [[0.0, 0.0, 1.0], [0.3, 0.2, 1.0]])
    sat = Satellite(fac, (lumos_phong(0.1, 0.4, 30.0), bj.Model({"d": bj.Lambertian(0.2)})), Attitude.nadir(yaw=0.05), (0, 1))
    disk = SunDisk.rings(2)
    target = 6.0

    def loss(st):
        mag = magnitude(facet_flux(st, geo, disk)["flux"].sum(-1))
        return jnp.mean(jnp.square(mag - target))

    assert np.all(np.isfinite(np.asarray(loss(sat))))
    grads = eqx.filter_grad(loss)(sat)
    getters = (
        (lambda st: st.models[0].terms["phong"].rho, 1e-6),
        (lambda st: st.attitude.yaw, 1e-6),
        (lambda st: st.models[1].terms["d"].rho_d, 1e-7),
    )
    for get, h in getters:
        x0 = float(get(sat))
        lp = loss(eqx.tree_at(get, sat, np.asarray(x0 + h, np.float64)))
        lm = loss(eqx.tree_at(get, sat, np.asarray(x0 - h, np.float64)))
        fd = float((lp - lm) / (2 * h))
        g = float(get(grads))
        assert np.isfinite(g) and g != 0.0
        assert g == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_albedo_of_lambertian():
    lam = bj.Model({"d": bj.Lambertian(0.3)})
    assert directional_albedo(lam, 0.5, n_theta=400, n_phi=256) == pytest.approx(0.3, rel=3e-4)


@pytest.mark.slow  # the full 5-million-point grid
def test_albedo_of_seed_cell():
    # seed cell at normal incidence: centre rho_s1 (F_s+F_p)/2 + offset + bars (0.0278 at 550 nm)
    a = directional_albedo(bj.solar_cell(), 0.0, 550e-9)
    Fs, Fp = bj.fresnel(3.6, 0.0)
    assert a > 0.015 * float(Fs + Fp) / 2
    assert a == pytest.approx(0.0278, rel=0.01)


# --- against lumos-sat -----------------------------------------------------------------------------------


def _lumos():
    lumos = pytest.importorskip("lumos")
    try:
        import lumos.calculator as calc  # noqa: F401
    except (ImportError, AttributeError):
        # lumos.calculator imports astropy.coordinates only for its get_sun_alt_az helper; an astropy too old
        # for this numpy fails to import.  The functions compared here are pure NumPy: stand the module in.
        sys.modules.setdefault("astropy", types.ModuleType("astropy"))
        sys.modules["astropy.coordinates"] = types.ModuleType("astropy.coordinates")
        sys.modules.pop("lumos.calculator", None)
        import lumos.calculator as calc  # noqa: F811
    import lumos.brdf.library as lib
    import lumos.geometry as lgeo

    return lumos, calc, lib, lgeo


def test_matches_lumos_sat_lambertian_and_phong(tmp_path):
    """Same satellite, pass and BRDFs (Lambertian bus, Phong array): total flux within 0.01 mag of lumos-sat."""
    _, calc, lib, lgeo = _lumos()
    cfg = load_lightcurve_config(_small_config(tmp_path, **{"start = 2026-12-02T07:15:00Z": "start = 2026-12-02T07:11:00Z",
                                                            "stop = 2026-12-02T07:16:00Z": "stop = 2026-12-02T07:19:00Z",
                                                            "step_s = 10.0": "step_s = 15.0"}))
    job = build_job(cfg)
    kd, ks, nexp = 0.1, 0.3, 20.0
    models = {"cell": lumos_phong(kd, ks, nexp), "bus": bj.Model({"d": bj.Lambertian(0.3)}), "back": bj.Model({"d": bj.Lambertian(0.1)})}
    sat = Satellite(job.facets, tuple(models[n] for n in job.model_names), job.attitude, job.model_of)
    out = facet_flux(sat, job.geometry, SunDisk.point())
    disk_flux = np.asarray(facet_flux(sat, job.geometry, SunDisk.rings(8))["flux"]).sum(-1)
    g = job.geometry
    ours = np.asarray(out["flux"]).sum(-1) * (np.asarray(g.d_sun) / AU_M) ** 2  # lumos: 1 AU irradiance everywhere
    M = np.asarray(job.attitude.matrix(g.r_hat, g.v_hat))
    s_body = np.einsum("tij,ti->tj", M, np.asarray(g.s))
    x, y, n = (np.asarray(a) for a in job.facets.frames(jnp.asarray(s_body)))
    brdfs = {"cell": lib.PHONG(kd, ks, nexp), "bus": lib.LAMBERTIAN(0.3), "back": lib.LAMBERTIAN(0.1)}
    r_obs = job.passes.r_obs
    dm, dm_disk = [], []
    for t in range(len(g)):
        if float(out["sunlit"][t]) < 1.0:
            continue
        z = np.asarray(g.r_hat[t])
        s = np.asarray(g.s[t])
        yb = s - s.dot(z) * z
        yb /= np.linalg.norm(yb)
        xb = np.cross(yb, z)
        frame = np.stack([xb, yb, z])  # rows: lumos's brightness-frame axes in TEME
        a = -np.arcsin(s.dot(z))
        surfaces = []
        for j, name in enumerate(job.facets.names):
            n_teme = M[t] @ n[t, j]
            surfaces.append(lgeo.Surface(float(job.facets.area[j]), frame @ n_teme, brdfs[cfg.satellite.facets[name].model]))
        height = float(g.r[t]) - 6378e3
        horizon = np.arccos(6378e3 / (6378e3 + height))
        if a > horizon:
            continue
        lum = calc.get_intensity_satellite_frame(surfaces, height, a, frame @ r_obs[t], include_sun=True,
                                                 include_earthshine=False) / 1360.0
        if lum == 0:
            continue
        dm.append(-2.5 * np.log10(ours[t] / lum))
        dm_disk.append(-2.5 * np.log10(disk_flux[t] * (float(g.d_sun[t]) / AU_M) ** 2 / lum))
    print(f"lumos-sat vs brdfjax: {len(dm)} steps, max |dm| = {np.max(np.abs(dm)):.2e} mag (point Sun), "
          f"{np.max(np.abs(dm_disk)):.2e} mag (solar disk)")
    assert len(dm) >= 10
    assert np.max(np.abs(dm)) < 0.01 and np.max(np.abs(dm_disk)) < 0.01


# --- CLI, outputs and bad input ------------------------------------------------------------------------------


def _small_config(tmp_path: Path, **replace: str) -> Path:
    text = SHIPPED.read_text()
    text = text.replace("start = 2026-12-02T00:00:00Z", "start = 2026-12-02T07:15:00Z")
    text = text.replace("stop = 2026-12-02T10:00:00Z", "stop = 2026-12-02T07:16:00Z")
    text = text.replace("step_s = 1.0", "step_s = 10.0").replace("disk_rings = 16 ", "disk_rings = 2 ")
    # a fixed albedo instead of the 5-million-point directional-albedo integral (tested on its own above)
    text = text.replace('albedo_of = "cell"', "lambertian_albedo = 0.0278")
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    p = tmp_path / "lc.toml"
    p.write_text(text)
    return p


def test_cli_writes_csv_json_png(tmp_path, capsys):
    cfg = _small_config(tmp_path)
    assert main(["lightcurve", str(cfg), "--out", str(tmp_path / "out")]) == 0
    summary = json.loads((tmp_path / "out" / "lightcurve.json").read_text())
    lines = (tmp_path / "out" / "lightcurve.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert {"time_utc", "phase_deg", "mag_total", "mag_array_front", "theta_i_deg_array_front", "theta_s_deg_bus_nadir",
            "mag_total_no_diffraction", "mag_total_lambertian"} <= set(header)
    assert len(lines) - 1 == summary["n_visible_steps"] == 7
    assert set(summary["comparisons"]) == {"no_diffraction", "lambertian"}
    lam = summary["comparisons"]["lambertian"]
    assert lam["max_abs_diff_mag"] > 0.1 and lam["n_compared"] == 7
    assert (tmp_path / "out" / "lightcurve.png").stat().st_size > 1000
    tot = np.array([float(r.split(",")[header.index("mag_total")]) for r in lines[1:]])
    per = np.array([[float(v) if v else np.inf for v in r.split(",")[header.index("mag_bus_nadir"):header.index("mag_total")]]
                    for r in lines[1:]])
    assert np.allclose(-2.5 * np.log10(np.sum(10 ** (-0.4 * per), 1)), tot, atol=2e-5)  # CSV rounding


@pytest.mark.parametrize(
    "replace, key",
    [
        ({"0  9997": "0  9998"}, "orbit.tle"),
        ({"normal = [0.0, 0.0, 1.0]\nmodel = \"bus\"": "normal = [0.0, 0.0, 0.0]\nmodel = \"bus\""}, "satellite.facets.bus_nadir.normal"),
        ({"[models.bus]\nlambertian_albedo = 0.3": "[models.bus]\npreset = \"solar_cel\""}, "models.bus.preset"),
        ({"model = \"back\"": "model = \"bak\""}, "satellite.facets.array_back.model"),
        ({'disk = "adaptive"': 'disk = "adaptiv"'}, "sun.disk"),
        ({"start = 2026-12-02T07:15:00Z": "start = 2026-12-02T03:00:00Z",
          "stop = 2026-12-02T07:16:00Z": "stop = 2026-12-02T03:30:00Z"}, "time"),
    ],
    ids=["tle_checksum", "zero_normal", "unknown_preset", "unknown_model", "sun_disk", "never_visible"],
)
def test_bad_input_exit_2_names_file_and_key(tmp_path, capsys, replace, key):
    cfg = _small_config(tmp_path, **replace)
    assert main(["lightcurve", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{cfg}: {key}" in err or (f"{cfg}" in err and key in err), err
    assert not (tmp_path / "out" / "lightcurve.json").exists()


def test_tle_checksum_message():
    l1, l2 = load_lightcurve_config(SHIPPED).orbit.tle
    with pytest.raises(ValueError, match="bad TLE checksum"):
        parse_tle(l1[:-1] + "0", l2, where="x.toml: orbit.tle")


# --- posterior bands and the glint map -------------------------------------------------------------------


def _fake_chain(path: Path, names: list[str], center: list[float], spread: list[float], steps: int = 12, walkers: int = 8):
    """A chain.h5 in the layout ``brdfjax sample`` writes (emcee's HDF5 backend + the brdfjax meta group)."""
    import emcee
    import h5py

    rng = np.random.default_rng(1)
    backend = emcee.backends.HDFBackend(str(path), name="mcmc")
    backend.reset(walkers, len(names))
    backend.grow(steps, None)
    for _ in range(steps):
        coords = np.asarray(center) * (1 + np.asarray(spread) * rng.normal(size=(walkers, len(names))))
        state = emcee.State(coords, log_prob=np.zeros(walkers), random_state=np.random.RandomState(0).get_state())
        backend.save_step(state, np.ones(walkers, bool))
    with h5py.File(path, "a") as f:
        f.require_group("brdfjax").attrs["meta"] = json.dumps({"names": names})


def test_posterior_bands(tmp_path):
    _fake_chain(tmp_path / "chain.h5", ["rho_s2", "rho_s3"], [0.7, 300.0], [0.3, 0.3])
    # the seconds around the shipped pass's diffraction glint, where the array's bars light the observer
    cfg = _small_config(tmp_path, **{'[models.cell]\npreset = "solar_cell"':
                                     '[models.cell]\npreset = "solar_cell"\nposterior = "chain.h5"\nposterior_samples = 8',
                                     "start = 2026-12-02T07:15:00Z": "start = 2026-12-02T07:13:38Z",
                                     "stop = 2026-12-02T07:16:00Z": "stop = 2026-12-02T07:13:44Z",
                                     "step_s = 10.0": "step_s = 1.0"})
    assert main(["lightcurve", str(cfg), "--out", str(tmp_path / "out"), "--no-figures"]) == 0
    summary = json.loads((tmp_path / "out" / "lightcurve.json").read_text())
    assert summary["posterior"] == {"model": "cell", "n_samples": 8}
    band = {k: np.array(v, float) for k, v in summary["series"]["mag_band"].items()}
    q = np.stack([band[k] for k in ("q025", "q16", "q50", "q84", "q975")])
    assert np.all(np.diff(q, axis=0) >= -1e-12)
    # the array's offset peak and bars vary by 30 %: where the array matters the band is open
    assert np.max(q[-1] - q[0]) > 0


def test_posterior_with_foreign_parameters_exits_2(tmp_path, capsys):
    _fake_chain(tmp_path / "chain.h5", ["rho_s2", "sigma_x"], [0.7, 1.0], [0.1, 0.1])
    cfg = _small_config(tmp_path, **{'[models.cell]\npreset = "solar_cell"':
                                     '[models.cell]\npreset = "solar_cell"\nposterior = "chain.h5"'})
    assert main(["lightcurve", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "models.cell" in err and "sigma_x" in err and "chain.h5" in err


def test_glint_map_diffraction_widens_the_glints():
    from brdfjax.lightcurve.glintmap import glint_map

    cell = bj.solar_cell()
    nodiff = bj.Model({k: v for k, v in cell.terms.items() if k != "bars"})
    base = bj.Model({"d": bj.Lambertian(0.0278)})
    th = np.deg2rad(30.0)
    kw = {"du": 1e-4, "dv": 2e-4, "half_width_v": 0.1}
    g1, g2 = glint_map(cell, base, th, **kw), glint_map(nodiff, base, th, **kw)
    # without diffraction: the two peaks, each blurred into the Sun's image (an ellipse of area pi r^2 cos theta_i)
    # grown by the lobe's tail (sigma ~ 2.8e-4 rad) where the ~3e4-times-brighter peak stays > 2.5 x the baseline
    r = SunDisk.rings(1).radius
    ellipse = np.pi * r**2 * np.cos(th)
    assert 2 * ellipse < g2.solid_angle_sr < 2 * ellipse * (1 + 6 * 2.8e-4 / r) ** 2
    assert g1.solid_angle_sr > 5 * g2.solid_angle_sr


# --- the adaptive solar disk -------------------------------------------------------------------------------


def _glint_sweep(T=96, theta=np.deg2rad(30.0)):
    """Observer directions sweeping over the mirror direction of a facet (normal +z) and on to the offset peak's."""
    s = np.array([np.sin(theta), 0.0, np.cos(theta)])
    o0 = np.array([-np.sin(theta), 0.0, np.cos(theta)])
    az = 0.3 + np.deg2rad(45.0)  # phi_ref + the offset peak's dphi0
    tilt = np.deg2rad(0.5)
    n2 = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    o_off = 2 * n2.dot(s) * n2 - s
    t = np.linspace(-0.8, 1.8, T)
    o = o0 + t[:, None] * (o_off - o0) + np.deg2rad(0.05) * np.cross(o0, [0.0, 1.0, 0.0])
    o /= np.linalg.norm(o, axis=-1, keepdims=True)
    r = np.tile([[0.0, 0.0, 7e6]], (T, 1))
    return Geometry.from_positions(r, np.tile([[7e3, 0, 0]], (T, 1)), r + s * AU_M, r + o * 1e6)


def _cell_sat(yaw=0.0):
    cell = bj.solar_cell()
    floor = bj.Model({**cell.terms, "floor": bj.Lambertian(0.02)}, cell.aliases)
    fac = Facets.build(["cell", "white"], [1.0, 0.3], [[0, 0, 1.0], [0.2, 0.1, 1.0]], phi_ref=[0.3, 0.0])
    return Satellite(fac, (floor, bj.Model({"d": bj.Lambertian(0.3)})), Attitude.inertial(yaw=yaw), (0, 1))


@pytest.fixture(scope="module")
def sweep():
    """The glint sweep with the adaptive, full (8 rings) and point disks (compiled once for the tests below)."""
    from brdfjax.lightcurve.engine import AdaptiveDisk

    geo, sat, full = _glint_sweep(), _cell_sat(), SunDisk.rings(8)
    disk = AdaptiveDisk(full).plan(sat, geo)
    outs = {k: facet_flux(sat, geo, d) for k, d in (("adaptive", disk), ("full", full), ("point", SunDisk.point()))}
    return geo, sat, full, disk, outs


def test_adaptive_disk_matches_full_disk_through_glints(sweep):
    """A pass over the centre peak, the diffraction streak and the offset peak: adaptive = full disk, point Sun far off."""
    from brdfjax.lightcurve.engine import _units

    geo, sat, full, disk, outs = sweep
    out = outs["adaptive"]
    mags = {k: np.asarray(magnitude(o["flux"].sum(-1))) for k, o in outs.items()}
    dm, dm_point = np.max(np.abs(mags["adaptive"] - mags["full"])), np.max(np.abs(mags["point"] - mags["full"]))
    print(f"adaptive vs full disk: max |dm| = {dm:.1e} mag over {len(geo)} steps; point Sun: {dm_point:.2f} mag")
    assert dm < 0.01 and dm < 1e-6
    assert dm_point > 1.0  # the glints are there
    flagged = dict(zip([f"{m}.{n}" for m, n, _ in _units(sat)], np.asarray(out["disk_flagged"]).tolist()))
    assert flagged["0.center"] > 0 and flagged["0.offset"] > 0 and flagged["0.bars"] > 0
    assert flagged["0.floor"] == 0 and flagged["1.d"] == 0  # Lambertian terms: the cheap rule is exact
    assert int(np.sum(out["disk_overflow"])) == 0
    assert 0 < int(np.sum(out["disk_full"])) < 0.5 * len(geo) * 4


def test_adaptive_disk_without_glints_is_the_cheap_rule():
    """No sharp feature in reach: every pair takes the centre with the rule's mean cosine; the Lambertian plate exact."""
    from brdfjax.lightcurve.engine import AdaptiveDisk

    geo = _glint_sweep(T=24)
    full = SunDisk.rings(8)
    fac = Facets.build(["a", "b"], [1.0, 2.0], [[0, 0, 1.0], [0.5, -0.2, 1.0]])
    sat = Satellite(fac, (lumos_phong(0.1, 0.3, 20.0), bj.Model({"d": bj.Lambertian(0.3)})), Attitude.inertial(), (0, 1))
    disk = AdaptiveDisk(full).plan(sat, geo)
    assert disk.capacity == (0, 0, 0)  # units: lumos_phong's Lambertian and Phong terms, the plate's Lambertian
    out = facet_flux(sat, geo, disk)
    assert int(np.sum(out["disk_full"])) == 0 and int(np.sum(out["disk_overflow"])) == 0
    cheap = np.asarray(facet_flux(sat, geo, SunDisk.point())["flux"]) * float(full.mean_cos())
    np.testing.assert_allclose(np.asarray(out["flux"]), cheap, rtol=1e-13)
    # Lambertian facet: the cheap rule equals the full rule (to rounding)
    np.testing.assert_allclose(np.asarray(out["flux"])[:, 1], np.asarray(facet_flux(sat, geo, full)["flux"])[:, 1], rtol=1e-12)


@pytest.fixture(scope="module")
def light_sweep():
    """The sweep with a light model (a Phong spike and the bars' streak: no complex Fresnel) for overflow and gradients."""
    from brdfjax.lightcurve.engine import AdaptiveDisk

    geo, full = _glint_sweep(T=48), SunDisk.rings(6)
    spike = bj.Model({"spike": bj.Phong(0.5, 2e4), "bars": bj.solar_cell().terms["bars"], "d": bj.Lambertian(0.02)})
    fac = Facets.build(["cell", "white"], [1.0, 0.3], [[0, 0, 1.0], [0.2, 0.1, 1.0]], phi_ref=[0.3, 0.0])
    sat = Satellite(fac, (spike, bj.Model({"d": bj.Lambertian(0.3)})), Attitude.inertial(yaw=1e-3), (0, 1))
    disk = AdaptiveDisk(full, slot_chunk=8).plan(sat, geo)
    return geo, sat, full, disk, {"full": facet_flux(sat, geo, full)}


def test_adaptive_disk_capacity_overflow(light_sweep):
    from brdfjax.lightcurve.engine import AdaptiveDisk, light_curve

    geo, sat, full, planned, outs = light_sweep
    assert min(c for c in planned.capacity if c) > 8
    with pytest.raises(ValueError, match="no capacity; plan it first"):
        facet_flux(sat, geo, AdaptiveDisk(full))
    small = planned.with_capacity([min(c, 8) for c in planned.capacity])
    out = facet_flux(sat, geo, small)
    counts = np.asarray(out["disk_flagged"])
    # every flagged pair beyond a unit's capacity is counted and got the cheap rule
    assert int(np.sum(out["disk_overflow"])) == int(np.sum(np.maximum(counts - 8, 0))) > 0
    ref = np.asarray(outs["full"]["flux"]).sum(-1)
    assert np.max(np.abs(np.asarray(out["flux"]).sum(-1) / ref - 1)) > 0.1
    with pytest.warns(RuntimeWarning, match="exceeded the capacity"):
        again = light_curve(sat, geo, small)  # replans from the counts and reruns
    assert int(np.sum(again["disk_overflow"])) == 0
    np.testing.assert_allclose(np.asarray(again["flux"]).sum(-1), ref, rtol=1e-9)


def test_adaptive_disk_gradients_finite_and_equal_to_full(light_sweep):
    geo, sat, full, disk, _ = light_sweep

    def loss(st, d):
        return jnp.mean(jnp.square(magnitude(facet_flux(st, geo, d)["flux"].sum(-1)) - 3.0))

    ga, gf = eqx.filter_grad(loss)(sat, disk), eqx.filter_grad(loss)(sat, full)
    for get in (lambda s: s.models[0].terms["spike"].rho, lambda s: s.models[0].terms["spike"].k,
                lambda s: s.models[0].terms["bars"].rho, lambda s: s.attitude.yaw):
        a, f = float(get(ga)), float(get(gf))
        assert np.isfinite(a) and a != 0.0
        assert a == pytest.approx(f, rel=1e-6)


def test_adaptive_disk_multi_lobe():
    """A multi_lobe term (spike + halo): one radius per tabulated disk radius, the widest lobe's; adaptive = full disk."""
    from brdfjax.lightcurve.engine import AdaptiveDisk
    from brdfjax.lightcurve.sharp import disk_deltas, term_features

    spike, halo = bj.Beckmann(0.003), bj.Beckmann(0.02)
    ml = bj.MultiLobeSpecular({"spike": bj.Lobe(spike, 0.5), "halo": bj.Lobe(halo, 0.3)}, n=1.5)
    r = SunDisk.rings(8).radius
    (feat,) = term_features(ml, r)
    radii = np.asarray(feat.radius)
    assert radii.shape == disk_deltas(r).shape
    single = [np.asarray(term_features(bj.Specular(d, rho_s=0.5, n=1.5), r)[0].radius) for d in (spike, halo)]
    np.testing.assert_array_equal(radii, np.maximum(*single))
    assert np.all(radii > 0)

    geo, full = _glint_sweep(T=24), SunDisk.rings(8)
    sat = Satellite(Facets.build(["a"], [1.0], [[0, 0, 1.0]]), (bj.Model({"ml": ml, "d": bj.Lambertian(0.02)}),),
                    Attitude.inertial(), (0,))
    disk = AdaptiveDisk(full).plan(sat, geo)
    mags = {k: np.asarray(magnitude(facet_flux(sat, geo, d)["flux"].sum(-1)))
            for k, d in (("adaptive", disk), ("full", full), ("point", SunDisk.point()))}
    assert np.max(np.abs(mags["adaptive"] - mags["full"])) < 1e-6
    assert np.max(np.abs(mags["point"] - mags["full"])) > 0.1  # the spike's glint needs the disk
