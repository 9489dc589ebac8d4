"""Solar-cell fits on noisy rendered frames: automatic initialisation, joint recovery, robustness, outliers.

The data are the seed's solar-cell model (§6.4 parameters) rendered at
theta_i = 20, 40, 60 deg on every 8th pixel of the seed camera, times
log-normal noise of 3 % (``render_noisy_frames``), with pixels below 0.1
sr^-1 masked as undetected.  Every frame of a fit here has the same usable
pixels, so one compiled solver serves the whole module.
"""

import json

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import Param, fit, init_solar_cell, render_noisy_frames

NAMES = ["m1", "rho_s1", "n1", "m2", "rho_s2", "n2", "dtheta", "dphi0", "a", "b", "c", "rho_s3"]
TRUTH = dict(bj.SOLAR_CELL_SEED)
ANGLES = ("dtheta", "dphi0")
#: Bounds from physics and the instrument: indices of real media; the bar width b such that the
#: single-bar envelope sinc^2(b u) has no zero inside the frame (it hardly constrains b otherwise).
INDEX = dict(lower=1.0, upper=6.0)
B_BOUNDS = dict(lower=1e-6, upper=4e-5)
MODEL = bj.solar_cell()
#: Long statistical runs (issue 4's full 20-start and 30-dataset studies): run with --slow.
slow = pytest.mark.slow


def _spec(values=None, phi_ref=None):
    v = values or {}
    spec = {k: Param(v.get(k, "auto")) for k in NAMES}
    spec["n1"] = Param(v.get("n1", "auto"), **INDEX)
    spec["n2"] = Param(v.get("n2", "auto"), **INDEX)
    spec["b"] = Param(v.get("b", "auto"), **B_BOUNDS)
    spec["phi_ref"] = Param("auto" if phi_ref is None else phi_ref)  # per frame
    return spec


@pytest.fixture(scope="module")
def frames():
    return render_noisy_frames(MODEL, [20, 40, 60], step=8, noise_rel=0.03, floor=0.1, seed=1)


@pytest.fixture(scope="module")
def reference(frames):
    return fit(MODEL, frames, _spec())


def test_auto_init_lands_within_a_fraction_of_a_peak_width(frames):
    init = init_solar_cell(MODEL, frames)
    assert init["a"] == pytest.approx(TRUTH["a"], rel=2e-3)  # from the fringe periodogram
    for k in ("m1", "m2"):
        assert init[k] == pytest.approx(TRUTH[k], rel=0.05)
    # the offset normal within a tenth of a peak width (m2 = 2e-4 rad)
    assert abs(init["dtheta"] - TRUTH["dtheta"]) < 0.1 * TRUTH["m2"]
    assert abs(init["dphi0"] - TRUTH["dphi0"]) * TRUTH["dtheta"] < 0.1 * TRUTH["m2"]
    np.testing.assert_allclose(init["phi_ref"], 0.0, atol=np.radians(0.01))
    np.testing.assert_allclose(init["theta_i"], np.radians([20, 40, 60]), atol=1e-5)
    for k in ("rho_s1", "rho_s2", "rho_s3", "c"):
        assert init[k] == pytest.approx(TRUTH[k], rel=0.25)


def test_joint_fit_recovers_the_seed_parameters(reference, frames):
    res = reference
    print("\n" + res.summary())
    assert res.converged, res.message
    assert 0.8 < res.chi2_reduced < 1.3
    assert res.dof == sum(int(f.usable().sum()) for f in frames) - len(res.free_names)
    pulls = {}
    for k in NAMES:
        v, s = res.value(k), res.sigma(k)
        pulls[k] = (v - TRUTH[k]) / s
        assert abs(pulls[k]) < 3.0, f"{k}: {v} +- {s} vs truth {TRUTH[k]}"
    for f in frames:
        name = f"phi_ref[{f.name}]"
        pulls[name] = res.value(name) / res.sigma(name)
        assert abs(pulls[name]) < 3.0
        assert abs(np.degrees(res.value(name))) < 0.05
    assert res.value("a") == pytest.approx(TRUTH["a"], rel=0.01)
    assert res.value("m1") == pytest.approx(TRUTH["m1"], rel=0.05)
    assert res.value("m2") == pytest.approx(TRUTH["m2"], rel=0.05)
    for k in ANGLES:
        assert abs(np.degrees(res.value(k) - TRUTH[k])) < 0.05
    print("pulls:", {k: round(p, 2) for k, p in pulls.items()})
    # the output contract, angles in degrees
    out = json.loads(res.to_json())
    assert out["parameters"]["dtheta"]["unit"] == "deg"
    assert out["parameters"]["dtheta"]["value"] == pytest.approx(0.5, abs=0.05)
    assert out["parameters"]["dphi0"]["value"] == pytest.approx(45.0, abs=0.05)
    assert out["parameters"]["theta_i[ti40]"] == {"value": pytest.approx(40.0), "sigma": None, "unit": "deg", "free": False, "initial": pytest.approx(40.0)}
    assert out["parameters"]["a"]["unit"] == "m" and out["parameters"]["rho_s3"]["unit"] == "sr^-1"
    assert out["instrument_function"]["convolved"] is False
    assert len(out["correlation"]["matrix"]) == len(res.free_names) == 15


