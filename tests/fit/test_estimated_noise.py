"""Tables without uncertainties: the log-normal noise is estimated (profiled) the same way by the fit, the
sampler and the diagnosis's information criteria."""

from __future__ import annotations

import math

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.diagnose.context import gap_measures
from brdfjax.fit import TableData, fit
from brdfjax.sample import sample

S_TRUE = 0.15  # sigma of ln BRDF


def _table(sigma_rel=None, seed=3):
    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.15), rho_s=0.6, n=1.5), "d": bj.Lambertian(0.1)})
    ts = np.radians(np.arange(-80.0, 81.0, 4.0))
    ti = np.radians(np.repeat([20.0, 45.0], ts.size))
    ts2 = np.tile(ts, 2)
    dirs = bj.Directions.from_angles(ti, np.zeros_like(ti), np.abs(ts2), np.where(ts2 < 0, 0.0, np.pi))
    f = np.asarray(model(dirs, 632.8e-9))
    d = f * np.exp(S_TRUE * np.random.default_rng(seed).standard_normal(f.size))
    return model, TableData(ti, np.zeros_like(ti), np.abs(ts2), np.where(ts2 < 0, 0.0, np.pi), d,
                            sigma_rel=sigma_rel, name="t")


PARAMS = {"s.alpha": "free", "s.rho_s": "free", "d.rho_d": "free"}


def test_fit_and_sampler_agree_on_widths_with_estimated_noise():
    model, tab = _table()
    res = fit(model, tab, PARAMS)
    assert res.converged and res.sigma_estimated
    assert res.noise["sigma_ln"] == pytest.approx(S_TRUE, rel=0.2)
    assert res.chi2_reduced == pytest.approx(res.n_points / res.dof, rel=1e-6)  # 1 by construction, not a test
    assert res.to_dict()["goodness_of_fit"].startswith("not available")
    post = sample(model, tab, PARAMS, start=res, n_walkers=16, n_steps=300, burn=100, seed=1, figures=False)
    flat = post.flat()
    for i, name in enumerate(post.names):
        ratio = float(np.std(flat[:, i])) / res.sigma(name)
        print(f"{name}: sampler sd / fit sigma = {ratio:.3f}")
        assert 0.8 < ratio < 1.25, (name, ratio)
    assert post.summary["likelihood"]["sigma_estimated"] is True


def test_bic_comes_from_the_profile_likelihood_and_sigma_rel_replaces_the_estimate():
    model, tab = _table()
    res = fit(model, tab, PARAMS)
    n = res.n_points
    rss = res.noise["rss_ln"]
    g = gap_measures(res)
    assert g["sigma_estimated"] and g["chi2"] == pytest.approx(n * math.log(rss / n) + n, rel=1e-9)
    assert g["bic"] == pytest.approx(g["chi2"] + 3 * math.log(n), rel=1e-9)
    # a model with one parameter fewer: its BIC differs by the change of N ln(RSS/N), not of RSS in ln units
    res2 = fit(model, tab, {"s.alpha": "free", "s.rho_s": "free"})
    assert res2.m2ll - res.m2ll == pytest.approx(n * math.log(res2.noise["rss_ln"] / rss), rel=1e-9)
    _, tab_s = _table(sigma_rel=0.05)
    res_s = fit(model, tab_s, PARAMS)
    assert not res_s.sigma_estimated and res_s.m2ll == res_s.chi2
    assert res_s.chi2_reduced == pytest.approx((S_TRUE / 0.05) ** 2, rel=0.3)
