"""The shared case lists (tests/helpers.py): every shipped model renders in float32 under strict dtype
promotion, every shipped config is listed and reads."""

from __future__ import annotations

import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CONFIG_CASES, CONFIGS, MODEL_CASES

import brdfjax as bj
from brdfjax.config import ModelConfig, build_model

DET = bj.Detector.seed()


@pytest.mark.parametrize("name", sorted(MODEL_CASES))
def test_every_shipped_model_renders_float32_without_promotion(name):
    model, frame = MODEL_CASES[name](), bj.Conditions.from_degrees(30.0, 10.0)
    with jax.numpy_dtype_promotion("strict"):
        f32 = bj.render(model, frame, DET, step=64, precision="float32")
    assert f32.dtype == jnp.float32
    f64 = np.asarray(bj.render(model, frame, DET, step=64, precision="float64"))
    f32 = np.asarray(f32, np.float64)
    assert np.all(np.isfinite(f32)) and np.all(f32 >= 0) and f64.max() > 0
    keep = f64 > 1e-3 * f64.max()
    assert np.max(np.abs(f32[keep] - f64[keep]) / f64[keep]) < 1e-3


def test_every_shipped_config_is_a_case():
    listed = {n for names in CONFIG_CASES.values() for n in names}
    assert sorted(p.name for p in CONFIGS.glob("*.toml")) == sorted(listed)
    assert all(names for names in CONFIG_CASES.values())


@pytest.mark.parametrize("kind, name", [(k, n) for k, names in CONFIG_CASES.items() for n in names])
def test_every_shipped_config_reads_and_its_model_builds(kind, name):
    doc = tomllib.loads((CONFIGS / name).read_text())
    if "model" in doc and kind in ("fit", "sample", "diagnose", "simulate"):
        model = build_model(str(CONFIGS / name), ModelConfig.model_validate(doc["model"]))
        assert model.params(), name
    if kind == "observe":  # the observation files, the lab fits and the facets it names load
        from brdfjax.lightcurve.observe_config import load_observe_config

        assert load_observe_config(CONFIGS / name).facets, name
    if kind == "skygap":  # its observe config, the set it names and its candidate kinds load
        from brdfjax.lightcurve.skygap_config import load_skygap_config

        assert load_skygap_config(CONFIGS / name).observe, name
    if kind == "batch":
        from brdfjax.batch import load_study

        study, _ = load_study(CONFIGS / name)
        assert study.jobs, name
