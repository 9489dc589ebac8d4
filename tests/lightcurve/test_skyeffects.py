"""Every sky gap effect written as an observe config reruns in ``brdfjax observe`` to the fit's magnitudes (the
search they enter is tested in tests/diagnose/test_diagnose_search.py)."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[2]
CSV = ROOT / "tests/data/satellites/observations/slingshot_v2mini.csv"

CONFIG = """
[photometry]
convention = "lumos"
[attitude]
normals = "lumos"
[[observations]]
name = "s"
path = "{csv}"
format = "slingshot"
earth_radius_m = 6378000.0
every = 32
[bands]
draws = 0
[facets.chassis]
area_m2 = 12.0
normal = [0.0, 0.0, -1.0]
model = "chassis"
[facets.side]
area_m2 = 3.0
normal = [0.0, 0.7071, -0.7071]
model = "side"
[facets.array]
area_m2 = 5.0
normal = [0.0, 1.0, 0.0]
x_axis = [1.0, 0.0, 0.0]
tracking = true
model = "array"
[models.chassis]
phong = {{ kd = 0.05, ks = 0.4, exponent = 8.0 }}
[models.side]
phong = {{ kd = 0.1, ks = 0.5, exponent = 300.0 }}
[models.array]
phong = {{ kd = 0.02, ks = 0.3, exponent = 20.0 }}
"""

VALUES = {
    "earthshine": {"es.albedo": 0.45},
    "solar_disk": {"disk.on": 1.0},
    "missing_facet": {"miss.arho": 1.2, "miss.tilt": 2.0, "miss.az": 0.7},
    "offset.array": {"yaw.array": 0.2},
    "offset.side": {"cant.side": -0.15},
    "wide_lobe.chassis": {"wide.chassis.k": 0.4, "wide.chassis.w": 0.3},
    "out_of_plane.side": {"oop.side.k": 0.5, "oop.side.delta": 0.25},
    "diffraction.chassis": {"diff.chassis.k": 0.6, "diff.chassis.s": 0.15},
}


def test_every_effect_reruns_in_observe(tmp_path):
    from brdfjax.io.observations import read_observations
    from brdfjax.lightcurve.config import build_models
    from brdfjax.lightcurve.observe_config import _facet_specs, load_observe_config, predict_all
    from brdfjax.lightcurve.skyfit import SkyFit, SkyProblem, sky_data, write_observe_config
    from brdfjax.lightcurve.skygap import SkyGapProblem, add_effects
    from brdfjax.lightcurve.skygap_config import diagnosed_sections

    src = tmp_path / "base.toml"
    src.write_text(CONFIG.format(csv=CSV))
    cfg = load_observe_config(src)
    built = build_models(cfg, 550e-9)
    facets = _facet_specs(cfg)
    obs = read_observations(CSV, "slingshot")
    obs = obs.take(np.arange(0, len(obs), 32))
    d = sky_data("s", obs, convention="lumos", earth_radius=6378000.0)
    P = SkyProblem.build(d, facets, {f.families[0]: built[f.families[0]].model for f in facets}, normals="lumos")
    cands = add_effects(P, earthshine_grid=(8, 16), disk_rings=3, limb_darkening=0.6)
    gp = SkyGapProblem(P, cands)
    base = P.predict(P.u0())
    # every effect changes some row by far more than the 1e-6 mag checked below (the check is not vacuous; the
    # disk changes a 3-deg Phong lobe by 3e-4 mag) ...
    for name, vals in VALUES.items():
        v = P.u0()
        for k, x in vals.items():
            v[P.index(k)] = P.params[P.index(k)].to_u(x)
        assert np.max(np.abs(P.predict(v) - base)) > (1e-4 if name == "solar_disk" else 0.01), name
    # ... and the written config reproduces them: all but earthshine together, and earthshine with fitted areas
    # (the candidate's earthshine is computed once with the configured facet orientations and models)
    for names in ([n for n in VALUES if n != "earthshine"], ["earthshine"]):
        u = P.u0()
        u[P.index("area.chassis")] = P.params[P.index("area.chassis")].to_u(9.0)
        for n in names:
            for k, v in VALUES[n].items():
                u[P.index(k)] = P.params[P.index(k)].to_u(v)
        fit = SkyFit(P, u, gp.mask(tuple(names)), P.m2ll(u), len(d))
        sections = diagnosed_sections(fit, gp, tuple(names), cfg)
        if "solar_disk" in names:
            assert sections["sun"]["disk"] == "rings" and set(sections["effects"]) == {
                "missing_facet", "wide_lobe", "out_of_plane", "diffraction"}
        else:
            assert sections["earthshine"]["albedo"] == pytest.approx(0.45) and sections["sun"]["disk"] == "point"
        out = write_observe_config(fit, src, tmp_path / "model.toml", sections=sections, effects_written=True)
        pred = predict_all(load_observe_config(out))[0]
        assert np.max(np.abs(pred.mag - fit.predict())) < 1e-6, names
    with pytest.raises(Exception, match="no observe-config form"):
        write_observe_config(fit, src, tmp_path / "bad.toml")
