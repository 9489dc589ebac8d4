"""The sky gap diagnosis on small synthetic sets: the withheld effect is named first, a null set stays quiet."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from brdfjax.io.observations import read_observations
from brdfjax.lightcurve.models import lumos_phong
from brdfjax.lightcurve.observe import FacetSpec
from brdfjax.lightcurve.skyfit import SkyProblem, block_groups, group_folds, sky_data
from brdfjax.lightcurve.skygap import add_effects, diagnose_sky, zones

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def data():
    obs = read_observations("tests/data/satellites/observations/slingshot_v2mini.csv", "slingshot")
    obs = obs.take(np.arange(0, len(obs), 8))
    return sky_data("s", obs, convention="lumos", earth_radius=6378000.0)


def _problem(d, effect: dict, seed: int):
    models = {"chassis": lumos_phong(0.05, 0.4, 8.0), "array": lumos_phong(0.02, 0.3, 20.0)}
    facets = [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"], max_theta_i_deg=60.0),
              FacetSpec("array", 5.0, (0, 1.0, 0.0), ["array"], x_axis=(1.0, 0, 0), tracking=True)]
    P = SkyProblem.build(d, facets, models, normals="lumos")
    cands = add_effects(P, kinds=("offset", "wide_lobe", "missing_facet"), earth_radius=6378000.0)
    truth = P.u0()
    for k, v in effect.items():
        truth[P.index(k)] = P.params[P.index(k)].to_u(v)
    noise = 0.15 * np.random.default_rng(seed).standard_normal(len(d))
    P.data = d.with_mag(P.predict(truth) + noise)
    P._fns.clear()
    return P, cands, float(np.sqrt(np.mean(noise**2)))


def test_withheld_wide_lobe_named_first_and_gap_closed(data):
    P, cands, truth_rms = _problem(data, {"wide.chassis.k": 0.4, "wide.chassis.w": np.deg2rad(20.0)}, 1)
    folds = group_folds(block_groups(len(data), 8), 4)
    res = diagnose_sky(P, cands, folds)
    assert res["named"] == "wide_lobe" and res["path"][0]["facet"] == "chassis"
    h = res["heldout"]
    assert h["path_rms"] <= 1.2 * truth_rms < h["base_rms"]
    # the step changes the residuals only where the chassis is lit beyond its measured 60 deg
    before, after = P.fit().predict(), res["_final_fit"].predict()
    zs = [z for z in zones(P, before, after, min_rows=1, top=100) if z["axis"] == "theta_i.chassis"]
    below = sum(z["share"] for z in zs if z["range"][1] <= 60)
    above = sum(z["share"] for z in zs if z["range"][0] >= 60)
    assert below < 0.05 and above > 0.9


def test_null_set_nothing_significant_and_bounds_keep_effects_off(data):
    P, cands, _ = _problem(data, {}, 2)
    res = diagnose_sky(P, cands)
    assert res["path"] == [] and res["named"] is None
    # an amplitude fitted to zero sits on its bound: such candidates are flagged, never on a path
    flagged = [r for r in res["ranking"] if r["on_bound"]]
    assert flagged and all(r["delta_bic"] > -res["threshold"] or r["on_bound"] for r in res["ranking"])
    # the flags are the effect's own (the shared search keeps an effect with flags of its own off the path)
    assert all(any(k in f and "on its bound" in f for f in r["flags"] for k in r["on_bound"]) for r in flagged)
    assert all(not r["flags"] for r in res["ranking"] if not r["on_bound"] and not r["dead"])


def test_solar_disk_as_a_static_choice_matches_the_switch_inside(data):
    # the compiled fits choose the disk by its (fixed) switch before tracing; the lax.cond on the switch (a free
    # or traced switch) gives the same -2 ln L with the disk off and on
    import jax.numpy as jnp

    models = {"chassis": lumos_phong(0.05, 0.4, 8.0)}
    P = SkyProblem.build(data, [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"])], models, normals="lumos")
    add_effects(P, kinds=("solar_disk",), earth_radius=6378000.0)
    u_off = P.u0()
    u_on = u_off.copy()
    u_on[P.index("disk.on")] = P.params[P.index("disk.on")].to_u(1.0)
    assert P.disk_at(u_off) is False and P.disk_at(u_on) is True
    free = P.default_free()
    free[P.index("disk.on")] = True
    assert P.disk_at(u_on, free) is None
    w = jnp.ones(len(P.data))
    cond = jax.jit(lambda u: P._m2ll(u, w, 1.0))
    for u in (u_off, u_on):
        assert P.m2ll(u) == pytest.approx(float(cond(jnp.asarray(u))), rel=1e-10)
    assert np.max(np.abs(P.predict(u_on) - P.predict(u_off))) > 0  # the disk changes something on these rows
