"""Fits of real measurements by others (tests/data/real, copied from ../shared/data/real with their licences): specular microfacet + Lambertian models.

The tables carry no uncertainties, so every point is weighted 1 and the
quality measure is the log-RMS, the rms of ``ln(f_model / f_data)`` per
incident angle (printed; ``pytest -s`` shows it).  A single-lobe model is a
coarse description of these materials (MERL aluminium, a metallic paint with
flakes) and Eq 70 has no shadowing-masking factor, so grazing incidence (80
deg) fits worst: the bounds below record what the model achieves, not a claim
of accuracy.
"""

from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.core.terms import ABg, Binomial, MultiLobeSpecular, Specular
from brdfjax.fit import fit, read_cornell_brdf, read_merl_inplane
from brdfjax.fit.config import load_fit_config
from brdfjax.fit.job import build_fit_job

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
CONFIGS = Path(__file__).resolve().parents[2] / "configs"

#: Aluminium near 550 nm (Rakic 1995): n + i k = 0.96 + 6.69 i; paints: a dielectric binder, n = 1.5.
ALUMINIUM = dict(n=0.96, k=6.69)
PAINT = dict(n=1.5)


def _model(distribution, **index):
    width = bj.GGX(0.1) if distribution == "ggx" else bj.Beckmann(0.1)
    return bj.Model(terms={"spec": bj.Specular(width, rho_s=0.5, **index, **bj.SEED_FORM), "diffuse": bj.Lambertian(0.05)})


def _report(label, res):
    groups = res.blocks[0].groups
    rows = ", ".join(f"{g['theta_i_deg']:g}: {g['log_rms']:.3f}" for g in groups)
    width = "spec.alpha" if "spec.alpha" in res.parameters else "spec.m"
    print(
        f"\n{label}: {res.message}\n  {width} = {res.value(width):.4g} +- {res.sigma(width):.2g}, "
        f"rho_s = {res.value('spec.rho_s'):.4g}, rho_d = {res.value('diffuse.rho_d'):.4g}; "
        f"log-RMS {res.blocks[0].log_rms:.3f} overall, per theta_i (deg): {rows}"
    )
    return {g["theta_i_deg"]: g["log_rms"] for g in groups}


CASES = [
    # file, reader, distribution, index, bound on the overall log-RMS, bound per incident angle
    ("merl_aluminium_inplane.txt", "merl", "ggx", ALUMINIUM, 1.3, 2.0),
    ("cornell_cayman_metallic.brdf", "cornell", "beckmann", PAINT, 1.4, 3.5),
    ("cornell_krylon_blue.brdf", "cornell", "ggx", PAINT, 0.55, 1.5),
]


@pytest.mark.parametrize("file, reader, distribution, index, overall, per_angle", CASES, ids=[f"{c[0].split('.')[0]}-{c[2]}" for c in CASES])
def test_real_data_fit_converges_from_auto(file, reader, distribution, index, overall, per_angle):
    table = read_merl_inplane(REAL / file) if reader == "merl" else read_cornell_brdf(REAL / file)
    width = "spec.alpha" if distribution == "ggx" else "spec.m"
    res = fit(_model(distribution, **index), table, {width: "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"})
    per = _report(f"{file} ({distribution} + Lambertian)", res)
    assert res.converged, res.message
    assert not res.covariance_absolute  # no uncertainties in the file: scaled by the residual variance
    assert 1e-3 < res.value(width) < 1.0
    assert res.value("spec.rho_s") > 0 and res.value("diffuse.rho_d") > 0
    assert np.isfinite(res.sigma(width)) and res.sigma(width) < 0.2 * res.value(width)
    assert res.blocks[0].log_rms < overall
    assert max(per.values()) < per_angle
    assert len(per) == len(table.incident_angles())


#: The shipped configs (configs/fit_*.toml: the best physically based model per material from
#: experiments/real_data_fits.py, its fitted values as start values) against today's single
#: microfacet lobe + Lambertian (log-RMS 1.17, 0.48, 1.32 before issue 14).
SHIPPED = [
    ("fit_merl_aluminium.toml", 1.17),
    ("fit_cornell_krylon_blue.toml", 0.48),
    ("fit_cornell_cayman.toml", 1.32),
]


@pytest.mark.parametrize("config, today", SHIPPED, ids=[c[0].removesuffix(".toml") for c in SHIPPED])
def test_shipped_config_beats_todays_model(config, today):
    """The shipped model at its shipped values (every parameter held: no solve) has a lower log-RMS than today's."""
    job = build_fit_job(load_fit_config(CONFIGS / config))
    res = fit(job.model, job.blocks, {})  # nothing free: the log-RMS of the shipped values, the fit's own measure
    block = res.blocks[0]
    print(f"\n{config}: log-RMS {block.log_rms:.3f} (today {today}); per theta_i:",
          {g["theta_i_deg"]: round(g["log_rms"], 3) for g in block.groups})
    assert block.log_rms < today - 0.02
    microfacet = [t for t in job.model.terms.values() if isinstance(t, Specular | MultiLobeSpecular)]
    assert microfacet and all(t.shadowing in ("smith", "smith_mixture") for t in microfacet)


