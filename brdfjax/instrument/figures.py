"""Figures of the reduction: the two HDR merges side by side."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.raw import RawStack
from ..plotting import agg_pyplot
from ..runtime.atomic import atomic_output
from .stitch import SYNTHETIC_NONLINEARITY_CURVE, NonlinearityCurve, _curve, stitch_replacement, stitch_weighted

__all__ = ["plot_merge_comparison"]


def plot_merge_comparison(
    stack: RawStack,
    background: RawStack,
    path: str | os.PathLike,
    *,
    row: int | None = None,
    truth: np.ndarray | None = None,
    nonlinearity_curve: NonlinearityCurve | Sequence[tuple[float, float]] | None = SYNTHETIC_NONLINEARITY_CURVE,
    corrected: bool = True,
    taper_start: float | None = None,
    average_rows: bool = False,
    saturation_fraction: float = 0.98,
) -> Path:
    """Figure: one row of a stack stitched by the replacement scheme (§3.6) and by the weighted merge.

    Top: the stitched flux (sDC, log scale) of each merge along the row, each
    exposure's scaled counts faint behind.  Bottom: relative error against
    ``truth`` (expected sDC; without it, against the weighted merge), with
    the replacement scheme's switching points marked -- its seams -- for
    the weighted merge (inverse full variance with ``nonlinearity_curve``),
    with ``corrected``: the weighted merge of readings corrected by the
    curve, and with ``taper_start`` (None: left out): the weighted merge
    with that hand-over taper.  ``row`` defaults to the row of the brightest
    pixel; ``average_rows`` plots the bottom panel's errors averaged over
    all rows (for a target constant down each column, so that seams stand
    out of the noise).  Written atomically as PNG (matplotlib Agg).
    """
    plt = agg_pyplot()
    kw = dict(saturation_fraction=saturation_fraction)
    curve = _curve(nonlinearity_curve)
    merges = {"replacement (seed §3.6)": stitch_replacement(stack, background, **kw),
              "weighted (noise + non-linearity variance)": stitch_weighted(
                  stack, background, nonlinearity_curve=curve, **kw)}
    if corrected and curve is not None:
        merges["weighted, readings corrected by the curve"] = stitch_weighted(
            stack, background, nonlinearity_curve=curve, correct_nonlinearity=True, **kw)
    if taper_start is not None:
        merges[f"weighted, hand-over taper from {taper_start:g} FS"] = stitch_weighted(
            stack, background, nonlinearity_curve=curve, taper_start=taper_start, **kw
        )
    rep, wei = list(merges.values())[:2]
    if row is None:
        row = int(np.unravel_index(np.argmax(wei.flux), wei.flux.shape)[0])
    x = np.arange(stack.shape[1])
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(9, 7), sharex=True, height_ratios=(3, 2))
    t_ref = rep.t_ref
    for e, b in zip(stack.exposures, background.exposures):
        d = (e.counts[row].astype(np.float64) - b.counts[row]) * (t_ref / e.exposure_s)
        sat = e.counts[row] >= saturation_fraction * stack.attrs.full_scale
        ax0.plot(x, np.where(sat | (d <= 0), np.nan, d), lw=0.6, alpha=0.4, label=f"{e.exposure_s * 1e3:g} ms, scaled")
    styles = ["k-", "C3--", "C2-.", "C0:"]
    for (name, m), st in zip(merges.items(), styles):
        ax0.plot(x, np.where(m.flux[row] > 0, m.flux[row], np.nan), st, lw=1.0, label=name)
    if truth is not None:
        ax0.plot(x, truth[row], ":", color="0.3", lw=1.0, label="truth")
    ax0.set_yscale("log")
    ax0.set_ylabel("scatter flux (sDC)")
    ax0.set_title(f"{stack.path.name if stack.path else 'stack'}: row {row}")
    ax0.legend(fontsize=7, loc="best")
    rows = slice(None) if average_rows else slice(row, row + 1)
    ref = truth[rows] if truth is not None else wei.flux[rows]
    ok = np.abs(ref) > 0
    for (name, m), st in zip(merges.items(), styles):
        if truth is None and m is wei:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.nanmean(np.where(ok, m.flux[rows] / ref - 1.0, np.nan), axis=0)
        ax1.plot(x, 100 * rel, st, lw=0.8, label=name.split(" (")[0])
    for s in np.nonzero(np.diff(rep.source[row].astype(int)))[0]:
        ax1.axvline(s + 0.5, color="0.6", lw=0.5, ls=":")
    ax1.axhline(0.0, color="0.8", lw=0.5)
    ax1.set_ylim(-5, 5) if average_rows else ax1.set_ylim(-10, 10)
    what = "relative error (%)" if truth is not None else "merge / weighted - 1 (%)"
    ax1.set_ylabel(f"{what}, mean of {stack.shape[0]} rows" if average_rows else what)
    ax1.set_xlabel("column (array offset); dotted: exposure switches of the replacement scheme")
    ax1.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return path
