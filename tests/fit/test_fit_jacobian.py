"""The structured Jacobian (brdfjax.fit._jacobian) equals jax.jacfwd of the residuals, and fits do not change with it."""

import jax
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import FrameData, LevenbergMarquardt, TableData, _prepare as fitmod, _problem as problem_mod, fit
from brdfjax.fit._jacobian import supports
from brdfjax.fit._problem import evaluate
from brdfjax.fit.internal import prepare_problem
from brdfjax.instrument.synthetic import convolve_footprint, footprint_kernel

# three kinds of term: a nonlinear one with a scale (rho_s), a pure scale (rho_d), and one only phi_ref turns
MODEL = bj.Model(
    terms={
        "peak": bj.Specular(bj.Beckmann(1e-4), rho_s=0.7, n=1.5, **bj.SEED_FORM),
        "floor": bj.Lambertian(rho_d=1e-3),
        "bars": bj.Diffraction(rho=30.0, a=8e-4, b=1e-5, c=4e-5),
    }
)
SPEC = {"peak.m": 1.2e-4, "peak.rho_s": 0.6, "peak.n": 1.4, "floor.rho_d": 1.2e-3, "bars.a": 8.1e-4, "bars.c": 4.2e-5,
        "phi_ref": 0.001}


def _frames(kernel):
    det = bj.Detector.seed()
    g = det.grid(8, (-320, 320, -240, 240))
    out = []
    for i, ti in enumerate((20.0, 40.0)):
        img = np.asarray(bj.render(MODEL, bj.Conditions.from_degrees(ti), det, grid=g, precision="float64"))
        if kernel is not None:  # the data through the instrument function the fit convolves with
            img = np.clip(convolve_footprint(img, kernel / kernel.sum()), 0.0, None)
        rng = np.random.default_rng(i)
        noisy = img * np.exp(0.03 * rng.standard_normal(img.shape))
        mask = img > (1e-6 if i == 0 else 1e-5) * img.max()  # different usable sets: different padding
        out.append(FrameData(noisy, 0.03, np.radians(ti), det, g, mask=mask, footprint=kernel, name=f"ti{ti:g}"))
    return out


def _table():
    ts = np.radians(np.linspace(29.99, 30.01, 9))
    dirs = dict(theta_i=np.full(9, np.radians(30.0)), phi_i=np.zeros(9), theta_s=ts, phi_s=np.full(9, np.pi))
    brdf = np.asarray(MODEL(bj.Directions.from_angles(dirs["theta_i"], dirs["phi_i"], ts, dirs["phi_s"]), 632.8e-9))
    return TableData(**dirs, brdf=brdf * 1.01, sigma_rel=0.05, wavelength=632.8e-9, name="table")


V = np.array([0.3, -0.2, 0.1, 0.05, -0.1, 0.2, 0.02, -0.03])  # 7 model entries + 2 phi_ref: trimmed to size


def test_structured_jacobian_equals_jacfwd_with_a_separable_footprint(assert_jacobian_matches_jacfwd):
    """Stacked frames, the direct separable convolution (the Gaussian footprint)."""
    prep = prepare_problem(MODEL, _frames(footprint_kernel(25.0 / 8, tail=1e-6)), SPEC, solver=LevenbergMarquardt())
    p = prep.problem
    assert p.stack is not None and p.stack.blocks.sep_rows is not None and p.stack.blocks.dirs is not None
    assert_jacobian_matches_jacfwd(p, np.resize(V, p.u0.shape[0]))


def test_structured_jacobian_equals_jacfwd_with_a_general_footprint_and_a_table(assert_jacobian_matches_jacfwd):
    """A kernel that is not separable (the FFT box) and a goniometer table: blocks one by one."""
    k = footprint_kernel(25.0 / 8, tail=1e-6)
    k = k + 0.2 * np.roll(k, 1, axis=0) * np.roll(k, -1, axis=1) / k.max()  # rank > 1, asymmetric
    prep = prepare_problem(MODEL, _frames(k) + [_table()], SPEC, solver=LevenbergMarquardt())
    p = prep.problem
    assert p.stack is None and p.blocks[0].box_shape is not None and p.blocks[0].sep_rows is None
    assert_jacobian_matches_jacfwd(p, np.resize(V, p.u0.shape[0]))


