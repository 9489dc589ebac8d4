"""Noise weights at the fitted model (brdfjax.fit._reweight): the bias of weights taken at each noisy reading.

A reduction's relative noise is the pixel's noise over its own reading, so an upward fluctuation gets more
weight (and passes a ``max_sigma_rel`` cut more easily): a log-space fit then reads faint wings too bright.
That biased the diffraction width ``c`` of the shipped synthetic solar-cell fit by about +2.5 sigma
(experiments/c_asimov.py).  These tests build dark-noise-limited data by hand (constant absolute noise,
not the synthetic instrument) and check the bias, the fix and the job's refit.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import FrameData
from brdfjax.fit._reweight import model_noise_weights, warm_params
from brdfjax.fit.job import FitJob

jax.config.update("jax_enable_x64", True)


def _block(shape, brdf, sigma_rel, mask=None):
    det = bj.Detector.seed()
    rows, cols = shape
    grid = det.grid(1, (0, cols - 1, 0, rows - 1))
    return FrameData(brdf=brdf, sigma_rel=sigma_rel, theta_i=0.3, detector=det, grid=grid, mask=mask)


def test_weights_at_the_reading_bias_the_log_mean_and_model_weights_do_not():
    """Weighted mean of log(d / m) over 200k dark-limited pixels (SNR 8-40, a smooth ramp).

    Weights ``(d / sigma)^2`` at each reading and a cut on its own SNR >= 10 read the level too high by
    about ``1.5 u^2`` (plus the cut's selection); weights at the model with the ``exp(u^2 / 2)`` correction
    read it right within the statistical error; without the correction the log's own bias ``-u^2 / 2``
    is left.
    """
    rng = np.random.default_rng(20261205)
    rows, cols = 400, 500
    sigma = 1.0
    m = np.linspace(8.0, 40.0, cols)[None, :] * np.ones((rows, 1))  # model level, sigma = 1: SNR 8-40
    d = m + sigma * rng.standard_normal(m.shape)
    with np.errstate(invalid="ignore"):
        u_own = np.where(d > 0, sigma / d, np.inf)
    finite = d > 0
    own = finite & (u_own <= 0.1)
    w_own = 1.0 / u_own[own] ** 2
    bias_own = float(np.sum(w_own * np.log(d[own] / m[own])) / np.sum(w_own))

    block = _block(m.shape, d, u_own, finite)
    new = model_noise_weights(block, d, u_own, np.zeros(m.shape), finite, m, max_sigma_rel=0.1)
    keep = new.usable()
    w = 1.0 / new.sigma_rel[keep] ** 2
    se = 1.0 / math.sqrt(float(np.sum(w)))
    bias_new = float(np.sum(w * np.log(new.brdf[keep] / m[keep])) / np.sum(w))
    bias_uncorrected = float(np.sum(w * np.log(d[keep] / m[keep])) / np.sum(w))
    expected_log_bias = -0.5 * float(np.sum(w * new.sigma_rel[keep] ** 2) / np.sum(w))

    assert bias_own > 30 * se  # the reading's weights: a bias far beyond the noise
    assert abs(bias_new) < 4 * se  # the model's weights and the correction: none
    assert bias_uncorrected == pytest.approx(expected_log_bias, rel=0.15)
    # the new sigma is the model's SNR (noise 1 over m): the cut keeps m >= 10, whatever the noise
    assert np.allclose(new.sigma_rel[keep], sigma / m[keep], rtol=1e-12)
    assert np.array_equal(keep, finite & (m >= 10.0))


def test_model_weights_keep_other_sigma_parts_and_pixels_without_a_model():
    d = np.full((5, 6), 100.0)
    u = np.full(d.shape, 0.05)
    m = np.full(d.shape, 50.0)
    m[2, 3] = 0.0  # the model underflows here: the reading's noise and data are kept
    other = np.full(d.shape, 0.02)
    new = model_noise_weights(_block(d.shape, d, np.hypot(u, other)), d, u, other, np.ones(d.shape, bool), m)
    assert new.sigma_rel[0, 0] == pytest.approx(math.hypot(5.0 / 50.0, 0.02))
    assert new.brdf[0, 0] == pytest.approx(100.0 * math.exp(0.5 * 0.1**2))
    assert new.sigma_rel[2, 3] == pytest.approx(math.hypot(0.05, 0.02))
    assert new.brdf[2, 3] == 100.0


def test_job_refits_with_model_weights_and_reads_the_wings_right():
    """A GGX peak with dark-limited noise: the fit with the readings' weights comes out too wide (alpha
    high by several sigma); the job's refit with the model's weights recovers alpha.

    (Seeds 1-3, tried while writing this: alpha pulls +3.8, +4.4, +4.7 with the readings' weights, -0.5,
    +0.1, +0.5 after the refit.)"""
    truth = bj.Model(terms={"s": bj.Specular(bj.GGX(0.004), rho_s=60.0, n=1.5)})
    det = bj.Detector.seed()
    grid = det.grid(40, (-1200, 1200, -1200, 1200))  # 61 x 61 points out to ~2.5 lobe widths
    frame = bj.Conditions.from_degrees(20.0, 0.0, 632.8)
    m = np.asarray(bj.render(truth, frame, det, grid=grid, precision="float64"), np.float64)
    sigma = float(m.max()) / 300.0  # SNR 300 at the peak, under 10 in the outer wings
    rng = np.random.default_rng(4)
    d = m + sigma * rng.standard_normal(m.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(d > 0, sigma / d, np.inf)
    finite = np.isfinite(u)
    max_sigma_rel = 0.2
    block = FrameData(brdf=np.where(finite, d, 1.0), sigma_rel=np.where(finite, u, 1.0), theta_i=float(frame.theta_i),
                      detector=det, grid=grid, mask=finite & (u <= max_sigma_rel), name="ggx")
    info = {"data": d, "u_noise": np.where(finite, u, np.inf), "sigma_other": np.zeros(m.shape), "mask": finite,
            "max_sigma_rel": max_sigma_rel}
    params = {"s.alpha": 0.005, "s.rho_s": 50.0}
    job = FitJob(truth, [block], params, {"absolute_sigma": True}, reweight=[info])
    r = job.run()
    first = job.first_result
    assert first is not None and "reweighted" in r.noise and job.reweight is None
    assert job.blocks[0] is not block and not np.array_equal(job.blocks[0].mask, block.mask)
    pull_first = (first.value("s.alpha") - 0.004) / first.sigma("s.alpha")
    pull = (r.value("s.alpha") - 0.004) / r.sigma("s.alpha")
    assert pull_first > 3.0
    assert abs(pull) < 2.0
    # the refit started from the first fit's values
    warm = warm_params(params, first, ["ggx"])
    assert warm["s.alpha"].value == pytest.approx(first.value("s.alpha"))


def test_detection_cuts_are_made_on_the_model_not_the_reading():
    """A reading under the reduction's artifact floor whose model is above it is kept, and the reverse
    dropped; likewise for the noise-equivalent BRDF and min_snr (times the reading's absolute noise)."""
    d = np.array([[5.0, 20.0, 50.0, 50.0, 50.0]])
    m = np.array([[20.0, 5.0, 50.0, 50.0, 50.0]])
    u = np.array([[0.01, 0.01, 0.01, 0.01, 0.2]])  # absolute noise 0.05, 0.2, 0.5, 0.5, 10
    neb = np.array([[1.0, 1.0, 1.0, 60.0, 1.0]])
    det = {"noise_equivalent_brdf": neb, "artifact_floor": 10.0, "min_snr": 6.0}
    ones = np.ones(d.shape, bool)
    new = model_noise_weights(_block(d.shape, d, u), d, u, np.zeros(d.shape), ones, m, detection=det)
    # 0: reading under the floor, model above: kept; 1: the reverse: dropped; 2: kept;
    # 3: model under its noise-equivalent BRDF: dropped; 4: model 50 < 6 x 10: dropped
    assert new.usable().tolist() == [[True, False, True, False, False]]
    # the structural mask stays: a pixel masked for another reason is not revived
    masked = ones.copy()
    masked[0, 0] = False
    new = model_noise_weights(_block(d.shape, d, u), d, u, np.zeros(d.shape), masked, m, detection=det)
    assert not new.usable()[0, 0]
