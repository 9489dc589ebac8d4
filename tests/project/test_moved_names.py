"""The one render entry and the names that moved: old spellings still work, with a warning naming the new one."""

from __future__ import annotations

import importlib
import sys

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.core import render as render_mod


def _frame():
    return bj.Conditions.from_degrees(20.0)


def test_render_outputs_come_from_the_frame_and_geometry_programs():
    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.05), rho_s=0.5, n=1.5), "d": bj.Lambertian(0.1)})
    kw = dict(step=128, precision="float32")
    brdf = np.asarray(bj.render(model, _frame(), **kw))
    every = bj.render(model, _frame(), outputs="all", **kw)
    assert sorted(every) == sorted(bj.OUTPUTS)
    np.testing.assert_allclose(np.asarray(every["brdf"]), brdf, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(every["terms"]["s"] + every["terms"]["d"]), brdf, rtol=1e-5)
    geo = bj.render(None, _frame(), outputs=("theta_s", "omega"), **kw)
    assert sorted(geo) == ["omega", "theta_s"]
    np.testing.assert_array_equal(np.asarray(geo["theta_s"]), np.asarray(every["theta_s"]))
    with pytest.raises(ValueError, match="unknown output.*'brfd'"):
        bj.render(model, _frame(), outputs=("brfd",), **kw)
    with pytest.raises(ValueError, match="need a model"):
        bj.render(None, _frame(), outputs=("brdf",), **kw)
    with pytest.raises(ValueError, match="BRDF only"):
        bj.render(model, _frame(), devices="all", per_term=True, **kw)


@pytest.mark.parametrize("old, new", [("render_frame", "outputs=\"all\""), ("render_geometry", "outputs="),
                                      ("render_sharded", "devices=\"all\""), ("sample_directions", "pixel_directions")])
def test_moved_top_level_names_warn_and_still_work(old, new):
    with pytest.warns(DeprecationWarning, match=f"brdfjax.{old} is deprecated: use .*{new}".replace("(", r"\(")):
        fn = getattr(bj, old)
    assert fn is getattr(render_mod, old)


@pytest.mark.parametrize("old, new", [("brdfjax.terms", "brdfjax.core.terms"), ("brdfjax.errors", "brdfjax.runtime.errors"),
                                      ("brdfjax.instrument.raw", "brdfjax.io.raw"), ("brdfjax.fit.cli_fit", "brdfjax.cli.fit")])
def test_moved_module_paths_import_the_new_module_with_a_warning(old, new):
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=f"{old} moved to {new}"):
        mod = importlib.import_module(old)
    assert mod is importlib.import_module(new)


def test_frame_is_now_conditions_with_a_warning():
    # the measurement conditions were called Frame, the word every file format and image type uses for an image
    with pytest.warns(DeprecationWarning, match=r"brdfjax.Frame is deprecated: use bj.Conditions"):
        old = bj.Frame
    assert old is bj.Conditions
    from brdfjax.core import conditions
    with pytest.warns(DeprecationWarning, match="conditions.Frame is deprecated: use Conditions"):
        assert conditions.Frame is bj.Conditions
    assert old.from_degrees(20.0).theta_i == pytest.approx(np.deg2rad(20.0))


def test_unknown_attribute_is_still_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        bj.no_such_name  # noqa: B018
