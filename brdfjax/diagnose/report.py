"""The reports of a diagnosis: Markdown (numbers) and a self-contained HTML page (numbers + figures as base64 PNG).

Figures (matplotlib, Agg): per frame the normalised residual map of the base
fit in detector pixels and in specular-relative angles with the zones
outlined; the columns through the named peaks before/after
(:func:`column_profile`: the column through the specular peak -- the grid
point nearest the specular direction, ``sx = sy = 0`` -- and, where it lies in
another column, the one through the base model's maximum; data only where
usable, masked pixels shaded as masked, never plotted as data; each model
curve labelled with its chi^2 on the plotted points); the explanation path
as a chart (reduced chi^2 and, when measured, the held-out rms of log10 per
step).  Tables (goniometer data) get the residual against ``sx`` per
incidence angle.

Warnings (:func:`report_warnings`, at the top of both reports): a held-out
gap that grew at a step of the path, a parameter that ended on its bound (the
fits' own warnings), and a plotted model that does not reproduce the fit's
residuals in the plotted column.  The "Not ranked" table says when a
candidate not refitted at the first step was refitted at a later one.
"""

from __future__ import annotations

import base64
import html
import io
import math
from typing import Any

import numpy as np

from ..fit import FrameData
from ..plotting import agg_pyplot

# ``d`` below is a :class:`~brdfjax.diagnose.results.Diagnosis`; not imported: results imports this module to
# write the reports (Any keeps the two out of a cycle)
Diagnosis = Any

__all__ = ["markdown_report", "html_report", "figures", "column_profile", "report_warnings", "heldout_verdict", "heldout_grew"]


def _f(x: Any, fmt: str = ".4g") -> str:
    if x is None:
        return "-"
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    return "-" if not math.isfinite(x) else format(x, fmt)


def _tables(d: Diagnosis) -> list[tuple[str, list[str], list[list[str]]]]:
    g = d.gap
    out = []
    out.append(
        (
            "Gap of the base model",
            ["chi2_reduced", "rms_log10", "held-out rms_log10", "points", "free parameters", "share in significant regions"],
            [[_f(g["chi2_reduced"]), _f(g["rms_log10"]), _f(g.get("heldout_rms_log10")), str(g["n_points"]), str(g["n_free"]), _f(100 * g["regions_share"], ".1f") + " %"]],
        )
    )
    out.append(
        (
            "Where: significant residual regions (zones)",
            ["zone", "block", "share", "centre sx, sy (deg)", "extent major, minor (deg)", "orientation (deg)", "sign", "description"],
            [
                [z["label"], str(z["block"]), _f(100 * z["share"], ".1f") + " %", f"{_f(z['center_deg'][0])}, {_f(z['center_deg'][1])}",
                 f"{_f(z['extent_deg'][0])}, {_f(z['extent_deg'][1])}", _f(z["orientation_deg"], ".0f"), z["sign"], z["description"]]
                for z in d.zones
            ],
        )
    )
    out.append(
        (
            "Which: candidate effects ranked by BIC gain (decreases: positive = explains part of the gap); "
            "a detection (an unresolved peak, marked 'detected') comes first by its own signature; the effects of the "
            "final explanation come before the candidates it does without (marked 'in the final model'); a specific "
            "effect that still gains more than the threshold beside the generic effect ranked first, on their joint "
            "refit, is ranked before it (marked 'required')",
            ["rank", "effect", "delta BIC", "delta chi2", "new params", "chi2_reduced after", "signature score", "signature"],
            [
                [str(i + 1) + {"detection": " (detected)", "specific": " (required)", "explanation": " (in the final model)"}.get(c.ranked_by, ""), c.effect, _f(c.delta_bic, ".1f"), _f(c.delta_chi2, ".1f"), str(c.n_new), _f(c.gap_after.get("chi2_reduced")),
                 _f(c.signature.get("score"), ".3g"), str(c.signature.get("detail", ""))]
                for i, c in enumerate(d.ranking)
            ],
        )
    )
    if d.skipped:
        out.append(("Not ranked", ["effect", "status", "reason"], [_not_ranked_row(d, c) for c in d.skipped]))
    zone_names = list(d.path[0].zones)
    truth = getattr(d, "truth_gap", None)
    th = None if truth is None else truth.get("heldout")
    out.append(
        (
            "How far: the explanation path",
            ["step", "effect", "chi2_reduced", "rms_log10", "held-out rms_log10", "held-out chi2_reduced"]
            + (["truth: chi2_reduced", "truth: held-out rms_log10"] if truth is not None else [])
            + ["delta BIC"] + [f"chi2_red {z}" for z in zone_names],
            [
                [str(i), _name(s), _f(s.gap["chi2_reduced"]), _f(s.gap["rms_log10"]), _f(None if s.heldout is None else s.heldout["rms_log10"]),
                 _f(None if s.heldout is None else s.heldout.get("chi2_reduced"))]
                + ([_f(truth.get("chi2_reduced")), _f(th.get("rms_log10") if th else None)] if truth is not None else [])
                + [_f(s.delta_bic, ".1f")] + [_f(s.zones[z]["chi2_reduced"]) for z in zone_names]
                for i, s in enumerate(d.path)
            ],
        )
    )
    return out