def test_structured_jacobian_equals_jacfwd_without_a_footprint(assert_jacobian_matches_jacfwd):
    prep = prepare_problem(MODEL, _frames(None), SPEC, solver=LevenbergMarquardt())
    assert_jacobian_matches_jacfwd(prep.problem, np.resize(V, prep.problem.u0.shape[0]))


def test_box_convolution_equals_the_whole_grid_one(monkeypatch):
    """The FFT box (circular, small) gives the zero-padded whole-grid convolution at the usable points."""
    k = footprint_kernel(25.0 / 8, tail=1e-6)
    k = k + 0.2 * np.roll(k, 1, axis=0) / k.max() * k
    frames = _frames(k)
    box = prepare_problem(MODEL, frames, SPEC, solver=LevenbergMarquardt()).problem
    monkeypatch.setattr(fitmod, "SUPPORT_FRACTION", 0.0)  # the whole grid, no box
    whole = prepare_problem(MODEL, frames, SPEC, solver=LevenbergMarquardt()).problem
    assert whole.stack.blocks.box_shape is None and box.stack.blocks.box_shape is not None
    v = np.resize(V, box.u0.shape[0])
    np.testing.assert_allclose(np.asarray(evaluate(v, box)[0]), np.asarray(evaluate(v, whole)[0]), rtol=1e-9, atol=1e-9)


def test_theta_i_free_falls_back_to_jacfwd():
    spec = {**SPEC, "theta_i": {"value": None, "lower": 0.3, "upper": 0.8}}
    prep = prepare_problem(MODEL, _frames(None)[:1], spec, solver=LevenbergMarquardt())
    assert not supports(prep.problem) and prep.problem.blocks[0].dirs is None


@pytest.mark.parametrize("first_stage", [None])
def test_fit_is_unchanged_by_the_structured_jacobian(monkeypatch, first_stage):
    """The same fit with the structured Jacobian and with jacfwd: the same chi^2 and parameters."""
    frames = _frames(footprint_kernel(25.0 / 8, tail=1e-6))
    spec = {"peak.m": 1.05e-4, "peak.rho_s": 0.65, "bars.c": 4.1e-5, "phi_ref": 0.0}
    a = fit(MODEL, frames, spec, first_stage=first_stage)
    monkeypatch.setattr(problem_mod, "STRUCTURED_JACOBIAN", False)
    jax.clear_caches()  # the switch is read when the solve is traced
    b = fit(MODEL, frames, spec, first_stage=first_stage)
    assert a.converged and b.converged, (a.message, b.message)
    assert a.chi2 == pytest.approx(b.chi2, rel=1e-8)
    for name in ("peak.m", "peak.rho_s", "bars.c"):
        assert a.value(name) == pytest.approx(b.value(name), rel=1e-6, abs=1e-3 * b.sigma(name))


def test_progress_is_heard_whether_or_not_a_solve_without_listeners_was_compiled_first():
    """A solve nobody listens to is compiled without the progress callback (so it can come from the
    persistent cache); one with a listener still reports every evaluation."""
    lamb = bj.Model(terms={"diffuse": bj.Lambertian(rho_d=0.1)})
    ts = np.radians(np.linspace(5.0, 60.0, 12))
    tab = TableData(theta_i=np.full(12, np.radians(30.0)), phi_i=np.zeros(12), theta_s=ts, phi_s=np.full(12, np.pi),
                    brdf=np.full(12, 0.2 / np.pi), sigma_rel=0.05)
    quiet = fit(lamb, tab, {"diffuse.rho_d": 0.1}, first_stage=None)
    heard = []
    loud = fit(lamb, tab, {"diffuse.rho_d": 0.1}, first_stage=None, progress=lambda k, chi2: heard.append(chi2))
    assert quiet.converged and loud.converged and quiet.chi2 == pytest.approx(loud.chi2, rel=1e-12)
    assert len(heard) >= 2 and heard[-1] == pytest.approx(loud.cost, rel=1e-6, abs=1e-9)


