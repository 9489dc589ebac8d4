"""``brdfjax skygap`` on a small synthetic set: the withheld effect is named, the written model reruns in observe."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
CSV = ROOT / "tests/data/satellites/observations/slingshot_v2mini.csv"

FACETS = """
[photometry]
convention = "lumos"

[attitude]
law = "nadir_sun_yaw"
normals = "lumos"

[[observations]]
name = "synthetic"
path = "{csv}"
format = "slingshot"
earth_radius_m = 6378000.0

[bands]
draws = 0

[facets.chassis]
area_m2 = 12.0
normal = [0.0, 0.0, -1.0]
model = "chassis"
lab = "chassis"

[facets.array]
area_m2 = 5.0
normal = [0.0, 1.0, 0.0]
x_axis = [1.0, 0.0, 0.0]
tracking = true
model = "array"

[lab.chassis]
max_theta_i_deg = 60.0
in_plane = true

[models.chassis]
phong = {{ kd = 0.05, ks = 0.4, exponent = 8.0 }}

[models.array]
phong = {{ kd = 0.02, ks = 0.3, exponent = 20.0 }}
"""

TRUTH = """
[effects.wide_lobe.chassis]
k = 0.4
width_deg = 20.0
"""


def _write_set(tmp: Path) -> Path:
    """Every 16th Slingshot row with the magnitudes of the truth (a wide lobe on the chassis) plus 0.15 mag noise."""
    from brdfjax.lightcurve.observe_config import load_observe_config, predict_all

    lines = CSV.read_text().splitlines()
    sub = tmp / "rows.csv"
    sub.write_text("\n".join([lines[0]] + lines[1::16]) + "\n")
    truth = tmp / "truth.toml"
    truth.write_text(FACETS.format(csv=sub) + TRUTH)
    mag = predict_all(load_observe_config(truth))[0].mag
    mag = mag + 0.15 * np.random.default_rng(3).standard_normal(mag.size)
    head = lines[0].split(",")
    k = head.index("measured_ab")
    rows = []
    for line, m in zip(lines[1::16], mag):
        cells = line.split(",")
        cells[k] = f"{m:.6f}"
        rows.append(",".join(cells))
    out = tmp / "synthetic.csv"
    out.write_text("\n".join([lines[0]] + rows) + "\n")
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("skygap")
    csv = _write_set(tmp)
    (tmp / "base.toml").write_text(FACETS.format(csv=csv))
    (tmp / "skygap.toml").write_text(
        'observe = "base.toml"\n[candidates]\nkinds = ["offset", "wide_lobe"]\n[search]\npair_top = 2\n'
        '[holdout]\nby = "block"\nfolds = 3\nblocks = 6\n[bands]\ndraws = 40\n')
    out = tmp / "out"
    p = subprocess.run([sys.executable, "-m", "brdfjax", "skygap", str(tmp / "skygap.toml"), "--out", str(out)],
                       capture_output=True, text=True, cwd=ROOT)
    return tmp, out, p


def test_withheld_lobe_named_and_outputs_written(run):
    tmp, out, p = run
    assert p.returncode == 0, p.stderr
    s = json.loads((out / "skygap.json").read_text())
    assert s["named_first"] == "wide_lobe" and s["effects_named"][0] == "wide_lobe.chassis"
    held = [x["heldout_rms"] for x in s["path_held_out"]]
    assert held[1] < 0.8 * held[0] and held[1] < 0.2  # noise 0.15 mag: the lobe closes the gap on held-out blocks
    assert s["failed_refits"] == 0 and s["refits"] > 0
    assert (out / "residuals_by_step.png").stat().st_size > 1000
    report = (out / "report.md").read_text()
    assert "wide_lobe.chassis" in report and "Held-out RMS" in report
    assert 0.4 < s["band"]["heldout_coverage_68"] <= 1.0 and s["band"]["heldout_coverage_95"] >= s["band"]["heldout_coverage_68"]


def test_written_model_reruns_in_observe_to_the_same_magnitudes(run):
    from brdfjax.lightcurve.observe_config import load_observe_config, predict_all

    tmp, out, p = run
    assert p.returncode == 0, p.stderr
    s = json.loads((out / "skygap.json").read_text())
    assert s["rerun_check"]["max_abs_diff_mag"] < 1e-6
    cfg = load_observe_config(out / "skygap_model.toml")
    assert "chassis" in cfg.effects.wide_lobe
    pred = predict_all(cfg.model_copy(update={"bands": cfg.bands.model_copy(update={"draws": 0})}))[0]
    final = np.loadtxt(out / "predictions.csv", delimiter=",", skiprows=1, usecols=5)
    assert np.max(np.abs(pred.mag - final)) < 1e-6


def test_unknown_set_and_kind_exit_2(tmp_path):
    (tmp_path / "a.toml").write_text(f'observe = "{ROOT / "configs/observe_v2mini_slingshot.toml"}"\nset = "nope"\n')
    p = subprocess.run([sys.executable, "-m", "brdfjax", "skygap", str(tmp_path / "a.toml"), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 2 and "no observation set 'nope'" in p.stderr and "slingshot" in p.stderr
    (tmp_path / "b.toml").write_text('observe = "x.toml"\n[candidates]\nkinds = ["glitter"]\n')
    p = subprocess.run([sys.executable, "-m", "brdfjax", "skygap", str(tmp_path / "b.toml"), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 2 and "glitter" in p.stderr and "candidates.kinds" in p.stderr
