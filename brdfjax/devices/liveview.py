"""Live view while capturing: the current frame in BRDF units on the detector grid, with theta_s / phi_s contours.

Each exposure read during a sample measurement is turned into a BRDF preview
with the same pixel mapping as the reduction (Eq 45, :func:`brdfjax.instrument.radiometry.brdf_from_flux`:
``f_r = rate 10^OD / (Phi_i cos(theta_s) Omega_d)``, ``rate`` = counts above
the black level per second, ``Phi_i`` the unattenuated incident flux from the
beam signature) and merged with the earlier exposures of the measurement
(per pixel, the longest unsaturated one).  It is drawn by
:func:`brdfjax.plotting.plot_frame` -- the forward model's figure, contours
included -- on a decimated grid (at most ``max_width`` columns).

Output: ``mode = "window"`` shows it in a matplotlib window (needs a
display); ``"png"`` rewrites ``DIR/live.png`` atomically and a small
``DIR/index.html`` that reloads it every few seconds (open it in a browser,
also over ssh port forwarding); ``"auto"`` picks the window when a display
and an interactive backend are available, the PNG otherwise.  Updates are
rate-limited to one per ``min_interval_s`` except the last exposure of a
measurement.  Before the beam signature is known, or for the beam itself,
the preview shows counts/s.
"""

from __future__ import annotations

import html
import math
import os
import time
from pathlib import Path

import matplotlib
import numpy as np

from ..core.render import Conditions, render_geometry
from ..instrument.nd import stack_od
from ..instrument.radiometry import brdf_from_flux
from ..io import atomic_output
from ..plotting import plot_frame
from .interfaces import bench_detector

__all__ = ["LiveView", "display_available"]


def _interactive_pyplot():
    import matplotlib.pyplot as plt  # window mode only: importing pyplot settles the session's (GUI) backend

    return plt


def display_available() -> bool:
    """A display and an interactive matplotlib backend are available."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return False
    return matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "ps", "cairo", "template")


class LiveView:
    """See the module docstring.  ``folder``: where ``live.png`` and ``index.html`` go (png mode)."""

    def __init__(self, folder: str | os.PathLike, *, mode: str = "auto", min_interval_s: float = 1.0,
                 max_width: int = 400, refresh_s: int = 2):
        if mode not in ("auto", "window", "png"):
            raise ValueError(f"LiveView: mode must be auto, window or png, got {mode!r}")
        self.folder = Path(folder)
        self.mode = ("window" if display_available() else "png") if mode == "auto" else mode
        self.min_interval_s = float(min_interval_s)
        self.max_width = int(max_width)
        self.refresh_s = int(refresh_s)
        self.png = self.folder / "live.png"
        self.page = self.folder / "index.html"
        self.updates = 0
        self._last = -math.inf
        self._key = None
        self._best: np.ndarray | None = None
        self._geom = None
        self._fig = None

    # -- public ----------------------------------------------------------------------------------
    def update_exposure(self, m, nd: str, exposure, black: float, full_scale: float, beam_flux: float | None,
                        alignment: dict, bench) -> bool:
        """Merge one exposure of measurement ``m`` and redraw if due; returns whether it redrew."""
        counts = np.asarray(exposure.counts, np.float64)
        key = (m.name, nd)
        if key != self._key:
            self._key, self._best, self._geom = key, None, None
        det, grid, frame = self._geometry(m, alignment, bench, counts.shape)
        sl = (slice(None, None, self._step), slice(None, None, self._step))
        rate = (counts[sl] - black) / exposure.exposure_s
        ok = counts[sl] < 0.9 * full_scale
        if self._best is None:
            self._best = np.where(ok, rate, np.nan)
        else:
            self._best = np.where(ok, rate, self._best)  # exposures come shortest first
        last = abs(exposure.exposure_s - m.exposures_s[-1]) < 1e-12
        now = time.monotonic()
        if not last and now - self._last < self.min_interval_s:
            return False
        self._last = now
        if m.kind == "sample" and beam_flux:
            theta_s, omega = self._geom
            img = brdf_from_flux(self._best * 10 ** stack_od(nd), beam_flux, theta_s, omega)
            unit = "BRDF"
        else:
            img = self._best
            unit = "counts/s"
        img = np.where(np.isfinite(img) & (img > 0), img, np.nan)
        title = (f"LIVE {m.name}: {unit}, exposure {exposure.exposure_s * 1e3:g} ms, ND '{nd or 'none'}', "
                 f"update {self.updates + 1}")
        self._draw(img, grid, det, frame, title)
        return True

    def close(self) -> None:
        if self._fig is not None:
            plt = _interactive_pyplot()
            plt.close(self._fig)
            self._fig = None

    # -- internals -------------------------------------------------------------------------------
    def _geometry(self, m, alignment: dict, bench, shape):
        n_v, n_h = shape
        self._step = max(1, int(math.ceil(n_h / self.max_width)))
        theta_c = m.theta_c if m.kind == "sample" else 0.0
        det = bench_detector(bench, alignment, shape, np.asarray(theta_c, dtype=np.float64))
        grid = det.grid(self._step)
        f64 = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
        frame = Conditions(f64(m.theta_i), f64(m.phi_ref), f64(bench.wavelength))
        if self._geom is None:
            g = render_geometry(frame, det, grid=grid, precision="float32")
            self._geom = (np.asarray(g["theta_s"], np.float64), np.asarray(g["omega"], np.float64))
        return det, grid, frame

    def _draw(self, img, grid, det, frame, title: str) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        if np.all(np.isnan(img)):
            img = np.full(img.shape, 1e-12)
        plot_frame(img, grid, det, frame, self.png, title=title, dpi=80)
        self.updates += 1
        with atomic_output(self.page) as tmp:
            tmp.write_text(
                "<!doctype html><html><head><meta charset='utf-8'>"
                f"<meta http-equiv='refresh' content='{self.refresh_s}'><title>brdfjax live view</title></head>"
                f"<body style='background:#111;color:#ddd;font-family:sans-serif'><p>{html.escape(title)} "
                f"({time.strftime('%H:%M:%S')})</p><img src='live.png?u={self.updates}' style='max-width:100%'>"
                "</body></html>",
                encoding="utf-8",
            )
        if self.mode == "window":
            plt = _interactive_pyplot()
            if self._fig is None:
                plt.ion()
                self._fig = plt.figure("brdfjax live view", figsize=(11, 5))
            self._fig.clf()
            ax = self._fig.add_axes((0, 0, 1, 1))
            ax.imshow(plt.imread(self.png))
            ax.set_axis_off()
            self._fig.canvas.draw_idle()
            plt.pause(0.001)