def _later_refits(d: Diagnosis, effect: str) -> list[tuple[int, Any]]:
    """``[(step number, candidate)]`` where ``effect`` was refitted at a later step of the path."""
    out = []
    for k, ranking in enumerate(d.path_rankings[1:], start=2):
        for c in ranking:
            if c.effect == effect and c.status == "ranked":
                out.append((k, c))
    return out


def _not_ranked_row(d: Diagnosis, c: Any) -> list[str]:
    later = _later_refits(d, c.effect) if c.status == "not refitted" else []
    if not later:
        return [c.effect, c.status, c.note]
    k, lc = later[0]
    return [c.effect, f"not refitted at step 1; refitted at step {k}",
            f"{c.note}; at step {k}: delta BIC {_f(lc.delta_bic, '.1f')}, signature score {_f(lc.signature.get('score'), '.3g')}"]


def heldout_grew(prev: dict[str, Any] | None, cur: dict[str, Any] | None) -> bool:
    """Whether the held-out gap grew from ``prev`` to ``cur`` by more than the noise: the rms of log10 rose and, where
    both carry a reduced chi^2 and a point count, the reduced chi^2 rose by more than ``3 sqrt(2/N)``.  (Measured on
    the shipped example: taking the second lobe out moved the held-out rms from 0.01066 to 0.01131, reduced chi^2
    0.86 -> 0.94 on 1355 points, within the noise of 0.115; the final model predicts as well as the truth.)"""
    if not prev or not cur:
        return False
    a, b = prev.get("rms_log10"), cur.get("rms_log10")
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or not b > a:
        return False
    ca, cb, n = prev.get("chi2_reduced"), cur.get("chi2_reduced"), cur.get("n_points")
    if ca is None or cb is None or not n or not (math.isfinite(ca) and math.isfinite(cb)):
        return True
    return cb - ca > 3.0 * math.sqrt(2.0 / n)


def report_warnings(d: Diagnosis) -> list[str]:
    """What a reader must not miss (see the module docstring); each a sentence."""
    out = []
    prev = None
    for k, s in enumerate(d.path):
        h = None if s.heldout is None else s.heldout.get("rms_log10")
        if prev is not None and h is not None and prev[1] is not None and heldout_grew(prev[2], s.heldout):
            out.append(
                f"the held-out gap grew at step {k} ({_name(s)}): rms of log10 {_f(prev[1], '.4g')} -> {_f(h, '.4g')}"
                + ("; the effect explains the fitted frames but not the held-out ones (overfitting, or a different cause)"
                   if getattr(s, "action", "add") != "remove" else "; taking the effect out made the held-out prediction worse")
            )
        prev = (s.effect, h, s.heldout) if h is not None else (prev or (s.effect, None, None))
    for label, res in (("base fit", d.base_result), ("final fit", d.final_result)):
        for w in getattr(res, "warnings", ()) or ():
            if "on its bound" in w:
                out.append(f"{label}: {w}")
    out += [w for _, w in _column_checks(d)]
    t = getattr(d, "truth_gap", None)
    hw = heldout_verdict(d)
    if hw is not None and hw["worse"]:
        out.append(hw["text"])
    if t is not None and t.get("within_20pct") is False:
        out.append(f"the final reduced chi^2 {_f(t.get('final_chi2_reduced'), '.4g')} is {_f(t.get('final_over_truth'), '.3g')} "
                   f"times the truth's own ({_f(t.get('chi2_reduced'), '.4g')}) on these frames: the path has not reached the "
                   "truth's structure (an effect the library lacks, or a dead end)")
    return out


