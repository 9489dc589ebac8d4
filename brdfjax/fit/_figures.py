"""Figures of a fit (matplotlib, Agg; written atomically): frames and tables against the fitted model.

Per detector frame, ``fit_<name>.png``: the data and the fitted model as
``log10`` BRDF on one colour scale, and the normalised residual ``(ln f_model
- ln f_data) / sigma_rel`` on a symmetric scale, each with lines of constant
``theta_s`` (solid) and ``phi_s`` (dashed); below, the pixel column through
the brightest pixel and the column through the second peak with the data's
1-sigma band and the model.  Unusable pixels are grey.

Per goniometer table, ``fit_<name>.png``: one panel per incident angle
with the data (dots) and the model (line), log scale, against the signed
in-plane scatter angle (in-plane tables) or the angle from the mirror
direction (out-of-plane tables), with each panel's log-RMS.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..core.geometry import Directions, direction
from ..core.render import render
from ..instrument.synthetic import convolve_footprint
from ..io.blocks import FrameData, TableData
from ..plotting import colormap, log10_floor, new_figure, save_figure_atomic, visible_contours

__all__ = ["write_figures", "frame_model_image", "plot_frame_fit", "plot_table_fit"]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


def frame_model_image(model: Any, frame: Any, block: FrameData, use_footprint: bool = True) -> np.ndarray:
    """The fitted model on a frame's grid (convolved with its footprint when the fit did), float64."""
    precision = "float64" if jax.config.jax_enable_x64 else "float32"
    img = np.asarray(render(model, frame, block.arm_detector(), grid=block.grid, precision=precision), np.float64)
    if block.footprint is not None and use_footprint:
        k = np.asarray(block.footprint, np.float64)
        img = convolve_footprint(img, k / k.sum()).astype(np.float64)
    return img


