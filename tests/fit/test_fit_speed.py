"""Issue 19 (fit speed): the structured Jacobian's shortcuts equal jax.jacfwd, and a fit with progress
reaches the same point as one without (stepped from Python, no host callback in its programs)."""

import jax
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import FrameData, LevenbergMarquardt, TableData, fit
from brdfjax.fit._jacobian import _local, _plan, supports
from brdfjax.fit.internal import prepare_problem
from brdfjax.instrument.synthetic import convolve_footprint, footprint_kernel

# a tilted specular peak (turned by dtheta, dphi0 + phi_ref) beside an untilted one (phi_ref cannot reach it)
# and the bars' diffraction (every column written by hand: brdfjax.fit._analytic; its rho held fixed, so the
# hand-written columns carry it)
MODEL = bj.Model(
    terms={
        "center": bj.Specular(bj.Beckmann(1.5e-3), rho_s=0.05, n=3.0, **bj.SEED_FORM),
        "offset": bj.OffsetNormal(bj.Specular(bj.Beckmann(1.5e-3), rho_s=0.7, n=1.4, **bj.SEED_FORM), dtheta=np.radians(0.15),
                                  dphi0=np.radians(45.0)),
        "bars": bj.Diffraction(rho=30.0, a=8e-4, b=1e-5, c=4e-4),
    }
)
SPEC = {"center.m": 1.6e-3, "center.n": 2.9, "offset.m": 1.4e-3, "offset.n": 1.5, "offset.dtheta": np.radians(0.16),
        "offset.dphi0": np.radians(44.0), "offset.rho_s": 0.65,
        "bars.a": 8.1e-4, "bars.b": 1.1e-5, "bars.c": 3.9e-4, "phi_ref": 0.002}


def _frame(kernel):
    det = bj.Detector.seed()
    g = det.grid(16, (-320, 640, -320, 640))
    img = np.asarray(bj.render(MODEL, bj.Conditions.from_degrees(20.0), det, grid=g, precision="float64"))
    if kernel is not None:
        img = np.clip(convolve_footprint(img, kernel / kernel.sum()), 0.0, None)
    noisy = img * np.exp(0.03 * np.random.default_rng(0).standard_normal(img.shape))
    return FrameData(noisy, 0.03, np.radians(20.0), det, g, mask=img > 1e-4 * img.max(), footprint=kernel)


@pytest.mark.parametrize("kernel", [None, footprint_kernel(25.0 / 16, tail=1e-6)], ids=["no_footprint", "footprint"])
def test_turn_shortcuts_equal_jacfwd(kernel, assert_jacobian_matches_jacfwd):
    """phi_ref skipped for the untilted peak and taken from dphi0 for the tilted one, the hand-written columns
    (specular widths and indices one pass each, diffraction a, b, c, phi_ref): == jacfwd to 1e-10."""
    prep = prepare_problem(MODEL, [_frame(kernel)], SPEC, solver=LevenbergMarquardt())
    problem = prep.problem
    assert supports(problem)
    names = tuple((b, kd) for _, b, kd in _local(problem, 0))
    plan = {t: (js, alias) for t, js, _, alias in _plan(problem.blocks[0].template, names).terms}
    j_phi = [b for b, _ in names].index("phi_ref")
    j_dphi0 = [b for b, _ in names].index("offset.dphi0")
    assert j_phi not in plan["center"][0] and not plan["center"][1]  # not differentiated, no alias
    assert j_phi not in plan["offset"][0] and plan["offset"][1] == ((j_phi, j_dphi0),)
    # off the start (where the frame's own phi_ref differs from the free one), unscaled coordinates: a
    # unit step is a radian, or a factor e
    v = 1e-3 * np.linspace(-1.0, 1.0, problem.u0.shape[0])
    assert_jacobian_matches_jacfwd(problem, v, residual_rtol=1e-10)