def heldout_verdict(d: Diagnosis) -> dict[str, Any] | None:
    """The final model's prediction of the held-out frames against the base's and (where known) the truth's.

    ``{"worse": bool, "text": str, "ratio": rms ratio to the truth}`` or None without held-out frames.  "Worse
    than the truth" means a held-out reduced chi^2 above the truth's by more than the noise allows
    (``3 sqrt(2 / N)``, N held-out points): then the prediction misses something the truth has.
    """
    if not d.path or d.path[-1].heldout is None:
        return None
    base_h, fin_h = d.path[0].heldout or {}, d.path[-1].heldout
    b, f = base_h.get("rms_log10"), fin_h.get("rms_log10")
    if f is None or not math.isfinite(f):
        return {"worse": True, "ratio": math.nan,
                "text": f"the held-out frames could not be predicted by the final model ({fin_h.get('error', 'no figure')})"}
    grew = b is not None and math.isfinite(b) and f > b
    text = (f"held-out prediction: rms of log10 {_f(b)} (base) -> {_f(f)} (final), "
            + ("WORSE than the base" if grew else "better than the base"))
    t = getattr(d, "truth_gap", None)
    th = None if t is None else t.get("heldout")
    worse, ratio = grew, math.nan
    if th is not None and th.get("chi2_reduced") is not None:
        n = max(int(th.get("n_points") or 1), 1)
        tol = 3.0 * math.sqrt(2.0 / n)
        fc, tc = fin_h.get("chi2_reduced", math.nan), float(th["chi2_reduced"])
        ratio = f / th["rms_log10"] if th.get("rms_log10") else math.nan
        beyond = not (math.isfinite(fc) and fc <= tc + tol)
        worse = worse or beyond
        text += (f"; the truth's own held-out rms of log10 is {_f(th.get('rms_log10'))} (reduced chi^2 {_f(tc)} against "
                 f"the final model's {_f(fc)}): the final model predicts the held-out frames "
                 + (f"WORSE than the truth by more than the noise (3 sqrt(2/N) = {tol:.3g})" if beyond
                    else "as well as the truth, within the noise"))
    und = fin_h.get("undetermined")
    if und:
        text += (f"; the prediction rests on parameters the fitted frames do not determine ({', '.join(und)}: no "
                 "finite sigma), whose values there are their starts")
    return {"worse": bool(worse), "text": text, "ratio": ratio}


def _name(s: Any) -> str:
    """A path step's name: ``base``, ``+effect`` (added) or ``-effect`` (taken out again)."""
    return {"add": "+", "remove": "-"}.get(getattr(s, "action", "add"), "") + s.effect if getattr(s, "action", "") != "base" else s.effect


def _headline(d: Diagnosis) -> str:
    p = " -> ".join(f"{_name(s)} ({_f(s.gap['chi2_reduced'], '.3g')})" for s in d.path)
    by = d.effects_by_side()
    sides = (f" Material effects: {', '.join(by['material']) or 'none'}; instrument effects: "
             f"{', '.join(by['instrument']) or 'none'}. The path stopped because {d.stop_reason}.")
    flags = "".join(f" Flag at {_name(s)}: {f}." for s in d.path for f in s.flags)
    flags += "".join(f" Detected ({c.effect}, ranked first by its own signature, not by a BIC gain): "
                     f"{c.signature.get('detail', '')}." for c in d.ranking if c.ranked_by == "detection")
    truth = "" if getattr(d, "truth_gap", None) is None else f" The {truth_line(d.truth_gap)}."
    hv = heldout_verdict(d)
    if hv is not None:
        truth += f" The {hv['text']}."
    if d.significant:
        # the ranking's first effect that the final model holds (the ranking puts the final explanation first)
        lead = next((c.effect for c in d.ranking if c.effect in d.explained_by), d.explained_by[0])
        return (f"The gap is most likely caused by **{lead}**. Explanation path (reduced chi^2): {p}.{sides}{flags}"
                f"{truth} {noise_line(d.gap)}.")
    return (f"No candidate effect is significant (BIC gain > {d.bic_threshold:g}). Path: {p}.{sides}{flags}{truth} "
            f"{noise_line(d.gap)}.")