def plot_frame_fit(block: FrameData, model_img: np.ndarray, frame: Any, path: Path, *, title: str = "", dpi: int = 100) -> Path:
    """The data / model / residual figure of one frame (module docstring)."""
    d = np.asarray(block.brdf, np.float64)
    u = block.usable()
    sig = np.broadcast_to(np.asarray(block.sigma_rel, np.float64), d.shape)
    data_shown = np.where(u, d, np.nan)
    _, vmin, vmax = log10_floor(np.where(u, d, 0.0), decades=8.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lm = np.log10(np.where(model_img > 0, model_img, np.nan))
        ld = np.log10(data_shown)
        res = np.where(u, (np.log(model_img) - np.log(d)) / sig, np.nan)
    vmin = min(vmin, float(np.nanmin(ld))) if np.isfinite(ld).any() else vmin
    lm = np.where(np.isfinite(lm), np.maximum(lm, vmin), vmin)  # zero / underflowing model: the floor
    rmax = float(np.nanpercentile(np.abs(res), 99)) if np.isfinite(res).any() else 1.0
    rmax = max(3.0, min(rmax, 50.0))

    n_h, n_v = np.asarray(block.grid.n_h), np.asarray(block.grid.n_v)
    dh = float(n_h[1] - n_h[0]) if n_h.size > 1 else 1.0
    dv = float(n_v[1] - n_v[0]) if n_v.size > 1 else 1.0
    box = (n_h[0] - dh / 2, n_h[-1] + dh / 2, n_v[0] - dv / 2, n_v[-1] + dv / 2)
    det = block.arm_detector()  # the arm is fixed: its contours need no theta_c
    try:
        lines = visible_contours(det, None, box)
    except Exception:  # contours are decoration; never fail a figure on them
        lines = []

    fig = new_figure(figsize=(16.0, 9.0), layout="constrained")
    axes = fig.subplots(2, 3, height_ratios=[1.25, 1.0])
    magma = _with_bad("magma")
    rdbu = _with_bad("RdBu_r")
    extent = (box[0], box[1], box[3], box[2])
    aspect = "equal" if 0.25 < (box[1] - box[0]) / (box[3] - box[2]) < 4 else "auto"
    for ax, img, label in ((axes[0, 0], ld, "data"), (axes[0, 1], lm, "model")):
        im = ax.imshow(img, extent=extent, origin="upper", cmap=magma, vmin=vmin, vmax=vmax,
                       interpolation="nearest", aspect=aspect)
        ax.set_title(f"{label}: log$_{{10}}$ BRDF (sr$^{{-1}}$)", fontsize=10)
    fig.colorbar(im, ax=axes[0, :2], shrink=0.9, pad=0.01)
    im = axes[0, 2].imshow(res, extent=extent, origin="upper", cmap=rdbu, vmin=-rmax, vmax=rmax,
                           interpolation="nearest", aspect=aspect)
    axes[0, 2].set_title(r"residual (ln model $-$ ln data) / $\sigma_{rel}$", fontsize=10)
    fig.colorbar(im, ax=axes[0, 2], shrink=0.9, pad=0.01)
    for ax in axes[0]:
        for line in lines:
            th = line["kind"] == "theta_s"
            ax.plot(line["n_h"], line["n_v"], color="#7fdbff" if th else "#b8f5a0", lw=0.6, alpha=0.8,
                    ls="-" if th else "--")
        ax.set_xlim(box[0], box[1])
        ax.set_ylim(box[3], box[2])
        ax.set_xlabel(r"$n_h$ (pixel)")
        ax.set_ylabel(r"$n_v$ (pixel)")
    # level labels on the data panel
    for line in lines:
        finite = np.flatnonzero(np.isfinite(line["n_h"]))
        if finite.size:
            k = finite[finite.size // 2 if line["kind"] == "phi_s" else finite.size // 8]
            axes[0, 0].annotate(
                ("θs" if line["kind"] == "theta_s" else "φs") + f"={line['level_deg']:.4g}°",
                (line["n_h"][k], line["n_v"][k]), fontsize=6.5, color="black",
                bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.7),
            )

    # column slices: through the brightest usable pixel and through the brightest pixel far from it
    score = np.where(u, d, -np.inf)
    r0, c0 = np.unravel_index(int(np.argmax(score)), d.shape)
    far = np.abs(np.arange(d.shape[1]) - c0) > max(3, d.shape[1] // 20)
    cols = [c0]
    if (score[:, far] > -np.inf).any():
        sc = np.where(far[None, :], score, -np.inf)
        cols.append(int(np.unravel_index(int(np.argmax(sc)), d.shape)[1]))
    for ax, ci in zip(axes[1, :2], cols):
        ok = u[:, ci]
        x = n_v
        ax.fill_between(x, np.where(ok, d[:, ci] * np.exp(-sig[:, ci]), np.nan),
                        np.where(ok, d[:, ci] * np.exp(sig[:, ci]), np.nan), color="C0", alpha=0.3, lw=0,
                        label=r"data $\pm 1\sigma$")
        ax.semilogy(x, np.where(ok, d[:, ci], np.nan), ".", color="C0", ms=3, label="data")
        ax.semilogy(x, np.where(model_img[:, ci] > 0, model_img[:, ci], np.nan), "-", color="C3", lw=1.0, label="model")
        ax.set_xlabel(r"$n_v$ (pixel)")
        ax.set_ylabel(r"BRDF (sr$^{-1}$)")
        ax.set_title(f"column $n_h$ = {n_h[ci]}", fontsize=10)
        ax.set_ylim(10 ** (vmin - 0.2), 10 ** (vmax + 0.3))
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        for a in axes[0]:
            a.axvline(n_h[ci], color="white", lw=0.6, ls=":")
    for ax in axes[1, len(cols):2]:
        ax.set_visible(False)
    ax = axes[1, 2]
    rr = res[np.isfinite(res)]
    if rr.size:
        ax.hist(np.clip(rr, -rmax, rmax), bins=60, density=True, color="C0", alpha=0.7, label="residuals")
        t = np.linspace(-rmax, rmax, 200)
        ax.plot(t, np.exp(-t * t / 2) / math.sqrt(2 * math.pi), "k-", lw=1, label="N(0, 1)")
        ax.set_title(f"{rr.size} usable pixels, rms {np.sqrt(np.mean(rr**2)):.3g}", fontsize=10)
        ax.legend(fontsize=8)
    ax.set_xlabel("normalised residual")
    th = math.degrees(float(np.asarray(frame.theta_i)))
    ph = math.degrees(float(np.asarray(frame.phi_ref)))
    fig.suptitle(f"{title}frame '{block.name}': θi = {th:.4g}°, φref = {ph:.4g}°  ({d.shape[0]} x {d.shape[1]} grid)",
                 fontsize=11)
    return save_figure_atomic(fig, Path(path), dpi)


def _with_bad(name: str):
    return colormap(name).with_extremes(bad="#bbbbbb")


def table_model(model: Any, block: TableData) -> np.ndarray:
    """The fitted model at a table's rows (sr^-1)."""
    ti, pi_, ts, ps = (np.asarray(getattr(block, f), np.float64) for f in ("theta_i", "phi_i", "theta_s", "phi_s"))
    dirs = Directions.from_angles(ti, pi_, ts, ps)
    wl = np.broadcast_to(np.asarray(block.wavelength, np.float64), ti.shape)
    return np.asarray(model(dirs, wl), np.float64)


def plot_table_fit(block: TableData, model_vals: np.ndarray, path: Path, *, title: str = "", dpi: int = 100) -> Path:
    """Data and model per incident angle, one panel each, in one figure (module docstring)."""
    u = block.usable()
    ti = np.degrees(np.asarray(block.theta_i, float))
    ts = np.asarray(block.theta_s, float)
    ps = np.asarray(block.phi_s, float)
    pi_ = np.broadcast_to(np.asarray(block.phi_i, float), ts.shape)
    d = np.asarray(block.brdf, float)
    rel = ps - pi_
    inplane = bool(np.all(np.abs(np.sin(rel[u])) < 1e-6))
    if inplane:
        x = np.degrees(ts) * np.where(np.cos(rel) < 0, 1.0, -1.0)  # + forward (mirror side)
        xlabel = r"signed in-plane $\theta_s$ (deg; + mirror side)"
    else:
        tia = np.asarray(block.theta_i, float)
        mirror = np.stack([np.sin(tia) * np.cos(pi_ + np.pi) * -1, np.sin(tia) * np.sin(pi_ + np.pi) * -1, np.cos(tia)], -1)
        ws = np.asarray(direction(ts, ps))
        x = np.degrees(np.arccos(np.clip(np.sum(ws * mirror, -1), -1.0, 1.0)))
        xlabel = "angle from the mirror direction (deg)"
    angles = np.unique(np.round(ti[u], 6))
    n = angles.size
    ncol = min(4, n)
    nrow = int(math.ceil(n / ncol))
    fig = new_figure(figsize=(4.0 * ncol + 1, 3.3 * nrow + 0.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for ax, a in zip(axes, angles):
        sel = u & (np.abs(ti - a) < 1e-6)
        order = np.argsort(x[sel])
        xs, ds, ms = x[sel][order], d[sel][order], model_vals[sel][order]
        with np.errstate(divide="ignore", invalid="ignore"):
            lr = np.log(ms / ds)
        rms = float(np.sqrt(np.mean(lr[np.isfinite(lr)] ** 2))) if np.isfinite(lr).any() else float("nan")
        ax.semilogy(xs, ds, ".", ms=3, color="C0", label="data")
        ax.semilogy(xs, ms, "-" if inplane else ".", ms=2, lw=1.0, color="C3", label="model")
        ax.set_title(f"θi = {a:.4g}°: log-RMS {rms:.3f}", fontsize=10)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(r"BRDF (sr$^{-1}$)", fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.suptitle(f"{title}table '{block.name}': data and fitted model per incident angle", fontsize=11)
    return save_figure_atomic(fig, Path(path), dpi)


def write_figures(job: Any, result: Any, out: Path, *, dpi: int = 100) -> list[Path]:
    """Every figure of a fit into ``out``; returns the paths."""
    out = Path(out)
    paths = []
    use_fp = bool(job.fit_kwargs.get("use_footprint", True))
    state = "" if result.converged else "NOT CONVERGED - "
    for k, block in enumerate(job.blocks):
        model = result.models[k]
        name = _safe(block.name)
        if isinstance(block, FrameData):
            frame = result.frames[k]
            img = frame_model_image(model, frame, block, use_fp)
            paths.append(plot_frame_fit(block, img, frame, out / f"fit_{name}.png", title=state, dpi=dpi))
        else:
            vals = table_model(model, block)
            paths.append(plot_table_fit(block, vals, out / f"fit_{name}.png", title=state, dpi=dpi))
    return paths
