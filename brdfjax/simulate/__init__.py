"""The simulate pipeline: render every frame of a simulate config to OpenEXR + PNG + ``summary.json``.

:func:`run_simulate` is what ``brdfjax simulate`` runs; :func:`simulate_frame`
renders one frame into a :class:`FrameResult` (NumPy arrays of the BRDF, each
term and the pixel geometry), as ``experiments/reproduce_seed.py`` uses it.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..core.render import render_frame
from ..io import frame_attrs, write_frame_exr, write_json_atomic
from ..plotting import plot_frame, term_labels

__all__ = ["FrameResult", "run_simulate", "simulate_frame"]


@dataclass(frozen=True)
class FrameResult:
    """One rendered frame in memory: ``(rows, cols)`` NumPy arrays of the grid and timings."""

    stem: str
    frame: Any  # brdfjax.Conditions
    grid: Any  # brdfjax.PixelGrid
    brdf: np.ndarray  # sr^-1
    terms: dict[str, np.ndarray]  # sr^-1, each term of the model
    geometry: dict[str, np.ndarray]  # theta_s, phi_s (rad), omega (sr)
    render_s: float
    files: dict[str, str] = field(default_factory=dict)
    write_s: float = 0.0  # wall time from the files' start to the last one written (they are written in parallel)
    wall_s: float = 0.0  # wall time from the render's start to the frame's last file
    file_s: dict[str, float] = field(default_factory=dict)  # each file's own writing time

    def argmax(self, image: np.ndarray | None = None) -> tuple[int, int]:
        """``(n_h, n_v)`` pixel indices of the maximum of ``image`` (default: the BRDF)."""
        a = self.brdf if image is None else image
        r, c = np.unravel_index(int(np.nanargmax(a)), a.shape)
        return int(self.grid.n_h[c]), int(self.grid.n_v[r])

    def at(self, image: np.ndarray, n_h: int, n_v: int) -> float:
        """Value of ``image`` at pixel ``(n_h, n_v)`` (which must be on the grid)."""
        c = int(np.flatnonzero(self.grid.n_h == n_h)[0])
        r = int(np.flatnonzero(self.grid.n_v == n_v)[0])
        return float(image[r, c])


def simulate_frame(model, frame, detector, grid, precision: str = "float32", stem: str = "frame") -> FrameResult:
    """Render ``model`` and the pixel geometry on ``grid``; returns NumPy arrays (blocks until done).

    One compiled program (:func:`brdfjax.core.render.render_frame`) gives the BRDF
    (the sum of the per-term images, in the model's order), each term and the
    pixel geometry.
    """
    t0 = time.perf_counter()
    out = render_frame(model, frame, detector, grid=grid, precision=precision)
    terms = {k: np.asarray(v) for k, v in out["terms"].items()}
    geometry = {k: np.asarray(out[k]) for k in ("theta_s", "phi_s", "omega")}
    return FrameResult(stem, frame, grid, np.asarray(out["brdf"]), terms, geometry, time.perf_counter() - t0)


def _frame_attrs(cfg, detector, frame, stem: str) -> dict[str, Any]:
    roi = cfg.roi if cfg.roi is not None else detector.index_range
    return {
        **frame_attrs(detector, frame, step=cfg.grid.step, roi=roi),
        "model": cfg.describe_model(),
        "precision": cfg.precision,
        "frame": stem,
        "brdfjax_version": __version__,
    }


def _frame_summary(cfg, res: FrameResult, fcfg) -> dict[str, Any]:
    def peak(image: np.ndarray) -> dict[str, Any]:
        n_h, n_v = res.argmax(image)
        return {"value": float(np.nanmax(image)), "pixel": [n_h, n_v]}

    n_h, n_v = res.argmax()
    th = res.at(res.geometry["theta_s"], n_h, n_v)
    ph = res.at(res.geometry["phi_s"], n_h, n_v)
    return {
        "name": res.stem,
        "theta_i_deg": fcfg.theta_i_deg,
        "phi_ref_deg": fcfg.phi_ref_deg,
        "wavelength_nm": fcfg.wavelength_nm,
        "max_brdf": float(np.nanmax(res.brdf)),
        "max_pixel": [n_h, n_v],
        "max_theta_s_deg": float(np.rad2deg(th)),
        "max_phi_s_deg": float(np.rad2deg(ph)),
        "term_max": {k: peak(v) for k, v in res.terms.items()},
        "grid_shape": list(res.brdf.shape),
        "step": cfg.grid.step,
        "roi": cfg.roi,
        "precision": cfg.precision,
        "config": cfg.source,
        "render_s": round(res.render_s, 4),
        "write_s": round(res.write_s, 4),
        "file_s": {k: round(v, 4) for k, v in res.file_s.items()},
        "wall_s": round(res.wall_s if res.wall_s else res.render_s + res.write_s, 4),
        "files": res.files,
    }


def run_simulate(
    cfg,
    out: str | os.PathLike,
    *,
    plot: bool = True,
    console: Any = None,
    on_frame: Callable[[FrameResult], None] | None = None,
) -> dict[str, Any]:
    """Render every frame of a :class:`~brdfjax.config.SimulateConfig` into ``out``.

    Writes ``<stem>.exr``, ``<stem>.png`` (unless ``plot=False``) and
    ``summary.json``; returns the summary.  ``on_frame`` receives each
    :class:`FrameResult` (full arrays) before it is dropped.  ``console`` is a
    ``rich`` console for one status line per frame (``None``: silent).
    A config with ``precision = "float64"`` needs ``jax_enable_x64`` on; the
    CLI turns it on, library callers decide for themselves.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    detector = cfg.build_detector()
    grid = cfg.build_grid(detector)
    model = cfg.build_model()
    frames = cfg.build_frames()

    labels = term_labels(model)
    t_start = time.perf_counter()
    entries = []

    def write_exr(res: FrameResult) -> tuple[str, float, float]:
        t0 = time.perf_counter()
        path = write_frame_exr(
            out / f"{res.stem}.exr",
            res.brdf,
            res.geometry["theta_s"],
            res.geometry["phi_s"],
            res.geometry["omega"],
            _frame_attrs(cfg, detector, res.frame, res.stem),
        )
        return path.name, t0, time.perf_counter()

    def write_png(res: FrameResult) -> tuple[str, float, float]:
        t0 = time.perf_counter()
        png = plot_frame(res.brdf, grid, detector, res.frame, out / f"{res.stem}.png",
                         terms=res.terms if len(res.terms) > 1 else None, labels=labels)
        return png.name, t0, time.perf_counter()

    def finish(res: FrameResult, futures: dict[str, Any], fcfg, t_frame: float, t_submit: float) -> None:
        # Wait for this frame's files (an exception in a writer is raised here), then report it.  The EXR and
        # PNG writers run in parallel threads (and beside the next frame's render): the frame's times are wall
        # spans (render start -> last file, first file start -> last file), never sums of overlapping spans.
        done = {kind: fut.result() for kind, fut in futures.items()}
        files = {kind: name for kind, (name, _, _) in done.items()}
        t_end = max(end for _, _, end in done.values())
        res = dataclasses.replace(res, files=files, write_s=t_end - t_submit, wall_s=t_end - t_frame,
                                  file_s={kind: end - start for kind, (_, start, end) in done.items()})
        entry = _frame_summary(cfg, res, fcfg)
        entries.append(entry)
        if console is not None:
            n_h, n_v = entry["max_pixel"]
            console.print(
                f"[green]done[/] {res.stem}: {res.brdf.shape[0]} x {res.brdf.shape[1]} px, "
                f"max {entry['max_brdf']:.4g} sr^-1 at (n_h, n_v) = ({n_h}, {n_v}), "
                f"render {res.render_s:.2f} s, write {res.write_s:.2f} s -> {', '.join(files.values())}",
                highlight=False,
            )
        if on_frame is not None:
            on_frame(res)

    # The files of a frame are written by background threads while the next frame renders (JAX,
    # OpenEXR's compression and most of matplotlib's drawing release the GIL); at most two frames
    # are held in memory.
    pending: deque = deque()
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="brdfjax-write") as pool:
        try:
            for (stem, frame), fcfg in zip(frames, cfg.frames, strict=True):
                t_frame = time.perf_counter()
                status = console.status(f"rendering {stem} ({grid.shape[0]} x {grid.shape[1]} pixels)") if console else None
                if status:
                    status.start()
                try:
                    res = simulate_frame(model, frame, detector, grid, cfg.precision, stem)
                finally:
                    if status:
                        status.stop()
                t_submit = time.perf_counter()
                futures = {"exr": pool.submit(write_exr, res)}
                if plot:
                    futures["png"] = pool.submit(write_png, res)
                pending.append((res, futures, fcfg, t_frame, t_submit))
                del res
                while len(pending) > 1:
                    finish(*pending.popleft())
            while pending:
                finish(*pending.popleft())
        except BaseException:
            for _, futures, *_ in pending:
                for fut in futures.values():
                    fut.cancel()
            raise

    summary = {
        "brdfjax_version": __version__,
        "config": cfg.source,
        "precision": cfg.precision,
        "step": cfg.grid.step,
        "roi": cfg.roi,
        "grid_shape": list(grid.shape),
        "detector": {**cfg.detector.resolved(), "theta_c_deg": cfg.detector.theta_c_deg},
        "model": cfg.describe_model(),
        "wall_s": round(time.perf_counter() - t_start, 4),
        "frames": entries,
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