def _peak_on_floor_table(lo_deg: float, hi_deg: float, n: int, seed: int):
    """A Beckmann lobe on a Lambertian floor scanned in-plane at theta_i = 30 deg, 2 % log-normal noise."""
    ts = np.radians(np.linspace(lo_deg, hi_deg, n))
    dirs = dict(theta_i=np.full(n, np.radians(30.0)), phi_i=np.zeros(n), theta_s=ts, phi_s=np.full(n, np.pi))
    model = bj.Model(terms={"peak": bj.Specular(bj.Beckmann(0.05), rho_s=0.5, n=1.5, **bj.SEED_FORM), "floor": bj.Lambertian(rho_d=0.01)})
    brdf = np.asarray(model(bj.Directions.from_angles(dirs["theta_i"], dirs["phi_i"], ts, dirs["phi_s"]), 632.8e-9))
    brdf = brdf * np.exp(0.02 * np.random.default_rng(seed).standard_normal(n))
    return model, TableData(**dirs, brdf=brdf, sigma_rel=0.02, wavelength=632.8e-9)


def test_progress_is_reported_per_step_without_changing_the_fit():
    """With progress= the Levenberg-Marquardt solve is stepped from Python: the same steps, chi^2 and values."""
    model, tab = _peak_on_floor_table(25.0, 35.0, 41, seed=1)
    spec = {"peak.m": 0.08, "peak.rho_s": 0.3, "floor.rho_d": 0.02}
    quiet = fit(model, tab, spec, first_stage=None)
    heard = []
    loud = fit(model, tab, spec, first_stage=None, progress=lambda k, chi2: heard.append((k, chi2)))
    assert quiet.converged and loud.converged, (quiet.message, loud.message)
    assert quiet.n_iterations == loud.n_iterations >= 3
    assert [k for k, _ in heard] == list(range(1, loud.n_iterations + 1))  # one report per step
    assert loud.chi2 == pytest.approx(quiet.chi2, rel=1e-10)
    for name in spec:
        assert loud.value(name) == pytest.approx(quiet.value(name), rel=1e-8)
    assert heard[-1][1] == pytest.approx(loud.cost, rel=1e-6)
    jax.clear_caches()


def test_a_fit_traces_its_jacobian_and_residuals_once(monkeypatch):
    """The step scales, the solver's linearisations, the covariance and the final residuals share one trace of
    the structured Jacobian and one of the residuals (before: the Jacobian was traced twice, the residuals
    twice: Python tracing is what a cold process pays even with the persistent compilation cache)."""
    import brdfjax.fit._jacobian as jac_mod
    import brdfjax.fit._problem as problem_mod

    counts = {"columns": 0, "residuals": 0}
    columns, weighted = jac_mod._columns, problem_mod.Problem.weighted_residuals

    def counted_columns(*a, **k):
        counts["columns"] += 1
        return columns(*a, **k)

    def counted_weighted(self, v):
        counts["residuals"] += 1
        return weighted(self, v)

    monkeypatch.setattr(jac_mod, "_columns", counted_columns)
    monkeypatch.setattr(problem_mod.Problem, "weighted_residuals", counted_weighted)
    model, tab = _peak_on_floor_table(5.0, 70.0, 53, seed=2)  # the floor seen beside the peak
    spec = {"peak.m": 0.08, "peak.rho_s": 0.3, "floor.rho_d": 0.02}
    for progress in (None, lambda k, chi2: None):  # one optx.least_squares loop; stepped from Python (the CLI's)
        jax.clear_caches()
        counts.update(columns=0, residuals=0)
        res = fit(model, tab, spec, first_stage=None, progress=progress)
        assert res.converged and res.n_iterations >= 3, res.message
        assert res.covariance is not None
        assert counts == {"columns": 1, "residuals": 1}, (progress, counts)
    jax.clear_caches()


def test_ftol_stops_earlier_at_the_same_chi2():
    """scipy-like ftol: fewer steps than the Cauchy test alone (ftol=0, which on this frame runs to max_steps
    without its test firing), chi^2 within 1e-6 relative of that long solve's."""
    frame = _frame(None)
    tight = fit(MODEL, frame, SPEC, first_stage=None, solver_options={"ftol": 0.0})
    quick = fit(MODEL, frame, SPEC, first_stage=None)
    assert quick.converged, quick.message
    assert quick.n_iterations < tight.n_iterations, (quick.n_iterations, tight.n_iterations)
    assert quick.chi2 == pytest.approx(tight.chi2, rel=1e-6)
    jax.clear_caches()


@pytest.mark.parametrize("bad", [-1e-8, "1e-8", float("nan"), True])
def test_bad_ftol_is_a_clear_error(bad):
    from brdfjax.fit import FitInputError, get_solver

    with pytest.raises(FitInputError, match="'ftol'"):
        get_solver("levenberg_marquardt", ftol=bad)
