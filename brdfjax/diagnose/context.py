"""The base fit as the effects see it: :class:`Context` and the measures of a fit.

:func:`build_context` turns a fit (:class:`~brdfjax.fit.FitResult`) into a
:class:`Context`: the fitted model, the parameter spec warm-started at the
optimum (:func:`warm_params`), per block the normalised residual
``r = (ln d - ln f) / sigma_ln`` (:func:`residual_maps`), the fitted model's
values and the scatter geometry with the specular-relative coordinates
``sx, sy``.  :func:`gap_measures` is the global gap of a fit (chi^2, reduced
chi^2, rms of log10, BIC).  The engine and every effect build on this module;
it imports neither.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import numpy as np

from ..core.geometry import Directions
from ..core.render import Conditions, render, render_geometry
from ..core.terms import Model
from ..fit import FitResult, FrameData, TableData
from ..fit.internal import warm_params
from ..instrument.synthetic import convolve_footprint
from .zones import specular_coordinates

__all__ = ["Context", "build_context", "warm_params", "residual_maps", "gap_measures", "precision_name", "LN10"]

LN10 = math.log(10.0)


def precision_name() -> str:
    """The precision of the fits and renders (``"float64"`` when 64-bit JAX is on)."""
    return "float64" if jax.config.jax_enable_x64 else "float32"


# --- the context ---------------------------------------------------------------------------


@dataclass
class Context:
    """The base fit as the effects see it (built by :func:`build_context`)."""

    model: Model
    params: dict
    result: FitResult
    blocks: list
    residuals: list
    model_values: list
    geometry: list
    fit_kwargs: dict = field(default_factory=dict)  # the options of the diagnosis' fits (loss, floor, ...)

    def block_model(self, k: int) -> Model:
        return self.result.models[k] if self.result.models else self.model

    def block_frame(self, k: int) -> Conditions:
        b = self.blocks[k]
        if self.result.frames and self.result.frames[k] is not None:
            return self.result.frames[k]
        return Conditions(b.theta_i, b.phi_ref, b.wavelength)

    def frames(self) -> list[int]:
        return [k for k, b in enumerate(self.blocks) if isinstance(b, FrameData)]

    def sigma(self, k: int) -> np.ndarray:
        """The sigma of ln BRDF the residuals are in units of: the data's, or the fit's estimate for a table
        without uncertainties."""
        b = self.blocks[k]
        if isinstance(b, TableData) and b.sigma_rel is None:
            return np.full(np.shape(b.brdf), float(self.result.noise.get("sigma_ln", 1.0)))
        return np.broadcast_to(np.asarray(b.sigma_rel, float), np.shape(b.brdf))



# --- measures ------------------------------------------------------------------------------



def residual_maps(result: FitResult, blocks: Sequence[FrameData | TableData]) -> list[np.ndarray]:
    """Per block ``r = (ln d - ln f) / sigma_ln`` on the block's grid (frames) or rows (tables); NaN where unused."""
    out = []
    for b, r in zip(blocks, result.residuals):
        u = b.usable()
        m = np.full(u.shape, np.nan)
        m[u] = -np.asarray(r, float)  # the fit's residuals are (ln f - ln d) / sigma
        out.append(m)
    return out


def gap_measures(result: FitResult) -> dict[str, float]:
    """The global gap of a fit: chi2 (-2 ln L), dof, chi2_reduced, rms_log10 (rms of log10 f - log10 d), BIC,
    and whether the noise was estimated (``sigma_estimated``, ``sigma_ln``)."""
    n = sum(b.n_points for b in result.blocks)
    ms = sum(b.n_points * b.log_rms**2 for b in result.blocks) / max(n, 1)
    k = len(result.free_names)
    # With estimated noise chi2 is ~N by construction: the misfit of the information criteria (and the
    # "chi2" whose differences the diagnosis reports) is -2 ln L of the profile likelihood instead.
    return {
        "chi2": float(result.m2ll),
        "sigma_estimated": bool(result.sigma_estimated),
        "sigma_ln": float(result.noise["sigma_ln"]) if result.sigma_estimated else None,
        "n_points": int(result.n_points),
        "n_free": k,
        "dof": int(result.dof),
        "chi2_reduced": float(result.chi2_reduced),
        "rms_log10": float(math.sqrt(ms) / LN10),
        "bic": float(result.m2ll + k * math.log(max(result.n_points, 2))),
    }


