"""Fit data from reduced frames (brdfjax.fit._frames_io) and the TOML fit config (brdfjax.fit.config)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.core.render import render_geometry
from brdfjax.fit import FitInputError, frame_data_from_reduced, read_frame_data
from brdfjax.instrument.reduce import read_reduced_frame, reduce_measurement_set

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def reduced_example(tmp_path_factory):
    """The example measurement set (64 x 48 coarse camera, solar cell at 20 deg) reduced at step 1."""
    out = tmp_path_factory.mktemp("reduced")
    (path,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", out)
    return path


def test_read_frame_data_round_trips_detector_grid_and_channels(reduced_example):
    r = read_reduced_frame(reduced_example)
    f = read_frame_data(reduced_example)  # sigma "auto": the frame has u_scatter_flux, so "pixel"
    assert f.name == "solar_cell_20deg"
    assert f.detector.shape == (48, 64)
    assert f.detector.theta_c is None  # the arm sat on the peak: it follows theta_i
    assert f.theta_i == pytest.approx(np.radians(20.0), abs=1e-15)
    assert f.wavelength == pytest.approx(632.8e-9)
    assert f.grid.shape == (48, 64)
    assert (f.grid.n_h[0], f.grid.n_h[-1], f.grid.n_v[0], f.grid.n_v[-1]) == (-31, 32, -23, 24)
    np.testing.assert_array_equal(f.brdf, r.brdf.astype(np.float64))
    np.testing.assert_array_equal(f.sigma_rel, r.extra["u_scatter_flux"].astype(np.float64))
    total = read_frame_data(reduced_example, sigma="total")
    np.testing.assert_array_equal(total.sigma_rel, r.extra["sigma_rel"].astype(np.float64))
    np.testing.assert_array_equal(f.mask, r.extra["mask"] > 0.5)
    # the rebuilt detector and grid map the pixels to the stored scatter directions
    geom = render_geometry(bj.Conditions(f.theta_i, f.phi_ref, f.wavelength), f.arm_detector(), grid=f.grid)
    np.testing.assert_allclose(np.asarray(geom["theta_s"]), r.theta_s, atol=2e-7)
    np.testing.assert_allclose(np.asarray(geom["omega"]), r.omega, rtol=1e-6)
    assert 0 < f.usable().sum() == int((r.extra["mask"] > 0.5).sum())
    assert f.footprint is None


def test_frame_data_decimates_cuts_roi_masks_and_adds_footprint(reduced_example):
    r = read_reduced_frame(reduced_example)
    f = frame_data_from_reduced(r, step=3, name="x")
    assert f.name == "x" and f.grid.shape == (16, 22)
    np.testing.assert_array_equal(f.grid.n_h, np.arange(-31, 33, 3))
    np.testing.assert_array_equal(f.brdf, r.brdf[::3, ::3].astype(np.float64))
    g = frame_data_from_reduced(r, roi=(-10, 10, -5, 5))
    assert g.grid.shape == (11, 21) and g.grid.n_h[0] == -10 and g.grid.n_v[-1] == 5
    user = np.zeros(r.brdf.shape, bool)
    user[:, :32] = True
    h = frame_data_from_reduced(r, mask=user)
    assert not h.mask[:, 32:].any() and h.mask[:, :32].sum() == (r.extra["mask"][:, :32] > 0.5).sum()
    k = frame_data_from_reduced(r, footprint_w_px=25.0 / 8, step=1)
    assert k.footprint.shape[0] % 2 == 1 and k.footprint.sum() == pytest.approx(1.0)
    with pytest.raises(FitInputError, match=r"region of interest \(100, 110, 0, 1\) holds no pixel"):
        frame_data_from_reduced(r, roi=(100, 110, 0, 1))
    with pytest.raises(FitInputError, match="mask has shape"):
        frame_data_from_reduced(r, mask=np.ones((3, 3), bool))


def test_frame_data_errors_name_the_file(reduced_example, tmp_path):
    with pytest.raises(FitInputError, match="nope.exr: no such frame file"):
        read_frame_data(tmp_path / "nope.exr")
    bad = tmp_path / "bad.exr"
    bad.write_text("not an exr")
    with pytest.raises(FitInputError, match="bad.exr: not a readable OpenEXR"):
        read_frame_data(bad)
    r = read_reduced_frame(reduced_example)
    no_sigma = dataclasses.replace(r, extra={"mask": r.extra["mask"]})
    with pytest.raises(FitInputError, match="no 'sigma_rel' channel"):
        frame_data_from_reduced(no_sigma)
    nan = dataclasses.replace(r, brdf=np.full_like(r.brdf, np.nan))
    with pytest.raises(FitInputError, match="'brdf' is all NaN"):
        frame_data_from_reduced(nan)


# --- the TOML fit config ------------------------------------------------------------------------

import textwrap  # noqa: E402

from helpers import write_config  # noqa: E402
from pydantic import BaseModel, ConfigDict  # noqa: E402

from brdfjax.config import ConfigError  # noqa: E402
from brdfjax.fit import Param  # noqa: E402
from brdfjax.fit.config import load_fit_config  # noqa: E402
from brdfjax.fit.job import build_fit_job  # noqa: E402
from brdfjax.instrument.reduce import write_reduced_frame  # noqa: E402

HEAD = """
precision = "float64"
[data]
frames = ["{frame}"]
footprint_w_px = 3.125
sigma = "noise"
[model]
preset = "solar_cell"
"""


def _config(tmp_path, body, frame, name="fit.toml"):
    return write_config(tmp_path, HEAD.format(frame=Path(frame).as_posix()) + textwrap.dedent(body), name)


def _error(path, **kw) -> str:
    with pytest.raises(ConfigError) as e:
        load_fit_config(path, **kw)
    return str(e.value)


def test_params_convert_units_and_shorthands(tmp_path, reduced_example):
    p = _config(tmp_path, """
        [params]
        m1 = "auto"
        rho_s1 = 0.02
        n1 = { value = "auto", lower = 1.0, upper = 6.0 }
        dtheta_deg = { value = 0.5, lower = -5.0, upper = 5.0 }
        a_m = { value = 8e-4, free = false }
        phi_ref_deg = { value = [0.1], per_frame = true }
        offset = { k = "fixed" }
        """, reduced_example)
    cfg = load_fit_config(p)
    ps = cfg.build_params()
    assert ps["m1"] == Param("auto")
    assert ps["rho_s1"] == Param(0.02)
    assert ps["n1"] == Param("auto", lower=1.0, upper=6.0)
    assert ps["dtheta"].value == pytest.approx(np.radians(0.5))
    assert (ps["dtheta"].lower, ps["dtheta"].upper) == pytest.approx((np.radians(-5.0), np.radians(5.0)))
    assert ps["a"] == Param(8e-4, free=False)
    assert ps["phi_ref"].value == pytest.approx([np.radians(0.1)]) and ps["phi_ref"].per_frame is True
    assert ps["offset.k"] == Param.fixed()
    assert cfg.source == p and cfg.data.frames == [Path(reduced_example).as_posix()]


def test_unknown_parameter_is_named_with_the_known_ones(tmp_path, reduced_example):
    msg = _error(_config(tmp_path, "[params]\nm3 = 'auto'\n", reduced_example))
    assert "fit.toml: params.m3: unknown parameter 'm3' for this model" in msg
    assert "known: m1, rho_s1, n1" in msg and "dtheta_deg" in msg and "phi_ref_deg" in msg
    msg = _error(_config(tmp_path, "[params]\ndtheta = 0.5\n", reduced_example))
    assert "params.dtheta: unknown parameter 'dtheta'" in msg and "did you mean 'dtheta_deg'?" in msg


def test_lower_above_upper_is_an_error(tmp_path, reduced_example):
    msg = _error(_config(tmp_path, "[params]\nn1 = { value = 'auto', lower = 6.0, upper = 1.0 }\n", reduced_example))
    assert "params.n1: lower bound 6.0 > upper bound 1.0; swap them" in msg
    msg = _error(_config(tmp_path, "[params]\nn1 = { value = 9.0, lower = 1.0, upper = 6.0 }\n", reduced_example))
    assert "params.n1.value: start value 9.0 is outside its bounds [1.0, 6.0]" in msg


def test_param_rules_are_reported_in_the_keys_unit(tmp_path, reduced_example):
    # the rules of fit._params.param_problems, reported at the config key in degrees, not radians
    msg = _error(_config(tmp_path, "[params]\ndtheta_deg = { value = 7.5, lower = -5.0, upper = 5.0 }\n", reduced_example))
    assert "params.dtheta_deg.value: start value 7.5 is outside its bounds [-5.0, 5.0]" in msg
    msg = _error(_config(tmp_path, "[params]\ndtheta_deg = { value = 0.5, lower = 2.0, upper = 2.0 }\n", reduced_example))
    assert "params.dtheta_deg: lower == upper == 2.0 leaves nothing to fit; fix it with free=False" in msg
    msg = _error(_config(tmp_path, "[params]\ndtheta_deg = { value = 0.5, scale = -1.0 }\n", reduced_example))
    assert "params.dtheta_deg.scale: scale must be a positive number" in msg
    msg = _error(_config(tmp_path, "[params]\nphi_ref_deg = { value = [0.1, 0.2], per_frame = false }\n", reduced_example))
    assert "params.phi_ref_deg.value: a list of values needs per_frame = true" in msg
    # a fixed parameter may sit on equal bounds
    p = _config(tmp_path, "[params]\nn1 = { value = 2.0, lower = 2.0, upper = 2.0, free = false }\n", reduced_example)
    assert load_fit_config(p).build_params()["n1"] == Param(2.0, lower=2.0, upper=2.0, free=False)


def test_unknown_keys_and_bad_values_name_the_key(tmp_path, reduced_example):
    msg = _error(_config(tmp_path, "[fit]\nsolvr = 'lbfgsb'\n", reduced_example))
    assert "fit.solvr: unknown key (did you mean 'solver'?)" in msg
    msg = _error(_config(tmp_path, "[fit]\nsolver = 'newton'\n", reduced_example))
    assert "fit.solver: unknown solver 'newton'; known: levenberg_marquardt, lbfgsb" in msg
    # solver options are checked at loading, before any data are made or read
    msg = _error(_config(tmp_path, "[fit]\nsolver_options = { ftol = -1.0 }\n", reduced_example))
    assert "fit: solver_options: solver option 'ftol' must be a finite number >= 0 (0 turns it off), got -1.0" in msg
    msg = _error(_config(tmp_path, "[fit]\nsolver_options = { tolerance = 1e-3 }\n", reduced_example))
    assert "fit: solver_options: solver 'levenberg_marquardt': unknown option(s) ['tolerance']" in msg
    msg = _error(_config(tmp_path, "[fit]\nloss = 'l1'\n", reduced_example))
    assert "fit.loss:" in msg and "'linear', 'huber' or 'cauchy'" in msg
    msg = _error(_config(tmp_path, "[params]\nn1 = { value = 1.5, lowr = 1.0 }\n", reduced_example))
    assert "params.n1: unknown key(s) ['lowr']" in msg
    msg = _error(_config(tmp_path, "[sample]\nn_walkers = 8\n", reduced_example))
    assert "sample: unknown key" in msg


def test_missing_files_and_bad_toml(tmp_path, reduced_example):
    msg = _error(_config(tmp_path, "", tmp_path / "nope.exr"))
    assert "data.frames[0]: no such frame file" in msg and "nope.exr" in msg
    msg = _error(tmp_path / "absent.toml")
    assert "absent.toml: config file not found" in msg
    bad = tmp_path / "bad.toml"
    bad.write_text("[data\n")
    assert "not valid TOML" in _error(bad)
    t = tmp_path / "t.toml"
    t.write_text('[[data.tables]]\npath = "missing.csv"\n[model]\npreset = "solar_cell"\n')
    msg = _error(t)
    assert "data.tables[0]: format 'table' needs 'columns'" in msg
    t.write_text('[[data.tables]]\npath = "missing.csv"\nformat = "merl"\n[model]\npreset = "solar_cell"\n')
    assert "data.tables[0].path: no such table file" in _error(t)


def test_extra_sections_are_validated_by_their_models(tmp_path, reduced_example):
    class Sample(BaseModel):
        model_config = ConfigDict(extra="forbid", strict=True)
        n_walkers: int = 32

    p = _config(tmp_path, "[sample]\nn_walkers = 8\n", reduced_example)
    cfg = load_fit_config(p, sections={"sample": Sample})
    assert cfg.sections["sample"].n_walkers == 8
    p = _config(tmp_path, "[sample]\nn_walker = 8\n", reduced_example)
    assert "sample.n_walker: unknown key" in _error(p, sections={"sample": Sample})


def test_empty_mask_is_an_error_naming_the_options(tmp_path, reduced_example):
    p = _config(tmp_path, "", reduced_example)
    assert len(build_fit_job(load_fit_config(p)).blocks) == 1
    p.write_text(p.read_text().replace('sigma = "noise"', 'sigma = "noise"\nmin_brdf = 1e12'))
    with pytest.raises(ConfigError, match=r"data.frames\[0\]: empty mask: frame 'solar_cell_20deg': no usable points: "
                       r"the mask selects none of the 3072 points \(after min_brdf = 1000000000000.0\)"):
        build_fit_job(load_fit_config(p))
    p.write_text(p.read_text().replace("min_brdf = 1e12", "roi = [100, 120, 0, 5]"))
    with pytest.raises(ConfigError, match=r"data.frames\[0\]: .*region of interest \(100, 120, 0, 5\) holds no pixel"):
        build_fit_job(load_fit_config(p))


def test_all_nan_frame_is_an_error(tmp_path, reduced_example):
    r = read_reduced_frame(reduced_example)
    nan = write_reduced_frame(tmp_path / "nan.exr", dataclasses.replace(r, brdf=np.full_like(r.brdf, np.nan)))
    with pytest.raises(ConfigError, match=r"data.frames\[0\]: frame 'nan': 'brdf' is all NaN"):
        build_fit_job(load_fit_config(_config(tmp_path, "", nan)))


def test_frames_from_different_detectors_need_to_say_so(tmp_path, reduced_example):
    r = read_reduced_frame(reduced_example)
    other = write_reduced_frame(tmp_path / "other.exr", dataclasses.replace(r, attrs={**r.attrs, "R": 0.3}))
    body = HEAD.format(frame=Path(reduced_example).as_posix()).replace(
        "frames = [", f'frames = ["{other.as_posix()}", '
    )
    p = tmp_path / "two.toml"
    p.write_text(body)
    with pytest.raises(ConfigError, match=r"two.toml: data: frames 'other' and 'solar_cell_20deg' were taken with "
                       "different detectors.*allow_different_detectors = true"):
        build_fit_job(load_fit_config(p))
    p.write_text(body.replace("[model]", "allow_different_detectors = true\n[model]"))
    job = build_fit_job(load_fit_config(p))
    assert [b.name for b in job.blocks] == ["other", "solar_cell_20deg"]
    assert job.fit_kwargs["allow_different_detectors"] is True


def test_a_table_with_a_column_mapping(tmp_path):
    csv = tmp_path / "gonio.csv"
    rows = ["inc_deg,scat_deg,azi_deg,f"]
    for ti in (20, 40):
        for ts in (10, 20, 30, 40, 50):
            rows.append(f"{ti},{ts},180,{1.0 + 0.1 * ts}")
    csv.write_text("\n".join(rows) + "\n")
    p = tmp_path / "tab.toml"
    p.write_text(textwrap.dedent("""
        [[data.tables]]
        path = "gonio.csv"
        columns = { theta_i = "inc_deg", theta_s = "scat_deg", phi_s = "azi_deg", brdf = "f" }
        angle_unit = "deg"
        theta_i_deg = [40]
        max_theta_s_deg = 45
        sigma_rel = 0.05
        [model.terms.diffuse]
        kind = "lambertian"
        params = { rho_d = 0.5 }
        [params]
        "diffuse.rho_d" = "auto"
    """))
    job = build_fit_job(load_fit_config(p))
    (t,) = job.blocks
    assert t.name == "gonio" and len(t) == 10
    assert t.usable().sum() == 4  # theta_i = 40, theta_s <= 45
    np.testing.assert_allclose(np.asarray(t.theta_s)[t.usable()], np.radians([10, 20, 30, 40]))
    np.testing.assert_allclose(np.asarray(t.phi_s), np.pi)
    np.testing.assert_allclose(np.asarray(t.sigma_rel), 0.05)
    p.write_text(p.read_text().replace("theta_i_deg = [40]", "theta_i_deg = [30]"))
    with pytest.raises(ConfigError, match=r"data.tables\[0\].theta_i_deg: none of \[30.0\] is in .*gonio.csv \(it has: 20, 40\)"):
        build_fit_job(load_fit_config(p))


def test_a_raw_manifest_is_reduced_into_the_work_dir(tmp_path):
    p = tmp_path / "raw.toml"
    manifest = (DATA / "example_set" / "manifest.toml").as_posix()
    p.write_text(textwrap.dedent(f"""
        [data]
        manifest = "{manifest}"
        roi = [-20, 20, -15, 15]
        exclude = [[-20, -10, -15, 15]]
        [data.reduce]
        step = 2
        [model]
        preset = "solar_cell"
    """))
    job = build_fit_job(load_fit_config(p), work_dir=tmp_path / "work")
    (f,) = job.blocks
    assert (tmp_path / "work" / "reduced" / "solar_cell_20deg.exr").is_file()
    assert f.grid.n_h[0] == -19 and f.grid.n_h[-1] == 19 and f.grid.n_v[0] == -15  # the step-2 grid inside the roi
    assert not f.mask[:, f.grid.n_h <= -10].any()
    r = read_reduced_frame(tmp_path / "work" / "reduced" / "solar_cell_20deg.exr")
    u = f.usable()
    assert r.attrs["step"] == 2 and u.sum() > 20
    # "pixel" weights (the default): u_scatter_flux, without the frame-wide terms of sigma_rel (ND, incident flux)
    rows = np.searchsorted(np.arange(-23, 25, 2), f.grid.n_v)
    cols = np.searchsorted(np.arange(-31, 33, 2), f.grid.n_h)
    np.testing.assert_allclose(f.sigma_rel[u], r.extra["u_scatter_flux"][np.ix_(rows, cols)][u], rtol=1e-6)
    assert np.all(f.sigma_rel[u] < r.extra["sigma_rel"][np.ix_(rows, cols)][u])
    assert job.fit_kwargs["precision"] == "float64" and job.fit_kwargs["solver"] == "levenberg_marquardt"


def test_an_astm_file_through_the_config(tmp_path):
    (tmp_path / "scan.txt").write_text(textwrap.dedent("""
        # ASTM E1392-style export
        Sample: test
        Wavelength: 632.8 nm
        Angle unit: deg
        Incident angle: 20
        theta_s  BRDF  sigma
        -10  0.10  0.01
        10   0.50  0.05
        20   5.00  0.50
        30   0.40  0.04
        Incident angle: 40
        40   6.00  0.60
        50   0.30  0.03
    """))
    p = tmp_path / "astm.toml"
    p.write_text(textwrap.dedent("""
        [[data.tables]]
        path = "scan.txt"
        format = "astm"
        name = "scan"
        min_brdf = 0.2
        [model.terms.diffuse]
        kind = "lambertian"
        params = { rho_d = 0.5 }
    """))
    (t,) = build_fit_job(load_fit_config(p)).blocks
    assert t.name == "scan" and len(t) == 6 and t.usable().sum() == 5  # 0.10 < min_brdf
    np.testing.assert_allclose(np.degrees(np.asarray(t.theta_i)), [20, 20, 20, 20, 40, 40])
    np.testing.assert_allclose(np.asarray(t.sigma_rel), 0.1)
    p.write_text(p.read_text().replace('format = "astm"', 'format = "astm"\nsigma_rel = 0.05'))
    with pytest.raises(ConfigError, match=r"data.tables\[0\].sigma_rel: .*scan.txt has its own uncertainties"):
        build_fit_job(load_fit_config(p))