@pytest.mark.parametrize("n_starts", [pytest.param(6, id="6"), pytest.param(20, id="20", marks=slow)])
def test_robustness_from_perturbed_starts(reference, frames, n_starts):
    """Random starts: every parameter scaled by U(0.5, 1.5) (indices and b within their bounds), the
    bar spacing by up to 1 %, and the angles moved by up to 2 peak widths each (dtheta by 2 m2; dphi0
    and every phi_ref by 2 m2 / dtheta, which moves the offset peak by 2 widths), auto disabled.
    Issue 4 asks for at least 19 of 20 (the 20-start run is marked slow; 6 starts run by default)."""
    x = {k: reference.value(k) for k in NAMES}
    phis = [reference.value(f"phi_ref[{f.name}]") for f in frames]
    m2, dth = x["m2"], x["dtheta"]
    rng = np.random.default_rng(2026)
    same = 0
    steps = []
    for _ in range(n_starts):
        v = {k: x[k] * rng.uniform(0.5, 1.5) for k in ("m1", "rho_s1", "m2", "rho_s2", "c", "rho_s3", "b")}
        v["n1"] = float(np.clip(x["n1"] * rng.uniform(0.5, 1.5), 1.05, 5.9))
        v["n2"] = float(np.clip(x["n2"] * rng.uniform(0.5, 1.5), 1.05, 5.9))
        v["b"] = float(np.clip(v["b"], 1.1e-6, 3.9e-5))
        v["a"] = x["a"] * (1 + rng.uniform(-0.01, 0.01))
        v["dtheta"] = x["dtheta"] + rng.uniform(-2, 2) * m2
        v["dphi0"] = x["dphi0"] + rng.uniform(-2, 2) * m2 / dth
        phi = [p + rng.uniform(-2, 2) * m2 / dth for p in phis]
        r = fit(MODEL, frames, _spec(v, phi))
        steps.append(r.n_iterations)
        ok = r.converged and abs(r.chi2 - reference.chi2) < 1e-6 * reference.chi2 and all(
            abs(r.value(k) - x[k]) < 0.1 * reference.sigma(k) for k in NAMES
        )
        same += ok
    print(f"\nrobustness: {same}/{n_starts} starts converged to the reference optimum; steps {min(steps)}-{max(steps)}")
    assert same >= n_starts - n_starts // 20


def test_robust_loss_resists_stray_light(reference, frames):
    """2 % of the usable pixels get stray light (x 3 to x 30); Cauchy keeps the solution, linear does not."""
    rng = np.random.default_rng(4)
    hit = []
    for f in frames:
        b = np.array(f.brdf)
        u = np.flatnonzero(f.usable())
        sel = rng.choice(u, size=u.size // 50, replace=False)
        b.flat[sel] *= rng.uniform(3.0, 30.0, sel.size)
        hit.append(bj.fit.FrameData(b, f.sigma_rel, f.theta_i, f.detector, f.grid, mask=f.mask, phi_ref=f.phi_ref, wavelength=f.wavelength, name=f.name))
    start = {k: reference.value(k) for k in NAMES}
    phi = [reference.value(f"phi_ref[{f.name}]") for f in frames]
    lin = fit(MODEL, hit, _spec(start, phi))
    rob = fit(MODEL, hit, _spec(start, phi), loss="cauchy")
    assert rob.converged, rob.message
    worse = 0
    for k in NAMES:
        d_rob = abs(rob.value(k) - TRUTH[k]) / reference.sigma(k)
        d_lin = abs(lin.value(k) - TRUTH[k]) / reference.sigma(k)
        assert d_rob < 4.0, k
        worse += d_lin > 4.0
    assert worse >= 3  # the linear loss is pulled off in several parameters
    assert rob.n_downweighted >= 0.9 * sum(f.usable().sum() // 50 for f in frames)
    print(f"\nstray light: linear loss pulled {worse} parameters > 4 sigma off; Cauchy none; "
          f"{rob.n_downweighted} points down-weighted")


@pytest.mark.slow
def test_uncertainties_are_honest_across_noise_seeds():
    """30 noise realisations: the truth lies within 1 sigma for 55-80 % of (dataset, parameter) pairs."""
    inside = total = 0
    for seed in range(100, 130):
        fr = render_noisy_frames(MODEL, [20, 40, 60], step=8, noise_rel=0.03, floor=0.1, seed=seed)
        r = fit(MODEL, fr, _spec())
        assert r.converged, r.message
        for k in NAMES:
            inside += abs(r.value(k) - TRUTH[k]) <= r.sigma(k)
            total += 1
        for f in fr:
            inside += abs(r.value(f"phi_ref[{f.name}]")) <= r.sigma(f"phi_ref[{f.name}]")
            total += 1
    frac = inside / total
    print(f"\ncoverage: truth within 1 sigma for {inside}/{total} = {frac:.3f} of (dataset, parameter) pairs")
    assert 0.55 <= frac <= 0.80
