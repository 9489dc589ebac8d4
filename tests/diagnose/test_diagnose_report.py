"""The diagnosis report shows the data where its text says (issue 16): named-peak columns, masks, chi^2 labels, warnings."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.core.detector import PixelGrid
from brdfjax.diagnose.report import _not_ranked_row, column_profiles, plot_column_profile, report_warnings
from brdfjax.diagnose.results import Candidate, Step
from brdfjax.fit import FrameData

N_H = np.arange(-20, 21, 4)  # 11 columns
N_V = np.arange(-12, 13, 4)  # 7 rows


def _frame():
    hh, vv = np.meshgrid(N_H, N_V)
    brdf = 10.0 * np.exp(-((hh - 8) ** 2 + vv**2) / 50.0) + 0.1
    mask = np.ones(brdf.shape, bool)
    mask[1, 7] = mask[4, 7] = False  # two masked pixels in the column through the specular peak (n_h = 8)
    brdf[1, 7] = 1e6  # a masked outlier: must not appear as data
    b = FrameData(brdf=brdf, sigma_rel=0.05, theta_i=math.radians(20), detector=bj.Detector.seed(),
                  grid=PixelGrid(N_H, N_V), mask=mask, name="ti20")
    geo = {"sx": (hh - 8) * 0.01, "sy": vv * 0.01}  # the specular direction at n_h = 8, n_v = 0
    base = np.full(brdf.shape, 0.5)
    base[:, 0] = 100.0  # the base model's maximum at the region's edge (the n_h = 89 column)
    return b, geo, base, brdf, mask


def test_the_plotted_column_is_through_the_named_peak_and_masked_pixels_are_not_data():
    b, geo, base, brdf, mask = _frame()
    final = 1.1 * brdf
    spec, edge = column_profiles(b, geo, base, ("+ diffraction", final))
    assert spec["name"] == "the specular peak" and spec["n_h"] == 8 and spec["col"] == 7
    assert "through the specular peak" in spec["title"] and "outside the region" not in spec["title"]
    assert edge["name"] == "the base model's maximum" and edge["n_h"] == -20
    # masked rows are NaN in the plotted data, usable rows are the data
    assert np.isnan(spec["data"][[1, 4]]).all() and np.array_equal(spec["masked"], ~mask[:, 7])
    u = mask[:, 7]
    np.testing.assert_array_equal(spec["data"][u], brdf[u, 7])
    # each curve carries its chi^2 on the plotted (usable) points
    (lb, _, chi_b), (lf, _, chi_f) = spec["curves"]
    want_f = float(np.sum((np.log(brdf[u, 7]) - np.log(final[u, 7])) ** 2) / 0.05**2)
    assert math.isclose(chi_f, want_f, rel_tol=1e-12) and f"chi^2 {chi_f:.4g} on 5 points" in lf
    assert lb.startswith("base model (chi^2 ") and chi_b > chi_f
    # the figure: the data artist holds no masked value (the 1e6 outlier is not drawn), the masked rows are shaded
    fig = plot_column_profile(spec)
    ax = fig.axes[0]
    (data_line,) = [ln for ln in ax.get_lines() if ln.get_label() == "data (usable)"]
    y = np.asarray(data_line.get_ydata(), float)
    assert np.isnan(y[[1, 4]]).all() and np.nanmax(y) < 1e3
    assert len(ax.patches) == 2 and ax.patches[0].get_label() == "masked (not data)"
    labels = [ln.get_label() for ln in ax.get_lines()]
    assert any(lbl.startswith("+ diffraction (chi^2 ") for lbl in labels)


def test_specular_direction_outside_the_region_is_said():
    b, geo, base, *_ = _frame()
    geo = {"sx": geo["sx"] + 1.0, "sy": geo["sy"]}  # the specular direction far left of the region
    (spec, *_) = column_profiles(b, geo, base)
    assert spec["col"] == 0 and "outside the region: the nearest column" in spec["title"]


def _step(effect, held):
    return Step(effect, {"chi2_reduced": 1.0}, {}, None if held is None else {"rms_log10": held})


def test_warnings_held_out_gap_grew_bound_and_not_refitted_text():
    later = Candidate("stray_light", "stray light", "ranked", signature={"score": 281.0}, delta_bic=55.0)
    d = SimpleNamespace(
        path=[_step("base", 2.04), _step("lambertian", 0.948), _step("diffraction", 1.128)],
        base_result=SimpleNamespace(warnings=("parameter 'm1' ended on its bound 1e-05; its sigma is not meaningful",)),
        final_result=None, context=None, final_context=None, significant=True,
        path_rankings=[[], [later]],
    )
    w = report_warnings(d)
    assert w[0].startswith("the held-out gap grew at step 2 (+diffraction): rms of log10 0.948 -> 1.128")
    assert w[1] == "base fit: parameter 'm1' ended on its bound 1e-05; its sigma is not meaningful"
    assert len(w) == 2  # the first step shrank the held-out gap: no warning for it
    skipped = Candidate("stray_light", "stray light", "not refitted", note="signature score 0 below the 4 best")
    row = _not_ranked_row(d, skipped)
    assert row[1] == "not refitted at step 1; refitted at step 2" and "delta BIC 55.0, signature score 281" in row[2]
    other = Candidate("ambient", "ambient", "not refitted", note="signature score 0 below the 4 best")
    assert _not_ranked_row(d, other) == ["ambient", "not refitted", "signature score 0 below the 4 best"]


def test_truth_outside_its_interval_is_a_warning():
    from brdfjax.fit import FitResult, ParameterEstimate

    params = {
        "m1": ParameterEstimate(2.0e-4, 1e-6, "1", True, 2.1e-4),
        "phi_ref[ti20]": ParameterEstimate(math.radians(-0.0013), math.radians(0.0004), "rad", True, 0.0),
        "n1": ParameterEstimate(3.6, None, "1", False, 3.6),
    }
    res = SimpleNamespace(parameters=params)
    assert FitResult.truth_warnings(res, {"m1": 2.02e-4, "phi_ref": 0.0, "n1": 9.0}) == [
        "the truth of 'phi_ref[ti20]' (0 deg) lies -3.2 sigma from the estimate (-0.0013 +- 0.0004 deg): the sigma "
        "misses an error the data carry (an effect the model or the reduction does not describe), not noise"
    ]
    (w,) = FitResult.truth_warnings(res, {"m1": 1.96e-4})
    assert w.startswith("the truth of 'm1' (0.000196 1) lies +4.0 sigma")


def test_candidate_progress_estimates_the_time_left_and_progress_lines_are_plain_off_a_terminal(monkeypatch):
    import io

    from rich.console import Console

    from brdfjax.cli.diagnose import _CandidateProgress
    from brdfjax.runtime.progress import ProgressLine, make_console

    buf = io.StringIO()
    con = Console(file=buf, force_terminal=False, width=200)
    p = _CandidateProgress(con)
    clock = iter([0.0, 10.0, 10.01, 14.0])  # base; two refits started together (a parallel step); a third 4 s on
    monkeypatch.setattr("brdfjax.cli.diagnose.time.perf_counter", lambda: next(clock))
    p("fitting the base model")
    p("step 1: refitting with diffraction (1/4, signature 4.72)")
    p("step 1: refitting with lambertian (2/4, signature 363)")
    p("step 1: refitting with misalignment (3/4, signature 2.5)")
    lines = buf.getvalue().splitlines()
    assert lines[1] == "step 1: refitting with diffraction (1/4, signature 4.72)"  # nothing measured yet
    assert lines[2] == "step 1: refitting with lambertian (2/4, signature 363)"  # started with the first: no interval
    assert lines[3] == "step 1: refitting with misalignment (3/4, signature 2.5); ~8 s left in this step (a refit every 4 s)"
    assert p.t_refits == pytest.approx([3.99])
    monkeypatch.undo()  # (the clock patched is the time module's own)
    # plain lines off a terminal (no bar), each with the count and an estimate; nothing when quiet
    buf = io.StringIO()
    bar = ProgressLine(Console(file=buf, force_terminal=False), "reduce", 4, unit="sample(s)", min_interval_s=0.0)
    bar.update(1, "reduced ti20")
    bar.update(4, "reduced ti80")
    assert bar._bar is None and bar.lines[0].startswith("reduce: 1/4 sample(s) (") and "left); reduced ti20" in bar.lines[0]
    assert bar.lines[1].startswith("reduce: 4/4 sample(s) (") and "left" not in bar.lines[1]
    quiet = ProgressLine(make_console(quiet=True), "fit", None)
    quiet.update(3, "chi2 = 1")
    assert quiet.lines == []


def test_a_removal_step_is_named_as_one_and_the_held_out_verdict_is_against_the_truth():
    """The shipped example's path (issue 35's figures): a removal step is '-lambertian', never '+ lambertian'; a final
    held-out prediction far worse than the truth's is a warning and in the headline, with the truth's figure."""
    from brdfjax.diagnose.report import heldout_verdict

    def held(rms, chi2):
        return {"rms_log10": rms, "chi2_reduced": chi2, "n_points": 1471}

    path = [Step("base", {"chi2_reduced": 18951.0}, {}, held(0.95, 2e5), action="base"),
            Step("lambertian", {"chi2_reduced": 3008.0}, {}, held(1.43, 3e5)),
            Step("diffraction", {"chi2_reduced": 1.019}, {}, held(1.81, 4e5)),
            Step("lambertian", {"chi2_reduced": 1.028}, {}, held(1.9, 4.2e5), action="remove")]
    truth = {"chi2_reduced": 1.045, "heldout": {"rms_log10": 0.012, "chi2_reduced": 1.022, "n_points": 1471}}
    d = SimpleNamespace(path=path, base_result=None, final_result=None, context=None, final_context=None,
                        significant=True, path_rankings=[], truth_gap=truth)
    w = report_warnings(d)
    assert any(x.startswith("the held-out gap grew at step 3 (-lambertian)") for x in w)
    assert not any("(+ lambertian)" in x for x in w if "step 3" in x)
    v = heldout_verdict(d)
    assert v["worse"] and v["ratio"] == pytest.approx(1.9 / 0.012)
    assert "WORSE than the base" in v["text"] and "WORSE than the truth by more than the noise" in v["text"]
    assert v["text"] in w
    # a final prediction as good as the truth's, within 3 sqrt(2/N) in reduced chi^2: no warning
    path[-1] = Step("lambertian", {"chi2_reduced": 1.028}, {}, held(0.0125, 1.08), action="remove")
    v = heldout_verdict(d)
    assert not v["worse"] and "as well as the truth, within the noise" in v["text"]
    assert not any("held-out prediction" in x for x in report_warnings(d))
