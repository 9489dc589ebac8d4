"""Reduction (brdfjax.instrument.reduce): §4.2 figures, round trip synthetic -> raw -> BRDF, merges, safety."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

import brdfjax as bj
from brdfjax.instrument.reduce import (
    FLAG_SATURATED,
    SYNTHETIC_NONLINEARITY_CURVE,
    NonlinearityCurve,
    ReductionError,
    dynamic_range_decades,
    incident_flux,
    max_measurable_brdf,
    noise_equivalent_brdf,
    plot_merge_comparison,
    read_reduced_frame,
    reduce_measurement_set,
    scatter_flux_high,
    stitch_replacement,
    stitch_weighted,
)
from brdfjax.io.exr import read_frame_exr
from brdfjax.io.raw import Calibration, read_raw_exr, write_manifest, write_raw_exr

DATA = Path(__file__).resolve().parents[1] / "data"
_spec = importlib.util.spec_from_file_location("make_example_set", DATA / "make_example_set.py")
example = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(example)

#: Characterised ND filters (tolerance 0): the ND term of Eq 97 vanishes, so the round trip tests the rest.
CHARACTERISED = {4.0: 0.0, 1.0: 0.0, 0.2: 0.0, 0.1: 0.0, 3.0: 0.0}
#: Sample name -> (theta_i deg, ND stack): the solar cell through 3.0 OD, and through the seed's §4.2 stacks.
SAMPLES = {"solar_cell": (20.0, "3.0"), "mirror_od": (20.0, "4.0+1.0+0.2"), "aluminium_od": (20.0, "4.0+0.1")}


def _sha(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A synthetic set from the seed solar-cell model on the example camera (every effect at its default)."""
    folder = tmp_path_factory.mktemp("set")
    ins = example.example_instrument(seed=11)
    model = bj.solar_cell()
    frame = bj.Conditions.from_degrees(20.0)
    brdf = ins.render_brdf(model, frame)
    samples = {name: (brdf, bj.Conditions.from_degrees(ti), nd) for name, (ti, nd) in SAMPLES.items()}
    manifest = ins.write_set(folder, samples, calibration=Calibration(nd_tolerances={3.0: 0.15}))
    light = ins.sample_flux(brdf, frame, "3.0") - ins.camera.ambient  # expected sDC (t_ref = 1 s)
    return dict(folder=folder, manifest=manifest, truth=ins.expected_brdf(brdf), light=light, ins=ins)


@pytest.fixture(scope="module")
def reduced(measured, tmp_path_factory):
    before = _sha(measured["folder"])
    out = {}
    for merge in ("weighted", "replacement"):
        paths = reduce_measurement_set(
            measured["manifest"], tmp_path_factory.mktemp(merge), merge=merge, nd_tolerances=CHARACTERISED
        )
        out[merge] = {p.stem: read_reduced_frame(p) for p in paths}
    out["seed_tolerances"] = {
        p.stem: read_reduced_frame(p)
        for p in reduce_measurement_set(measured["manifest"], tmp_path_factory.mktemp("seed"))
    }
    out["hashes"] = (before, _sha(measured["folder"]))
    return out


def _selected(r, truth):
    """Pixels whose *true* BRDF is above the noise floor and the artifact floor, and not saturated."""
    flags = r.extra["flags"].astype(int)
    return (truth >= r.extra["noise_equivalent_brdf"]) & (truth >= r.attrs["artifact_floor"]) & (
        flags & FLAG_SATURATED == 0
    )


def _fractions(r, truth):
    sel = _selected(r, truth)
    z = (r.brdf[sel] / truth[sel] - 1.0) / r.extra["sigma_rel"][sel]
    return sel.sum(), np.mean(np.abs(z) <= 1), np.mean(np.abs(z) <= 2)


# --- §4.2 figures ----------------------------------------------------------------------------------


