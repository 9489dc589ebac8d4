"""A 0.1-deg-wide lobe sampled every 1 deg: the fit says its width and weight are not determined (with the range
the data allow, which holds the truth) and the diagnosis's angular_sampling says the peak is unresolved."""

from __future__ import annotations

import math

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.diagnose import diagnose
from brdfjax.diagnose.report import markdown_report
from brdfjax.fit import Param, TableData, fit, prepare
from brdfjax.fit.internal import lobe_fwhm

M_TRUE, RHO_TRUE = 0.000526, 0.5  # Beckmann slope width: an in-plane FWHM of 0.10 deg at 30 deg incidence


def _model(m: float) -> bj.Model:
    return bj.Model(terms={"s": bj.Specular(bj.Beckmann(m), rho_s=RHO_TRUE, n=1.5, **bj.SEED_FORM), "d": bj.Lambertian(0.05)})


@pytest.fixture(scope="module")
def table():
    truth = _model(M_TRUE)
    ts = np.radians(np.arange(0.0, 86.0, 1.0))  # the mirror direction (30 deg) is one sample
    ti = np.full(ts.shape, math.radians(30.0))
    dirs = bj.Directions.from_angles(ti, 0 * ti, ts, np.full(ts.shape, math.pi))
    f = np.asarray(truth(dirs, 632.8e-9))
    d = f * np.exp(0.05 * np.random.default_rng(0).standard_normal(f.size))
    return TableData(ti, 0 * ti, ts, np.full(ts.shape, math.pi), d, name="narrow")


PARAMS = {"s.m": Param(0.02, lower=1e-5, upper=1.0), "s.rho_s": "free", "d.rho_d": "free"}


def test_truth_is_a_tenth_of_a_degree_wide():
    fwhm = lobe_fwhm(_model(M_TRUE).terms["s"], math.radians(30.0), 632.8e-9, math.radians(1.0))
    assert math.degrees(fwhm) == pytest.approx(0.10, abs=0.01)


def test_fit_reports_width_and_weight_not_determined_with_a_range_holding_the_truth(table):
    res = fit(_model(0.02), table, PARAMS)
    assert res.converged, res.message
    u = res.undetermined
    assert set(u) == {"s.m", "s.rho_s"}
    lo, hi = u["s.m"]["range"]
    assert lo <= M_TRUE <= hi and u["s.m"]["open_below"] and "the peak is unresolved" in u["s.m"]["reason"]
    assert u["s.m"]["fwhm_deg_range"][0] <= 0.1 <= u["s.m"]["fwhm_deg_range"][1]
    lo_a, hi_a = u["s.rho_s"]["range"]
    assert lo_a <= RHO_TRUE <= hi_a and hi_a / lo_a > 10  # the weight trades off against the width
    doc = res.to_dict()
    assert doc["parameters"]["s.m"]["sigma"] is None and doc["undetermined"]["s.m"]["range"][1] == pytest.approx(hi)
    assert "s.m is NOT determined" in res.summary() or "NOT determined" in res.summary()
    assert res.sigma("d.rho_d") > 0 and math.isfinite(res.sigma("d.rho_d"))  # the rest keeps its covariance


def test_diagnosis_ranks_angular_sampling_and_says_the_peak_is_unresolved(table):
    d = diagnose(prepare(_model(0.02), table, PARAMS, resolution_check=False),
                 effects=["angular_sampling", "offset_normal_peak"], max_steps=1)
    ranked = {c.effect: c for c in d.ranking}
    assert "angular_sampling" in ranked
    c = ranked["angular_sampling"]
    assert "peak unresolved" in c.signature["detail"] and "peak unresolved" in c.note
    scores = {n: (x.signature.get("score") or 0.0) for n, x in ranked.items()}
    assert max(scores, key=scores.get) == "angular_sampling" and scores["angular_sampling"] > 5
    # ranked FIRST by its own detection (its refit, an aperture, gains nothing in chi^2), and it says so
    assert d.ranking[0].effect == "angular_sampling" and d.ranking[0].ranked_by == "detection"
    assert d.ranking[0].delta_bic < 10 and "ranked by its own detection" in c.note and "not in chi^2" in c.note
    assert d.to_dict()["ranking"][0]["ranked_by"] == "detection"
    assert "ranked by its detection: peak unresolved" in d.summary()
    md = markdown_report(d)
    assert "| 1 (detected) | angular_sampling |" in md and "Detected (angular_sampling, ranked first" in md
    assert d.gap["sigma_estimated"] and "sigma ESTIMATED" in d.summary()


