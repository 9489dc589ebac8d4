"""Execute every notebook in ``notebooks/`` on a coarse pixel grid and check its key numbers.

Each notebook has a first code cell tagged ``parameters`` that defines ``STEP``
(the decimation of full-frame images); it is replaced by ``STEP = COARSE_STEP``
here.  Notebooks collect their key figures in a module-level dict ``RESULTS``;
after the notebook has run, one extra cell prints it as JSON and the checks
below compare it with the seed's numbers.  Notebooks are committed without
outputs; nothing is written back.

Requires ``nbclient``, ``nbformat`` and ``ipykernel`` (the ``test`` extra); the
``python3`` kernel is the one ipykernel installs.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
COARSE_STEP = 32
TIMEOUT_S = 300  # per cell
RESULTS_MARKER = "__NOTEBOOK_RESULTS__"


def _rel(value: float, expected: float) -> float:
    return abs(value / expected - 1.0)


def _check_01_forward_model(r: dict) -> None:
    # the parameters cell was replaced: frames are decimated by COARSE_STEP
    assert r["frame_shape"] == [-(-2472 // COARSE_STEP), -(-3296 // COARSE_STEP)]
    # (a) pixel mapping: seed Tables 7 and 3, inverse map Eq 82
    assert r["table7_within_4th_figure"], r["table7_max_abs_diff_deg"]
    assert r["table7_max_abs_diff_deg"] < 0.05
    assert r["table3_within_4th_figure"]
    assert _rel(r["solid_angle_centre_sr"], 2.864e-10) < 2e-4
    assert r["inverse_map_roundtrip_px"] < 1e-6
    assert r["inverse_map_vs_oracle_px"] < 1e-6
    # (b) terms
    assert r["normalisation_max_abs_err"] < 1e-5
    assert r["student_t2_vs_ggx"] < 1e-10
    assert r["q_vs_fresnel_max_abs"] < 1e-10
    for theta in ("20", "60"):
        assert r[f"offset_peak_miss_px_{theta}"] < 1.5
        assert r[f"diffraction_maxima_{theta}"] == 26  # seed §6.4, both angles
        assert _rel(r[f"bars_at_centre_{theta}"], 300.0) < 1e-9
    assert r["diffraction_maxima_no_factor_20"] == 14
    assert r["diffraction_maxima_no_factor_60"] == 26
    # (c) Figure 33 maxima: centre term alone (physics.md) and the seed's quoted peak values
    assert _rel(r["center_term_max_20"], 1.08e4) < 0.02
    assert _rel(r["center_peak_total_max_20"], 1.11e4) < 0.02
    assert _rel(r["offset_peak_total_max_20"], 4.44e4) < 0.02
    assert _rel(r["center_peak_total_max_60"], 3.91e4) < 0.02
    assert _rel(r["offset_peak_total_max_60"], 4.19e5) < 0.02


def _check_03_diagnosis(r: dict) -> None:
    # diffraction withheld from the base model: found first, in the path, the gap shrinks (fitted and held out)
    assert r["top1"] == "diffraction"
    assert r["path"][:2] == ["base", "diffraction"] and r["significant"]
    assert r["chi2_reduced_after"] < 0.5 * r["chi2_reduced_before"]
    assert r["heldout_after"] < r["heldout_before"]
    assert "band" in r["zone_names"]
    assert {"gap", "zones", "ranking", "path", "significant"} <= set(r["json_keys"])


def _check_04_posterior(r: dict) -> None:
    # the sampled grid is never coarser than every 6th pixel of a 181 px square (the peak is ~24 px wide)
    assert r["grid_shape"] == [31, 31]
    assert r["n_steps"] == 300
    # the likelihood is the fit's: -2 log L at the optimum is its chi^2
    assert _rel(r["chi2_at_fit"], r["fit_chi2"]) < 1e-9
    # the degeneracy: rho_s1 and n1 anti-correlated along a ridge; m1 stays sharp
    assert r["corr_rho_s1_n1"] < -0.8
    assert r["m1_rel_err"] < 0.01
    assert 0.1 < r["acceptance"] < 0.9
    assert {"chain.h5", "corner.png", "posterior.json", "predictive_ti20.png", "trace.png"} <= set(r["files"])


def _check_05_lightcurves(r: dict) -> None:
    # ten minutes of the shipped second pass at COARSE_STEP-second steps
    assert 0 < r["n_visible_steps"] <= 600 // COARSE_STEP + 1
    # the Lambertian array differs everywhere; a narrow lobe's glint: disk average to 1e-3, point Sun > 100x
    assert r["max_dm_lambertian"] > 0.1
    assert abs(r["disk_over_analytic"] - 1) < 1e-3
    assert r["point_over_analytic"] > 100
    assert r["glint_ratio_30"] > 5


def _check_06_sky(r: dict) -> None:
    # every COARSE_STEP-th row of both sets (a Slingshot row or two in the Earth's shadow drop)
    assert 1584 // COARSE_STEP - 2 <= r["slingshot_n"] <= -(-1584 // COARSE_STEP)
    assert 2782 // COARSE_STEP - 4 <= r["score_n"] <= -(-2782 // COARSE_STEP)
    for name in ("slingshot", "score"):
        assert 0.3 < r[f"{name}_rms"] < 2.0
        assert 0.0 <= r[f"{name}_coverage_68"] <= r[f"{name}_coverage_95"] <= 1.0
        assert 0.5 < r[f"{name}_fraction_outside_lab"] <= 1.0  # the sky mostly sees these facets out of plane
    assert r["slingshot_r"] > 0.5
    # the satellites below every operational shell are flagged and predicted far too faint; the rest fit better
    assert r["score_operational_n"] + r["score_off_shell_n"] == r["score_n"] and r["score_off_shell_n"] > 0
    assert r["score_off_shell_bias"] < -0.5 and r["score_operational_rms"] < r["score_rms"]


CHECKS = {
    "01_forward_model": _check_01_forward_model,
    "03_diagnosis": _check_03_diagnosis,
    "04_posterior": _check_04_posterior,
    "05_lightcurves": _check_05_lightcurves,
    "06_sky": _check_06_sky,
}


def _set_parameters(nb, step: int) -> None:
    cells = [c for c in nb.cells if c.cell_type == "code" and "parameters" in c.metadata.get("tags", [])]
    assert len(cells) == 1, "a notebook needs exactly one code cell tagged 'parameters' (defining STEP)"
    assert "STEP" in cells[0].source, "the 'parameters' cell must define STEP"
    cells[0].source = f"STEP = {step}  # injected by tests/project/test_notebooks.py"


def _results(nb) -> dict:
    for out in nb.cells[-1].get("outputs", []):
        if out.output_type == "stream" and RESULTS_MARKER in out.text:
            return json.loads(out.text.split(RESULTS_MARKER, 1)[1])
    raise AssertionError("the notebook's RESULTS could not be read back")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, monkeypatch) -> None:
    nb = nbformat.read(path, as_version=4)
    _set_parameters(nb, COARSE_STEP)
    nb.cells.append(
        nbformat.v4.new_code_cell(
            f"import json as _json\nprint({RESULTS_MARKER!r} + _json.dumps(globals().get('RESULTS', {{}}), default=float))"
        )
    )
    # The kernel inherits this environment: make the checkout importable without installing it,
    # and keep plotting headless.
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    client = nbclient.NotebookClient(
        nb, timeout=TIMEOUT_S, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}
    )
    client.execute()  # raises CellExecutionError with the failing cell's traceback
    results = _results(nb)
    check = CHECKS.get(path.stem)
    if check is not None:
        check(results)