def test_section_4_2_figures_from_seed_inputs():
    """Seed §4.2: cos = 1, Omega = 2.864e-10 sr, Phi_b = 9.828e9 sDC, OD_b = 5.2, floor 48.05 (std 23.11) sDC."""
    phi_high = scatter_flux_high(16383, (1e-3, 1e-2, 1e-1, 1.0))
    assert phi_high == pytest.approx(1.6383e7)
    cases = [(5.2, 17.07, 8.21, 5.82e6), (5.2 - 1.1, 1.36, 0.65, 4.62e5), (0.0, 1.08e-4, 5.18e-5, 36.7)]
    for od_m, neb, neb_std, f_max in cases:
        assert noise_equivalent_brdf(48.05, 9.828e9, 5.2, od_m) == pytest.approx(neb, rel=5e-3)
        assert noise_equivalent_brdf(23.11, 9.828e9, 5.2, od_m) == pytest.approx(neb_std, rel=5e-3)
        assert max_measurable_brdf(phi_high, 9.828e9, 5.2, od_m) == pytest.approx(f_max, rel=5e-3)
    assert dynamic_range_decades(phi_high, 48.05) == pytest.approx(5.53, abs=5e-3)
    assert dynamic_range_decades(phi_high, 1.0) == pytest.approx(7.21, abs=5e-3)  # noise-free (§4.2)
    assert incident_flux(9.828e9, 5.2, 5.2) == 9.828e9  # Eq 87: no adjustment with the same filters
    assert incident_flux(1.0, 5.2, 4.1) == pytest.approx(10**1.1)


def test_section_4_2_figures_computed_by_the_reduction(reduced):
    """The reduction recomputes the figures from the raw stacks of a seed-like synthetic instrument."""
    got = {name: r.attrs for name, r in reduced["weighted"].items()}
    mirror, alu = got["mirror_od"], got["aluminium_od"]
    print("\n§4.2 from the synthetic set (seed): NEB, std, max, decades")
    cases = (("OD_m = OD_b", mirror, (17.07, 8.21, 5.82e6)), ("OD_b - OD_m = 1.1", alu, (1.36, 0.65, 4.62e5)))
    for name, a, seed in cases:
        print(f"  {name}: {a['noise_equivalent_brdf']:.4g} ({seed[0]}), {a['noise_equivalent_brdf_std']:.3g} "
              f"({seed[1]}), {a['max_measurable_brdf']:.4g} ({seed[2]:.3g}), {a['dynamic_range_decades']:.3f} (5.53)")
        assert a["noise_equivalent_brdf"] == pytest.approx(seed[0], rel=0.03)
        assert a["noise_equivalent_brdf_std"] == pytest.approx(seed[1], rel=0.03)
        assert a["max_measurable_brdf"] == pytest.approx(seed[2], rel=0.01)
        assert a["dynamic_range_decades"] == pytest.approx(5.53, abs=0.01)
    assert mirror["phi_s_high_sdc"] == 1.6383e7
    assert mirror["beam_flux_sdc"] == pytest.approx(9.828e9 / 64, rel=0.005)  # coarse camera: Phi_b / 8^2
    assert alu["incident_flux_sdc"] == pytest.approx(alu["beam_flux_sdc"] * 10**1.1)


# --- round trip ------------------------------------------------------------------------------------


def test_round_trip_within_stated_uncertainty(measured, reduced):
    truth = measured["truth"]
    n, f1, f2 = _fractions(reduced["weighted"]["solar_cell"], truth)
    n_s, f1_s, f2_s = _fractions(reduced["seed_tolerances"]["solar_cell"], truth)
    print(f"\nround trip, {n} pixels above the floors: within 1 sigma {f1:.3f}, within 2 sigma {f2:.3f} "
          f"(characterised ND filters); {f1_s:.3f} / {f2_s:.3f} with the seed's ND tolerances")
    assert n > 500
    assert f2 >= 0.95
    assert f1 >= 0.68
    assert f2_s >= f2
    r = reduced["weighted"]["solar_cell"]
    sel = _selected(r, truth)
    assert np.mean(r.extra["mask"][sel]) > 0.9  # nearly all of them are usable
    assert r.attrs["u_nd"] == 0.0 and reduced["seed_tolerances"]["solar_cell"].attrs["u_nd"] > 0.5


