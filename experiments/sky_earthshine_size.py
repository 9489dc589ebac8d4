"""How much earthshine changes the predicted magnitudes of the V2 Mini at the real sets' geometry, and a check of
brdfjax's earthshine against lumos-sat's on SCORE rows (tests/lightcurve/test_observe.py checks the Slingshot rows).

For each shipped observe config (the lab fits, configs/observe_v2mini_<set>.toml) the rows are predicted with and
without a Lambertian Earth of albedo 0.3 (32 x 64 cap elements): the magnitude change per row, its quantiles, and
where it is largest (phase angle, the Sun's elevation at the satellite).  The benchmark's three-facet model
(experiments/sky_withheld.py) gets the same figures.  The lumos-sat check: a nadir Lambertian plate (lumos-sat's
PHONG(0.056, 0, 0.194), as in the Slingshot test) on SCORE rows where earthshine is largest, lumos-sat's 200 x 200
Earth mesh against brdfjax's 96 x 192 cap grid, both on lumos-sat's 6,378 km sphere.

    PYTHONPATH=$PWD python experiments/sky_earthshine_size.py

Writes experiments/results/sky_earthshine_size.json.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from brdfjax.io.observations import read_observations  # noqa: E402
from brdfjax.lightcurve.earthshine import earthshine_flux  # noqa: E402
from brdfjax.lightcurve.engine import Attitude, Satellite  # noqa: E402
from brdfjax.lightcurve.models import lumos_phong  # noqa: E402
from brdfjax.lightcurve.observe import FacetSpec, _facets, predict_set  # noqa: E402
from brdfjax.lightcurve.observe_config import load_observe_config, predict_all  # noqa: E402
from brdfjax.lightcurve.skygeometry import enu_basis, geodetic_to_ecef, sky_geometry, sun_ecef  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LUMOS_R = 6378000.0


def quantiles(x) -> dict:
    return {f"p{q}": float(np.percentile(x, q)) for q in (50, 90, 99)} | {"max": float(np.max(x))}


def shipped(which: str) -> dict:
    cfg = load_observe_config(ROOT / f"configs/observe_v2mini_{which}.toml")
    cfg = cfg.model_copy(update={"bands": cfg.bands.model_copy(update={"draws": 0})})
    on = predict_all(cfg.model_copy(update={"earthshine": cfg.earthshine.model_copy(update={"albedo": 0.3})}))[0]
    off = predict_all(cfg.model_copy(update={"earthshine": cfg.earthshine.model_copy(update={"albedo": None})}))[0]
    dm = off.mag - on.mag
    elev = on.geometry.sun_elevation_at_satellite_deg()
    top = np.argsort(-dm)[: max(1, len(dm) // 10)]
    return {"rows": len(dm), "delta_mag": quantiles(dm), "rows_above_0.05_mag": int(np.sum(dm > 0.05)),
            "rows_above_0.1_mag": int(np.sum(dm > 0.1)),
            "top_decile": {"phase_deg_median": float(np.median(on.phase_deg[top])),
                           "sun_elevation_at_satellite_deg_median": float(np.median(elev[top]))},
            "all": {"phase_deg_median": float(np.median(on.phase_deg)),
                    "sun_elevation_at_satellite_deg_median": float(np.median(elev))},
            "corr_with_phase": float(np.corrcoef(dm, on.phase_deg)[0, 1]),
            "corr_with_sun_elevation": float(np.corrcoef(dm, elev)[0, 1])}


def benchmark_model(which: str) -> dict:
    sys.path.insert(0, str(ROOT / "experiments"))
    from sky_withheld import facets_and_models

    facets, models = facets_and_models()
    path = ROOT / "tests/data/satellites/observations" / ("slingshot_v2mini.csv" if which == "slingshot"
                                                          else "score_v2mini.csv")
    obs = read_observations(path, which)
    kw = dict(normals="lumos", convention="lumos" if which == "slingshot" else "physical",
              band_map={"CLEAR": "V"}, earth_radius=LUMOS_R if which == "slingshot" else None)
    bm = {k: types.SimpleNamespace(model=m, draws=None) for k, m in models.items()}
    on = predict_set(which, obs, facets, bm, earthshine_albedo=0.3, **kw)
    off = predict_set(which, obs, facets, bm, **kw)
    dm = off.mag - on.mag
    elev = on.geometry.sun_elevation_at_satellite_deg()
    return {"rows": len(dm), "delta_mag": quantiles(dm), "rows_above_0.05_mag": int(np.sum(dm > 0.05)),
            "rows_above_0.1_mag": int(np.sum(dm > 0.1)),
            "corr_with_phase": float(np.corrcoef(dm, on.phase_deg)[0, 1]),
            "corr_with_sun_elevation": float(np.corrcoef(dm, elev)[0, 1]),
            "delta_mag_by_sun_elevation": {f"[{lo},{hi})": quantiles(dm[(elev >= lo) & (elev < hi)])
                                           for lo, hi in ((-90, -20), (-20, -10), (-10, 0), (0, 90))
                                           if np.any((elev >= lo) & (elev < hi))}}


def lumos_check(n: int = 8) -> dict:
    try:
        import lumos.calculator as calc
    except (ImportError, AttributeError):  # lumos-sat imports astropy only for functions not used here
        sys.modules.setdefault("astropy", types.ModuleType("astropy"))
        sys.modules["astropy.coordinates"] = types.ModuleType("astropy.coordinates")
        sys.modules.pop("lumos.calculator", None)
        import lumos.calculator as calc
    import lumos.brdf.library as lib
    import lumos.conversions  # noqa: F401 -- the calculator reaches it as an attribute of the package
    import lumos.geometry as lgeo

    obs = read_observations(ROOT / "tests/data/satellites/observations/score_v2mini.csv", "score")
    g = sky_geometry(obs, earth_radius=LUMOS_R)
    geo = g.engine_geometry(sun_distance_factor=False)
    plate = [FacetSpec("plate", 1.0, (0, 0, -1.0), ["plate"])]
    sat = Satellite(_facets(plate, "lumos"), (lumos_phong(0.056, 0.0, 0.194),), Attitude.nadir(), (0,))
    ours_all = np.asarray(earthshine_flux(sat, geo, 0.3, n_psi=32, n_chi=64, earth_radius=LUMOS_R))[:, 0]
    pick = np.argsort(-ours_all)[::max(1, len(ours_all) // (4 * n))][:n]  # spread over the brighter rows
    ours = np.asarray(earthshine_flux(sat, geo, 0.3, n_psi=96, n_chi=192, earth_radius=LUMOS_R))[pick, 0]
    theirs = []
    for i in pick:
        k = g.keep[i]
        lat, lon, h = obs.lat_deg[k], obs.lon_deg[k], obs.height_m[k]
        e, nn, u = enu_basis(lat, lon)
        r_obs = geodetic_to_ecef(lat, lon, h)
        sv = sun_ecef(obs.time[k:k + 1])[0] - r_obs
        sun_alt = np.rad2deg(np.arcsin(sv @ u / np.linalg.norm(sv)))
        sun_az = np.rad2deg(np.arctan2(sv @ e, sv @ nn))
        height = np.linalg.norm(g.r_sat[i]) - LUMOS_R
        # lumos-sat's observer frame: the observer on its sphere, the satellite at (alt, az = 0), the Sun at
        # (sun_alt, sun_az - sat_az); its satellite altitude comes from the same sphere
        rel = g.r_sat[i] - g.r_obs[i]
        up = g.r_obs[i] / np.linalg.norm(g.r_obs[i])
        alt = np.rad2deg(np.arcsin(rel @ up / np.linalg.norm(rel)))
        e2 = np.cross([0, 0, 1.0], up)
        e2 /= np.linalg.norm(e2)
        n2 = np.cross(up, e2)
        sat_az = np.rad2deg(np.arctan2(rel @ e2, rel @ n2))
        sun_alt2 = np.rad2deg(np.arcsin(np.clip(g.s[i] @ up, -1, 1)))  # the Sun is at infinity for lumos-sat
        sun_az2 = np.rad2deg(np.arctan2(g.s[i] @ e2, g.s[i] @ n2))
        val = calc.get_intensity_observer_frame([lgeo.Surface(1.0, (0, 0, -1), lib.PHONG(0.056, 0, 0.194))], height,
                                                np.array([alt]), np.array([0.0]), sun_alt2, sun_az2 - sat_az,
                                                include_sun=False, include_earthshine=True, earth_panel_density=200,
                                                earth_brdf=lib.LAMBERTIAN(0.3))
        theirs.append(float(val[0]) / 1360.0)
        del sun_alt, sun_az
    theirs = np.asarray(theirs)
    rel = ours / theirs - 1
    return {"rows": len(pick), "max_relative_difference": float(np.max(np.abs(rel))),
            "relative_differences": rel.tolist()}


def main() -> int:
    out = {"lumos_check_score": lumos_check()}
    print(f"lumos-sat check on SCORE rows: {out['lumos_check_score']}", flush=True)
    out["shipped_lab_fits"] = {w: shipped(w) for w in ("slingshot", "score")}
    out["benchmark_model"] = {w: benchmark_model(w) for w in ("slingshot", "score")}
    for k, v in out["shipped_lab_fits"].items():
        print(f"lab fits, {k}: earthshine changes the magnitude by {v['delta_mag']} mag; rows > 0.05 mag "
              f"{v['rows_above_0.05_mag']} of {v['rows']}")
    for k, v in out["benchmark_model"].items():
        print(f"benchmark model, {k}: {v['delta_mag']}; rows > 0.05 mag {v['rows_above_0.05_mag']}; by Sun elevation "
              f"at the satellite {v['delta_mag_by_sun_elevation']}")
    write_json_atomic(ROOT / "experiments/results/sky_earthshine_size.json", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
