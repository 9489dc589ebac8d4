"""Synthetic instrument (brdfjax.instrument.synthetic): seed calibration figures, each effect, reproducibility."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

import brdfjax as bj
from brdfjax.instrument.reduce import stitch_raw
from brdfjax.instrument.synthetic import (
    EFFECTS,
    SEED_BEAM_FLUX,
    Camera,
    Footprint,
    InstrumentConfig,
    StrayLight,
    SyntheticInstrument,
    convolve_footprint,
    footprint_kernel,
    lens_cap_std,
)


def _det(shape=(48, 64), k=8, **kw):
    return bj.Detector.seed(shape=shape, pixel_pitch=5.5e-6 * k, pixel_pitch_v=5.5e-6 * k, **kw)


# --- config --------------------------------------------------------------------------------------


def test_config_switches_by_name():
    cfg = InstrumentConfig()
    assert set(cfg.enabled_effects()) == set(EFFECTS) - {"source_drift", "nd_error"}
    off = cfg.without("shot_noise", "dark")
    assert not off.shot_noise.enabled and not off.dark.enabled and off.nonlinearity.enabled
    assert cfg.shot_noise.enabled  # frozen: the original is unchanged
    assert cfg.ideal().enabled_effects() == ("footprint",)
    with pytest.raises(ValueError, match="unknown effect.*'shot'.*known: footprint, stray_light"):
        cfg.without("shot")
    with pytest.raises(ValidationError, match="strictly increasing"):
        InstrumentConfig(exposures_s=(1e-2, 1e-3))
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        InstrumentConfig(exposure=(1e-3,))
    with pytest.raises(ValidationError, match="greater than 0"):
        Footprint(w_px=-1.0)
    c8 = cfg.coarse(8)
    assert c8.footprint.w_px == 25.0 / 8 and c8.incident_flux_cps == pytest.approx(cfg.incident_flux_cps / 64)
    assert cfg.full_scale == 16383.0


# --- seed calibration figures ----------------------------------------------------------------------


def test_lens_cap_figures_seed_3_1():
    """§3.1: lens cap, 32-frame average: mean 29.29 / std 2.14 counts at 1 ms, std 11.21 at 15 ms."""
    cfg = InstrumentConfig(exposures_s=(1e-3, 15e-3))
    ins = SyntheticInstrument(_det((200, 200), k=1), cfg, seed=4)
    beam = ins.measure_beam()
    dark = ins.measure_dark(beam.attrs)
    e1, e15 = dark.exposures
    assert e1.counts.mean() == pytest.approx(29.29, abs=0.03)
    assert e1.counts.std() == pytest.approx(2.14, rel=0.01)
    assert e15.counts.std() == pytest.approx(11.21, rel=0.01)
    assert e15.counts.mean() == pytest.approx(29.62, abs=0.15)  # linear dark signal gives 29.52
    # The unclipped model through the same points:
    assert float(lens_cap_std(cfg.dark, 1e-3)) == pytest.approx(2.14, rel=0.01)


def test_background_figures_seed_4_2():
    """§4.2: background stitched over 1-1000 ms: mean 48.05 sDC, std 23.11; lens cap mean 45.88."""
    ins = SyntheticInstrument(_det((200, 200), k=1), InstrumentConfig(), seed=5)
    beam = ins.measure_beam()
    bg = stitch_raw(ins.measure_background(beam.attrs))
    assert bg.mean() == pytest.approx(48.05, abs=0.25)
    assert bg.std() == pytest.approx(23.11, rel=0.01)
    dark = stitch_raw(ins.measure_dark(beam.attrs))
    assert dark.mean() == pytest.approx(45.88, abs=0.25)


def test_beam_signature_seed_3_3_and_4_2():
    """Beam at OD 5.2: unsaturated at 1 ms with a ~1e4-count peak; Phi_b = 9.828e9 sDC; 1/e^2 radius 25 px."""
    ins = SyntheticInstrument(_det((256, 256), k=1), InstrumentConfig().ideal(), seed=0)
    beam = ins.measure_beam("4.0+1.0+0.2")
    e1 = beam.exposures[0]
    assert e1.counts.max() == pytest.approx(9.828e9 * 1e-3 * 2 / (np.pi * 25**2), rel=0.01)  # Eq 73 peak
    phi_b = e1.counts.sum(dtype=np.float64) * 1e3  # sDC referred to 1 s
    assert phi_b == pytest.approx(SEED_BEAM_FLUX, rel=1e-4)
    # Second moment of exp(-2 r^2 / w^2): <x^2> = w^2 / 4 (plus 1/12 for pixel integration).
    v, h = np.indices(e1.counts.shape)
    p = e1.counts / e1.counts.sum()
    ch = (p * h).sum()
    w = np.sqrt(4 * ((p * (h - ch) ** 2).sum() - 1 / 12))
    assert w == pytest.approx(25.0, rel=1e-3)
    assert (beam.exposures[-1].counts >= 16383).any()  # 1000 ms saturates the centre
    full = SyntheticInstrument(_det((256, 256), k=1), InstrumentConfig(), seed=0).measure_beam()
    assert full.exposures[0].counts.max() < 16383  # "by design, no pixels are saturated at 1 ms"


def test_stray_light_subpeaks():
    """Displaced copies of the image 4.85, 5.05 and 5.3 decades below the main peak (seed §4.6)."""
    cfg = InstrumentConfig().ideal().with_effects(stray_light=True)
    cfg = cfg.model_copy(update={"stray_light": StrayLight(peaks=((60, -40, -4.85), (-70, 30, -5.3)))})
    phi = SyntheticInstrument(_det((256, 256), k=1), cfg, seed=0).beam_flux("4.0+1.0+0.2")
    main = SyntheticInstrument(_det((256, 256), k=1), cfg.ideal(), seed=0).beam_flux("4.0+1.0+0.2")
    stray = phi.astype(np.float64) - main
    r0, c0 = np.unravel_index(np.argmax(main), main.shape)
    assert np.log10(stray[r0 - 40, c0 + 60] / main[r0, c0]) == pytest.approx(-4.85, abs=1e-3)
    assert np.log10(stray[r0 + 30, c0 - 70] / main[r0, c0]) == pytest.approx(-5.3, abs=1e-3)
    assert stray.sum() / main.sum() == pytest.approx(10**-4.85 + 10**-5.3, rel=1e-2)


def test_nonlinearity_map_statistics():
    """§4.2: dNL_s mean 2.18 %, std 0.50 %, max 16.32 %, 0.021 % of pixels above 5.19 %; common part 1.72 %."""
    cfg = InstrumentConfig()
    cam = Camera.build(cfg, (1000, 1000))
    dnl = cam.nonlinearity_map(cfg)
    assert dnl.mean() == pytest.approx(0.0218, abs=2e-4)
    assert dnl[dnl < 0.0519].std() == pytest.approx(0.0050, rel=0.1)
    assert dnl.min() >= 0.0172 and dnl.max() <= 0.1632
    assert np.mean(dnl > 0.0519) == pytest.approx(2.1e-4, rel=0.3)
    assert np.mean(cam.nonlinearity > 0) == pytest.approx(0.5, abs=0.01)
    # The response of one pixel across the range: its largest deviation from the array-average line is dNL_s.
    ins = SyntheticInstrument(_det((4, 4)), cfg.ideal().with_effects(nonlinearity=True), seed=0)
    g = ins.camera.nonlinearity
    levels = np.linspace(1e-4, 1.0, 50) * 16383
    errs = [ins.expose(np.full((4, 4), lev, np.float32), 1.0).counts / lev - 1 for lev in levels]
    np.testing.assert_allclose(np.max(np.abs(errs), axis=0), ins.camera.nonlinearity_map(cfg), atol=1e-5)
    assert g.shape == (4, 4)


# --- effects -----------------------------------------------------------------------------------------


def test_ideal_instrument_is_exact():
    """No noise or non-linearity: counts = flux x exposure, clipped only by saturation (off here)."""
    ins = SyntheticInstrument(_det(), InstrumentConfig().coarse(8).ideal(), seed=0)
    frame = bj.Conditions.from_degrees(20)
    brdf = ins.render_brdf(bj.solar_cell(), frame)
    st = ins.measure_sample(brdf, frame, "3.0")
    flux = ins.sample_flux(brdf, frame, "3.0")
    for e in st.exposures:
        np.testing.assert_allclose(e.counts, flux * e.exposure_s, rtol=1e-6)
    # Eq 45 inverted on the convolved BRDF: f_r = Phi_s / (Phi_i cos(theta_s) Omega_d)
    geom = bj.render(None, frame, ins.detector, outputs=("theta_s", "phi_s", "omega"))
    f = flux / (ins.incident_flux("3.0") * np.cos(geom["theta_s"]) * geom["omega"])
    np.testing.assert_allclose(f, ins.expected_brdf(brdf), rtol=1e-5, atol=1e-6 * float(brdf.max()))
    assert ins.incident_flux("3.0") == pytest.approx(SEED_BEAM_FLUX * 10**5.2 / 64 * 1e-3)


def test_quantisation_saturation_and_averaging():
    cfg = InstrumentConfig().coarse(8).ideal().with_effects(quantisation=True, saturation=True)
    cfg = cfg.model_copy(update={"n_frames": 8})
    st = SyntheticInstrument(_det(), cfg, seed=0).measure_beam()
    for e in st.exposures:
        assert np.all(e.counts == np.round(e.counts))  # the camera's averaged output: integer counts
        assert e.counts.max() <= 16383 and e.counts.min() >= 0
    assert (st.exposures[-1].counts == 16383).any()
    q = cfg.quantisation.model_copy(update={"round_average": False})
    st = SyntheticInstrument(_det(), cfg.model_copy(update={"quantisation": q}), seed=0).measure_beam()
    e = st.exposures[0].counts
    assert np.all(e * 8 == np.round(e * 8)) and not np.all(e == np.round(e))  # mean of 8 integer frames


def test_shot_noise_variance():
    cfg = InstrumentConfig().coarse(8).ideal().with_effects(shot_noise=True)
    cfg = cfg.model_copy(update={"n_frames": 4, "write_counts_std": True})
    ins = SyntheticInstrument(_det((200, 200)), cfg, seed=1)
    flat = np.full((200, 200), 2000.0, np.float32)  # counts/s
    e = ins.expose(flat, 1.0)
    gain = cfg.shot_noise.gain_e_per_count
    assert e.counts.mean() == pytest.approx(2000, rel=1e-3)
    assert e.counts.var() == pytest.approx(2000 / gain / 4, rel=0.02)
    assert np.mean(e.counts_std.astype(np.float64) ** 2) == pytest.approx(2000 / gain, rel=0.02)  # per frame


def test_source_drift_and_nd_error():
    base = InstrumentConfig().coarse(8).ideal()
    a = SyntheticInstrument(_det(), base.with_effects(nd_error=True), seed=0)
    # Filters shared by beam and sample cancel: only the 0.2 filter's error remains in 10^(OD_b - OD_m).
    true_b, true_m = a.camera.true_od("4.0+1.0+0.2", a.config), a.camera.true_od("4.0+1.0", a.config)
    assert true_b - true_m == pytest.approx(0.2 + a.camera.nd_offsets[(0.2, 0)])
    assert abs(a.camera.nd_offsets[(4.0, 0)]) <= 0.2 and a.camera.nd_offsets[(4.0, 0)] != 0
    with pytest.raises(ValueError, match="no tolerance for the 3 OD filter"):
        a.camera.true_od("3.0", a.config)
    drift = SyntheticInstrument(_det(), base.with_effects(source_drift=True), seed=0)
    fluxes = [drift.beam_flux("4.0+1.0+0.2").sum() for _ in range(20)]
    assert np.std(fluxes) / np.mean(fluxes) == pytest.approx(0.0101, rel=0.5)


def test_footprint_kernel_and_fft_convolution():
    k = footprint_kernel(2.5)
    assert k.shape[0] % 2 == 1 and k.sum() == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(0)
    img = rng.random((23, 17)) * 10 ** rng.uniform(-5, 5, (23, 17))  # 10 decades: FFT must not swamp the faint
    # Direct convolution oracle (zero outside the image).
    h = k.shape[0] // 2
    pad = np.zeros((23 + 2 * h, 17 + 2 * h))
    pad[h:-h, h:-h] = img
    ref = np.zeros_like(img)
    for i in range(k.shape[0]):
        for j in range(k.shape[1]):
            ref += k[::-1, ::-1][i, j] * pad[i : i + 23, j : j + 17]
    for strip in (1, 5, 23):
        out = convolve_footprint(img, k, strip_rows=strip)
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-12 * img.max())
    with pytest.raises(ValueError, match="odd sizes"):
        convolve_footprint(img, np.ones((2, 3)))


# --- reproducibility ----------------------------------------------------------------------------------


def test_same_seeds_same_stacks():
    def make(seed):
        ins = SyntheticInstrument(_det(), InstrumentConfig().coarse(8), seed=seed)
        return ins.measure_sample(bj.solar_cell(), bj.Conditions.from_degrees(20), "3.0")

    a, b, c = make(7), make(7), make(8)
    for ea, eb, ec in zip(a.exposures, b.exposures, c.exposures):
        np.testing.assert_array_equal(ea.counts, eb.counts)
        np.testing.assert_array_equal(ea.counts_std, eb.counts_std)
        assert not np.array_equal(ea.counts, ec.counts)
    assert a.attrs == b.attrs
    assert "shot_noise" in a.attrs.extra["synthetic_effects"]


def test_misaligned_detector_moves_the_beam():
    det = _det((64, 64), k=1, m_h=3.0, m_v=-5.0)
    ins = SyntheticInstrument(det, InstrumentConfig().coarse(4).ideal(), seed=0)
    e = ins.measure_beam().exposures[0].counts
    v, h = np.indices(e.shape)
    p = e / e.sum()
    h_min, _, v_min, _ = det.index_range
    assert (p * h).sum() + h_min == pytest.approx(-3.0, abs=0.05)
    assert (p * v).sum() + v_min == pytest.approx(5.0, abs=0.05)


def test_shape_mismatch_message():
    ins = SyntheticInstrument(_det(), InstrumentConfig().coarse(8), seed=0)
    with pytest.raises(ValueError, match=r"BRDF frame has shape \(3, 3\); the detector's array is \(48, 64\)"):
        ins.measure_sample(np.ones((3, 3)), bj.Conditions.from_degrees(20), "3.0")


def test_footprint_kernel_on_a_decimated_grid_keeps_the_raw_variance():
    """Sampled every `step` pixels, the kernel keeps the raw kernel's second moment; cell-integrated it would
    gain (step^2 - 1)/12 pixel^2 (the bias that made fitted widths 1 % low at step 4)."""
    raw = footprint_kernel(12.5, tail=1e-9)
    n_raw = np.arange(raw.shape[0]) - raw.shape[0] // 2
    var_raw = float((raw.sum(0) * n_raw**2).sum())
    for step in (2, 4, 8):
        k = footprint_kernel(12.5, tail=1e-9, step=step)
        assert k.shape[0] % 2 == 1 and abs(k.sum() - 1) < 1e-12
        n = (np.arange(k.shape[0]) - k.shape[0] // 2) * step
        assert abs(float((k.sum(0) * n**2).sum()) / var_raw - 1) < 1e-3  # Riemann-sum error of the sampling
        cell = footprint_kernel(12.5 / step, tail=1e-9)
        n_cell = (np.arange(cell.shape[0]) - cell.shape[0] // 2) * step
        assert abs(float((cell.sum(0) * n_cell**2).sum()) - var_raw - (step**2 - 1) / 12) < 1e-3
    with pytest.raises(ValueError, match="step must be a positive integer"):
        footprint_kernel(3.0, step=0)