def test_merl_physical_model_is_at_least_as_good_as_abg():
    """MERL aluminium: the shipped physically based model (spike + mid + halo microfacet lobes sharing the
    index, Smith G2 of their mixture, + Lambertian) at its shipped values has a log-RMS no higher than an ABg + Lambertian fit of
    the same data, overall and at the grazing 78.75 deg (ABg fitted here from a plain start: about 20 s; the
    multi-lobe fit itself takes minutes, experiments/real_data_fits.py)."""
    job = build_fit_job(load_fit_config(CONFIGS / "fit_merl_aluminium.toml"))
    spec = job.model.terms["spec"]
    assert isinstance(spec, MultiLobeSpecular) and len(spec.lobes) == 3 and spec.shadowing in ("smith", "smith_mixture")
    phys = fit(job.model, job.blocks, {}).blocks[0]
    abg_model = bj.Model(terms={"spec": ABg(0.003, 4e-6, 2.0), "diffuse": bj.Lambertian(1e-3)})
    free = {"spec.A": "free", "spec.B": "free", "spec.g": "free", "diffuse.rho_d": "free"}
    abg = fit(abg_model, job.blocks, free, first_stage=None, resolution_check=False)
    assert abg.converged, abg.message
    a = abg.blocks[0]
    per_p = {g["theta_i_deg"]: g["log_rms"] for g in phys.groups}
    per_a = {g["theta_i_deg"]: g["log_rms"] for g in a.groups}
    print(f"\nMERL: physically based {phys.log_rms:.3f} {per_p}\n      ABg {a.log_rms:.3f} {per_a}")
    assert phys.log_rms <= a.log_rms
    assert per_p[78.75] <= per_a[78.75]


RESULTS = Path(__file__).resolve().parents[2] / "experiments" / "results"


def _stored_binomial(dataset):
    """The binomial + Lambertian fit of experiments/real_data_fits.py (its stored optimum)."""
    import json  # function-local: only these tests read the experiment's results

    fits = json.loads((RESULTS / f"real_data_fits_{dataset}.json").read_text())["fits"]
    model = bj.Model(terms={"spec": Binomial(np.zeros((2, 3)), np.zeros((2, 1)), 1.0, l1=1), "diffuse": bj.Lambertian(0.01)})
    return model.with_params(fits["binomial"]["parameters"]), fits["binomial"]["log_rms"]


@pytest.mark.parametrize("config, dataset", [("fit_cornell_krylon_blue.toml", "cornell_krylon_blue"),
                                             ("fit_cornell_cayman.toml", "cornell_cayman")], ids=["krylon", "cayman"])
def test_shipped_physical_model_is_at_least_as_good_as_the_binomial(config, dataset):
    """Krylon and Cayman: the shipped physically based config at its values has a log-RMS no higher than the
    binomial + Lambertian fit of experiments/real_data_fits.py, its stored optimum evaluated here on the same
    table (no solve on either side: the binomial's own fit takes 1-3 min here)."""
    job = build_fit_job(load_fit_config(CONFIGS / config))
    phys = fit(job.model, job.blocks, {}).blocks[0]
    model, stored = _stored_binomial(dataset)
    binom = fit(model, job.blocks, {}).blocks[0]
    assert binom.log_rms == pytest.approx(stored, rel=1e-6)  # the same data and measure as the experiment's
    print(f"\n{dataset}: physically based {phys.log_rms:.3f}, binomial {binom.log_rms:.3f}")
    assert phys.log_rms <= binom.log_rms


def test_merl_binomial_is_below_the_floor_of_any_single_lobe_shape():
    """MERL aluminium, where the physically based fits stay above the binomial (issue 14: below ABg only): no
    distribution D(theta_h) whatever, times Eq 70's factor with the aluminium index, reaches the binomial's
    log-RMS (the least-squares floor over a 40-knot spline in ln tan theta_h); the gap is in the angular
    factor, not in the lobe's shape (experiments/merl_gap.py has the floors of other factors)."""
    from scipy.interpolate import BSpline  # function-local: only this test builds a spline basis

    table = read_merl_inplane(REAL / "merl_aluminium_inplane.txt")
    dirs = bj.Directions.from_angles(*(np.asarray(getattr(table, f)) for f in ("theta_i", "phi_i", "theta_s", "phi_s")))
    f = np.asarray(table.brdf)
    tx2, ty2, _ = (np.asarray(v) for v in dirs.half_slopes())
    x = np.log(np.maximum(np.sqrt(tx2 + ty2), 1e-5))
    knots = np.r_[[x.min()] * 3, np.linspace(x.min(), x.max(), 40), [x.max()] * 3]
    basis = BSpline.design_matrix(x, knots, 3).toarray()
    ci, cs = np.asarray(dirs.cos_theta_i), np.asarray(dirs.cos_theta_s)
    y = np.log(f * 2 * (ci + cs) ** 2 / np.asarray(bj.q_factor(ALUMINIUM["n"], dirs, ALUMINIUM["k"])))
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    floor = float(np.sqrt(np.mean((y - basis @ coef) ** 2)))
    model, _ = _stored_binomial("merl_aluminium")
    binom = float(np.sqrt(np.mean(np.log(np.asarray(model(dirs, np.asarray(table.wavelength))) / f) ** 2)))
    print(f"\nMERL: any D(theta_h) x Eq 70 >= {floor:.3f}; binomial {binom:.3f}")
    assert binom < floor - 0.1


def test_auto_start_keeps_the_lobe_of_a_hazy_table():
    """The 'auto' start of GGX + Lambertian on the Cornell Cayman table (every 2nd row) is the best of a width
    profile: the log-quadratic width alone (alpha 0.57) left the lobe at rho_s 1.6e-15, which the fit kept."""
    from brdfjax.fit import init_specular_lambertian

    table = read_cornell_brdf(REAL / "cornell_cayman_metallic.brdf").select(slice(None, None, 2))
    model = _model("ggx", **PAINT)
    start = init_specular_lambertian(model, [table])
    assert 0.01 < start["spec.alpha"] < 0.2 and start["spec.rho_s"] > 0.1
    res = fit(model, [table], {"spec.alpha": "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"}, resolution_check=False)
    assert res.value("spec.rho_s") > 0.1 and res.noise["sigma_ln"] < 1.85  # the collapsed lobe's was 2.03
