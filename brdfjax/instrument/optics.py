"""The synthetic instrument's deterministic forward operators (NumPy, float64 internally): the beam's
footprint on the array and its convolution, scatter and beam flux images, the lens-cap dark noise.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.fft import fast_len
from .config import (
    Dark,
)
from .radiometry import flux_from_brdf

# --- deterministic forward operators (NumPy, float64 internally) ------------------------------------


def lens_cap_std(dark: Dark, exposure_s: float | np.ndarray) -> np.ndarray:
    """Array std of an ``n_ref_frames`` lens-cap average at exposure ``t`` (s), counts (module docstring)."""
    t = np.asarray(exposure_s, dtype=np.float64)
    return np.sqrt(dark.read_std**2 + dark.sat_std**2 * np.tanh(t / dark.tau_s) ** 2)


def _integrated_gaussian_1d(n: np.ndarray, centre: float, w: float) -> np.ndarray:
    s = math.sqrt(2.0) / w  # exp(-2 x^2 / w^2) = exp(-(x s)^2)
    erf_v = np.vectorize(math.erf)
    return 0.5 * (erf_v((n + 0.5 - centre) * s) - erf_v((n - 0.5 - centre) * s))


def footprint_kernel(w_px: float, *, tail: float = 1e-12, step: int = 1) -> np.ndarray:
    """The beam footprint: pixel-integrated ``exp(-2 r^2 / w^2)`` (Eq 73), odd square array summing to 1.

    Truncated where the Gaussian falls below ``tail`` of its peak
    (``r = w sqrt(-ln(tail) / 2)``).  ``step > 1``: the kernel for a grid of
    every ``step``-th pixel, i.e. the raw-pixel kernel *sampled* every
    ``step`` pixels from its centre and renormalised (a Riemann sum of the
    convolution on the grid).  Integrating the Gaussian over the grid's
    ``step``-wide cells instead (``footprint_kernel(w_px / step)``) adds
    ``step^2 / 12`` pixel^2 of variance and biased fitted widths by -1 % at
    step 4 (experiments/fit_recovery.py).
    """
    if not (isinstance(step, int | np.integer) and step >= 1):
        raise ValueError(f"footprint_kernel: step must be a positive integer, got {step!r}")
    half = int(math.ceil(w_px * math.sqrt(-math.log(tail) / 2.0))) + 1
    half = max(step, half - half % step)  # a multiple of step: the samples are symmetric about the centre
    n = np.arange(-half, half + 1, dtype=np.float64)
    g = _integrated_gaussian_1d(n, 0.0, w_px)[::step]
    k = np.outer(g, g)
    return k / k.sum()


def convolve_footprint(image: np.ndarray, kernel: np.ndarray, *, strip_rows: int = 512) -> np.ndarray:
    """Linear 2-D convolution of ``image`` with a centred odd ``kernel`` (zero outside), float32 out.

    FFT in float64 over strips of ``strip_rows`` output rows (overlap-save), so
    memory stays bounded for the full 3296 x 2472 frame and the absolute
    error stays ~1e-16 of the image maximum (float32 FFTs would lose the
    faint parts of a 5-decade frame).  Non-negative inputs give a
    non-negative output (round-off below zero is clipped).
    """
    image = np.asarray(image)
    kernel = np.asarray(kernel, dtype=np.float64)
    kh, kw = kernel.shape
    if kh % 2 == 0 or kw % 2 == 0:
        raise ValueError(f"convolve_footprint: kernel must have odd sizes, got {kernel.shape}")
    ph, pw = kh // 2, kw // 2
    rows, cols = image.shape
    strip_rows = max(1, min(strip_rows, rows))
    fr = fast_len(strip_rows + kh - 1)
    fc = fast_len(cols + kw - 1)
    kf = np.fft.rfft2(kernel, s=(fr, fc))
    out = np.empty((rows, cols), dtype=np.float32)
    for r0 in range(0, rows, strip_rows):
        r1 = min(rows, r0 + strip_rows)
        a0, a1 = max(0, r0 - ph), min(rows, r1 + ph)
        block = np.zeros((r1 - r0 + kh - 1, cols), dtype=np.float64)
        block[a0 - (r0 - ph) : a0 - (r0 - ph) + (a1 - a0)] = image[a0:a1]
        full = np.fft.irfft2(np.fft.rfft2(block, s=(fr, fc)) * kf, s=(fr, fc))
        out[r0:r1] = full[kh - 1 : kh - 1 + (r1 - r0), pw : pw + cols]
    if image.min() >= 0 and kernel.min() >= 0:
        np.maximum(out, 0.0, out=out)  # FFT round-off (~1e-16 of the maximum) must not make light negative
    return out


def scatter_flux_image(
    brdf: np.ndarray, theta_s: np.ndarray, solid_angle: np.ndarray, incident_flux: float
) -> np.ndarray:
    """Eq 45 inverted (:func:`~brdfjax.instrument.radiometry.flux_from_brdf`) per pixel in float64, as float32."""
    f64 = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
    return flux_from_brdf(f64(brdf), float(incident_flux), f64(theta_s), f64(solid_angle)).astype(np.float32)


def beam_flux_image(shape: tuple[int, int], centre: tuple[float, float], w_px: float, flux: float) -> np.ndarray:
    """A focused beam of total ``flux`` centred at array offsets ``(row, col)``, pixel-integrated Eq 73, float32."""
    rows, cols = shape
    gv = _integrated_gaussian_1d(np.arange(rows, dtype=np.float64), centre[0], w_px)
    gh = _integrated_gaussian_1d(np.arange(cols, dtype=np.float64), centre[1], w_px)
    return (float(flux) * np.outer(gv, gh)).astype(np.float32)


def shift_add(out: np.ndarray, image: np.ndarray, dv: int, dh: int, scale: float) -> None:
    """``out += scale * image`` shifted by ``(dv, dh)`` pixels (zero fill), in place."""
    rows, cols = image.shape
    if abs(dv) >= rows or abs(dh) >= cols:
        return
    src_r = slice(max(0, -dv), rows - max(0, dv))
    dst_r = slice(max(0, dv), rows - max(0, -dv))
    src_c = slice(max(0, -dh), cols - max(0, dh))
    dst_c = slice(max(0, dh), cols - max(0, -dh))
    out[dst_r, dst_c] += np.float32(scale) * image[src_r, src_c]
