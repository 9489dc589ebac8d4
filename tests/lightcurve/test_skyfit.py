"""Learning from observations: the sky likelihood, its fits, posterior, joint lab term and grouped cross-validation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from brdfjax.core.geometry import Directions
from brdfjax.io.observations import read_observations
from brdfjax.lightcurve.models import lumos_phong
from brdfjax.lightcurve.observe import FacetSpec, predict_set
from brdfjax.lightcurve.skyfit import (
    LabTable,
    Param,
    SkyProblem,
    block_groups,
    cross_validate,
    group_folds,
    night_groups,
    nuts_posterior,
    sky_data,
)
from brdfjax.runtime.errors import InputError

jax.config.update("jax_enable_x64", True)

DATA = "tests/data/satellites/observations/"


@pytest.fixture(scope="module")
def sling():
    obs = read_observations(DATA + "slingshot_v2mini.csv", "slingshot")
    obs = obs.take(np.arange(0, len(obs), 8))
    return obs, sky_data("s", obs, convention="lumos", earth_radius=6378000.0)


def _problem(d, **kw):
    models = {"chassis": lumos_phong(0.1, 0.5, 10.0), "side": lumos_phong(0.2, 0.3, 5.0)}
    facets = [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"]),
              FacetSpec("side", 3.0, (0, 0.7071, -0.7071), ["side"])]
    return SkyProblem.build(d, facets, models, normals="lumos", **kw), facets, models


def test_forward_matches_the_engine(sling):
    obs, d = sling
    P, facets, models = _problem(d, cant=["side"])
    bm = {k: type("B", (), {"model": v, "draws": None})() for k, v in models.items()}
    ref = predict_set("s", obs, facets, bm, normals="lumos", convention="lumos", earth_radius=6378000.0)
    assert np.max(np.abs(ref.mag - P.predict(P.u0()))) < 1e-9


def test_recovers_cant_area_and_parameter_within_posterior_sigma(sling):
    _, d = sling
    P, _, _ = _problem(d, cant=["side"], model_params={"chassis": ["phong.k"]})
    truth = P.u0()
    true = {"cant.side": np.deg2rad(10.0), "area.side": 4.5, "chassis.phong.k": 14.0}
    for k, v in true.items():
        truth[P.index(k)] = P.params[P.index(k)].to_u(v)
    rng = np.random.default_rng(7)
    P.data = d.with_mag(P.predict(truth) + 0.1 * rng.standard_normal(len(d)))
    P._fns.clear()
    f = P.fit(P.default_free("cant.side", "chassis.phong.k"))
    assert not f.on_bound()
    post = nuts_posterior(f, n_draws=150, n_warmup=150, seed=3)
    assert post["divergent"] < 10
    for k, v in true.items():
        col = post["draws"][:, post["keys"].index(k)]
        assert abs(np.mean(col) - v) < 3 * np.std(col), (k, np.mean(col), np.std(col), v)
        assert np.std(col) < 0.2 * abs(v)


def test_uncertainties_weight_rows_and_scatter_is_profiled(sling):
    _, d = sling
    P, _, _ = _problem(d)
    u = P.u0()
    r = 0.3 * np.random.default_rng(0).standard_normal(len(d))
    P.data = d.with_mag(P.predict(u) + r)
    P._fns.clear()
    n = len(d)
    assert np.isclose(P.m2ll(u), n * np.log(np.sum(r**2) / n) + n, rtol=1e-9)
    err = np.full(n, 0.2)
    P.data = P.data.with_mag(P.data.mag, err)
    P._fns.clear()
    s = P.params[P.index("scatter")].value
    assert np.isclose(P.m2ll(u), np.sum(r**2 / (0.04 + s**2) + np.log(0.04 + s**2)), rtol=1e-9)


def test_joint_lab_term_pulls_towards_the_lab(sling):
    _, d = sling
    P, _, models = _problem(d, model_params={"chassis": ["phong.k"]})
    truth = P.u0()
    truth[P.index("chassis.phong.k")] = P.params[P.index("chassis.phong.k")].to_u(20.0)
    P.data = d.with_mag(P.predict(truth) + 0.05 * np.random.default_rng(2).standard_normal(len(d)))
    # a lab table of the chassis material at k = 10 (the config's value), with 2 % noise
    ti = np.deg2rad(np.repeat([15.0, 35.0, 55.0], 40))
    ts = np.deg2rad(np.tile(np.linspace(-80, 80, 40), 3))
    dirs = Directions.from_angles(jnp.asarray(ti), jnp.zeros_like(jnp.asarray(ti)), jnp.asarray(np.abs(ts)),
                                  jnp.asarray(np.where(ts < 0, np.pi, 0.0)))
    val = np.asarray(models["chassis"](dirs, 550e-9)) * np.exp(0.02 * np.random.default_rng(3).standard_normal(120))
    free = P.default_free("chassis.phong.k")
    sky_only = P.fit(free).values()["chassis.phong.k"]
    P.labs = [LabTable("chassis", dirs, val, weight=1.0)]
    P._fns.clear()
    joint = P.fit(free).values()["chassis.phong.k"]
    off = P.fit(free, joint=0.0).values()["chassis.phong.k"]
    assert abs(sky_only - 20.0) < 1.0 and abs(off - sky_only) < 1e-3
    assert 10.0 <= joint < sky_only - 1.0


def test_folds_hold_out_whole_groups():
    g = np.repeat(np.arange(9), np.arange(1, 10))
    folds = group_folds(g, 3, seed=1)
    assert np.all(np.sum(folds, 0) == 1)
    for f in folds:
        assert not set(g[f]) & set(g[~f])
    assert list(block_groups(10, 3)) == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    with pytest.raises(InputError, match="at least 2 groups"):
        group_folds(np.zeros(5), 3)


def test_nights_of_score_rows():
    obs = read_observations(DATA + "score_v2mini.csv", "score")
    n = night_groups(obs)
    # rows of one night share it: consecutive rows from one site less than an hour apart
    t = obs.time.astype("datetime64[s]").astype(np.int64)
    same = (np.abs(np.diff(t)) < 3600) & (np.diff(obs.lon_deg) == 0)
    assert np.all(np.diff(n)[same] == 0)
    assert len(np.unique(n)) > 20


def test_cross_validation_and_bad_bounds(sling):
    obs, d = sling
    P, _, _ = _problem(d)
    P.data = d.with_mag(P.predict(P.u0()) + 0.1 * np.random.default_rng(5).standard_normal(len(d)))
    cv = cross_validate(P, P.default_free(), group_folds(block_groups(len(d), 6), 3))
    assert cv["n"] == len(d) and 0.08 < cv["rms"] < 0.13
    with pytest.raises(InputError, match="outside its bounds"):
        Param("x", "area", 5.0, 0.1, 1.0, True)
    with pytest.raises(InputError, match="no time and site"):
        night_groups(obs)


def test_fitted_model_written_as_an_observe_config_reruns_to_the_same_numbers(tmp_path):
    from dataclasses import replace

    from brdfjax.lightcurve.config import build_models
    from brdfjax.lightcurve.observe_config import _facet_specs, load_observe_config, predict_all
    from brdfjax.lightcurve.skyfit import write_observe_config

    src = "configs/observe_v2mini_slingshot.toml"
    cfg = load_observe_config(src)
    built = build_models(cfg, 550e-9)
    # each lab facet's ABg fit (the shipped config defines every family fitted to each table)
    abg = {t: f"{t}_abg" for t in ("mirror", "bare_al", "black_c138", "lrb50xl2", "a700")}
    facets = [replace(f, families=[next((abg[t] for t in abg if f.families[0].startswith(t + "_")), f.families[0])])
              for f in _facet_specs(cfg)]
    obs = read_observations(DATA + "slingshot_v2mini.csv", "slingshot")
    obs = obs.take(np.arange(0, len(obs), 16))
    d = sky_data("slingshot", obs, convention="lumos", earth_radius=6378000.0)
    P = SkyProblem.build(d, facets, {f.families[0]: built[f.families[0]].model for f in facets}, normals="lumos",
                         cant=["twist"], model_params={"mirror_abg": ["spec.g"]})
    f = P.fit(P.default_free("cant.twist", "mirror_abg.spec.g"))
    assert abs(f.values()["mirror_abg.spec.g"] - 3.117) > 0.01 and abs(f.values()["cant.twist"]) > 0.01
    out = write_observe_config(f, src, tmp_path / "fitted.toml")
    text = out.read_text()
    assert "cant_deg" in text and "../tests" not in text
    cfg2 = load_observe_config(out)
    cfg2 = cfg2.model_copy(update={"observations": [cfg2.observations[0].model_copy(update={"every": 16})],
                                   "bands": cfg2.bands.model_copy(update={"draws": 0})})
    pred = predict_all(cfg2)[0]
    assert np.max(np.abs(pred.mag - f.predict())) < 1e-9
