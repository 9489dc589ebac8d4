"""Systematic errors as nuisance parameters (brdfjax.fit._nuisance) and the NUTS sampler (brdfjax.sample._nuts).

Data: a small Beckmann peak on a Lambertian floor rendered with 2 % log-normal
noise (every 8th pixel of a 97 x 97 region), given the ND stacks of a frame that
came through the instrument and a known OD error of its 1.0 OD filter, so
that the truth of the flux-scaled weight is known; a cheap model keeps the
compile times of the fits and of NUTS short.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.config import ConfigError
from brdfjax.fit import FitInputError, fit, prepare, render_noisy_frames
from brdfjax.fit._nuisance import (
    FrameSystematics,
    NuisanceOptions,
    build_nuisance,
    default_nd_tolerances,
    systematics_from_attrs,
)
from brdfjax.instrument.uncertainty import optical_density_uncertainty
from brdfjax.sample import NUTS, Emcee, SampleError, sample

LN10 = math.log(10.0)
MODEL = bj.Model(
    terms={"specular": bj.Specular(bj.Beckmann(4e-4), rho_s=0.5, n=1.5, k=0.0, **bj.SEED_FORM), "diffuse": bj.Lambertian(0.05)},
    aliases=(("m", "specular.m"), ("rho_s", "specular.rho_s")),
)
SPEC = {"m": 4.2e-4, "rho_s": 0.45}
#: The true OD error of the 1.0 OD filter (in the sample stack only): the data read 10^-0.06 = 0.87 times the truth.
DELTA = 0.06


def _syst(beam: str, sample: str, temporal: float = 0.0101) -> FrameSystematics:
    return FrameSystematics(beam, sample, temporal, 1.8e-4, 0.0)


class _Block:
    def __init__(self, s):
        self.systematics = s


def test_nd_nuisance_design_reproduces_the_seed_budget():
    """Filters shared by the beam and a sample stack cancel; each frame's combined ND prior is Eq 97's number."""
    blocks = [_Block(_syst("4.0+1.0+0.2", "4.0+0.3")), _Block(_syst("4.0+1.0+0.2", "4.0+1.0")), _Block(None)]
    spec = build_nuisance(blocks, ["a", "b", "t"], NuisanceOptions(nonlinearity=False))
    assert spec.names == ("nd[0.2]", "nd[0.3]", "nd[1.0]", "flux[a]", "flux[b]")
    d = dict(zip(spec.names, spec.design.T))
    np.testing.assert_allclose(d["nd[0.2]"], [LN10, LN10, 0.0])  # beam only: in both frames
    np.testing.assert_allclose(d["nd[0.3]"], [-LN10, 0.0, 0.0])  # sample of a only
    np.testing.assert_allclose(d["nd[1.0]"], [LN10, 0.0, 0.0])  # cancels in b (beam and sample share it)
    nd = [i for i, k in enumerate(spec.kinds) if k == "nd"]
    for k, (beam, samp) in enumerate([("4.0+1.0+0.2", "4.0+0.3"), ("4.0+1.0+0.2", "4.0+1.0")]):
        combined = math.sqrt(sum((spec.design[k, j] * spec.prior_sigma[j]) ** 2 for j in nd))
        assert combined == pytest.approx(optical_density_uncertainty(beam, samp), rel=1e-12)
    assert optical_density_uncertainty("4.0+1.0+0.2", "4.0+0.3") == pytest.approx(0.142, abs=5e-4)  # the seed's 14.2 %
    assert spec.prior_sigma[spec.names.index("flux[a]")] == pytest.approx(math.hypot(0.0101, 1.8e-4))
    rect = build_nuisance(blocks, ["a", "b", "t"], NuisanceOptions(nd_tolerance="rectangular", flux=False))
    assert rect.prior_sigma[0] == pytest.approx(0.01 / math.sqrt(3))
    # the response curve's level: from the header, scaled by the residual fraction after a correction
    s = systematics_from_attrs({"nd_beam": "4.0+3.0", "nd_sample": "4.0+1.0", "nonlinearity_curve": "0:-0.0172,1:0.0172",
                                "nonlinearity_corrected": 1, "u_temporal": 0.0101})
    assert s.nonlinearity_level == pytest.approx(0.0172 * 0.14 / 1.74)
    assert systematics_from_attrs({"theta_i": 0.3}) is None


def test_bad_nuisance_input_names_the_key():
    blocks = [_Block(_syst("4.0+3.0", "4.0+1.0"))]
    with pytest.raises(FitInputError, match=r'cfg.toml: nuisance.nd_tolerances."0.5": no frame\'s ND stacks have a 0.5 OD'):
        build_nuisance(blocks, ["a"], NuisanceOptions(nd_tolerances={"0.5": 0.02}), source="cfg.toml")
    with pytest.raises(FitInputError, match=r"the 2.0 OD filter has no tolerance"):
        build_nuisance([_Block(_syst("4.0+2.0", "4.0"))], ["a"], NuisanceOptions())
    from brdfjax.fit.config import parse_fit_config

    base = {"data": {"frames": ["x.exr"]}, "model": {"preset": "solar_cell"}}
    with pytest.raises(ConfigError, match=r'c.toml: nuisance.nd_tolerances: .*"1.0" = -0.1: an OD tolerance must be'):
        parse_fit_config({**base, "nuisance": {"nd_tolerances": {"1.0": -0.1}}}, source="c.toml")
    from brdfjax.sample.config import SampleSection

    with pytest.raises(ConfigError, match=r"c.toml: sample.sampler: unknown sampler 'hmc'; expected 'emcee' or 'nuts'"):
        parse_fit_config({**base, "sample": {"sampler": "hmc"}}, source="c.toml", sections={"sample": SampleSection})


def test_negative_calibration_tolerance_in_a_manifest_names_file_and_key(tmp_path):
    from brdfjax.io.raw import ManifestError, read_manifest

    p = tmp_path / "manifest.toml"
    p.write_text('[beam]\nfile = "b.exr"\nbackground = "bb.exr"\n[[sample]]\nname = "s"\nfile = "s.exr"\nbackground = "sb.exr"\n[calibration.nd_tolerances]\n"1.0" = -0.06\n')
    with pytest.raises(ManifestError, match=r'manifest.toml: calibration.nd_tolerances."1.0": must be a number >= 0'):
        read_manifest(p, check_files=False)


@pytest.fixture(scope="module")
def frames():
    (f,) = render_noisy_frames(MODEL, [20.0], roi=(-48, 48, -48, 48), step=8, noise_rel=0.02, seed=2, floor=0.05)
    # through an instrument whose 1.0 OD sample filter is DELTA thicker than nominal: every pixel reads 10^-DELTA low
    return [dataclasses.replace(f, brdf=np.asarray(f.brdf) * 10 ** -DELTA, systematics=_syst("4.0+3.0", "4.0+1.0", 0.0))]


def test_fit_with_nuisance_parameters_covers_the_truth_and_reports_both_sigmas(frames):
    plain = fit(MODEL, frames, SPEC)
    with_n = fit(MODEL, frames, SPEC, nuisance=NuisanceOptions(nonlinearity=False, flux=False))
    rho = 0.5
    # without the systematics the weight is biased by the OD error and its sigma is the noise's alone
    assert abs(plain.value("rho_s") - rho * 10**-DELTA) < 3 * plain.sigma("rho_s")
    assert abs(plain.value("rho_s") - rho) > 20 * plain.sigma("rho_s")
    # with them: sigma ~ rho x ln(10) x sqrt(0.15^2 + 0.06^2) (Eq 97 for 4.0+3.0 vs 4.0+1.0), the truth inside 2 sigma
    combined = optical_density_uncertainty("4.0+3.0", "4.0+1.0", default_nd_tolerances())
    assert with_n.sigma("rho_s") == pytest.approx(with_n.value("rho_s") * combined, rel=0.05)
    assert abs(with_n.value("rho_s") - rho) < 2 * with_n.sigma("rho_s")
    d = with_n.to_dict()
    assert d["parameters"]["rho_s"]["sigma_conditional"] == pytest.approx(plain.sigma("rho_s"), rel=0.05)
    assert d["parameters"]["m"]["sigma_conditional"] == pytest.approx(d["parameters"]["m"]["sigma"], rel=0.02)
    assert set(d["nuisance"]["parameters"]) == {"nd[1.0]", "nd[3.0]"}
    assert d["nuisance"]["parameters"]["nd[3.0]"]["prior_sigma"] == 0.15
    assert with_n.chi2 == pytest.approx(plain.chi2, rel=0.05)


blackjax = pytest.importorskip("blackjax")


def test_nuts_killed_mid_write_resumes_bit_identically(tmp_path):
    """Fast (one-parameter Lambertian table, 10 warm-up steps): a run stopped after 8 steps, whose file then holds
    the half-written rows a kill between the rows and the step counter leaves, resumes to the chain of an
    uninterrupted run, bit for bit (the slow test below does the same on a frame with nuisance parameters)."""
    import h5py

    model = bj.Model(terms={"diffuse": bj.Lambertian(1.0)}, aliases=(("rho_d", "diffuse.rho_d"),))
    n = 24
    rng = np.random.default_rng(1)
    table = bj.fit.TableData(theta_i=np.full(n, 0.3), phi_i=np.zeros(n), theta_s=np.linspace(0.1, 1.2, n),
                             phi_s=np.full(n, np.pi), brdf=np.exp(0.02 * rng.standard_normal(n)) / np.pi,
                             sigma_rel=np.full(n, 0.02))
    start = {"parameters": {"rho_d": {"value": 1.0, "sigma": 0.004, "unit": "1", "free": True}}}
    kw = dict(start=start, sampler="nuts", n_chains=2, n_warmup=10, seed=7, figures=False)
    full = sample(model, table, {"rho_d": 0.9}, n_steps=30, out_dir=tmp_path / "full", **kw)
    part = sample(model, table, {"rho_d": 0.9}, n_steps=8, out_dir=tmp_path / "part", **kw)
    with h5py.File(tmp_path / "part" / "chain.h5", "a") as f:  # rows 8..11 written, the counter still at 8
        g = f["nuts"]
        assert int(g.attrs["iteration"]) == 8
        for k in ("z", "x", "logdensity", "grad", "log_prob"):
            g[k].resize(12, axis=0)
            g[k][8:] = 1e3
    resumed = sample(model, table, {"rho_d": 0.9}, n_steps=30, out_dir=tmp_path / "part", resume=True, **kw)
    assert full.chain.shape == (30, 2, 1) and resumed.summary["new_steps"] == 22
    assert np.array_equal(resumed.chain[:8], part.chain) and np.array_equal(resumed.chain, full.chain)
    assert np.array_equal(resumed.log_prob, full.log_prob)
    s = resumed.summary
    assert s["sampler"] == "nuts" and s["nuts"]["n_chains"] == 2 and math.isfinite(s["parameters"]["rho_d"]["ess"])
    assert s["nuts"]["rhat"]["rho_d"] is not None and s["parameters"]["rho_d"]["median"] == pytest.approx(1.0, rel=0.02)


# Two NUTS programs (warm-up and steps) compile for about a minute on the loaded 2-core box: slow-gated.
@pytest.mark.slow
def test_nuts_resumes_bit_identically_with_diagnostics(frames, tmp_path):
    opts = NuisanceOptions(nonlinearity=False, flux=False)
    start = fit(MODEL, frames, SPEC, nuisance=opts)
    lik = prepare(MODEL, frames, SPEC, nuisance=opts)
    kw = dict(start=start, seed=7, figures=False)
    full = sample(lik, sampler=NUTS(n_chains=2, n_warmup=40, n_steps=20), out_dir=tmp_path / "full", **kw)
    part = sample(lik, sampler=NUTS(n_chains=2, n_warmup=40, n_steps=8), out_dir=tmp_path / "part", **kw)
    resumed = sample(lik, sampler=NUTS(n_chains=2, n_warmup=40, n_steps=20), out_dir=tmp_path / "part", resume=True, **kw)
    assert full.chain.shape == (20, 2, 4)
    assert np.array_equal(resumed.chain[:8], part.chain) and np.array_equal(resumed.chain, full.chain)
    assert np.array_equal(resumed.log_prob, full.log_prob)
    s = full.summary
    assert s["sampler"] == "nuts" and set(s["nuts"]["rhat"]) == {"m", "rho_s", "nd[1.0]", "nd[3.0]"}
    assert s["nuts"]["divergences"] >= 0 and all(h > 0 for h in s["nuts"]["step_size"])
    p = s["parameters"]["rho_s"]
    assert p["ess"] > 0 and p["sigma_conditional"] < 0.2 * p["sigma_marginal"]
    assert s["nuisance"]["parameters"]["nd[1.0]"]["prior_sigma"] == 0.06
    # an emcee chain file is not a NUTS chain; a sampler that does not exist is named
    import h5py

    (tmp_path / "em").mkdir()
    with h5py.File(tmp_path / "em" / "chain.h5", "w") as f:
        f.create_group("mcmc")
    with pytest.raises(SampleError, match=r"em/chain.h5: not a NUTS chain \(no 'nuts' group; an emcee chain\?"):
        sample(MODEL, frames, SPEC, n_steps=4, out_dir=tmp_path / "em", resume=True, **kw)
    with pytest.raises(SampleError, match=r"unknown sampler 'hmc'; known: 'emcee', 'nuts'"):
        sample(MODEL, frames, SPEC, start=start, sampler="hmc")


def test_samplers_move_the_weights_as_logarithms_from_the_fit_covariance():
    """With nuisance parameters the weights are sampled as log rho (log-Jacobian included) from walkers started
    along the fit's covariance: on a Lambertian frame whose rho_d is scaled by two ND filters the ridge is then
    straight, and a short emcee chain already has the Eq 97 width, ln 10 sqrt(0.15^2 + 0.06^2) = 0.372 in log rho."""
    model = bj.Model(terms={"diffuse": bj.Lambertian(1.0)}, aliases=(("rho_d", "diffuse.rho_d"),))
    (f,) = render_noisy_frames(model, [20.0], roi=(-48, 48, -48, 48), step=16, noise_rel=0.02, seed=2, floor=0.05)
    f = dataclasses.replace(f, brdf=np.asarray(f.brdf) * 10**-DELTA, systematics=_syst("4.0+3.0", "4.0+1.0", 0.0))
    opts = NuisanceOptions(nonlinearity=False, flux=False)
    start = fit(model, [f], {"rho_d": 0.9}, nuisance=opts)
    lik = prepare(model, [f], {"rho_d": 0.9}, nuisance=opts)
    res = sample(lik, start=start, sampler=Emcee(n_walkers=16, n_steps=500), seed=3, figures=False)
    post = res.posterior
    assert res.summary["sampled_as_log"] == ["rho_d"] and res.summary["start"].startswith("fit covariance")
    x = res.chain[-1]
    y = post.to_sampler(x)
    np.testing.assert_allclose(post.from_sampler(y), x, rtol=1e-15)
    # the sampler's density is the posterior of x plus the log-Jacobian of the logged entry
    np.testing.assert_allclose(post.sampler_log_prob(y), post(x) + y[:, 0], rtol=1e-12)
    np.testing.assert_allclose(res.log_prob[-1], post(x), rtol=1e-12)
    width = float(np.std(np.log(res.flat()[:, 0])))
    assert width == pytest.approx(LN10 * math.hypot(0.15, 0.06), rel=0.2)
    assert res.summary["tau_max"] < 100  # linear rho from a diagonal ball: tau about 250 on this posterior


def test_instrument_nuisance_parameters_footprint_width_and_misalignment():
    """Footprint width (log-scale) and misalignment (Eq 105 offsets) as nuisance parameters with the seed's priors:
    a frame measured by a detector whose peak sits 2 px off (m_h) is fitted back to the truth with them; their
    bad input names the key."""
    from brdfjax.fit._problem import scale_footprint
    from brdfjax.instrument.synthetic import footprint_kernel

    k = footprint_kernel(6.0, tail=1e-6)
    wide = np.asarray(scale_footprint(k, math.log(1.1)))
    ref = footprint_kernel(6.6, tail=1e-6)
    h = ref.shape[0] // 2 - k.shape[0] // 2
    np.testing.assert_allclose(wide, ref[h : h + k.shape[0], h : h + k.shape[0]], atol=2e-3 * ref.max())

    det = bj.Detector.seed(m_h=2.0)
    (f,) = render_noisy_frames(MODEL, [20.0], detector=det, roi=(-24, 24, -24, 24), step=4, noise_rel=0.02, seed=4,
                               floor=0.05)
    f = dataclasses.replace(f, detector=bj.Detector.seed(), systematics=_syst("4.0+3.0", "4.0+1.0", 0.0))
    base = NuisanceOptions(nd=False, flux=False, nonlinearity=False, misalignment=True,
                           alignment={"roll_deg": 0, "yaw_deg": 0, "pitch_deg": 0, "distance_m": 0, "m_v_px": 0,
                                      "m_h_px": 3.0})
    res = fit(MODEL, [f], SPEC, nuisance=base)
    d = res.to_dict()
    assert set(d["nuisance"]["parameters"]) == {"m_h[ti20]"}
    assert d["nuisance"]["parameters"]["m_h[ti20]"]["prior_sigma"] == 3.0
    assert res.value("m_h[ti20]") == pytest.approx(2.0, abs=3 * res.sigma("m_h[ti20]"))
    assert res.value("m_h[ti20]") > 5 * res.sigma("m_h[ti20]")  # the data say the peak is off (without it chi2 420)
    assert res.chi2 < 1.3 * res.dof
    # the defaults: the seed's accuracies, roll/yaw/pitch/distance shared, m_h/m_v per frame
    spec = build_nuisance([_Block(_syst("4.0+3.0", "4.0+1.0")), _Block(_syst("4.0+3.0", "4.0+1.0"))], ["a", "b"],
                          NuisanceOptions(nd=False, flux=False, nonlinearity=False, misalignment=True))
    assert spec.names == ("roll", "yaw", "pitch", "m_h[a]", "m_h[b]", "m_v[a]", "m_v[b]", "distance")
    assert spec.prior_sigma[0] == pytest.approx(math.radians(0.11)) and spec.prior_sigma[-1] == 0.005
    assert spec.blocks_of(0) == (0, 1) and spec.blocks_of(3) == (0,)
    with pytest.raises(FitInputError, match=r"cfg.toml: nuisance.footprint = true, but no frame with ND stacks has a beam"):
        build_nuisance([_Block(_syst("4.0+3.0", "4.0+1.0"))], ["a"], NuisanceOptions(footprint=True), source="cfg.toml")
    from brdfjax.fit.config import parse_fit_config

    cfg = {"data": {"frames": ["x.exr"]}, "model": {"preset": "solar_cell"}}
    with pytest.raises(ConfigError, match=r"c.toml: nuisance.alignment: .*unknown key 'rol_deg'; did you mean 'roll_deg'"):
        parse_fit_config({**cfg, "nuisance": {"alignment": {"rol_deg": 0.1}}}, source="c.toml")
    with pytest.raises(ConfigError, match=r"c.toml: nuisance.alignment: .*m_h_px = -1.0: an alignment accuracy must be"):
        parse_fit_config({**cfg, "nuisance": {"alignment": {"m_h_px": -1.0}}}, source="c.toml")
