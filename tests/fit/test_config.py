"""Simulate configs: parsing, unit conversion, and bad input named by file and key."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pydantic
import pytest
from helpers import write_config

import brdfjax as bj
from brdfjax.config import ConfigError, default_config_path, load_simulate_config
from brdfjax.core import registry

ROOT = Path(__file__).resolve().parents[2]

GOOD = """
precision = "float32"
[detector]
preset = "seed"
[grid]
step = 16
roi = [-160, 160, -160, 160]
[model]
preset = "solar_cell"
[[frames]]
theta_i_deg = 20.0
[[frames]]
theta_i_deg = 60.0
phi_ref_deg = 45.0
wavelength_nm = 532.0
name = "green"
"""


def write(tmp_path: Path, text: str, name: str = "job.toml") -> Path:
    return write_config(tmp_path, text, name)


def error_of(tmp_path: Path, text: str) -> str:
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_simulate_config(p)
    msg = str(info.value)
    assert str(p) in msg, "every config error names the file"
    return msg


def with_frames(body: str, frames: str = "[[frames]]\ntheta_i_deg = 20.0\n") -> str:
    return textwrap.dedent(body) + "\n" + frames


# --- good configs -------------------------------------------------------------------------------


def test_good_config_builds_core_objects(tmp_path):
    cfg = load_simulate_config(write(tmp_path, GOOD))
    assert cfg.source.endswith("job.toml")
    assert [f.stem for f in cfg.frames] == ["ti20", "green"]
    det = cfg.build_detector()
    assert det.shape == (2472, 3296)
    assert float(det.pixel_pitch) == pytest.approx(5.5e-6, rel=1e-15)
    assert float(det.distance) == 0.325 and det.theta_c is None
    grid = cfg.build_grid(det)
    assert grid.shape == (21, 21) and 0 in grid.n_h and 0 in grid.n_v
    (s0, f0), (s1, f1) = cfg.build_frames()
    assert (s0, s1) == ("ti20", "green")
    assert float(f0.theta_i) == np.deg2rad(20.0)
    assert float(f1.phi_ref) == np.deg2rad(45.0)
    assert float(f1.wavelength) == pytest.approx(532e-9, rel=1e-15)
    model = cfg.build_model()
    ref = bj.solar_cell().params()
    assert {k: float(v) for k, v in model.params().items()} == {k: float(v) for k, v in ref.items()}


def test_config_is_frozen(tmp_path):
    cfg = load_simulate_config(write(tmp_path, GOOD))
    with pytest.raises(pydantic.ValidationError, match="frozen"):
        cfg.precision = "float64"  # type: ignore[misc]


def test_preset_overrides_convert_units(tmp_path):
    text = with_frames(
        """
        [model]
        preset = "solar_cell"
        [model.params]
        m1 = 3e-4
        dtheta_deg = 1.0
        dphi0_deg = 30.0
        a_m = 1e-3
        center.k = 0.25       # a TOML dotted key: the flat name "center.k"
        """
    )
    p = load_simulate_config(write(tmp_path, text)).build_model().params()
    assert float(p["m1"]) == 3e-4
    assert float(p["dtheta"]) == pytest.approx(np.deg2rad(1.0), rel=1e-15)
    assert float(p["dphi0"]) == pytest.approx(np.deg2rad(30.0), rel=1e-15)
    assert float(p["a"]) == 1e-3
    assert float(p["center.k"]) == 0.25


def test_named_terms_build_through_the_registry(tmp_path):
    text = with_frames(
        """
        [model.terms.peak]
        kind = "offset_specular"
        distribution = "ggx"
        params = { alpha = 1e-3, rho_s = 0.5, n = 1.5, dtheta_deg = 0.5, dphi0_deg = 90.0 }
        [model.terms.bars]
        kind = "diffraction"
        grating_factor = false
        params = { rho = 100.0, a_m = 8e-4, b_m = 1e-5, c_m = 4e-5 }
        [model.terms.floor]
        kind = "lambertian"
        params = { rho_d = 0.1 }
        """
    )
    model = load_simulate_config(write(tmp_path, text)).build_model()
    assert list(model.terms) == ["peak", "bars", "floor"]
    assert isinstance(model.terms["peak"], bj.OffsetNormal)
    assert isinstance(model.terms["peak"].term.distribution, bj.GGX)
    assert float(model.terms["peak"].dtheta) == pytest.approx(np.deg2rad(0.5), rel=1e-15)
    assert model.terms["bars"].grating_factor is False
    assert float(model.terms["floor"].rho_d) == 0.1


def test_detector_keys_convert_units(tmp_path):
    text = with_frames(
        """
        [model]
        preset = "solar_cell"
        [detector]
        n_h = 101
        n_v = 81
        pixel_pitch_um = 4.0
        pixel_pitch_v_um = 6.0
        distance_m = 0.5
        theta_c_deg = 25.0
        roll_deg = 0.11
        m_h_px = 3.0
        """
    )
    det = load_simulate_config(write(tmp_path, text)).build_detector()
    assert det.shape == (81, 101)
    assert float(det.pixel_pitch) == 4e-6 and float(det.pixel_pitch_v) == 6e-6
    assert float(det.distance) == 0.5
    assert float(det.theta_c) == pytest.approx(np.deg2rad(25.0), rel=1e-15)
    assert float(det.roll) == pytest.approx(np.deg2rad(0.11), rel=1e-15)
    assert float(det.m_h) == 3.0


def test_with_overrides_revalidates(tmp_path):
    cfg = load_simulate_config(write(tmp_path, GOOD))
    new = cfg.with_overrides(step=32, precision="float64")
    assert (new.grid.step, new.precision, new.grid.roi) == (32, "float64", [-160, 160, -160, 160])
    assert new.source == cfg.source
    with pytest.raises(ConfigError, match=r"grid\.step"):
        cfg.with_overrides(step=0)


def test_packaged_default_equals_configs_default():
    assert default_config_path().read_bytes() == (ROOT / "configs" / "default.toml").read_bytes()
    cfg = load_simulate_config(None)
    assert [f.theta_i_deg for f in cfg.frames] == [20.0, 60.0]
    assert all(f.phi_ref_deg == 0 for f in cfg.frames)
    assert cfg.model.preset == "solar_cell" and cfg.grid.step == 1 and cfg.grid.roi is None


@pytest.mark.parametrize("name", ["default", "seed_fig33", "seed_fig34", "seed_fig35"])
def test_shipped_configs_load(name):
    cfg = load_simulate_config(ROOT / "configs" / f"{name}.toml")
    assert cfg.model.preset == "solar_cell" and cfg.grid.step == 1 and len(cfg.frames) == 2


def test_seed_figure_configs_have_the_seed_angles():
    angles = {
        n: [(f.theta_i_deg, f.phi_ref_deg) for f in load_simulate_config(ROOT / "configs" / f"seed_{n}.toml").frames]
        for n in ("fig33", "fig34", "fig35")
    }
    assert angles == {
        "fig33": [(20.0, 0.0), (60.0, 0.0)],
        "fig34": [(40.0, 45.0), (40.0, 90.0)],
        "fig35": [(20.0, 45.0), (60.0, 45.0)],
    }


# --- bad configs: each message names the file, the dotted key and what is expected ------------------


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.toml: config file not found"):
        load_simulate_config(tmp_path / "nope.toml")


def test_invalid_toml(tmp_path):
    msg = error_of(tmp_path, "precision = \n")
    assert "not valid TOML" in msg


@pytest.mark.parametrize("value", ["95.0", "90.0", "-1.0"])
def test_theta_i_out_of_range(tmp_path, value):
    text = with_frames(
        '[model]\npreset = "solar_cell"\n',
        f"[[frames]]\ntheta_i_deg = 20.0\n[[frames]]\ntheta_i_deg = {value}\n",
    )
    msg = error_of(tmp_path, text)
    assert "frames[1].theta_i_deg" in msg
    assert "0 <= theta_i_deg < 90" in msg and "degrees" in msg


def test_theta_i_wrong_type(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n', '[[frames]]\ntheta_i_deg = "20"\n'))
    assert "frames[0].theta_i_deg" in msg and "valid number" in msg


@pytest.mark.parametrize("value", ["0.0", "-632.8"])
def test_non_positive_wavelength(tmp_path, value):
    msg = error_of(
        tmp_path, with_frames('[model]\npreset = "solar_cell"\n', f"[[frames]]\ntheta_i_deg = 20.0\nwavelength_nm = {value}\n")
    )
    assert "frames[0].wavelength_nm" in msg and "greater than 0" in msg and "nanometres" in msg


def test_negative_roughness_in_preset_override(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n[model.params]\nm1 = -2e-4\n'))
    assert "model.params.m1" in msg and "m > 0" in msg


def test_negative_width_in_term(tmp_path):
    text = with_frames(
        """
        [model.terms.bars]
        kind = "diffraction"
        params = { rho = 300.0, a_m = 8e-4, b_m = -1e-5, c_m = 4e-5 }
        """
    )
    msg = error_of(tmp_path, text)
    assert "model.terms.bars.params.b_m" in msg and "b > 0" in msg


def test_negative_roughness_in_term(tmp_path):
    text = with_frames(
        """
        [model.terms.center]
        kind = "specular"
        distribution = "beckmann"
        params = { m = -2e-4, rho_s = 0.015, n = 3.6 }
        """
    )
    msg = error_of(tmp_path, text)
    assert "model.terms.center.params.m" in msg and "m > 0" in msg


def test_unknown_model_preset_lists_known(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar"\n'))
    assert "model.preset" in msg and "unknown model preset 'solar'" in msg
    assert "known: " + ", ".join(sorted(registry.PRESETS)) in msg


def test_unknown_detector_preset_lists_known(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n[detector]\npreset = "webcam"\n'))
    assert "detector.preset" in msg and "known: seed" in msg


def test_unknown_distribution_lists_known(tmp_path):
    text = with_frames(
        """
        [model.terms.center]
        kind = "specular"
        distribution = "ggxx"
        params = { alpha = 1e-3, rho_s = 1.0, n = 1.5 }
        """
    )
    msg = error_of(tmp_path, text)
    assert "model.terms.center.distribution" in msg and "unknown distribution 'ggxx'" in msg
    assert "known: " + ", ".join(sorted(registry.DISTRIBUTIONS)) in msg


def test_unknown_term_kind_lists_known(tmp_path):
    msg = error_of(tmp_path, with_frames('[model.terms.x]\nkind = "torrance"\nparams = {}\n'))
    assert "model.terms.x.kind" in msg and "known: " + ", ".join(sorted(registry.TERMS)) in msg


@pytest.mark.parametrize(
    "text, key, allowed",
    [
        ('[model]\npreset = "solar_cell"\n[[frames]]\ntheta_i = 20.0\n', "frames[0].theta_i", "theta_i_deg, phi_ref_deg"),
        ('detectr = {}\n[model]\npreset = "solar_cell"\n[[frames]]\ntheta_i_deg = 20.0\n', "detectr", "precision, detector"),
        ('[model]\npreset = "solar_cell"\n[grid]\nstride = 2\n[[frames]]\ntheta_i_deg = 20.0\n', "grid.stride", "step, roi"),
        ('[model]\npreset = "solar_cell"\n[detector]\ndistance = 0.3\n[[frames]]\ntheta_i_deg = 20.0\n', "detector.distance", "distance_m"),
    ],
)
def test_unknown_key_lists_allowed_keys(tmp_path, text, key, allowed):
    msg = error_of(tmp_path, text)
    assert f"{key}: unknown key" in msg and "allowed keys" in msg and allowed in msg


def test_unknown_parameter_suggests_unit_suffix(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n[model.params]\ndtheta = 0.5\n'))
    assert "model.params.dtheta" in msg and "did you mean 'dtheta_deg'" in msg and "known: m1" in msg


def test_missing_term_parameter(tmp_path):
    text = with_frames('[model.terms.c]\nkind = "specular"\ndistribution = "beckmann"\nparams = { rho_s = 1.0, n = 1.5 }\n')
    msg = error_of(tmp_path, text)
    assert "model.terms.c.params" in msg and "missing parameter 'm'" in msg


def test_model_needs_exactly_one_of_preset_or_terms(tmp_path):
    msg = error_of(tmp_path, with_frames("[model]\n"))
    assert "model: give exactly one of 'preset'" in msg


def test_missing_sections(tmp_path):
    msg = error_of(tmp_path, 'precision = "float32"\n')
    assert "model: Field required" in msg and "frames: Field required" in msg


def test_bad_precision(tmp_path):
    msg = error_of(tmp_path, with_frames('precision = "float16"\n[model]\npreset = "solar_cell"\n'))
    assert "precision" in msg and "'float32' or 'float64'" in msg


def test_roi_outside_the_array(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n[grid]\nroi = [0, 10, 0, 5000]\n'))
    assert "grid.roi" in msg and "outside the array" in msg


def test_roi_wrong_length(tmp_path):
    msg = error_of(tmp_path, with_frames('[model]\npreset = "solar_cell"\n[grid]\nroi = [0, 10, 0]\n'))
    assert "grid.roi" in msg and "[h0, h1, v0, v1]" in msg


def test_duplicate_frame_names(tmp_path):
    msg = error_of(
        tmp_path, with_frames('[model]\npreset = "solar_cell"\n', "[[frames]]\ntheta_i_deg = 20.0\n" * 2)
    )
    assert "frames:" in msg and "distinct 'name'" in msg


def test_all_problems_reported_at_once(tmp_path):
    msg = error_of(
        tmp_path,
        '[model]\npreset = "solar_cell"\n[[frames]]\ntheta_i_deg = 95.0\nwavelength_nm = -1.0\n',
    )
    assert "frames[0].theta_i_deg" in msg and "frames[0].wavelength_nm" in msg
    assert len(msg.splitlines()) == 2
