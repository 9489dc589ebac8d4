"""One likelihood object shared by fit, sample and diagnose (brdfjax.fit.prepare)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import FitInputError, Likelihood, TableData, fit, prepare
from brdfjax.sample import NUTS, Emcee, SampleError, sample

ROOT = Path(__file__).resolve().parents[2]


def _readme_example() -> str:
    """The README's shared-likelihood example (the block that calls ``prepare``), verbatim."""
    text = (ROOT / "README.md").read_text()
    (block,) = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "prepare(" in b]
    return block


README_EXAMPLE = _readme_example()


def _table(seed: int = 3):
    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.15), rho_s=0.6, n=1.5), "d": bj.Lambertian(0.1)})
    ts = np.radians(np.arange(-80.0, 81.0, 4.0))
    ti = np.radians(np.repeat([20.0, 45.0], ts.size))
    ts2 = np.tile(ts, 2)
    phi_s = np.where(ts2 < 0, 0.0, np.pi)
    f = np.asarray(model(bj.Directions.from_angles(ti, np.zeros_like(ti), np.abs(ts2), phi_s), 632.8e-9))
    d = f * np.exp(0.02 * np.random.default_rng(seed).standard_normal(f.size))
    return model, TableData(ti, np.zeros_like(ti), np.abs(ts2), phi_s, d, sigma_rel=0.02, name="t")


PARAMS = {"s.alpha": "free", "s.rho_s": "free", "d.rho_d": "free"}


def test_readme_example_runs_and_its_three_results_share_one_likelihood():
    ns: dict = {}
    exec(compile(README_EXAMPLE, "README example", "exec"), ns)
    result, post, gap, lik = ns["result"], ns["post"], ns["gap"], ns["lik"]
    assert len([ln for ln in README_EXAMPLE.strip().splitlines()]) <= 15
    assert result.converged
    for name, truth in (("s.alpha", 0.15), ("s.rho_s", 0.6), ("d.rho_d", 0.1)):
        assert abs(result.value(name) - truth) < 3 * result.sigma(name), name
    # the sampler's chain is around the fit, with the fit's widths (the same likelihood)
    flat = post.flat()
    i = post.names.index("s.alpha")
    assert abs(np.mean(flat[:, i]) - result.value("s.alpha")) < result.sigma("s.alpha")
    assert 0.7 < np.std(flat[:, i]) / result.sigma("s.alpha") < 1.4
    # the diagnosis's base fit is the fit above: the same -2 ln L
    assert gap.base_result.m2ll == pytest.approx(result.m2ll, rel=1e-6)
    assert lik.n_points == result.n_points


def test_fit_of_a_likelihood_equals_the_fit_of_its_parts():
    model, tab = _table()
    lik = prepare(model, tab, PARAMS, loss="huber")
    a = fit(lik)
    b = fit(model, tab, PARAMS, loss="huber")
    assert a.m2ll == b.m2ll and all(a.value(n) == b.value(n) for n in PARAMS)


def test_likelihood_options_are_checked_where_they_are_given():
    model, tab = _table()
    with pytest.raises(FitInputError, match="unknown likelihood option 'los'.*did you mean 'loss'"):
        prepare(model, tab, PARAMS, los="huber")
    with pytest.raises(FitInputError, match="solver and its options are given to fit"):
        prepare(model, tab, PARAMS, solver="lm")
    with pytest.raises(FitInputError, match="unknown loss 'hubber'"):
        prepare(model, tab, PARAMS, loss="hubber")
    lik = prepare(model, tab, PARAMS)
    with pytest.raises(FitInputError, match="takes loss from the likelihood"):
        fit(lik, loss="cauchy")
    with pytest.raises(FitInputError, match="takes params from the likelihood"):
        fit(lik, params=PARAMS)
    assert lik.replace(loss="cauchy").loss == "cauchy" and lik.loss == "linear"
    with pytest.raises(FitInputError, match="Likelihood has no field 'los'"):
        lik.replace(los="x")
    assert isinstance(lik.with_params({"s.alpha": "free"}), Likelihood)


def test_sampler_options_live_on_the_sampler_object():
    model, tab = _table()
    lik = prepare(model, tab, PARAMS)
    with pytest.raises(SampleError, match="n_walkers belong on the sampler object"):
        sample(lik, None, sampler=Emcee(n_steps=10), n_walkers=8)
    with pytest.raises(SampleError, match="params and fit_kwargs are the likelihood's"):
        sample(lik, None, PARAMS)
    with pytest.raises(SampleError, match="sampler must be"):
        sample(lik, sampler=object())
    assert NUTS(n_chains=2).name == "nuts" and Emcee().name == "emcee"


def test_old_spelling_with_fit_kwargs_warns():
    model, tab = _table()
    with pytest.warns(DeprecationWarning, match="fit_kwargs=.*deprecated"):
        sample(model, tab, PARAMS, fit_kwargs={"loss": "linear"}, n_walkers=8, n_steps=20, figures=False)
