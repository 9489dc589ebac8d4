"""The reports of a diagnosis: Markdown (numbers) and a self-contained HTML page (numbers + figures as base64 PNG).

Figures (matplotlib, Agg): per frame the normalised residual map of the base
fit in detector pixels and in specular-relative angles with the zones
outlined; the column through the peak before/after (data, base model, the
model at the end of the explanation path); the explanation path as a chart
(reduced chi^2 and, when measured, the held-out rms of log10 per step).
Tables (goniometer data) get the residual against ``sx`` per incidence angle.
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

__all__ = ["markdown_report", "html_report", "figures"]


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
            "Which: candidate effects ranked by BIC gain (decreases: positive = explains part of the gap)",
            ["rank", "effect", "delta BIC", "delta chi2", "new params", "chi2_reduced after", "signature score", "signature"],
            [
                [str(i + 1), c.effect, _f(c.delta_bic, ".1f"), _f(c.delta_chi2, ".1f"), str(c.n_new), _f(c.gap_after.get("chi2_reduced")),
                 _f(c.signature.get("score"), ".3g"), str(c.signature.get("detail", ""))]
                for i, c in enumerate(d.ranking)
            ],
        )
    )
    if d.skipped:
        out.append(("Not ranked", ["effect", "status", "reason"], [[c.effect, c.status, c.note] for c in d.skipped]))
    zone_names = list(d.path[0].zones)
    out.append(
        (
            "How far: the explanation path",
            ["step", "effect", "chi2_reduced", "rms_log10", "held-out rms_log10", "delta BIC"] + [f"chi2_red {z}" for z in zone_names],
            [
                [str(i), _name(s), _f(s.gap["chi2_reduced"]), _f(s.gap["rms_log10"]), _f(None if s.heldout is None else s.heldout["rms_log10"]),
                 _f(s.delta_bic, ".1f")] + [_f(s.zones[z]["chi2_reduced"]) for z in zone_names]
                for i, s in enumerate(d.path)
            ],
        )
    )
    return out


def _name(s: Any) -> str:
    """A path step's name: ``base``, ``+effect`` (added) or ``-effect`` (taken out again)."""
    return {"add": "+", "remove": "-"}.get(getattr(s, "action", "add"), "") + s.effect if getattr(s, "action", "") != "base" else s.effect


def _headline(d: Diagnosis) -> str:
    p = " -> ".join(f"{_name(s)} ({_f(s.gap['chi2_reduced'], '.3g')})" for s in d.path)
    by = d.effects_by_side()
    sides = (f" Material effects: {', '.join(by['material']) or 'none'}; instrument effects: "
             f"{', '.join(by['instrument']) or 'none'}. The path stopped because {d.stop_reason}.")
    flags = "".join(f" Flag at {_name(s)}: {f}." for s in d.path for f in s.flags)
    if d.significant:
        return f"The gap is most likely caused by **{d.explained_by[0]}**. Explanation path (reduced chi^2): {p}.{sides}{flags}"
    return f"No candidate effect is significant (BIC gain > {d.bic_threshold:g}). Path: {p}.{sides}{flags}"


def markdown_report(d: Diagnosis) -> str:
    lines = ["# Sim-to-real gap diagnosis", "", _headline(d).replace("**", "**"), ""]
    for title, head, rows in _tables(d):
        lines += [f"## {title}", "", "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
        lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in rows]
        lines.append("")
    if d.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in d.notes] + [""]
    lines += ["Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in d.timings.items()), ""]
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
            # column through the peak: before/after
            mv = np.where(np.isfinite(ctx.model_values[bi]), ctx.model_values[bi], -np.inf)
            row, col = np.unravel_index(int(np.argmax(mv)), mv.shape)
            fig, ax = plt.subplots(figsize=(7, 4))
            data = np.asarray(b.brdf, float)[:, col]
            ax.semilogy(b.grid.n_v, np.where(data > 0, data, np.nan), ".", ms=3, color="0.4", label="data")
            ax.semilogy(b.grid.n_v, ctx.model_values[bi][:, col], "-", label="base model")
            if fin is not None and d.significant and bi < len(fin.model_values):
                ax.semilogy(b.grid.n_v, fin.model_values[bi][:, col], "--", label=" + ".join(d.explained_by))
            ax.set_xlabel("n_v (px)")
            ax.set_ylabel("BRDF (sr^-1)")
            ax.set_title(f"{d.block_names[bi]}: column n_h = {int(b.grid.n_h[col])} through the peak")
            ax.legend(fontsize=8)
            out.append((f"Before/after: the column through the peak, {d.block_names[bi]}", _png(fig)))
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


_figures = figures  # html_report's keyword ``figures`` (a flag) hides the function


def html_report(d: Diagnosis, *, figures: bool = True) -> str:
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>brdfjax diagnosis</title>",
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:collapse;font-size:12px}"
        "td,th{border:1px solid #bbb;padding:2px 6px}img{max-width:100%}</style></head><body>",
        "<h1>Sim-to-real gap diagnosis</h1>",
        f"<p>{html.escape(_headline(d)).replace('**', '')}</p>",
    ]
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
    parts.append("</body></html>")
    return "\n".join(parts)
