"""Noise weights evaluated at the fitted model instead of each pixel's own noisy reading.

A reduction's relative noise ``u_scatter_noise`` is each pixel's noise divided by its own reading ``d``,
so an upward fluctuation gets a smaller sigma, more weight and more chance to pass a ``max_sigma_rel``
cut.  A log-space fit with those weights leans on the high readings, and every faint wing comes out too
bright: with weights ``w(d) = 1 / u(d)^2`` that grow as ``d^kappa``, the expected score of a pixel is
biased by ``(kappa - 1/2) u^2`` in ``log d`` (``kappa = 2`` where dark noise dominates).  On the
synthetic solar-cell config (bin 8) that moves the diffraction band's width ``c`` by +2.5 sigma, the
roughness ``m1`` up and the bar width ``b`` down (experiments/c_asimov.py).

:func:`model_noise_weights` re-evaluates the noise part of a frame's weights at the fitted model:
``u = sigma / m`` with ``m`` the model on the frame's grid (footprint included) and ``sigma = u_0 d`` the
absolute noise the reduction gave the reading (``u_0`` its relative noise), so that neither the weight nor
the ``max_sigma_rel`` cut depends on the pixel's own fluctuation through the division by ``d``.  (The
absolute noise itself still grows with the reading where shot noise dominates, ``kappa`` between -1 and 0:
a bias of at most ``u^2`` there, where ``u`` is small; averaging it over the neighbours instead would
remove that too but mixes pixels of different HDR exposures near saturation, which gave weights 35 % off
around the peaks.)  The reduction's detection cuts (noise-equivalent BRDF, artifact floor, ``min_snr``),
made on each reading, are made on the model too: a cut on the reading keeps the upward fluctuations at
the faint edge of every feature.  The data are multiplied by ``exp(u^2 / 2)`` so that ``E[log d] = log m`` to second
order (``E[log d] = log E[d] - u^2 / 2``: -0.4 sigma on ``c`` there).  The other parts of the sigma
(non-linearity, frame-wide terms, ``sigma_floor``) are kept.  :class:`~brdfjax.fit.job.FitJob` fits
once with the reading's weights, re-evaluates them at that fit's model and refits from its values.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..io.blocks import FrameData
from ._params import Param, as_param

__all__ = ["NOISE_WEIGHTS", "model_noise_weights", "warm_params"]

#: Where the noise part of a frame's weights is evaluated: at the fitted model (a refit) or at the reading.
NOISE_WEIGHTS = ("model", "pixel")


def model_noise_weights(
    block: FrameData,
    data: np.ndarray,
    u_noise: np.ndarray,
    sigma_other: np.ndarray,
    mask: np.ndarray,
    model_image: np.ndarray,
    max_sigma_rel: float | None = None,
    detection: Mapping[str, Any] | None = None,
) -> FrameData:
    """``block`` with the noise part of its weights evaluated at ``model_image`` (module docstring).

    ``data``: the frame's BRDF as read; ``u_noise``: the reduction's relative noise at each reading;
    ``sigma_other``: the rest of the relative sigma (added in quadrature; ``sigma_floor`` included);
    ``mask``: the usable pixels before any ``max_sigma_rel`` cut, which is applied again to the new sigma.
    ``detection``: the reduction's detection cuts, made again on the model (``m`` at least the
    ``noise_equivalent_brdf`` map, the ``artifact_floor`` and ``min_snr`` times the reading's absolute
    noise; ``mask`` then holds the pixels before those cuts); ``None``: ``mask`` as it is.  A pixel where
    the model is not positive keeps the noise of its reading (and its data).
    """
    d = np.asarray(data, np.float64)
    u0 = np.asarray(u_noise, np.float64)
    m = np.asarray(model_image, np.float64)
    mask = np.asarray(mask, bool)
    with np.errstate(invalid="ignore", over="ignore"):
        good = mask & np.isfinite(d) & (d > 0) & np.isfinite(u0) & np.isfinite(m) & (m > 0)
        u = np.where(good, u0 * d / np.where(good, m, 1.0), u0)
        sig = np.sqrt(np.square(np.asarray(sigma_other, np.float64)) + np.square(u))
        brdf = np.where(good, d * np.exp(0.5 * np.square(np.where(good, u, 0.0))), d)
    keep = mask.copy()
    if detection is not None:
        with np.errstate(invalid="ignore"):
            keep &= good
            keep &= m >= np.asarray(detection["noise_equivalent_brdf"], np.float64)
            keep &= m >= float(detection["artifact_floor"])
            keep &= m >= float(detection["min_snr"]) * u0 * d
    if max_sigma_rel is not None:
        with np.errstate(invalid="ignore"):
            keep &= sig <= float(max_sigma_rel)
    return dataclasses.replace(block, brdf=brdf, sigma_rel=sig, mask=keep)


def warm_params(params: Mapping[str, Any], result: Any, block_names: Sequence[str] | None = None) -> dict[str, Any]:
    """``params`` with every free parameter's start moved to its value in ``result`` (strictly inside its bounds).

    Per-frame parameters (``name[block]`` in the result) become per-block lists (``block_names``: the result's
    blocks' names unless given).  The diagnosis's refits and the noise-weight refit both start here.
    """
    if block_names is None:
        block_names = [b.name for b in result.blocks]
    out: dict[str, Any] = {}
    for name, spec in params.items():
        p = as_param(name, spec)
        if not p.free:
            out[name] = p
            continue
        if name in result.parameters:
            value: Any = _inside(result.value(name), p)
        else:
            keys = [f"{name}[{bn}]" for bn in block_names]
            if not all(k in result.parameters for k in keys):
                out[name] = p
                continue
            value = [_inside(result.value(k), p) for k in keys]
        out[name] = dataclasses.replace(p, value=value)
    return out


def _inside(x: float, p: Param) -> float:
    lo = -math.inf if p.lower is None else float(p.lower)
    hi = math.inf if p.upper is None else float(p.upper)
    if math.isfinite(lo) and math.isfinite(hi):
        eps = 1e-6 * (hi - lo)
        return float(min(max(x, lo + eps), hi - eps))
    if math.isfinite(lo) and x <= lo:
        return lo + max(1e-9, 1e-6 * abs(lo))
    if math.isfinite(hi) and x >= hi:
        return hi - max(1e-9, 1e-6 * abs(hi))
    return float(x)
