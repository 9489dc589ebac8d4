"""Noisy rendered frames with known truth, for tests, examples and benchmarks of the fits.

This is not the synthetic instrument (``brdfjax.instrument``): it renders a
model with :func:`brdfjax.core.render` and multiplies each pixel by an independent
log-normal factor ``exp(N(0, noise_rel))``, so that ``log`` of the data is
the truth's log plus Gaussian noise of standard deviation ``noise_rel`` --
exactly the noise model of the log residuals -- and marks pixels below a
detection floor as unusable.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..core.detector import Detector
from ..core.render import Conditions, render
from ..core.terms import AbstractTerm
from ..io.blocks import FrameData

__all__ = ["render_noisy_frames"]


def render_noisy_frames(
    model: AbstractTerm,
    theta_i_deg: Sequence[float],
    *,
    phi_ref_deg: float | Sequence[float] = 0.0,
    wavelength_nm: float = 632.8,
    detector: Detector | None = None,
    step: int = 8,
    roi: tuple[int, int, int, int] | None = None,
    noise_rel: float = 0.03,
    floor: float = 0.1,
    seed: int = 0,
    precision: str = "float64",
) -> list[FrameData]:
    """One :class:`FrameData` per incidence angle: ``render(model) * exp(N(0, noise_rel))``.

    ``floor`` (sr^-1): pixels whose true BRDF is below it are masked (a
    detection limit).  ``sigma_rel`` is ``noise_rel`` everywhere.  Frames are
    named ``ti<angle>``.
    """
    det = Detector.seed() if detector is None else detector
    grid = det.grid(step, roi)
    phis = np.broadcast_to(np.asarray(phi_ref_deg, float), (len(theta_i_deg),))
    rng = np.random.default_rng(seed)
    out = []
    for ti, ph in zip(theta_i_deg, phis):
        frame = Conditions.from_degrees(ti, float(ph), wavelength_nm)
        truth = np.asarray(render(model, frame, det, grid=grid, precision=precision), np.float64)
        noisy = truth * np.exp(noise_rel * rng.standard_normal(truth.shape))
        out.append(
            FrameData(
                brdf=noisy,
                sigma_rel=np.full(truth.shape, noise_rel),
                mask=truth > floor,
                theta_i=float(frame.theta_i),
                phi_ref=float(frame.phi_ref),
                wavelength=float(frame.wavelength),
                detector=det,
                grid=grid,
                name=f"ti{ti:g}" if ph == 0 else f"ti{ti:g}_phi{ph:g}",
            )
        )
    return out