def truth_line(t: dict[str, Any]) -> str:
    """The truth's own reduced chi^2 on the fitted frames and the final model's against it, in words."""
    ratio = t.get("final_over_truth")
    verdict = ""
    if ratio is not None and math.isfinite(ratio):
        verdict = (f"; final / truth = {ratio:.3g} ("
                   + ("within" if abs(ratio - 1.0) <= 0.2 else "NOT within") + " 20 %)")
    h = t.get("heldout")
    held = "" if not h else (f"; on the held-out frames the truth's reduced chi^2 is {_f(h.get('chi2_reduced'), '.4g')}, "
                             f"rms log10 {_f(h.get('rms_log10'), '.3g')}")
    return (f"truth's own reduced chi^2 on these frames (the generator's model, nothing fitted): "
            f"{_f(t.get('chi2_reduced'), '.4g')} (rms log10 {_f(t.get('rms_log10'), '.3g')}, "
            f"{t.get('n_points', '?')} points); the final model's {_f(t.get('final_chi2_reduced'), '.4g')}{verdict}{held}")


def noise_line(gap: dict[str, Any]) -> str:
    """Whether sigma was estimated, in words (every diagnosis report states it)."""
    if gap.get("sigma_estimated"):
        return (
            f"noise: sigma ESTIMATED from the residuals (the data give none): sigma of ln BRDF = {gap['sigma_ln']:.4g}; "
            "chi2 and BIC are -2 ln L of the profile likelihood, chi2_reduced is not a goodness of fit"
        )
    return "noise: the data's own uncertainties (sigma not estimated)"


#: The rules by which the path admits and keeps an effect, stated in every report (and in docs/guides/diagnosis.md).
PATH_RULES = (
    "At every step every applicable candidate is refitted added to the current set; the residual signature only "
    "orders the refits and is reported, it excludes nothing.  A refit that drives a term of the model it extends "
    "below 1 % of its weight there is repeated with that term revived, and the lower chi^2 is kept.",
    "An effect is admissible when its own terms are sound: its own new parameters have a finite sigma and none ends "
    "on a bound, no weight or width of a term it added ends dead (below 1e-3 of its start), a lobe it added is not "
    "narrower than half the angular sampling, and it does not drive a term of the model to zero.  An inadmissible "
    "effect never enters, whatever its BIC gain.",
    "The best admissible candidates are also refitted in pairs, each warm-started at its better member's fit; where "
    "the step's best fit is not within the noise, the best single (and, where it is generic, the best specific one) "
    "is also paired with every other candidate, every candidate whose single refit failed or ended flagged is "
    "started again from the best single's fit, and the three lowest pairs are refitted in the other order too "
    "(started at the other member's fit), the better fit kept.  The single or pair with the largest BIC gain enters "
    "when the gain exceeds the threshold; a pair only when it beats its better member alone by more than the "
    "threshold.",
    "A generic effect (a floor, a response curve) does not enter where a specific candidate explains its residual: "
    "on their joint refit, taking the generic effect out costs less than the threshold.",
    "Every effect must pass the same test to stay: after every step each effect is taken out in turn (the model "
    "refitted from the larger fit and, where two effects or more are left, also forward from their fitted subset of "
    "lowest BIC, from each of its fits, the best kept); one whose removal costs less BIC than the threshold is taken out.  Where none can "
    "go alone, the two cheapest removals are refined as the committed set was (the footprint's width rescanned on "
    "their own fit) and judged again; where none can go alone and three effects or more are in, two are taken out "
    "together when that costs less than the threshold (two effects that stood in for one another hold each other "
    "in).",
    "Generic effects stand in for one another: after the removals each generic effect of the set is replaced in turn "
    "by each other generic candidate (refitted); the replacement of lowest BIC is made when it is admissible and its "
    "BIC is below the set's (shown as a removal and an addition).",
    "The final set is confirmed with noise weights evaluated at its model (a reading's relative noise falls as the "
    "reading rises, so the readings' own weights favour the upward fluctuations of faint pixels, as a floor would): "
    "each effect that added terms is taken out of the final fit refitted on those weights; one whose removal costs "
    "less than the threshold there is removed (its row is the set refitted with the readings' weights).",
    "A refit that fails (raises, ends non-finite, or above the model it extends) is retried from a second start and "
    "then with the effect's strength near its null; a refit that fails from every start is reported and counted "
    "(diagnosis.json settings.failed_refits), never ranked, unless a start came back to the model it extends (within "
    "1 in chi^2): the data then take nothing from the effect, and it is ranked with that gain.",
    "The search stops when no admissible move gains more than the threshold, when the reduced chi^2 after a move is "
    "within one standard deviation of pure noise's (1 + sqrt(2/dof), data with uncertainties; the base is always "
    "taken through step 1), or at max_steps.",
)


