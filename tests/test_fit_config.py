"""Fit data from reduced frames (brdfjax.fit._frames_io) and the TOML fit config (brdfjax.fit.config)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import FitInputError, frame_data_from_reduced, read_frame_data
from brdfjax.instrument.reduce import read_reduced_frame, reduce_measurement_set
from brdfjax.render import render_geometry

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def reduced_example(tmp_path_factory):
    """The example measurement set (64 x 48 coarse camera, solar cell at 20 deg) reduced at step 1."""
    out = tmp_path_factory.mktemp("reduced")
    (path,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", out)
    return path


def test_read_frame_data_round_trips_detector_grid_and_channels(reduced_example):
    r = read_reduced_frame(reduced_example)
    f = read_frame_data(reduced_example)
    assert f.name == "solar_cell_20deg"
    assert f.detector.shape == (48, 64)
    assert f.detector.theta_c is None  # the arm sat on the peak: it follows theta_i
    assert f.theta_i == pytest.approx(np.radians(20.0), abs=1e-15)
    assert f.wavelength == pytest.approx(632.8e-9)
    assert f.grid.shape == (48, 64)
    assert (f.grid.n_h[0], f.grid.n_h[-1], f.grid.n_v[0], f.grid.n_v[-1]) == (-31, 32, -23, 24)
    np.testing.assert_array_equal(f.brdf, r.brdf.astype(np.float64))
    np.testing.assert_array_equal(f.sigma_rel, r.extra["sigma_rel"].astype(np.float64))
    np.testing.assert_array_equal(f.mask, r.extra["mask"] > 0.5)
    # the rebuilt detector and grid map the pixels to the stored scatter directions
    geom = render_geometry(bj.Frame(f.theta_i, f.phi_ref, f.wavelength), f.arm_detector(), grid=f.grid)
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
