"""Seed-style figures of rendered frames (matplotlib's Figure API on Agg; no pyplot, no global backend).

:func:`plot_frame` draws what the seed's Figs 33-35 show: the log10 BRDF over
the CCD pixel grid with lines of constant ``theta_s`` and ``phi_s`` overlaid
and labelled in degrees, next to a slice along the pixel column through the
brightest pixel.  Figures are built on a bare ``Figure`` with the Agg canvas,
so no pyplot state or backend switch leaks into the caller.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Any

import numpy as np

# matplotlib (about 0.4 s to import) is imported by the functions that draw (_mpl): a command that writes
# no figure (``brdfjax fit --no-figures``, a batch worker, a reduction without plots) never loads it.
from .core.detector import Detector, PixelGrid
from .core.render import Conditions
from .core.terms import Diffraction, Lambertian, OffsetNormal
from .io import atomic_output

__all__ = ["plot_frame", "log10_floor", "term_labels"]


def term_labels(model: Any) -> dict[str, str]:
    """What each term of a model looks like on a frame, for figure labels: ``{"center": "centre peak (center)",
    "offset": "offset peak (offset)", "bars": "diffraction bars (bars)", ...}``."""
    out: dict[str, str] = {}
    first_peak = True
    for name, term in model.terms.items():
        if isinstance(term, Diffraction):
            what = "diffraction bars"
        elif isinstance(term, OffsetNormal):
            what = "offset peak"
        elif isinstance(term, Lambertian):
            what = "diffuse floor"
        elif hasattr(term, "distribution") or hasattr(term, "lobes") or hasattr(term, "term"):
            what = "centre peak" if first_peak else "specular peak"
            first_peak = False
        else:
            what = getattr(term, "kind", type(term).__name__)
        out[name] = f"{what} ({name})"
    return out

#: Decades below the maximum shown in the image.
DECADES = 8.0
# Images larger than this (per axis) are max-pooled for display so that
# peaks a few pixels wide stay visible after downsampling.
_MAX_DISPLAY = 900


def log10_floor(brdf: np.ndarray, decades: float = DECADES) -> tuple[np.ndarray, float, float]:
    """``log10`` of a BRDF image with zeros and values far below the peak clipped.

    Returns ``(image, vmin, vmax)`` with ``vmax = log10(max)`` and
    ``vmin = max(vmax - decades, log10(min positive))``.
    """
    b = np.asarray(brdf, dtype=np.float64)
    positive = b[np.isfinite(b) & (b > 0)]
    if positive.size == 0:
        return np.zeros_like(b), -1.0, 0.0
    vmax = float(np.log10(positive.max()))
    vmin = max(vmax - decades, float(np.log10(positive.min())))
    if vmin >= vmax:
        vmin = vmax - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        img = np.log10(np.where(b > 0, b, np.nan))
    return np.where(np.isfinite(img), np.maximum(img, vmin), vmin), vmin, vmax


def _log10_pooled(brdf: np.ndarray, decades: float = DECADES) -> tuple[np.ndarray, float, float]:
    """``_max_pool(log10_floor(brdf)[0])`` and its ``vmin, vmax``, pooling before the logarithm.

    The clipped ``log10`` is non-decreasing in the BRDF and sends zeros,
    negatives and non-finite values to its minimum, so the maximum of a pool
    commutes with it: the same image, with one logarithm per displayed pixel
    instead of one per detector pixel.
    """
    b = np.asarray(brdf)
    ok = np.isfinite(b) & (b > 0)
    if not ok.any():
        return _max_pool(np.zeros(b.shape))[0], -1.0, 0.0
    pos = np.where(ok, b, 0)
    vmax = float(np.log10(np.float64(pos.max())))
    vmin = max(vmax - decades, float(np.log10(np.float64(np.where(ok, b, np.inf).min()))))
    if vmin >= vmax:
        vmin = vmax - 1.0
    pooled = _max_pool(pos.astype(np.float64, copy=False))[0]
    with np.errstate(divide="ignore"):
        img = np.where(pooled > 0, np.log10(np.where(pooled > 0, pooled, 1.0)), vmin)
    return np.maximum(img, vmin), vmin, vmax


def _max_pool(img: np.ndarray, limit: int = _MAX_DISPLAY) -> tuple[np.ndarray, int, int]:
    fr, fc = (max(1, -(-n // limit)) for n in img.shape)
    if fr == 1 and fc == 1:
        return img, 1, 1
    rows, cols = -(-img.shape[0] // fr) * fr, -(-img.shape[1] // fc) * fc
    padded = np.full((rows, cols), -np.inf)
    padded[: img.shape[0], : img.shape[1]] = img
    return padded.reshape(rows // fr, fr, cols // fc, fc).max(axis=(1, 3)), fr, fc


def _levels(lo: float, hi: float, n: int = 7) -> np.ndarray:
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi - lo <= 0:
        return np.array([])
    ticks = _mpl().ticker.MaxNLocator(nbins=n, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
    return ticks[(ticks > lo) & (ticks < hi)]


def visible_contours(detector: Detector, theta_c: np.ndarray | None, box: tuple[float, float, float, float]) -> list[dict]:
    """Contours with round levels spanning the visible box ``(h0, h1, v0, v1)``."""
    h0, h1, v0, v1 = box
    hh, vv = np.meshgrid(np.linspace(h0, h1, 17), np.linspace(v0, v1, 17))
    th, ph = (np.rad2deg(np.asarray(a, dtype=np.float64)) for a in detector.angles(hh, vv, theta_c))
    # Azimuths may wrap at 0/360 deg (theta_c near 0): choose levels about the box centre's azimuth.
    centre = float(ph[8, 8])
    rel = (ph - centre + 180.0) % 360.0 - 180.0
    th_levels = _levels(th.min(), th.max())
    ph_levels = (centre + _levels(rel.min(), rel.max())) % 360.0
    return detector.contours(theta_s_deg=th_levels, phi_s_deg=ph_levels, theta_c=theta_c, n_points=600)


def _label_point(nh: np.ndarray, nv: np.ndarray, box, at: float) -> tuple[float, float] | None:
    """A point ``at`` (0..1) along the part of a polyline inside the box, away from its edges."""
    h0, h1, v0, v1 = box
    mh, mv = 0.07 * (h1 - h0), 0.03 * (v1 - v0)
    h0, h1, v0, v1 = h0 + mh, h1 - mh, v0 + mv, v1 - mv
    inside = np.isfinite(nh) & (nh >= h0) & (nh <= h1) & (nv >= v0) & (nv <= v1)
    idx = np.flatnonzero(inside)
    if idx.size < 2:
        return None
    k = idx[int(round(at * (idx.size - 1)))]
    return float(nh[k]), float(nv[k])


def _mpl() -> Any:
    """matplotlib with its Figure, ticker and Agg canvas modules, imported on first use: about 0.4 s that a
    process drawing no figure (``brdfjax fit --no-figures``, a batch worker, a diagnosis) never pays."""
    import matplotlib  # noqa: PLC0415 -- 0.4 s of every process otherwise; only a figure needs it

    for sub in ("figure", "ticker", "backends.backend_agg"):
        importlib.import_module(f"matplotlib.{sub}")
    return matplotlib


def new_figure(**kwargs: Any) -> Any:
    """A bare matplotlib ``Figure(**kwargs)`` (no pyplot state), drawn with Agg by :func:`save_figure_atomic`."""
    return _mpl().figure.Figure(**kwargs)


def colormap(name: str) -> Any:
    """matplotlib's colormap ``name``."""
    return _mpl().colormaps[name]