# --- context of a fit ----------------------------------------------------------------------



def _block_geometry(b: FrameData | TableData, frame: Any) -> dict[str, np.ndarray]:
    if isinstance(b, FrameData):
        g = render_geometry(frame, b.arm_detector(), grid=b.grid, precision=precision_name())
        ts, ps = np.asarray(g["theta_s"], float), np.asarray(g["phi_s"], float)
        sx, sy = specular_coordinates(ts, ps, float(frame.theta_i), 0.0)
        return {"theta_s": ts, "phi_s": ps, "sx": sx, "sy": sy}
    ts, ps = np.asarray(b.theta_s, float), np.asarray(b.phi_s, float)
    sx, sy = specular_coordinates(ts, ps, np.asarray(b.theta_i, float), np.asarray(b.phi_i, float))
    return {"theta_s": ts, "phi_s": ps, "sx": sx, "sy": sy, "theta_i": np.asarray(b.theta_i, float)}


def _block_model(b: FrameData | TableData, model: Model, frame: Any, use_footprint: bool = True,
                 residual: Any = None) -> np.ndarray:
    """The fitted model on a block as the fit compared it with the data.

    A frame's model is convolved with its footprint when the fit did (``use_footprint``); at the usable pixels
    the values are those the fit's own residuals imply (``ln f = ln d + r sigma``), so that per-frame terms and
    nuisance scales the fit applied are in them too: a plot or a start value built on these values sees the
    model the fit saw.  (Measured on the shipped withheld-diffraction example: the bare render missed the
    footprint-convolved model by chi^2 8.6e5 against 105 in the peak's column.)
    """
    if isinstance(b, FrameData):
        img = np.asarray(render(model, frame, b.arm_detector(), grid=b.grid, precision=precision_name()), float)
        if b.footprint is not None and use_footprint:
            k = np.asarray(b.footprint, float)
            img = np.asarray(convolve_footprint(img, k / k.sum()), float)
        if residual is not None:
            u = np.asarray(b.usable(), bool)
            r = np.asarray(residual, float)
            if r.shape == (int(u.sum()),) and np.all(np.isfinite(r)):
                sig = np.broadcast_to(np.asarray(b.sigma_rel, float), img.shape)[u]
                img = img.copy()
                img[u] = np.asarray(b.brdf, float)[u] * np.exp(r * sig)
        return img
    dirs = Directions.from_angles(*(np.asarray(getattr(b, f), float) for f in ("theta_i", "phi_i", "theta_s", "phi_s")))
    wl = np.broadcast_to(np.asarray(b.wavelength, float), np.shape(b.brdf))
    return np.asarray(model(dirs, wl), float)


def build_context(model_spec: Model, params: Mapping[str, Any], result: FitResult, blocks: Sequence[Any],
                  fit_kwargs: Mapping[str, Any] | None = None) -> Context:
    """The :class:`Context` of a fit (the fitted model, residual maps, model values, geometry)."""
    fitted = result.models[0] if result.models else model_spec
    geometry = [_block_geometry(b, f) for b, f in zip(blocks, result.frames)]
    use_fp = bool(dict(fit_kwargs or {}).get("use_footprint", True))
    res = list(result.residuals) if result.residuals else [None] * len(blocks)
    values = [_block_model(b, m, f, use_fp, r) for b, m, f, r in zip(blocks, result.models, result.frames, res)]
    return Context(
        model=fitted,
        params=warm_params(params, result),
        result=result,
        blocks=list(blocks),
        residuals=residual_maps(result, blocks),
        model_values=values,
        geometry=geometry,
        fit_kwargs=dict(fit_kwargs or {}),
    )
