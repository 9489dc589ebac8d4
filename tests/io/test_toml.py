"""brdfjax.io.toml: the one TOML writer (configs, raw manifests, capture state) reads back as it was given."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from brdfjax.io import toml

# the shape of a diagnosis's final model config: tables of tables, arrays of tables holding tables,
# non-finite floats, quoted keys, strings that need escapes
FINAL_MODEL = {
    "precision": "float64",
    "data": {
        "tables": [{"path": "/a/b \"c\".csv", "format": "astm", "name": "t1"}, {"path": "/x\\y.csv", "format": "merl"}],
        "sigma_rel": 0.05,
        "footprint_w_px": 3,
    },
    "fit": {"use_footprint": True, "ftol": 1e-10},
    "model": {"terms": {"spec": {"kind": "abg", "distribution": "abg", "rho_s": 0.02, "nested": {"deep": [1, 2]}},
                        "diff": {"kind": "diffraction", "grating_factor": False, "l1": 1}}},
    "params": {"spec.rho_s": {"value": 0.02, "lower": 0.0, "upper": math.inf}, "diff.sigma_nm": {"value": -math.inf}},
    "empty": {},
}


def test_round_trip_of_every_shape_written():
    assert tomllib.loads(toml.dumps(FINAL_MODEL)) == FINAL_MODEL


def test_numpy_values_tuples_and_paths_become_plain_toml():
    doc = {"a": np.float32(0.5), "b": np.int64(7), "c": np.bool_(True), "d": np.array([[1.0, 2.0], [3.0, 4.0]]),
           "e": (1, 2), "f": Path("x/y.exr"), "g": float("nan")}
    back = tomllib.loads(toml.dumps(doc))
    assert back["a"] == 0.5 and back["b"] == 7 and back["c"] is True
    assert back["d"] == [[1.0, 2.0], [3.0, 4.0]] and back["e"] == [1, 2] and back["f"] == "x/y.exr"
    assert math.isnan(back["g"])


def test_float_keys_as_the_manifests_write_them():
    doc = {"calibration": {"nd_tolerances": {repr(0.5): 0.02, repr(3.0): 0.15}}}
    text = toml.dumps(doc)
    assert '"0.5" = 0.02' in text
    assert tomllib.loads(text) == doc


def test_header_is_comments_before_the_document():
    text = toml.dumps({"a": 1}, header="first line\nsecond: [x]")
    assert text.startswith("# first line\n# second: [x]\n")
    assert tomllib.loads(text) == {"a": 1}


def test_unwritable_values_name_where_they_are():
    with pytest.raises(TypeError, match=r"NoneType.*at t\.b\[1\]"):
        toml.dumps({"t": {"b": [1, None]}})
    with pytest.raises(TypeError, match="a TOML document is a mapping"):
        toml.dumps([1, 2])


def test_write_is_atomic_and_leaves_no_temporary(tmp_path):
    p = toml.write(tmp_path / "sub" / "m.toml", {"beam": {"file": "b.exr"}}, header="h")
    assert tomllib.loads(p.read_text(encoding="utf-8")) == {"beam": {"file": "b.exr"}}
    with pytest.raises(TypeError):
        toml.write(p, {"x": object()})
    assert tomllib.loads(p.read_text(encoding="utf-8")) == {"beam": {"file": "b.exr"}}  # the old file stands
    assert sorted(x.name for x in p.parent.iterdir()) == ["m.toml"]


def test_the_diagnosis_writes_its_final_model_through_the_one_writer():
    from brdfjax.diagnose import model_config

    text = model_config.toml_text(FINAL_MODEL)
    assert tomllib.loads(text) == FINAL_MODEL
    assert text == toml.dumps(FINAL_MODEL)  # byte for byte the package writer's text


def test_one_toml_writer_in_the_package():
    # every TOML file brdfjax writes goes through brdfjax.io.toml: no other module formats TOML values
    root = Path(toml.__file__).resolve().parents[1]
    writers = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                     if "def _toml_value" in p.read_text() or "def _toml_str" in p.read_text())
    assert writers == []