def test_structured_jacobian_equals_jacfwd_for_the_standard_microfacet_form(assert_jacobian_matches_jacfwd):
    """The default Specular (Smith G2, Walter normalisation, Fresnel at the microfacet) on a wide lobe, phi_ref
    free: its phi_ref column is taken as 0 (the term cannot turn), which jacfwd checks."""
    model = bj.Model(terms={"peak": bj.Specular(bj.GGX(0.05), rho_s=0.7, n=1.5), "floor": bj.Lambertian(rho_d=1e-3),
                            "bars": bj.Diffraction(rho=30.0, a=8e-4, b=1e-5, c=4e-5)})  # bars: phi_ref's column
    det = bj.Detector.seed()
    g = det.grid(16, (-320, 320, -240, 240))
    frames = []
    for i, ti in enumerate((20.0, 60.0)):
        img = np.asarray(bj.render(model, bj.Conditions.from_degrees(ti), det, grid=g, precision="float64"))
        noisy = img * np.exp(0.03 * np.random.default_rng(i).standard_normal(img.shape))
        frames.append(FrameData(noisy, 0.03, np.radians(ti), det, g, name=f"ti{ti:g}"))
    spec = {"peak.alpha": 0.06, "peak.rho_s": 0.6, "peak.n": 1.4, "floor.rho_d": 1.2e-3, "phi_ref": 0.001}
    p = prepare_problem(model, frames, spec, solver=LevenbergMarquardt()).problem
    assert_jacobian_matches_jacfwd(p, np.resize(V, p.u0.shape[0]))



@pytest.mark.parametrize("listen", [False, True])
def test_the_solvers_jacobian_and_the_differenced_start_equal_the_jacobian_program(monkeypatch, listen):
    """The step scales come from differences of the residuals at the start and the covariance from
    the solver's last linearisation, so a fit compiles no Jacobian program: the differences equal the
    program's columns, and the fit's parameters and sigmas equal those of the same fit whose covariance takes
    the program's Jacobian; the solve stepped from Python (a listener) does the same."""
    import dataclasses

    from brdfjax.fit import _fit as fit_mod
    from brdfjax.fit._problem import jacobian, with_scale

    frames = _frames(footprint_kernel(25.0 / 8, tail=1e-6))
    prep = prepare_problem(MODEL, frames, SPEC, solver=LevenbergMarquardt())
    n = prep.problem.u0.shape[0]
    p = with_scale(prep.problem, np.asarray(prep.problem.u0) + 0.01 * np.resize(V, n), np.ones(n))
    J0 = np.asarray(jacobian(np.zeros(n), p), np.float64)
    for central, tol in ((True, 1e-6), (False, 1e-4)):
        fd = fit_mod._difference_columns(p, np.zeros(n), range(n), central=central)
        assert np.max(np.linalg.norm(fd - J0, axis=0) / np.linalg.norm(J0, axis=0)) < tol, central

    spec = {"peak.m": 1.05e-4, "peak.rho_s": 0.65, "bars.c": 4.1e-5, "phi_ref": 0.0}
    kw = {"progress": (lambda k, chi2: None)} if listen else {}
    calls = []
    monkeypatch.setattr(fit_mod, "jacobian", lambda *a: calls.append(1) or jacobian(*a))
    a = fit(MODEL, frames, spec, first_stage=None, **kw)
    assert a.converged and calls == []
    solve = LevenbergMarquardt.solve
    monkeypatch.setattr(LevenbergMarquardt, "solve",
                        lambda self, *x: dataclasses.replace(solve(self, *x), jacobian=None))
    b = fit(MODEL, frames, spec, first_stage=None, **kw)
    assert calls == [1] and a.chi2 == b.chi2
    for name in spec:
        if name != "phi_ref":
            assert a.value(name) == b.value(name) and a.sigma(name) == pytest.approx(b.sigma(name), rel=1e-9)