M_SPIKE = 0.000826  # a Beckmann spike of in-plane FWHM 0.157 deg at 30 deg incidence, beside a 0.03 halo


def _multi(m_spike: float, m_halo: float = 0.03) -> bj.Model:
    lobes = {"halo": bj.Lobe(bj.Beckmann(m_halo), 0.2), "spike": bj.Lobe(bj.Beckmann(m_spike), RHO_TRUE)}
    return bj.Model(terms={"ml": bj.MultiLobeSpecular(lobes, n=1.5), "d": bj.Lambertian(0.05)})


def test_each_lobe_of_a_multi_lobe_term_is_checked():
    from brdfjax.fit.internal import lobe_parameters, lobe_term

    model = _multi(M_SPIKE)
    assert lobe_parameters(model) == [("ml", "ml.halo.m", "ml.halo.rho_s"), ("ml", "ml.spike.m", "ml.spike.rho_s")]
    spike = lobe_term(model, "ml", "ml.spike.m")
    assert list(spike.lobes) == ["spike"]
    fwhm = lobe_fwhm(spike, math.radians(30.0), 632.8e-9, math.radians(1.0))
    assert math.degrees(fwhm) == pytest.approx(0.157, abs=0.01)
    # the whole term's half maximum would be the spike's too, but a halo's lobe alone is wide
    halo = lobe_fwhm(lobe_term(model, "ml", "ml.halo.m"), math.radians(30.0), 632.8e-9, math.radians(20.0))
    assert math.degrees(halo) > 2.0


def test_multi_lobe_spike_on_a_1deg_table_is_not_determined():
    truth = _multi(M_SPIKE)
    ts = np.radians(np.arange(0.0, 86.0, 1.0))
    ti = np.full(ts.shape, math.radians(30.0))
    dirs = bj.Directions.from_angles(ti, 0 * ti, ts, np.full(ts.shape, math.pi))
    f = np.asarray(truth(dirs, 632.8e-9))
    d = f * np.exp(0.05 * np.random.default_rng(1).standard_normal(f.size))
    table = TableData(ti, 0 * ti, ts, np.full(ts.shape, math.pi), d, name="spike_halo")
    params = {"ml.spike.m": Param(0.02, lower=1e-5, upper=1.0), "ml.spike.rho_s": "free",
              "ml.halo.m": Param(0.05, lower=1e-3, upper=1.0), "ml.halo.rho_s": "free", "d.rho_d": "free"}
    res = fit(_multi(0.02, 0.05), table, params)
    assert res.converged, res.message
    u = res.undetermined
    assert set(u) == {"ml.spike.m", "ml.spike.rho_s"}
    assert "the peak is unresolved" in u["ml.spike.m"]["reason"] and u["ml.spike.m"]["open_below"]
    assert u["ml.spike.m"]["range"][0] <= M_SPIKE <= u["ml.spike.m"]["range"][1]
    assert math.isnan(res.sigma("ml.spike.m")) and "ml.spike.m is NOT determined" in res.summary()
    # the resolved halo keeps its covariance, and its width is found
    assert math.isfinite(res.sigma("ml.halo.m")) and res.value("ml.halo.m") == pytest.approx(0.03, rel=0.05)


def test_aliased_lobe_of_a_preset_is_checked(table):
    """A preset's lobe under its public name (the mirror preset's ``m`` for ``specular.m``) is checked too."""
    from brdfjax.core.presets import mirror
    from brdfjax.fit.internal import lobe_parameters

    model = bj.Model({**mirror(m=0.02, rho_s=RHO_TRUE, n=1.5).terms, "d": bj.Lambertian(0.05)}, mirror().aliases)
    assert lobe_parameters(model) == [("specular", "m", "rho_s")]
    res = fit(model, table, {"m": Param(0.02, lower=1e-5, upper=1.0), "rho_s": "free", "d.rho_d": "free"})
    assert res.converged, res.message
    assert set(res.undetermined) == {"m", "rho_s"} and res.undetermined["m"]["open_below"]
    lo, hi = res.undetermined["m"]["range"]
    assert lo <= M_TRUE <= hi and math.isnan(res.sigma("m"))