def markdown_report(d: Diagnosis) -> str:
    lines = ["# Sim-to-real gap diagnosis", "", _headline(d).replace("**", "**"), ""]
    warns = report_warnings(d)
    if warns:
        lines += ["## Warnings", ""] + [f"- **warning:** {w}" for w in warns] + [""]
    for title, head, rows in _tables(d):
        lines += [f"## {title}", "", "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
        lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in rows]
        lines.append("")
    if d.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in d.notes] + [""]
    lines += ["Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in d.timings.items()), ""]
    lines += ["## Rules of the path", "", f"(BIC threshold {d.bic_threshold:g}.)", ""] + [f"- {r}" for r in PATH_RULES] + [""]
    fr = (getattr(d, "settings", None) or {}).get("failed_refits")
    if fr:
        lines += [f"Failed refits: {fr.get('candidates', 0)} candidate refit(s) failed after a retry"
                  + (f" ({', '.join(fr.get('which', []))})" if fr.get("which") else "")
                  + f", {fr.get('retried', 0)} retried, {fr.get('fresh_start_on_path', 0)} joint refit(s) from fresh "
                  "starts on the path failed.", ""]
    lines += ["Figures: see report.html; every number: diagnosis.json.", ""]
    return "\n".join(lines)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    agg_pyplot().close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def figures(d: Diagnosis) -> list[tuple[str, str]]:
    """``[(caption, base64 PNG)]`` of the diagnosis (see the module docstring)."""
    plt = agg_pyplot()
    ctx, fin = d.context, d.final_context
    out = []
    if ctx is None:
        return out
    colors = {"peak core": "k", "peak wings": "m", "band": "b", "secondary lobe": "g", "far field": "orange"}
    for bi, b in enumerate(ctx.blocks):
        r = np.asarray(ctx.residuals[bi], float)
        geo = ctx.geometry[bi]
        regs = [(k, reg) for k, reg in enumerate(d.regions) if reg.block == bi]
        lim = max(3.0, float(np.nanpercentile(np.abs(r), 99))) if np.isfinite(r).any() else 3.0
        if isinstance(b, FrameData):
            fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
            ext = [b.grid.n_h[0], b.grid.n_h[-1], b.grid.n_v[-1], b.grid.n_v[0]]
            im = axes[0].imshow(r, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=ext, aspect="auto")
            for _k, reg in regs:
                axes[0].contour(b.grid.n_h, b.grid.n_v, reg.mask.astype(float), levels=[0.5], colors=colors.get(reg.name, "k"), linewidths=1)
            axes[0].set_xlabel("n_h (px)")
            axes[0].set_ylabel("n_v (px)")
            axes[0].set_title(f"{d.block_names[bi]}: r = (ln d - ln f)/sigma, detector")
            fig.colorbar(im, ax=axes[0])
            ok = np.isfinite(r)
            sc = axes[1].scatter(geo["sx"][ok], geo["sy"][ok], c=r[ok], cmap="RdBu_r", vmin=-lim, vmax=lim, s=4)
            for k, reg in regs:
                axes[1].scatter(geo["sx"][reg.mask], geo["sy"][reg.mask], s=6, facecolors="none", edgecolors=colors.get(reg.name, "k"), linewidths=0.4)
                axes[1].annotate(f"{reg.name} #{k + 1}", reg.center_deg, fontsize=7)
            axes[1].set_xlabel("sx: theta from specular, in plane (deg)")
            axes[1].set_ylabel("sy: out of plane (deg)")
            axes[1].set_title("specular-relative angles, zones outlined")
            fig.colorbar(sc, ax=axes[1])
            out.append((f"Residual map of the base fit, {d.block_names[bi]}, with the zones outlined", _png(fig)))
            # the columns through the named peaks: before/after
            final = None
            if fin is not None and d.significant and bi < len(fin.model_values):
                final = (" + ".join(d.explained_by), fin.model_values[bi])
            for prof in column_profiles(b, geo, ctx.model_values[bi], final):
                fig = plot_column_profile(prof)
                out.append((f"Before/after: {prof['title']}", _png(fig)))
        else:
            fig, ax = plt.subplots(figsize=(7, 4))
            ok = np.isfinite(r)
            ax.scatter(geo["sx"][ok], r[ok], s=6, c="0.3")
            for _k, reg in regs:
                ax.axvspan(float(geo["sx"][reg.mask].min()), float(geo["sx"][reg.mask].max()), alpha=0.2, color=colors.get(reg.name, "k"))
            ax.set_xlabel("angle from specular (deg)")
            ax.set_ylabel("r = (ln d - ln f)/sigma")
            ax.set_title(f"{d.block_names[bi]}: residuals, zones shaded")
            out.append((f"Residuals of the base fit, {d.block_names[bi]}", _png(fig)))
    fig, ax = plt.subplots(figsize=(7, 4))
    xs = np.arange(len(d.path))
    ax.semilogy(xs, [s.gap["chi2_reduced"] for s in d.path], "o-", label="reduced chi^2 (fitted frames)")
    ax.set_xticks(xs, [_name(s) for s in d.path], rotation=20)
    ax.set_ylabel("reduced chi^2")
    if any(s.heldout is not None for s in d.path):
        ax2 = ax.twinx()
        ax2.plot(xs, [np.nan if s.heldout is None else s.heldout["rms_log10"] for s in d.path], "s--", color="C1", label="held-out rms log10")
        ax2.set_ylabel("held-out rms of log10 (decades)", color="C1")
    ax.set_title("explanation path")
    ax.legend(loc="upper right", fontsize=8)
    out.append(("The explanation path", _png(fig)))
    return out


def _column_chi2(data: np.ndarray, sigma: np.ndarray, model: np.ndarray, usable: np.ndarray) -> float:
    ok = usable & (data > 0) & (model > 0) & np.isfinite(model) & (sigma > 0)
    r = (np.log(data[ok]) - np.log(model[ok])) / sigma[ok]
    return float(np.sum(r * r))


def _peak_columns(b: FrameData, geo: dict[str, np.ndarray], base_values: np.ndarray) -> list[tuple[str, int, str]]:
    """``[(peak name, column index, note)]``: the specular peak's column and, if another, the model maximum's."""
    sx, sy = np.asarray(geo["sx"], float), np.asarray(geo["sy"], float)
    dist = np.where(np.isfinite(sx) & np.isfinite(sy), sx * sx + sy * sy, np.inf)
    row, col = np.unravel_index(int(np.argmin(dist)), dist.shape)
    # how far one grid step reaches in angle there: the specular direction is "in" the region if the
    # nearest grid point is within about one step of it
    steps = [float(np.nanmax(np.abs(np.diff(a, axis=k)))) for a, k in ((sx, 1), (sy, 0)) if a.shape[k] > 1]
    inside = not steps or math.sqrt(float(dist[row, col])) <= 1.5 * max(steps)
    note = "" if inside else " (the specular direction lies outside the region: the nearest column)"
    out = [("the specular peak", int(col), note)]
    mv = np.where(np.isfinite(base_values), base_values, -np.inf)
    _, mcol = np.unravel_index(int(np.argmax(mv)), mv.shape)
    if int(mcol) != int(col):
        out.append(("the base model's maximum", int(mcol), ""))
    return out


def column_profiles(b: FrameData, geo: dict[str, np.ndarray], base_values: np.ndarray,
                    final: tuple[str, np.ndarray] | None = None) -> list[dict[str, Any]]:
    """The columns through the named peaks of a frame, as plotted (see the module docstring).

    Each: ``name``, ``col`` (index on the grid), ``n_h`` (pixel index),
    ``n_v``, ``data`` (NaN where masked: masked pixels are not data),
    ``masked`` (bool per row), ``curves`` (``[(label with chi^2, values,
    chi2)]``: the base model and, with ``final = (label, values)``, the model
    at the end of the path), ``title``.
    """
    usable = np.asarray(b.usable(), bool)
    brdf = np.asarray(b.brdf, float)
    sigma = np.broadcast_to(np.asarray(b.sigma_rel, float), brdf.shape)
    out = []
    for name, col, note in _peak_columns(b, geo, base_values):
        u = usable[:, col]
        d = brdf[:, col]
        curves = []
        for label, values in [("base model", base_values)] + ([final] if final is not None else []):
            v = np.asarray(values, float)[:, col]
            chi2 = _column_chi2(d, sigma[:, col], v, u)
            curves.append((f"{label} (chi^2 {chi2:.4g} on {int(u.sum())} points)", v, chi2))
        out.append({
            "name": name, "col": col, "n_h": int(np.asarray(b.grid.n_h)[col]), "n_v": np.asarray(b.grid.n_v),
            "data": np.where(u & (d > 0), d, np.nan), "masked": ~u, "curves": curves,
            "title": f"{b.name}: column n_h = {int(np.asarray(b.grid.n_h)[col])} through {name}{note}",
        })
    return out


def column_profile(b: FrameData, geo: dict[str, np.ndarray], base_values: np.ndarray,
                   final: tuple[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The column through the specular peak (the first of :func:`column_profiles`)."""
    return column_profiles(b, geo, base_values, final)[0]


def plot_column_profile(prof: dict[str, Any]):
    """The figure of one :func:`column_profiles` entry: data points, masked rows shaded, labelled model curves."""
    plt = agg_pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    n_v = prof["n_v"]
    dv = float(np.min(np.diff(n_v))) if n_v.size > 1 else 1.0
    first = True
    for k in np.flatnonzero(prof["masked"]):
        ax.axvspan(n_v[k] - dv / 2, n_v[k] + dv / 2, color="0.85", lw=0, label="masked (not data)" if first else None)
        first = False
    ax.semilogy(n_v, prof["data"], ".", ms=3, color="0.3", label="data (usable)")
    for (label, values, _), style in zip(prof["curves"], ("-", "--")):
        ax.semilogy(n_v, np.where(values > 0, values, np.nan), style, label=label)
    ax.set_xlabel("n_v (px)")
    ax.set_ylabel("BRDF (sr^-1)")
    ax.set_title(prof["title"], fontsize=9)
    ax.legend(fontsize=7)
    return fig


def _column_checks(d: Diagnosis) -> list[tuple[str, str]]:
    """A plotted final model that misses the fit's own residuals in its column by more than 2x in chi^2."""
    ctx, fin = d.context, d.final_context
    out: list[tuple[str, str]] = []
    if ctx is None or fin is None or not d.significant:
        return out
    for bi, b in enumerate(ctx.blocks):
        if not isinstance(b, FrameData) or bi >= len(fin.model_values) or bi >= len(fin.residuals):
            continue
        for prof in column_profiles(b, ctx.geometry[bi], ctx.model_values[bi], ("final", fin.model_values[bi])):
            plotted = prof["curves"][-1][2]
            r = np.asarray(fin.residuals[bi], float)[:, prof["col"]]
            fitted = float(np.nansum(r * r))
            if fitted > 0 and not (0.5 <= plotted / fitted <= 2.0):
                out.append((d.block_names[bi], (
                    f"{d.block_names[bi]}, column n_h = {prof['n_h']}: the plotted final model gives chi^2 {plotted:.4g} "
                    f"on the plotted points but the fit's residuals give {fitted:.4g}: the curve is not the model the "
                    "fit compared with the data (a per-frame term or the footprint is missing from the plot)")))
    return out


_figures = figures  # html_report's keyword ``figures`` (a flag) hides the function


def html_report(d: Diagnosis, *, figures: bool = True) -> str:
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>brdfjax diagnosis</title>",
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:collapse;font-size:12px}"
        "td,th{border:1px solid #bbb;padding:2px 6px}img{max-width:100%}</style></head><body>",
        "<h1>Sim-to-real gap diagnosis</h1>",
        f"<p>{html.escape(_headline(d)).replace('**', '')}</p>",
    ]
    warns = report_warnings(d)
    if warns:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li><b>warning:</b> {html.escape(w)}</li>" for w in warns) + "</ul>")
    for title, head, rows in _tables(d):
        parts.append(f"<h2>{html.escape(title)}</h2><table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>")
        parts += ["<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows]
        parts.append("</table>")
    if figures:
        parts.append("<h2>Figures</h2>")
        for caption, b64 in _figures(d):
            parts.append(f"<figure><img alt='{html.escape(caption)}' src='data:image/png;base64,{b64}'><figcaption>{html.escape(caption)}</figcaption></figure>")
    if d.notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in d.notes) + "</ul>")
    parts.append(f"<h2>Rules of the path</h2><p>BIC threshold {d.bic_threshold:g}.</p><ul>"
                 + "".join(f"<li>{html.escape(r)}</li>" for r in PATH_RULES) + "</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)