def test_weighted_merge_beats_replacement(measured, reduced):
    """Relative BRDF error against the truth on the same stack: inverse-variance merge < replacement (§3.6)."""
    truth = measured["truth"]
    w, rp = reduced["weighted"]["solar_cell"], reduced["replacement"]["solar_cell"]
    sel = _selected(w, truth) & _selected(rp, truth)
    err_w = np.sqrt(np.mean((w.brdf[sel] / truth[sel] - 1) ** 2))
    err_r = np.sqrt(np.mean((rp.brdf[sel] / truth[sel] - 1) ** 2))
    print(f"\nRMS relative BRDF error over {sel.sum()} pixels: weighted {err_w:.4%}, replacement {err_r:.4%}")
    assert err_w < err_r


def _ramp(config, seed, shape=(48, 128)):
    """A 5.5-decade ramp target (constant down each column): stack, background, expected light (sDC)."""
    det = bj.Detector.seed(shape=shape, pixel_pitch=5.5e-6 * example.BIN, pixel_pitch_v=5.5e-6 * example.BIN)
    ins = example.example_instrument(seed=seed, detector=det, config=config)
    frame = bj.Conditions.from_degrees(20.0)
    ramp = np.broadcast_to(10 ** np.linspace(-1.0, 4.5, shape[1]), shape).astype(np.float32)
    st = ins.measure_sample(ramp, frame, "3.0")
    bg = ins.measure_background(st.attrs)
    light = ins.sample_flux(ramp, frame, "3.0")
    if ins.camera.ambient is not None:
        light = light - ins.camera.ambient
    return st, bg, light


def test_weighted_merge_lower_noise_error_on_ramp():
    """Noise only (no non-linearity), every flux level sampled: the inverse-variance merge has the lower error,
    and its stated standard deviation matches the scatter."""
    sq = {"replacement": [], "weighted": []}
    pulls = []
    for seed in (1, 2, 3):
        st, bg, light = _ramp(example.example_config().without("nonlinearity"), seed)
        # A camera without non-linearity: its calibration curve is flat, the weights are the noise's alone.
        w, r = stitch_weighted(st, bg, nonlinearity_curve=None), stitch_replacement(st, bg)
        sel = (light > 500) & ~w.saturated
        sq["weighted"].append(np.mean((w.flux[sel] / light[sel] - 1) ** 2))
        sq["replacement"].append(np.mean((r.flux[sel] / light[sel] - 1) ** 2))
        faint = (light > 0) & (light < 2e3)  # noise-dominated pixels, unbiased by clipping at 0 only above ~100 sDC
        pulls.append(((w.flux - light) / np.sqrt(w.variance))[faint & (light > 100)])
    e_w, e_r = (float(np.sqrt(np.mean(sq[k]))) for k in ("weighted", "replacement"))
    print(f"\nramp, noise only: RMS relative flux error weighted {e_w:.4%}, replacement {e_r:.4%}")
    assert e_w < e_r
    assert np.std(np.concatenate(pulls)) == pytest.approx(1.0, abs=0.15)


def _seams(merged, st, light):
    """Jump of the mean relative error across each exposure switch (85-97 % vs 103-120 % of the switch flux)."""
    t, fs = st.exposure_times, st.attrs.full_scale
    jumps = []
    for k in range(len(t) - 1):
        level = 0.98 * fs * t[-1] / t[k + 1]
        below = (light > 0.85 * level) & (light < 0.97 * level)
        above = (light > 1.03 * level) & (light < 1.2 * level)
        jumps.append(float(np.mean(merged.flux[above] / light[above]) - np.mean(merged.flux[below] / light[below])))
    return np.array(jumps)


