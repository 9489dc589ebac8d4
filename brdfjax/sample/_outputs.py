"""Outputs of a posterior study: the summary (posterior.json), corner, trace and posterior-predictive figures.

Every number is reported in natural units (angles in degrees, the rest as
stored), like the fit's result.  Files are written atomically
(:func:`brdfjax.io.atomic_output`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..plotting import agg_pyplot, save_figure_atomic

__all__ = ["summarise", "plot_corner", "plot_trace", "plot_predictive", "model_at_points", "QUANTILES"]

#: Reported quantiles: key -> percentile.
QUANTILES = {"q025": 2.5, "q16": 16.0, "median": 50.0, "q84": 84.0, "q975": 97.5}


def _num(x: Any) -> Any:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def summarise(
    flat_natural: np.ndarray,
    names: Sequence[str],
    units: Sequence[str],
    tau: np.ndarray,
    ess: np.ndarray,
    map_natural: np.ndarray,
    fit_values: np.ndarray | None,
    fit_sigmas: np.ndarray | None,
    priors: dict[str, str],
) -> dict[str, Any]:
    """Per-parameter summary: quantiles, mean, std, tau, ESS, MAP (and the fit's value and sigma)."""
    out: dict[str, Any] = {}
    q = np.percentile(flat_natural, list(QUANTILES.values()), axis=0)
    for i, name in enumerate(names):
        d = {k: _num(q[j, i]) for j, k in enumerate(QUANTILES)}
        d.update(
            mean=_num(np.mean(flat_natural[:, i])),
            std=_num(np.std(flat_natural[:, i], ddof=1)) if flat_natural.shape[0] > 1 else None,
            map=_num(map_natural[i]),
            tau=_num(tau[i]),
            ess=_num(ess[i]),
            unit=units[i],
            prior=priors.get(name, ""),
        )
        if fit_values is not None:
            d["fit_value"] = _num(fit_values[i])
            d["fit_sigma"] = _num(fit_sigmas[i]) if fit_sigmas is not None else None
        out[name] = d
    return out


def _labels(names: Sequence[str], units: Sequence[str]) -> list[str]:
    return [f"{n} [{u}]" if u not in ("1", "") else n for n, u in zip(names, units)]


class _NoContourWarning(logging.Filter):
    """Drops corner's "Too few points to create valid contours" (a parameter whose samples barely spread):
    the panel is drawn without contours and the figure says so, instead of a stray log line."""

    def __init__(self) -> None:
        super().__init__()
        self.dropped = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if "Too few points to create valid contours" in record.getMessage():
            self.dropped += 1
            return False
        return True


def plot_corner(path: Path, flat_natural: np.ndarray, names, units, truths=None, title: str | None = None,
                truth_label: str = "least-squares fit (the chain's start)") -> Path:
    """Marginals and pairwise densities; red lines: ``truths`` (here the least-squares fit), named in a legend."""
    plt = agg_pyplot()
    import corner  # imports pyplot at import time: only after agg_pyplot() has chosen the backend

    k = flat_natural.shape[1]
    fig = plt.figure(figsize=(max(2.3 * k, 5.0), max(2.3 * k, 5.0)))
    quiet = _NoContourWarning()
    logging.getLogger().addFilter(quiet)
    try:
        fig = corner.corner(
            flat_natural,
            fig=fig,
            labels=_labels(names, units),
            quantiles=[0.16, 0.5, 0.84],
            show_titles=True,
            title_fmt=".3g",
            truths=None if truths is None else list(truths),
            truth_color="tab:red",
            max_n_ticks=3,
            labelpad=0.12,
            label_kwargs={"fontsize": 9},
            title_kwargs={"fontsize": 8},
        )
    finally:
        logging.getLogger().removeFilter(quiet)
    for ax in fig.axes:
        ax.tick_params(labelsize=7)
    handles = [plt.Line2D([], [], color="k", ls="--", lw=1, label="16, 50, 84 % posterior quantiles")]
    if truths is not None:
        handles.insert(0, plt.Line2D([], [], color="tab:red", lw=1.5, label=f"red: {truth_label}"))
    if quiet.dropped:
        handles.append(plt.Line2D([], [], color="none", label=f"{quiet.dropped} panel(s) without contours: too few distinct samples"))
    fig.legend(handles=handles, loc="upper right", fontsize=9, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10, y=1.01)
    save_figure_atomic(fig, path, 90, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_trace(path: Path, chain_natural: np.ndarray, names, units, burn: int, max_params: int = 16) -> Path:
    """Every walker's trace per parameter (up to ``max_params``), the burn-in marked."""
    plt = agg_pyplot()
    p = min(len(names), max_params)
    fig, axes = plt.subplots(p, 1, figsize=(8, 1.3 * p + 0.6), sharex=True, squeeze=False)
    steps = np.arange(chain_natural.shape[0])
    for i, ax in enumerate(axes[:, 0]):
        ax.plot(steps, chain_natural[:, :, i], color="k", alpha=0.15, lw=0.6)
        ax.axvline(burn, color="tab:red", lw=0.8)
        ax.set_ylabel(_labels(names, units)[i], fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel("step (red: end of burn-in)")
    fig.tight_layout()
    save_figure_atomic(fig, path, 80)
    plt.close(fig)
    return path


def model_at_points(post: Any, X: np.ndarray) -> list[np.ndarray]:
    """The model at every usable point of every block for the draws ``X`` (stored units), per block ``(n_draws, n_k)``.

    Recovered from the fit's weighted residuals ``r = (log(f + floor) - log d) / sigma_rel``, so it is
    exactly the model the likelihood sees (convolved with the footprint where the fit convolves).
    """

    problem = post.problem
    R = np.asarray(_weighted_residuals(jnp.asarray(np.asarray(X, np.float64), post.dtype), problem), np.float64)
    out, off = [], 0
    for block, n in zip(problem.block_list(), problem.counts):
        d = np.asarray(block.data, np.float64)[:n]
        inv = np.asarray(block.inv_sigma, np.float64)[:n]
        floor = float(np.asarray(block.floor))
        out.append(d * np.exp(R[:, off : off + n] / inv) - floor)
        off += n
    return out


def _weighted_residuals(X, problem):

    return eqx.filter_jit(lambda X, p: jax.vmap(p.weighted_residuals)(X))(X, problem)


def plot_predictive(
    path: Path, data: Any, f_points: np.ndarray, col_idx: Sequence[int], title: str, seed: int = 0
) -> Path:
    """Data (1-sigma bars) and, along grid columns, the model's 95 % credible band and the 95 % posterior-
    predictive band (model draws times the data's log-normal noise), at the usable points.

    Top row: the BRDF on a log scale.  Bottom row: the same divided by the posterior median model, where
    bands a few per cent wide are visible (on the log scale they are thinner than the line)."""
    plt = agg_pyplot()
    brdf = np.asarray(data.brdf, np.float64)
    sigma = np.broadcast_to(np.asarray(data.sigma_rel, np.float64), brdf.shape)
    usable = data.usable()
    rows, cols = np.nonzero(usable)
    n_v = np.asarray(data.grid.n_v)
    n_h = np.asarray(data.grid.n_h)
    rng = np.random.default_rng(seed)
    noisy = f_points * np.exp(sigma[rows, cols][None, :] * rng.standard_normal(f_points.shape))
    n = len(col_idx)
    fig, axes = plt.subplots(2, n, figsize=(7.5 * n, 7.0), squeeze=False, sharex="col",
                             gridspec_kw={"height_ratios": [3, 2]})
    for j, c in enumerate(col_idx):
        ax, rax = axes[0, j], axes[1, j]
        sel = np.flatnonzero(cols == c)
        r = rows[sel]
        q = np.percentile(f_points[:, sel], [2.5, 50, 97.5], axis=0)
        qn = np.percentile(noisy[:, sel], [2.5, 97.5], axis=0)
        x = n_v[r]
        d = brdf[r, c]
        for a, scale in ((ax, 1.0), (rax, q[1])):
            a.fill_between(x, qn[0] / scale, qn[1] / scale, color="tab:orange", alpha=0.35, step="mid",
                           label="95 % posterior predictive (model x noise)")
            a.fill_between(x, q[0] / scale, q[2] / scale, color="tab:blue", alpha=0.6, step="mid",
                           label="95 % credible band of the model")
            a.plot(x, q[1] / scale, color="tab:blue", lw=1.0, label="posterior median model")
            a.errorbar(x, d / scale, yerr=d * sigma[r, c] / scale, fmt=".", ms=4, color="k", lw=0.7,
                       label="data (usable pixels, 1 sigma)")
        ax.set_yscale("log")
        ax.set_ylabel("BRDF (sr$^{-1}$)")
        ax.set_title(f"{title}: column n_h = {int(n_h[c])}", fontsize=11)
        rax.set_ylabel("ratio to the posterior median")
        rax.set_xlabel("pixel row n_v")
        rax.axhline(1.0, color="0.5", lw=0.6)
        for a in (ax, rax):
            a.tick_params(labelsize=9)
        if j == 0:
            ax.legend(fontsize=9, loc="best")
    fig.tight_layout()
    save_figure_atomic(fig, path, 100)
    plt.close(fig)
    return path


def slice_columns(data: Any) -> list[int]:
    """Grid columns to slice a frame along: through the brightest usable pixel and nearest the specular column."""
    brdf = np.where(data.usable(), np.asarray(data.brdf, np.float64), -np.inf)
    _, c_max = np.unravel_index(int(np.argmax(brdf)), brdf.shape)
    c0 = int(np.argmin(np.abs(np.asarray(data.grid.n_h))))
    return [int(c_max)] if c0 == c_max else [int(c_max), c0]