def agg_pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend, for figures drawn with pyplot (corner plots,
    traces, the merge-seam figure).  The backend is chosen before pyplot is first imported."""
    _mpl().use("Agg", force=False)
    return importlib.import_module("matplotlib.pyplot")


def save_figure_atomic(fig: Any, path: Path, dpi: int, **savefig_kw: Any) -> Path:
    """Save ``fig`` to ``path`` through :func:`~brdfjax.io.atomic_output` (Agg canvas; the format from the suffix,
    since the temporary name has none); ``savefig_kw`` go to ``Figure.savefig`` (e.g. ``bbox_inches``)."""
    agg = _mpl().backends.backend_agg.FigureCanvasAgg
    if not isinstance(fig.canvas, agg):  # a bare Figure (no pyplot): draw it with Agg
        agg(fig)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=dpi, **savefig_kw)
    return path


def plot_frame(
    brdf: Any,
    grid: PixelGrid,
    detector: Detector,
    frame: Conditions,
    path: str | os.PathLike,
    title: str | None = None,
    *,
    decades: float = DECADES,
    dpi: int = 110,
    terms: dict[str, Any] | None = None,
    labels: dict[str, str] | None = None,
) -> Path:
    """Save a seed-style PNG of one frame to ``path`` (atomically); returns the path.

    Left: ``log10`` BRDF (sr^-1) over the pixel grid, ``n_h`` to the right and
    ``n_v`` increasing downward as in an image, with lines of constant
    ``theta_s`` (solid) and ``phi_s`` (dashed) labelled in degrees.  Right: the
    BRDF along the pixel column through the centre peak (``n_h = 0``) and the
    column through the brightest pixel, log scale against ``n_v``.  ``brdf`` is the ``(rows, cols)`` image of ``grid``.

    ``terms`` (name -> image, e.g. the simulation's per-term images) names each term on the image, with an
    arrow to the brightest pixel where it makes at least half the BRDF, and draws each term's profile along
    the first column (dashed); ``labels`` (name -> text, default :func:`term_labels`-style names) says what
    each is ("centre peak", "offset peak", "diffraction bars").
    """
    b = np.asarray(brdf, dtype=np.float64)
    if b.shape != grid.shape:
        raise ValueError(f"plot_frame: brdf has shape {b.shape} but the grid is {grid.shape} (rows, cols)")
    n_h, n_v = np.asarray(grid.n_h), np.asarray(grid.n_v)
    dh = float(n_h[1] - n_h[0]) if n_h.size > 1 else 1.0
    dv = float(n_v[1] - n_v[0]) if n_v.size > 1 else 1.0
    box = (n_h[0] - dh / 2, n_h[-1] + dh / 2, n_v[0] - dv / 2, n_v[-1] + dv / 2)
    # An array, not a Python float: the detector's jitted methods would recompile for every new value.
    theta_c = np.asarray(detector.arm_angle(frame.theta_i), dtype=np.float64)

    shown, vmin, vmax = _log10_pooled(brdf, decades)

    fig = new_figure(figsize=(13.0, 5.6), layout="constrained")
    ax, ax_col = fig.subplots(1, 2, width_ratios=[1.45, 1.0])

    im = ax.imshow(
        shown,
        extent=(box[0], box[1], box[3], box[2]),  # row 0 (smallest n_v) at the top
        origin="upper",
        cmap="magma",
        vmin=vmin,
        vmax=vmax,
        interpolation="nearest",
        aspect="equal" if 0.25 < (box[1] - box[0]) / (box[3] - box[2]) < 4 else "auto",
    )
    cb = fig.colorbar(im, ax=ax, shrink=0.92, pad=0.01)
    cb.set_label(r"log$_{10}$ BRDF (sr$^{-1}$)")

    n_theta = 0
    for line in visible_contours(detector, theta_c, box):
        theta_line = line["kind"] == "theta_s"
        # theta_s lines run top to bottom: stagger their labels near the top; phi_s labels sit right.
        at = (0.02 + 0.07 * (n_theta % 2)) if theta_line else 0.9
        n_theta += theta_line
        style = dict(color="#7fdbff" if theta_line else "#b8f5a0", lw=0.8, alpha=0.9, ls="-" if theta_line else "--")
        ax.plot(line["n_h"], line["n_v"], **style)
        at = _label_point(line["n_h"], line["n_v"], box, at)
        if at is not None:
            sym = r"$\theta_s$" if theta_line else r"$\phi_s$"
            ax.annotate(
                f"{sym}={line['level_deg']:.4g}°",
                at,
                fontsize=7.5,
                color="black",
                ha="center",
                va="center",
                bbox=dict(boxstyle="round,pad=0.15", fc=style["color"], ec="none", alpha=0.85),
            )
    term_images = {k: np.asarray(v, dtype=np.float64) for k, v in (terms or {}).items()}
    offsets = [(60, -35), (-110, 40), (-110, -40), (70, 35), (-80, 0), (80, 0)]  # in the order labels are placed
    rows_i, cols_i = np.indices(b.shape)
    anchors: list[tuple[int, int]] = []
    # the peaks first, so that a band through a peak is labelled away from it
    for name, t in sorted(term_images.items(), key=lambda e: -float(np.nanmax(e[1], initial=0.0))):
        if t.shape != b.shape:
            continue
        dominant = np.isfinite(t) & (t > 0) & (t >= 0.5 * np.where(np.isfinite(b), b, np.inf))
        apart = dominant.copy()
        for ar, ac in anchors:
            apart &= np.hypot(rows_i - ar, cols_i - ac) > 0.12 * max(b.shape)
        pick = apart if apart.any() else dominant
        if not pick.any():
            continue
        rr, cc = np.unravel_index(int(np.argmax(np.where(pick, t, -np.inf))), t.shape)
        anchors.append((rr, cc))
        ax.annotate(
            (labels or {}).get(name, name), (n_h[cc], n_v[rr]), xytext=offsets[(len(anchors) - 1) % len(offsets)],
            textcoords="offset points", fontsize=8.5, color="black", ha="center", va="center",
            bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none", alpha=0.85),
            arrowprops=dict(arrowstyle="->", color="white", lw=1.0),
        )
    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[3], box[2])
    ax.set_xlabel(r"$n_h$ (pixel)")
    ax.set_ylabel(r"$n_v$ (pixel)")

    # Seed Fig 33 style: the column through the centre (specular) peak, n_h = 0 when the
    # detector is centred on it, and the column through the brightest pixel if that differs.
    finite = np.where(np.isfinite(b), b, -np.inf)
    r, c = np.unravel_index(int(np.argmax(finite)), b.shape)
    columns = []
    if n_h[0] <= 0 <= n_h[-1]:
        columns.append(int(np.argmin(np.abs(n_h))))
    if c not in columns:
        columns.append(c)
    for k, ci in enumerate(columns):
        col = b[:, ci]
        ax.axvline(n_h[ci], color="white", lw=0.6, ls=":", alpha=0.8)
        ax_col.semilogy(
            n_v, np.where(col > 0, col, np.nan), color=f"C{k}", lw=1.0, label=f"column $n_h$ = {n_h[ci]}"
        )
    for k, (name, t) in enumerate(term_images.items()):  # what each column is made of: the first column, per term
        if t.shape == b.shape and np.nanmax(t[:, columns[0]], initial=0.0) > 0:
            tc = t[:, columns[0]]
            ax_col.semilogy(n_v, np.where(tc > 0, tc, np.nan), ls="--", lw=0.9, color=f"C{k + 4}",
                            label=f"{(labels or {}).get(name, name)}, column $n_h$ = {n_h[columns[0]]}")
    ax_col.plot([n_v[r]], [b[r, c]], "o", ms=4, color="C3", label=f"maximum {b[r, c]:.4g} sr$^{{-1}}$")
    ax_col.legend(fontsize=7.5, loc="upper left")
    ax_col.set_ylim(10 ** vmin, 10 ** (vmax + 0.3))
    ax_col.set_xlim(box[2], box[3])
    ax_col.set_xlabel(r"$n_v$ (pixel)")
    ax_col.set_ylabel(r"BRDF (sr$^{-1}$)")
    ax_col.set_title(f"pixel columns; maximum at ($n_h$, $n_v$) = ({n_h[c]}, {n_v[r]})", fontsize=10)
    ax_col.grid(True, which="major", alpha=0.3)

    if title is None:
        title = (
            rf"$\theta_i$ = {np.rad2deg(float(frame.theta_i)):.4g}°, "
            rf"$\phi_{{ref}}$ = {np.rad2deg(float(frame.phi_ref)):.4g}°, "
            rf"$\lambda$ = {float(frame.wavelength) * 1e9:.5g} nm"
        )
    step_note = f"every {int(dh)}-th pixel, " if dh > 1 else ""
    fig.suptitle(f"{title}   ({step_note}{grid.shape[0]} x {grid.shape[1]} grid)", fontsize=11)
    return save_figure_atomic(fig, Path(path), dpi)