def _merges(st, bg):
    curve = SYNTHETIC_NONLINEARITY_CURVE
    return {
        "replacement": stitch_replacement(st, bg),
        "weighted": stitch_weighted(st, bg),  # default: noise + the curve's non-linearity variance
        "corrected": stitch_weighted(st, bg, nonlinearity_curve=curve, correct_nonlinearity=True),
        "taper": stitch_weighted(st, bg, taper_start=0.5),
    }


def test_seams_of_the_merges():
    """The camera's common non-linearity makes the replacement scheme jump ~2.8 % at each exposure switch; weighting
    by the full variance (noise + the curve's non-linearity error) shrinks the seams, correcting the readings by the
    curve (or the hand-over taper) removes them."""
    cfg = example.example_config().ideal().with_effects(
        nonlinearity=True, black_level=True, quantisation=True, saturation=True
    )
    a = cfg.nonlinearity.common_max
    assert SYNTHETIC_NONLINEARITY_CURVE.points == ((0.0, -a), (1.0, a))  # the curve the camera has
    st, bg, light = _ramp(cfg, 0)
    jumps = {name: _seams(m, st, light) for name, m in _merges(st, bg).items()}
    print("\nseams (mean relative error jump at the 10, 100, 1000 ms switches): "
          + "; ".join(f"{n} " + ", ".join(f"{j:+.2%}" for j in v) for n, v in jumps.items()))
    assert np.all(np.abs(jumps["replacement"]) > 0.02)
    assert np.max(np.abs(jumps["weighted"])) < 0.7 * np.min(np.abs(jumps["replacement"]))
    assert np.all(np.abs(jumps["corrected"]) < 0.005)
    assert np.all(np.abs(jumps["taper"]) < 0.005)


def test_rms_error_of_the_merges():
    """Every effect on, every flux level sampled: the full-variance weighted merge has a lower RMS error than the
    replacement scheme, the merge of corrected readings a much lower one; the taper pays for its seams in noise."""
    sq: dict = {}
    for seed in (1, 2):
        st, bg, light = _ramp(example.example_config(), seed)
        sel = light > 500
        for name, m in _merges(st, bg).items():
            sq.setdefault(name, []).append(np.mean((m.flux[sel] / light[sel] - 1) ** 2))
    rms = {k: float(np.sqrt(np.mean(v))) for k, v in sq.items()}
    print("\nramp, every effect: RMS relative flux error " + ", ".join(f"{k} {v:.4%}" for k, v in rms.items()))
    assert rms["weighted"] < rms["replacement"]
    assert rms["corrected"] < rms["weighted"] - 0.002


def test_nonlinearity_curve():
    """The curve inverts the synthetic camera's response ``S (1 + a (2 S / FS - 1))``; bad curves are refused."""
    curve = SYNTHETIC_NONLINEARITY_CURVE
    fs, a = 16383.0, 0.0172
    s = np.linspace(0.0, 1.0, 101) * fs
    reading = s * (1 + a * (2 * s / fs - 1))
    np.testing.assert_allclose(curve.linearise(reading, fs), s, rtol=1e-6, atol=1e-6)
    assert curve(0.5) == 0.0 and curve(2.0) == pytest.approx(a) and curve(-1.0) == pytest.approx(-a)
    assert NonlinearityCurve([[0.0, 0.0], [1.0, 0.01]]).describe() == "0:0,1:0.01"
    for bad in ([], [(0.5, 0.0), (0.5, 0.1)], [(0.0, 0.7)], [(1.2, 0.0)]):
        with pytest.raises(ValueError):
            NonlinearityCurve(bad)


