"""Frames with a footprint: the stacked, support-restricted evaluation equals the plain one (performance path)."""

import numpy as np

import brdfjax as bj
from brdfjax.core.presets import mirror
from brdfjax.fit import FrameData, LevenbergMarquardt, _prepare as fitmod
from brdfjax.fit.internal import prepare_problem
from brdfjax.instrument.synthetic import footprint_kernel

MODEL = mirror(m=1e-4)


def _frames():
    det = bj.Detector.seed()
    g = det.grid(4, (-100, 100, -80, 80))
    k = footprint_kernel(25.0 / 4, tail=1e-9)
    out = []
    for i, ti in enumerate((20.0, 40.0)):
        img = np.asarray(bj.render(MODEL, bj.Conditions.from_degrees(ti), det, grid=g, precision="float64"))
        rng = np.random.default_rng(i)
        noisy = img * np.exp(0.03 * rng.standard_normal(img.shape))
        mask = img > (1e-3 if i == 0 else 1e-1) * img.max()  # different usable sets: different padding
        out.append(FrameData(noisy, 0.03, np.radians(ti), det, g, mask=mask, footprint=k, name=f"ti{ti:g}"))
    return out


def test_stacked_footprint_frames_give_the_same_residuals_and_jacobian(monkeypatch):
    from brdfjax.fit._problem import evaluate, jacobian

    frames = _frames()
    spec = {"m": 1.2e-4, "rho_s": 0.7, "phi_ref": 0.001}
    solver = LevenbergMarquardt()
    monkeypatch.setattr(fitmod, "SUPPORT_FRACTION", 1.01)  # always restrict to the kernel's reach
    stacked = prepare_problem(MODEL, frames, spec, solver=solver).problem
    assert stacked.stack is not None and stacked.stack.blocks.support_index is not None
    # the reference: the whole grid evaluated, blocks one by one
    monkeypatch.setattr(fitmod, "SUPPORT_FRACTION", 0.0)
    monkeypatch.setattr(fitmod, "can_stack", lambda blocks: False)
    plain = prepare_problem(MODEL, frames, spec, solver=solver).problem
    assert plain.stack is None and plain.blocks[0].support_index is None
    v = np.array([0.3, -0.2, 0.1, 0.05])
    r1 = np.asarray(evaluate(v, stacked)[0])
    r2 = np.asarray(evaluate(v, plain)[0])
    assert r1.shape == r2.shape == (sum(int(f.usable().sum()) for f in frames),)
    np.testing.assert_allclose(r1, r2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jacobian(v, stacked)), np.asarray(jacobian(v, plain)), rtol=1e-7, atol=1e-7)