def test_manifest_curve_and_correction(measured, tmp_path):
    """The manifest's [calibration] nonlinearity_curve reaches the weighted merge; the corrected round trip holds."""
    folder = measured["folder"]
    for p in folder.iterdir():
        if p.suffix == ".exr":
            (tmp_path / p.name).write_bytes(p.read_bytes())
    curve = ((0.0, -0.0172), (1.0, 0.0172))
    m = write_manifest(tmp_path / "manifest.toml", ("beam.exr", "beam_background.exr"),
                       [("s", "solar_cell.exr", "solar_cell_background.exr")],
                       Calibration(nd_tolerances={3.0: 0.15}, nonlinearity_curve=curve))
    (path,) = reduce_measurement_set(m, tmp_path / "out", nd_tolerances=CHARACTERISED, correct_nonlinearity=True)
    r = read_reduced_frame(path)
    assert r.attrs["nonlinearity_curve"] == "0:-0.0172,1:0.0172" and r.attrs["nonlinearity_corrected"] == 1
    n, f1, f2 = _fractions(r, measured["truth"])
    print(f"\ncorrected round trip, {n} pixels: within 1 sigma {f1:.3f}, within 2 sigma {f2:.3f}")
    assert f2 >= 0.95
    with pytest.raises(ValueError, match="correct_nonlinearity needs merge='weighted'"):
        reduce_measurement_set(m, tmp_path / "out", merge="replacement", correct_nonlinearity=True)


def test_round_trip_misaligned(tmp_path):
    """Misalignment (seed §4.4 example rotations, m_h = 3, m_v = -5 px) is undone by the pixel mapping."""
    det = example.example_detector(
        roll=np.deg2rad(0.11), yaw=np.deg2rad(0.062), pitch=np.deg2rad(0.025), m_h=3.0, m_v=-5.0
    )
    ins = example.example_instrument(seed=5, detector=det)
    frame = bj.Conditions.from_degrees(20.0)
    brdf = ins.render_brdf(bj.solar_cell(), frame)
    manifest = ins.write_set(tmp_path / "set", {"s": (brdf, frame, "3.0")})
    (path,) = reduce_measurement_set(manifest, tmp_path / "out", nd_tolerances=CHARACTERISED)
    r = read_reduced_frame(path)
    n, f1, f2 = _fractions(r, ins.expected_brdf(brdf))
    print(f"\nmisaligned round trip, {n} pixels: within 1 sigma {f1:.3f}, within 2 sigma {f2:.3f}")
    assert f2 >= 0.95
    assert r.attrs["m_h"] == 3.0 and np.all(r.extra["u_scatter_angle"] > 0)


# --- outputs and safety ------------------------------------------------------------------------------


def test_inputs_unmodified(reduced):
    before, after = reduced["hashes"]
    assert before == after and len(before) == 2 + 2 * len(SAMPLES) + 1


def test_output_frame_format(measured, reduced):
    r = reduced["weighted"]["solar_cell"]
    assert r.brdf.shape == (48, 64)
    for k in ("sigma_rel", "mask", "flags", "noise_equivalent_brdf", "u_scatter_flux", "u_scatter_nonlinearity",
              "u_scatter_noise", "u_incident_flux", "u_scatter_angle", "u_solid_angle"):
        assert r.extra[k].shape == (48, 64) and r.extra[k].dtype == np.float32
    assert set(np.unique(r.extra["mask"])) <= {0.0, 1.0}
    assert r.attrs["roi"] == (-31, 32, -23, 24) and r.attrs["merge"] == "weighted"
    assert r.attrs["theta_i"] == pytest.approx(np.deg2rad(20.0), abs=0)
    # The core pixel mapping supplies theta_s and Omega_d.
    det = example.example_detector(theta_c=np.deg2rad(20.0))
    geom = bj.render(None, bj.Conditions.from_degrees(20.0), det, outputs=("theta_s", "phi_s", "omega"))
    np.testing.assert_allclose(r.omega, geom["omega"], rtol=1e-6)
    np.testing.assert_allclose(r.theta_s, geom["theta_s"], rtol=1e-6)


def test_step_and_figure(measured, tmp_path):
    (path,) = [p for p in reduce_measurement_set(measured["manifest"], tmp_path, step=2) if p.stem == "solar_cell"][:1]
    fd = read_frame_exr(path)
    assert fd.brdf.shape == (24, 32) and fd.attrs["step"] == 2
    folder = measured["folder"]
    png = plot_merge_comparison(
        read_raw_exr(folder / "solar_cell.exr"),
        read_raw_exr(folder / "solar_cell_background.exr"),
        tmp_path / "seams.png",
        truth=measured["light"],
    )
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_interrupted_write_leaves_old_or_new(measured, tmp_path, monkeypatch):
    out = tmp_path / "out"
    (first, *_) = reduce_measurement_set(measured["manifest"], out, merge="replacement")
    old = first.read_bytes()
    real_write = OpenEXR.File.write

    def interrupted(self, filename):
        Path(filename).write_bytes(b"half a frame")
        raise KeyboardInterrupt  # e.g. Ctrl-C in the middle of writing

    monkeypatch.setattr(OpenEXR.File, "write", interrupted)
    with pytest.raises(KeyboardInterrupt):
        reduce_measurement_set(measured["manifest"], out, merge="weighted")
    assert first.read_bytes() == old  # the old output, whole
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left
    monkeypatch.setattr(OpenEXR.File, "write", real_write)
    reduce_measurement_set(measured["manifest"], out, merge="weighted")
    assert read_frame_exr(first).attrs["merge"] == "weighted"  # the new output, whole


def test_reduction_errors(measured, tmp_path):
    folder = measured["folder"]
    with pytest.raises(ValueError, match="unknown merge 'median'; known: weighted, replacement"):
        reduce_measurement_set(measured["manifest"], tmp_path, merge="median")
    with pytest.raises(ReductionError, match="would overwrite an input"):
        reduce_measurement_set(measured["manifest"], folder)
    # A background taken with other exposure times.
    bg = read_raw_exr(folder / "solar_cell_background.exr")
    write_raw_exr(tmp_path / "bg3.exr", bg.attrs, bg.exposures[:3])
    for name in ("beam.exr", "beam_background.exr", "solar_cell.exr"):
        (tmp_path / name).write_bytes((folder / name).read_bytes())
    m = write_manifest(tmp_path / "manifest.toml", ("beam.exr", "beam_background.exr"),
                       [("s", "solar_cell.exr", "bg3.exr")], Calibration(nd_tolerances={3.0: 0.15}))
    with pytest.raises(ReductionError, match=r"exposure times differ .* take the background with the same exposures"):
        reduce_measurement_set(m, tmp_path / "out")
    # A beam signature that saturates even at 1 ms.
    beam = read_raw_exr(folder / "beam.exr")
    hot = [dataclasses.replace(e, counts=np.minimum(e.counts * 50, 16383).astype(np.float32)) for e in beam.exposures]
    write_raw_exr(tmp_path / "beam.exr", beam.attrs, hot)
    m = write_manifest(tmp_path / "manifest.toml", ("beam.exr", "beam_background.exr"),
                       [("s", "solar_cell.exr", "solar_cell_background.exr")])
    (tmp_path / "solar_cell_background.exr").write_bytes((folder / "solar_cell_background.exr").read_bytes())
    with pytest.raises(ReductionError, match="saturated even at the shortest exposure .* add ND filters"):
        reduce_measurement_set(m, tmp_path / "out")


def test_missing_nd_tolerance_is_reported(measured, tmp_path):
    """Without the manifest's [calibration] the 3.0 filter has no tolerance: the message says what to add."""
    folder = measured["folder"]
    for p in folder.iterdir():
        if p.suffix == ".exr":
            (tmp_path / p.name).write_bytes(p.read_bytes())
    m = write_manifest(tmp_path / "manifest.toml", ("beam.exr", "beam_background.exr"),
                       [("s", "solar_cell.exr", "solar_cell_background.exr")])
    with pytest.raises(ValueError, match="3 OD .* has no tolerance"):
        reduce_measurement_set(m, tmp_path / "out")
