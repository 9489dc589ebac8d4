"""Reduction of raw exposure stacks to calibrated BRDF frames with per-pixel uncertainty (seed §3.3, §3.6-3.8, §4.2).

Pipeline for a measurement set (:func:`reduce_measurement_set`):

1. **Background subtraction**, exposure by exposure: ``d_k = counts_k(measurement)
   - counts_k(background)`` (same exposure times; the black level, dark signal
   and ambient light cancel).  The seed stitches first and subtracts the
   stitched background (§3.8); subtracting per exposure keeps the black level
   of a short exposure from being scaled by ``t_ref / t_k`` along with the
   signal.
2. **HDR stitching** to scaled digital counts (sDC: counts referred to the
   stack's longest exposure ``t_ref``), with one of two merges:

   - ``"replacement"`` -- the seed's scheme (§3.6): start from the longest
     exposure; replace each saturated pixel by the next shorter unsaturated
     exposure scaled by ``t_ref / t_k``; repeat.
   - ``"weighted"`` -- inverse-variance weighting of every unsaturated
     exposure, ``sum_k w_k d_k t_ref / t_k / sum_k w_k`` with ``w_k = 1 /
     var_k``, ``var_k`` the *full* variance of the scaled reading: its noise
     plus the square of its non-linearity error.  The noise comes from a
     model evaluated at a pilot estimate (not from each pixel's own noisy
     counts, which would bias the merge low): shot noise ``max(rate t_k, 0)
     / gain`` per frame plus the dark/ambient noise of the background stack
     at that exposure (its ``counts_std`` if present, else its robust
     spatial spread; never below the rounding to integer counts), for both
     the measurement and its background.  The non-linearity error is the
     camera's calibrated response curve (:class:`NonlinearityCurve`:
     relative error vs count level as a fraction of full scale; the
     manifest's ``[calibration] nonlinearity_curve``, by default the
     synthetic instrument's documented curve) at the reading's expected
     count level, times the reading.  Optionally the readings are first
     corrected by that curve (``correct_nonlinearity``), which removes the
     seams of the replacement scheme; the weights then carry only the
     curve's residual uncertainty (see :func:`stitch_weighted`).

   A pixel is saturated in an exposure when its raw counts reach
   ``saturation_fraction * full_scale`` (the mean of averaged frames
   approaches full scale before every frame clips).
3. **Incident flux** (§3.8): the stitched, background-subtracted beam
   signature summed over the whole array, ``Phi_b`` (sDC), adjusted for the
   ND filters by Eq 87, ``Phi_i = Phi_b 10^(OD_b - OD_m)``; the scatter flux
   is multiplied by the exposure ratio ``t_ref(beam) / t_ref(measurement)``
   (§3.8; unity when both stacks end at the same exposure).
4. **BRDF** by Eq 45, ``f_r = Phi_s / (Phi_i cos(theta_s) Omega_d)``, with
   each pixel's ``theta_s`` and ``Omega_d`` from the core pixel mapping of
   the measurement's geometry attributes, misalignment (roll, yaw, pitch,
   m_h, m_v) included.
5. **Masks** (``mask`` = 1 usable, 0 excluded; ``flags`` says why, bits
   OR-ed): 1 saturated in every exposure; 2 below the noise-equivalent BRDF;
   4 below the artifact floor (the frame's peak ``10^-4.8``: stray-light
   sub-peaks sit "more than 4.8 orders of magnitude below the main peak",
   seed §4.6); 8 not finite; 16 signal-to-noise ratio under ``min_snr`` (3).
   The seed's floor is the *mean* background (48 sDC) while the noise of a
   background-subtracted pixel is about 33 sDC, so about 7 % of pixels with
   no signal at all pass it; the SNR test removes them.
6. **§4.2 figures**, computed from the inputs: the noise floor
   ``Phi_s,low`` = mean (and std) of the measurement's background stitched
   by the replacement scheme, black level included (seed: 48.05 sDC, std
   23.11); ``Phi_s,high = full_scale t_ref / t_min`` (1.6383e7 sDC); the
   noise-equivalent and maximum measurable BRDF (Eq 45 with Eq 87 at
   ``cos theta_s = 1`` and the centre pixel's solid angle) and the dynamic
   range ``log10(Phi_s,high / Phi_s,low)`` decades.  Per pixel, the
   noise-equivalent BRDF uses the pixel's own ``cos theta_s`` and ``Omega_d``.
7. **Uncertainty** (Chapter IV) per pixel from
   :func:`brdfjax.instrument.uncertainty.brdf_uncertainty`, with the
   stitched noise (``sqrt(var) / Phi_s``) passed as its ``scatter_noise``
   contribution; ``sigma_rel`` is the quadrature total.

Outputs: one BRDF frame file per sample (the frame format of
:mod:`brdfjax.io.exr`: ``brdf``, ``theta_s``, ``phi_s``, ``omega``) plus the
channels ``sigma_rel`` (total relative standard uncertainty), ``mask``,
``flags``, ``noise_equivalent_brdf`` (sr^-1, per pixel) and the uncertainty
contributions ``u_scatter_flux`` (with its parts ``u_scatter_nonlinearity``
and ``u_scatter_noise``), ``u_incident_flux``, ``u_scatter_angle`` and
``u_solid_angle`` (relative, dimensionless; ``detailed_uncertainty=True``
adds every sub-contribution), with the §4.2 figures, the contributions that
are equal on every pixel (``u_nd``, ``u_temporal``, ...), the merge's
options (``merge``, ``nonlinearity_curve`` as ``"x:error,..."``,
``nonlinearity_corrected``, ``taper_start``) and the inputs' names in header
attributes.  Files are written atomically; inputs are only read.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .. import __version__
from ..core.detector import Detector, PixelGrid
from ..core.render import render_geometry
from ..io import ExrFrame, atomic_output, frame_attrs, read_frame_exr, write_frame_exr
from ..io.raw import (
    Manifest,
    RawAttrs,
    RawFormatError,
    RawStack,
    read_manifest,
    read_raw_exr,
)
from ..plotting import agg_pyplot
from ..runtime.errors import InputError
from .nd import SEED_ND_TOLERANCES
from .radiometry import brdf_from_flux, incident_flux
from .uncertainty import (
    SEED_ARM_ANGLE_UNCERTAINTY,
    SEED_DISTANCE_UNCERTAINTY,
    SEED_PITCH_UNCERTAINTY,
    SEED_SCATTER_NONLINEARITY,
    brdf_uncertainty,
)

__all__ = [
    "MERGES",
    "NonlinearityCurve",
    "SYNTHETIC_NONLINEARITY_CURVE",
    "SEED_CURVE_RESIDUAL",
    "FLAG_SATURATED",
    "FLAG_BELOW_NOISE",
    "FLAG_BELOW_ARTIFACT_FLOOR",
    "FLAG_NOT_FINITE",
    "FLAG_LOW_SNR",
    "ReductionError",
    "Stitched",
    "BeamSignature",
    "beam_signature",
    "stitch",
    "stitch_replacement",
    "stitch_weighted",
    "stitch_raw",
    "incident_flux",
    "noise_equivalent_brdf",
    "max_measurable_brdf",
    "scatter_flux_high",
    "dynamic_range_decades",
    "SEED_CENTRE_SOLID_ANGLE",
    "reduce_measurement",
    "reduce_measurement_set",
    "write_reduced_frame",
    "read_reduced_frame",
    "plot_merge_comparison",
]

MERGES = ("weighted", "replacement")
#: Uncertainty contributions written as ``u_<name>`` channels (when they vary across the frame): the four
#: terms of Eq 71 and the two parts of the scatter-flux term.
PER_PIXEL_TERMS = (
    "scatter_flux", "scatter_nonlinearity", "scatter_noise", "incident_flux", "scatter_angle", "solid_angle",
)
FLAG_SATURATED = 1
FLAG_BELOW_NOISE = 2
FLAG_BELOW_ARTIFACT_FLOOR = 4
FLAG_NOT_FINITE = 8
FLAG_LOW_SNR = 16

#: Centre-pixel solid angle of the seed camera, sr (Eq 86, Table 3), used by the seed's §4.2 figures.
SEED_CENTRE_SOLID_ANGLE = 2.864e-10
#: Electrons per count of the seed's camera: the published full well (20000 e-) over the 14-bit range.
SEED_GAIN = 20000.0 / 16383.0


class ReductionError(InputError):
    """Inputs that cannot be reduced together; the message names the files and the problem."""


# --- non-linearity calibration --------------------------------------------------------------------


@dataclass(frozen=True)
class NonlinearityCurve:
    """The camera's calibrated response curve: relative error of a reading vs its count level (seed §4.2, Eq 91).

    ``points`` are ``(fraction, error)`` pairs: ``fraction`` the signal
    (counts above the black level) as a fraction of full scale, strictly
    increasing in [0, 1]; ``error`` the relative deviation of a reading at
    that level from the linear response, ``reading / linear - 1`` (the
    seed's Eq 91 on the array-wide pixel averages, its "baseline method";
    per-pixel gain differences are the separate ``scatter_nonlinearity``
    dNL_s of Eq 92).  Linear interpolation between the points, constant
    beyond the ends.  In a manifest: ``[calibration] nonlinearity_curve =
    [[0.0, -0.0172], [1.0, 0.0172]]`` (:mod:`brdfjax.io.raw`).
    """

    points: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        pts = tuple((float(x), float(e)) for x, e in self.points)
        if not pts:
            raise ValueError("NonlinearityCurve needs at least one (fraction, error) point")
        xs = [x for x, _ in pts]
        if not all(math.isfinite(x) and 0.0 <= x <= 1.0 for x in xs) or any(b <= a for a, b in zip(xs, xs[1:])):
            raise ValueError(f"NonlinearityCurve fractions must strictly increase within [0, 1], got {xs}")
        if not all(math.isfinite(e) and -0.5 < e < 0.5 for _, e in pts):
            raise ValueError(f"NonlinearityCurve errors must lie in (-0.5, 0.5), got {[e for _, e in pts]}")
        object.__setattr__(self, "points", pts)

    @classmethod
    def linear(cls, common_max: float) -> "NonlinearityCurve":
        """``error = common_max (2 x - 1)``: the synthetic instrument's common term (``NonLinearity.common_max``)."""
        return cls(((0.0, -float(common_max)), (1.0, float(common_max))))

    def __call__(self, fraction: np.ndarray | float) -> np.ndarray:
        """Relative error of a reading whose signal is ``fraction`` of full scale."""
        xs, es = zip(*self.points)
        return np.interp(np.asarray(fraction, dtype=np.float64), xs, es)

    def linearise(self, signal: np.ndarray, full_scale: float, iterations: int = 3) -> np.ndarray:
        """Invert the response: the linear signal ``s`` whose reading is ``signal`` (counts above black level).

        Solves ``s (1 + error(s / full_scale)) = signal`` by fixed-point
        iteration (each step shrinks the residual by ``|d error / dx| x``,
        under 4 % for the seed's curve).
        """
        signal = np.asarray(signal, dtype=np.float64)
        s = signal
        for _ in range(max(1, int(iterations))):
            s = signal / (1.0 + self(np.clip(s / full_scale, 0.0, 1.0)))
        return s

    def describe(self) -> str:
        """The points as ``"x:e,x:e"`` (a header attribute of reduced frames)."""
        return ",".join(f"{x:g}:{e:g}" for x, e in self.points)


#: The synthetic instrument's documented common non-linearity (:class:`brdfjax.instrument.synthetic.NonLinearity`:
#: ``error = 1.72 % (2 x - 1)``; the seed's baseline method over the full range reads 1.72 % at most, §4.2).
SYNTHETIC_NONLINEARITY_CURVE = NonlinearityCurve.linear(0.0172)
#: Residual non-linearity after correcting by the array-average curve, as a fraction of the curve: the seed's
#: per-pixel curves deviate from their own linear fits by 1.74 +- 0.14 % at most (§4.2, second method), so the
#: shape of one pixel's curve differs from the array's by about 0.14 / 1.74 = 8 %.
SEED_CURVE_RESIDUAL = 0.14 / 1.74


def _curve(curve: Any) -> NonlinearityCurve | None:
    if curve is None or isinstance(curve, NonlinearityCurve):
        return curve
    return NonlinearityCurve(tuple(tuple(p) for p in curve))


# --- stitching ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stitched:
    """A stitched exposure stack: ``flux`` in sDC (counts referred to ``t_ref``), its variance, bookkeeping.

    ``saturated`` is True where every exposure is saturated (``flux`` there is
    the shortest exposure's scaled value, a lower bound); ``source`` is the
    index of the exposure used (replacement) or the number of exposures
    merged (weighted).
    """

    flux: np.ndarray
    variance: np.ndarray
    saturated: np.ndarray
    source: np.ndarray
    t_ref: float
    merge: str


def _robust_std(a: np.ndarray) -> float:
    sample = a.reshape(-1)[:: max(1, a.size // 1_000_000)]
    med = np.median(sample)
    return float(1.4826 * np.median(np.abs(sample - med)))


def _frame_noise_var(stack: RawStack, k: int) -> float:
    """Per-frame variance (counts^2) of the dark/ambient noise of exposure ``k`` of a background stack."""
    e = stack.exposures[k]
    if e.counts_std is not None:
        return float(np.median(e.counts_std)) ** 2
    return _robust_std(e.counts) ** 2 * e.n_frames


def _check_pair(stack: RawStack, background: RawStack) -> None:
    name = f"{stack.path or 'measurement'} and its background {background.path or ''}"
    if background.shape != stack.shape:
        raise ReductionError(f"{name}: array shapes differ ({stack.shape} vs {background.shape})")
    t_s, t_b = stack.exposure_times, background.exposure_times
    if t_s.shape != t_b.shape or not np.allclose(t_s, t_b, rtol=1e-9, atol=0):
        raise ReductionError(
            f"{name}: exposure times differ ({t_s.tolist()} s vs {t_b.tolist()} s); "
            "take the background with the same exposures"
        )


def _differences(stack: RawStack, background: RawStack, saturation_fraction: float, order=None,
                 linearise: NonlinearityCurve | None = None):
    """Yield ``(k, t_k, d_k, saturated_k)`` per exposure (in ``order``), float64 differences in counts.

    One exposure at a time, so that a full frame never holds more than one difference array.
    ``linearise``: correct both readings by the response curve first (saturation is still judged on
    the raw counts).
    """
    fs = stack.attrs.full_scale
    level = saturation_fraction * fs
    for k in range(len(stack.exposures)) if order is None else order:
        e = stack.exposures[k]
        b = background.exposures[k].counts
        sat = (e.counts >= level) | (b >= level)
        if linearise is None:
            d = e.counts.astype(np.float64) - b
        else:
            d = (linearise.linearise(e.counts.astype(np.float64) - stack.attrs.black_level, fs)
                 - linearise.linearise(b.astype(np.float64) - background.attrs.black_level, fs))
        yield k, e.exposure_s, d, sat


def stitch_replacement(
    stack: RawStack, background: RawStack, *, saturation_fraction: float = 0.98,
    gain_e_per_count: float = SEED_GAIN,
) -> Stitched:
    """The seed's replacement scheme (§3.6) on background-subtracted exposures; sDC referred to the longest."""
    _check_pair(stack, background)
    t_ref = float(stack.exposure_times[-1])
    shape = stack.shape
    flux = np.zeros(shape, np.float64)
    source = np.full(shape, -1, np.int8)
    todo = np.ones(shape, bool)
    for k, t, d, sat in _differences(stack, background, saturation_fraction, order=range(len(stack.exposures))[::-1]):
        take = todo & ~sat
        flux[take] = d[take] * (t_ref / t)
        source[take] = k
        todo &= ~take
        if k == 0:
            flux[todo] = d[todo] * (t_ref / t)  # saturated in every exposure: a lower bound
            source[todo] = 0
        del d
    var = _model_variance_for_source(stack, background, flux / t_ref, source, gain_e_per_count)
    return Stitched(flux.astype(np.float32), var.astype(np.float32), todo, source, t_ref, "replacement")


def _noise_terms(stack: RawStack, background: RawStack) -> list[float]:
    """Per exposure: dark/ambient variance of the mean difference (counts^2), measurement and background.

    Never below the rounding of both to integer counts (1/12 count^2 each), so that a noise-free
    background cannot give infinite weights.
    """
    out = []
    for k, e in enumerate(stack.exposures):
        v = _frame_noise_var(background, k)
        out.append(max(v / e.n_frames + v / background.exposures[k].n_frames, 2.0 / 12.0))
    return out


def _model_variance_for_source(stack, background, rate, source, gain) -> np.ndarray:
    noise = _noise_terms(stack, background)
    t_ref = float(stack.exposure_times[-1])
    var = np.zeros(stack.shape, np.float64)
    for k, e in enumerate(stack.exposures):
        sel = source == k
        if not np.any(sel):
            continue
        t = e.exposure_s
        shot = np.maximum(rate[sel] * t, 0.0) / (gain * e.n_frames)
        var[sel] = (shot + noise[k]) * (t_ref / t) ** 2
    return var


def stitch_weighted(
    stack: RawStack,
    background: RawStack,
    *,
    saturation_fraction: float = 0.98,
    gain_e_per_count: float = SEED_GAIN,
    nonlinearity_curve: NonlinearityCurve | Sequence[tuple[float, float]] | None = SYNTHETIC_NONLINEARITY_CURVE,
    correct_nonlinearity: bool = False,
    curve_residual: float = SEED_CURVE_RESIDUAL,
    taper_start: float | None = None,
    iterations: int = 2,
) -> Stitched:
    """Merge every unsaturated exposure weighted by the inverse of its full variance; sDC referred to the longest.

    The weight of exposure ``k`` of a pixel is ``w_k = 1 / var_k`` with

        var_k = [noise_k + (u(x_k) F_k)^2] (t_ref / t_k)^2,

    evaluated at the previous estimate of the pixel's rate (the first pilot
    is the replacement scheme; ``iterations`` passes), never at its own
    noisy counts:

    * ``noise_k`` (counts^2): shot noise ``F_k / (gain n_k)``
      (``gain_e_per_count`` electrons per count, ``F_k`` the expected signal
      in counts, ``n_k`` frames) plus the dark/ambient noise of measurement
      and background and their rounding to integer counts;
    * ``u(x_k)``: the relative non-linearity error of the reading at its
      expected count level ``x_k`` = (signal + background counts - black
      level) / full scale, from the calibration ``nonlinearity_curve`` (a
      :class:`NonlinearityCurve`, or ``(fraction, error)`` pairs).  An
      uncorrected reading's error is the curve itself, ``u = error(x)``: the
      merge then leans on the readings the curve says are closest to linear
      (its mean error drops), but, for the synthetic curve that reads about
      as far off at 10 % of full scale as near it, a reading that is about
      to saturate keeps about half the weight, so about half of the
      replacement scheme's seams stay.  ``None``: noise only.

    ``correct_nonlinearity`` first corrects measurement and background
    readings by the curve (:meth:`NonlinearityCurve.linearise`; seed §7.3
    names this as future work); each corrected reading then keeps only the
    curve's residual uncertainty ``u = curve_residual * error(x)`` (default
    8 %, the spread of the seed's per-pixel curve shapes), and the exposures
    agree across each switch: no seams.  Saturation is judged on the raw
    counts either way.

    ``taper_start`` (a fraction of full scale, e.g. 0.5; default off) also
    hands every exposure but the shortest over gradually to the shorter
    ones as its expected raw counts rise from ``taper_start`` to
    ``saturation_fraction``: its share of the merge becomes its
    inverse-variance share times a ``sin^2`` ramp from 1 to 0 (``tau = S W /
    (W + (1 - S) w)`` with ``W`` the shorter exposures' weight).  That
    removes the seams of uncorrected readings, but costs noise in the
    hand-over band wherever the shorter exposure is dark-noise limited (the
    seed's dark noise hardly grows beyond 100 ms).

    ``variance`` of the result is the noise variance of the merge, ``sum
    w_k^2 noise_k (t_ref / t_k)^2 / (sum w_k)^2`` (the non-linearity enters
    the uncertainty budget separately, as ``scatter_nonlinearity``, Eq 92).
    """
    if taper_start is not None and not 0 <= taper_start < saturation_fraction:
        raise ValueError(
            f"taper_start = {taper_start!r} must be None or in [0, saturation_fraction = {saturation_fraction!r})"
        )
    curve = _curve(nonlinearity_curve)
    if correct_nonlinearity and curve is None:
        raise ValueError("correct_nonlinearity needs a nonlinearity_curve")
    if not (math.isfinite(curve_residual) and curve_residual >= 0):
        raise ValueError(f"curve_residual must be a number >= 0, got {curve_residual!r}")
    pilot = stitch_replacement(stack, background, saturation_fraction=saturation_fraction,
                               gain_e_per_count=gain_e_per_count)
    t_ref = pilot.t_ref
    fs = stack.attrs.full_scale
    black = stack.attrs.black_level
    u_scale = curve_residual if correct_nonlinearity else 1.0
    rate = pilot.flux.astype(np.float64) / t_ref
    noise = _noise_terms(stack, background)
    for _ in range(max(1, int(iterations))):
        sw = np.zeros(stack.shape, np.float64)
        swx = np.zeros(stack.shape, np.float64)
        sw2v = np.zeros(stack.shape, np.float64)
        w_below = np.zeros(stack.shape, np.float64)  # inverse-variance weight of the shorter exposures so far
        count = np.zeros(stack.shape, np.int8)
        lin = curve if correct_nonlinearity else None
        for k, t, d, sat in _differences(stack, background, saturation_fraction, linearise=lin):
            n = stack.exposures[k].n_frames
            scale2 = (t_ref / t) ** 2
            light = np.maximum(rate * t, 0.0)
            var_noise = (light / (gain_e_per_count * n) + noise[k]) * scale2
            x = (light + background.exposures[k].counts - black) / fs
            if curve is not None and u_scale > 0:
                var = var_noise + (u_scale * curve(np.clip(x, 0.0, 1.0)) * light) ** 2 * scale2
            else:
                var = var_noise
            w = 1.0 / var
            w[sat] = 0.0
            w_eff = w
            if k > 0 and taper_start is not None:
                ramp = np.clip((saturation_fraction - x) / (saturation_fraction - taper_start), 0.0, 1.0)
                s_ = np.sin(0.5 * np.pi * ramp) ** 2
                with np.errstate(invalid="ignore", divide="ignore"):
                    tau = np.where(w_below > 0, s_ * w_below / (w_below + (1.0 - s_) * w), 1.0)
                w_eff = w * tau
            sw += w_eff
            swx += w_eff * (d * (t_ref / t))
            sw2v += w_eff * w_eff * var_noise
            w_below += w
            count += (w_eff > 0).astype(np.int8)
            del d, var, var_noise, w, w_eff, light, x
        ok = sw > 0
        safe = np.where(ok, sw, 1.0)
        flux = np.where(ok, swx / safe, pilot.flux)
        rate = flux / t_ref
    variance = np.where(ok, sw2v / safe**2, pilot.variance)
    return Stitched(flux.astype(np.float32), variance.astype(np.float32), ~ok, count, t_ref, "weighted")


#: Keywords of :func:`stitch_weighted` that the replacement scheme does not take.
WEIGHTED_ONLY = ("nonlinearity_curve", "correct_nonlinearity", "curve_residual", "taper_start", "iterations")


def stitch(stack: RawStack, background: RawStack, *, merge: str = "weighted", **kw: Any) -> Stitched:
    """Background-subtract and stitch with ``merge`` = ``"weighted"`` or ``"replacement"``.

    ``nonlinearity_curve``, ``curve_residual``, ``taper_start`` and
    ``iterations`` apply to the weighted merge only (the replacement scheme
    ignores them); ``correct_nonlinearity=True`` needs the weighted merge
    (the replacement scheme is the seed's, uncorrected).  Other keywords go
    to both.
    """
    if merge == "weighted":
        return stitch_weighted(stack, background, **kw)
    if merge == "replacement":
        if kw.get("correct_nonlinearity"):
            raise ValueError(
                "correct_nonlinearity needs merge='weighted' (the replacement scheme is the seed's, §3.6)"
            )
        return stitch_replacement(stack, background, **{k: v for k, v in kw.items() if k not in WEIGHTED_ONLY})
    raise ValueError(f"unknown merge {merge!r}; known: {', '.join(MERGES)}")


def stitch_raw(stack: RawStack, *, saturation_fraction: float = 0.98) -> np.ndarray:
    """The seed's stitching of *raw* counts (black level included), sDC float32 -- as §4.2 reports backgrounds."""
    level = saturation_fraction * stack.attrs.full_scale
    t_ref = float(stack.exposure_times[-1])
    out = np.zeros(stack.shape, np.float64)
    todo = np.ones(stack.shape, bool)
    for e in reversed(stack.exposures):
        take = todo & (e.counts < level)
        out[take] = e.counts[take] * (t_ref / e.exposure_s)
        todo &= ~take
    e0 = stack.exposures[0]
    out[todo] = e0.counts[todo] * (t_ref / e0.exposure_s)
    return out.astype(np.float32)


# --- §3.8 and §4.2 --------------------------------------------------------------------------------


def _eq45_scalar(phi_s: float, phi_i: float, cos_theta_s: float, solid_angle: float) -> float:
    return float(brdf_from_flux(phi_s, phi_i, math.acos(cos_theta_s), solid_angle))


def noise_equivalent_brdf(
    phi_s_low: float,
    beam_flux: float,
    od_beam: float,
    od_sample: float,
    *,
    solid_angle: float = SEED_CENTRE_SOLID_ANGLE,
    cos_theta_s: float = 1.0,
    exposure_ratio: float = 1.0,
) -> float:
    """Noise-equivalent BRDF, sr^-1 (seed §4.2): Eq 45 with Eq 87 at the noise floor ``Phi_s,low`` (sDC).

    Seed: ``noise_equivalent_brdf(48.05, 9.828e9, 5.2, 5.2)`` = 17.07 sr^-1;
    1.36 at ``OD_b - OD_m = 1.1``; 1.08e-4 at ``OD_m = 0``.  Pass the floor's
    standard deviation (23.11) as ``phi_s_low`` for the seed's std figures.
    """
    return _eq45_scalar(phi_s_low * exposure_ratio, incident_flux(beam_flux, od_beam, od_sample),
                        cos_theta_s, solid_angle)


def max_measurable_brdf(
    phi_s_high: float,
    beam_flux: float,
    od_beam: float,
    od_sample: float,
    *,
    solid_angle: float = SEED_CENTRE_SOLID_ANGLE,
    cos_theta_s: float = 1.0,
    exposure_ratio: float = 1.0,
) -> float:
    """Maximum measurable BRDF, sr^-1 (seed §4.2): Eq 45 with Eq 87 at ``Phi_s,high`` (sDC).

    Seed: ``max_measurable_brdf(1.6383e7, 9.828e9, 5.2, 5.2)`` = 5.82e6;
    4.62e5 at ``OD_b - OD_m = 1.1``; 36.7 at ``OD_m = 0``.
    """
    return _eq45_scalar(phi_s_high * exposure_ratio, incident_flux(beam_flux, od_beam, od_sample),
                        cos_theta_s, solid_angle)


def scatter_flux_high(full_scale: float, exposures_s: Sequence[float]) -> float:
    """``Phi_s,high``, sDC: full scale at the shortest exposure referred to the longest (seed: 16383 x 1000)."""
    t = np.asarray(exposures_s, dtype=np.float64)
    return float(full_scale) * float(t.max() / t.min())


def dynamic_range_decades(phi_s_high: float, phi_s_low: float) -> float:
    """``log10(Phi_s,high / Phi_s,low)``: decades of BRDF in one stitched frame (seed §4.2: 5.53)."""
    return math.log10(float(phi_s_high) / float(phi_s_low))


# --- one measurement ------------------------------------------------------------------------------


def _grid_slices(detector: Detector, grid: PixelGrid) -> tuple[np.ndarray, np.ndarray]:
    h_min, _, v_min, _ = detector.index_range
    return grid.n_v - v_min, grid.n_h - h_min


def _aligned(detector: Detector) -> Detector:
    return Detector(
        shape=detector.shape,
        pixel_pitch=detector.pixel_pitch,
        pixel_pitch_v=detector.pixel_pitch_v,
        distance=detector.distance,
        theta_c=detector.theta_c,
    )


def _is_misaligned(detector: Detector) -> bool:
    return any(float(np.asarray(getattr(detector, k))) != 0.0 for k in ("roll", "yaw", "pitch", "m_h", "m_v"))


def _uncertainty_blocks(detector, theta_i, grid, nl, noise, kw, keep, block_rows=256):
    """:func:`brdf_uncertainty` over blocks of rows (bounded memory).

    Returns float32 ``(rows, cols)`` maps of the keys in ``keep`` (all relative
    contributions if ``keep`` is None) and the value of every relative
    contribution that is the same on every pixel.
    """
    rows, cols = grid.shape
    block_rows = min(block_rows, rows)
    maps: dict[str, np.ndarray] = {}
    lo: dict[str, float] = {}
    hi: dict[str, float] = {}
    for r0 in range(0, rows, block_rows):
        r1 = min(rows, r0 + block_rows)
        # Pad the last block to the block size (repeating its last row) so that one compiled program serves all.
        idx = np.minimum(np.arange(r0, r0 + block_rows), r1 - 1)
        sub = PixelGrid(grid.n_h, grid.n_v[idx])
        res = brdf_uncertainty(
            detector, theta_i, sub,
            scatter_nonlinearity=nl if np.ndim(nl) == 0 else nl[idx],
            scatter_noise=noise[idx],
            **kw,
        )
        for k, v in res.items():
            if k.startswith("dphi_s") or k.startswith("dtheta_s"):
                continue  # absolute angles, not relative contributions
            v = np.broadcast_to(np.asarray(v, dtype=np.float32), (block_rows, cols))[: r1 - r0]
            with np.errstate(invalid="ignore"):
                lo[k] = min(lo.get(k, np.inf), float(np.nanmin(v)) if np.any(np.isfinite(v)) else np.nan)
                hi[k] = max(hi.get(k, -np.inf), float(np.nanmax(v)) if np.any(np.isfinite(v)) else np.nan)
            if keep is None or k in keep:
                if k not in maps:
                    maps[k] = np.empty((rows, cols), np.float32)
                maps[k][r0:r1] = v
        del res
    uniform = {k: lo[k] for k in lo if lo[k] == hi[k]}
    return maps, uniform


@dataclass(frozen=True)
class BeamSignature:
    """What a reduction needs from the beam signature (§3.7-3.8): ``Phi_b`` and how it was measured.

    ``flux`` is the stitched, background-subtracted beam summed over the
    array (sDC referred to ``t_ref``, s), ``variance`` its noise variance,
    ``attrs`` the beam file's attributes (``optical_density``, ``nd_filters``).
    """

    flux: float
    variance: float
    t_ref: float
    attrs: RawAttrs
    shape: tuple[int, int]
    file: str = ""
    background_file: str = ""


def beam_signature(
    beam: RawStack,
    beam_background: RawStack,
    *,
    merge: Literal["weighted", "replacement"] = "weighted",
    saturation_fraction: float = 0.98,
    gain_e_per_count: float = SEED_GAIN,
    nonlinearity_curve: NonlinearityCurve | Sequence[tuple[float, float]] | None = SYNTHETIC_NONLINEARITY_CURVE,
    correct_nonlinearity: bool = False,
    curve_residual: float = SEED_CURVE_RESIDUAL,
    taper_start: float | None = None,
) -> BeamSignature:
    """Stitch a beam signature and sum it over the array (§3.8): the incident flux ``Phi_b`` at ``OD_b``.

    ``nonlinearity_curve``, ``correct_nonlinearity``, ``curve_residual`` and
    ``taper_start`` are the weighted merge's (:func:`stitch_weighted`).
    """
    if beam.attrs.kind != "beam":
        raise ReductionError(f"{beam.path}: kind is {beam.attrs.kind!r}, expected 'beam' for a beam signature")
    if beam_background.attrs.kind not in ("background", "dark"):
        raise ReductionError(
            f"{beam_background.path}: kind is {beam_background.attrs.kind!r}, expected 'background' (or 'dark')"
        )
    b = stitch(beam, beam_background, merge=merge, saturation_fraction=saturation_fraction,
               gain_e_per_count=gain_e_per_count, nonlinearity_curve=nonlinearity_curve,
               correct_nonlinearity=correct_nonlinearity, curve_residual=curve_residual, taper_start=taper_start)
    if np.any(b.saturated):
        raise ReductionError(
            f"{beam.path}: {int(b.saturated.sum())} pixel(s) of the beam signature are saturated even at the "
            f"shortest exposure ({beam.exposure_times[0]:g} s); add ND filters or shorten the exposure"
        )
    return BeamSignature(
        float(np.sum(b.flux, dtype=np.float64)),
        float(np.sum(b.variance, dtype=np.float64)),
        b.t_ref,
        beam.attrs,
        beam.shape,
        beam.path.name if beam.path else "",
        beam_background.path.name if beam_background.path else "",
    )


def reduce_measurement(
    sample: RawStack,
    sample_background: RawStack,
    beam: BeamSignature,
    *,
    merge: Literal["weighted", "replacement"] = "weighted",
    step: int = 1,
    scatter_nonlinearity: float | np.ndarray = SEED_SCATTER_NONLINEARITY["mean"],
    nd_tolerances: Mapping[Any, float] | None = None,
    dR: float = SEED_DISTANCE_UNCERTAINTY,
    dd: float = SEED_PITCH_UNCERTAINTY,
    dtheta_c: float = SEED_ARM_ANGLE_UNCERTAINTY,
    saturation_fraction: float = 0.98,
    gain_e_per_count: float = SEED_GAIN,
    artifact_decades: float = 4.8,
    min_snr: float = 3.0,
    nonlinearity_curve: NonlinearityCurve | Sequence[tuple[float, float]] | None = SYNTHETIC_NONLINEARITY_CURVE,
    correct_nonlinearity: bool = False,
    curve_residual: float = SEED_CURVE_RESIDUAL,
    taper_start: float | None = None,
    detailed_uncertainty: bool = False,
) -> ExrFrame:
    """Reduce one sample measurement against a beam signature (module docstring, steps 1-7).

    ``beam`` comes from :func:`beam_signature`.  ``scatter_nonlinearity`` is
    the per-pixel non-linearity dNL_s of the camera (Eq 92): a scalar
    (default: the seed's array mean, 2.18 %) or a map of the raw array's
    shape.  ``nd_tolerances`` maps nominal OD to its tolerance (default: the
    seed's).  ``dR``, ``dd`` (m) and ``dtheta_c`` (rad) are the geometry's
    standard uncertainties.  ``artifact_decades`` places the artifact floor
    below the frame's peak; pixels whose stitched flux is under ``min_snr``
    times its standard deviation are flagged too (0: off).
    ``nonlinearity_curve`` (the camera's response curve; None: noise-only
    weights), ``correct_nonlinearity``, ``curve_residual`` and
    ``taper_start`` are the weighted merge's (:func:`stitch_weighted`); the
    beam signature was stitched with its own options.
    ``detailed_uncertainty`` adds a channel for every sub-contribution of the
    geometric terms (``u_theta_R``, ``u_solid_angle_d``, ...).
    """
    if merge not in MERGES:
        raise ValueError(f"unknown merge {merge!r}; known: {', '.join(MERGES)}")
    if sample.attrs.kind != "sample":
        raise ReductionError(f"{sample.path}: kind is {sample.attrs.kind!r}, expected 'sample'")
    if sample_background.attrs.kind not in ("background", "dark"):
        raise ReductionError(
            f"{sample_background.path}: kind is {sample_background.attrs.kind!r}, expected 'background' (or 'dark')"
        )
    _check_pair(sample, sample_background)
    if beam.shape != sample.shape:
        raise ReductionError(
            f"{sample.path} and the beam signature {beam.file}: array shapes differ ({sample.shape} vs {beam.shape})"
        )
    a = sample.attrs
    od_b, od_m = beam.attrs.optical_density, a.optical_density
    beam_flux = beam.flux
    phi_i = incident_flux(beam_flux, od_b, od_m)
    curve = _curve(nonlinearity_curve)
    s = stitch(sample, sample_background, merge=merge, saturation_fraction=saturation_fraction,
               gain_e_per_count=gain_e_per_count, nonlinearity_curve=curve,
               correct_nonlinearity=correct_nonlinearity, curve_residual=curve_residual, taper_start=taper_start)
    exposure_ratio = float(beam.t_ref / sample.exposure_times[-1])

    # Geometry of the measurement (misalignment included) on the output grid.
    detector = sample.attrs.detector(sample.shape)
    frame = sample.attrs.frame()
    grid = detector.grid(step)
    rr, cc = _grid_slices(detector, grid)
    geom = {k: np.asarray(v) for k, v in render_geometry(frame, detector, grid=grid).items()}
    theta_s, phi_s, omega = geom["theta_s"], geom["phi_s"], geom["omega"]
    del geom
    phi_s_flux = s.flux[np.ix_(rr, cc)].astype(np.float64) * exposure_ratio
    phi_s_std = np.sqrt(s.variance[np.ix_(rr, cc)].astype(np.float64)) * exposure_ratio
    saturated = s.saturated[np.ix_(rr, cc)]
    # Partial saturation: usable, but merged without the exposures that saturated there (weighted: fewer
    # exposures merged than taken; replacement: not taken from the longest exposure).
    src = s.source[np.ix_(rr, cc)]
    n_exp = len(sample.exposures)
    partly = ~saturated & ((src < n_exp) if s.merge == "weighted" else (src < n_exp - 1))
    del s, src
    brdf = np.asarray(brdf_from_flux(phi_s_flux, phi_i, theta_s, omega), dtype=np.float32)

    # §4.2 figures from the inputs.
    bg_raw = stitch_raw(sample_background, saturation_fraction=saturation_fraction)
    phi_low = float(np.mean(bg_raw, dtype=np.float64))
    phi_low_std = float(np.std(bg_raw, dtype=np.float64))
    del bg_raw
    phi_high = scatter_flux_high(sample.attrs.full_scale, sample.exposure_times)
    omega_c = float(np.asarray(detector.solid_angle(0.0, 0.0)))
    nominal = dict(solid_angle=omega_c, exposure_ratio=exposure_ratio)
    neb = noise_equivalent_brdf(phi_low, beam_flux, od_b, od_m, **nominal)
    neb_std = noise_equivalent_brdf(phi_low_std, beam_flux, od_b, od_m, **nominal)
    f_max = max_measurable_brdf(phi_high, beam_flux, od_b, od_m, **nominal)
    decades = dynamic_range_decades(phi_high, phi_low)
    neb_map = np.asarray(brdf_from_flux(phi_low * exposure_ratio, phi_i, theta_s, omega), dtype=np.float32)

    # Masks.
    flags = np.zeros(brdf.shape, np.uint8)
    flags[saturated] |= FLAG_SATURATED
    flags[brdf < neb_map] |= FLAG_BELOW_NOISE
    finite = np.isfinite(brdf)
    flags[~finite] |= FLAG_NOT_FINITE
    good = finite & ~saturated & (brdf >= neb_map)
    peak = float(brdf[good].max()) if np.any(good) else float("nan")
    floor = peak * 10.0 ** (-artifact_decades) if math.isfinite(peak) else float("inf")
    flags[brdf < floor] |= FLAG_BELOW_ARTIFACT_FLOOR
    if min_snr > 0:
        flags[phi_s_flux < min_snr * phi_s_std] |= FLAG_LOW_SNR
    mask = (flags == 0).astype(np.float32)
    if not mask.any():
        _no_usable_pixel(sample, flags, saturation_fraction)

    # Uncertainty (Chapter IV) with the stitched noise as the scatter-noise contribution.
    with np.errstate(divide="ignore", invalid="ignore"):
        noise_rel = np.where(phi_s_flux > 0, phi_s_std / phi_s_flux, np.nan)
    nl = scatter_nonlinearity
    if np.ndim(nl) != 0:
        nl = np.asarray(nl, dtype=np.float64)
        if nl.shape != sample.shape:
            raise ValueError(
                f"scatter_nonlinearity has shape {nl.shape}; expected a scalar or the raw array's {sample.shape}"
            )
        nl = nl[np.ix_(rr, cc)]
    unc_kw: dict[str, Any] = dict(
        dR=dR,
        dd=dd,
        dtheta_c=dtheta_c,
        misaligned=_aligned(detector) if _is_misaligned(detector) else None,
    )
    if beam.attrs.filters or a.filters:
        unc_kw.update(nd_beam=beam.attrs.nd_filters or None, nd_sample=a.nd_filters or None,
                      nd_tolerances=nd_tolerances)
    else:
        unc_kw.update(nd=0.0)  # no filter anywhere: nothing to cancel or to doubt
    unc, uniform = _uncertainty_blocks(
        detector, sample.attrs.theta_i, grid, nl, noise_rel, unc_kw,
        keep=None if detailed_uncertainty else {"total", *PER_PIXEL_TERMS},
    )
    sigma_rel = unc.pop("total")
    uniform.pop("total", None)
    # Contributions equal on every pixel also go in the header (u_nd, u_temporal, ...).
    per_pixel = [k for k in PER_PIXEL_TERMS if k in unc]
    if detailed_uncertainty:
        per_pixel += [k for k in unc if k not in per_pixel]

    extra = {
        "sigma_rel": sigma_rel,
        "mask": mask,
        "flags": flags.astype(np.float32),
        "noise_equivalent_brdf": neb_map,
        **{f"u_{k}": unc[k] for k in per_pixel},
    }
    roi = (int(grid.n_h[0]), int(grid.n_h[-1]), int(grid.n_v[0]), int(grid.n_v[-1]))
    attrs = {
        # the frame header, with the raw array's shape (the roi is on its pixel indices)
        **frame_attrs(detector, frame, step=step, roi=roi, array_shape=True),
        "model": f"measured: {a.sample}" if a.sample else "measured",
        "frame": "reduced from raw exposure stacks (brdfjax.instrument.reduce)",
        "merge": merge,
        "sample_file": str(sample.path.name) if sample.path else "",
        "sample_background_file": str(sample_background.path.name) if sample_background.path else "",
        "beam_file": beam.file,
        "beam_background_file": beam.background_file,
        "nd_beam": beam.attrs.nd_filters,
        "nd_sample": a.nd_filters,
        "od_beam": od_b,
        "od_sample": od_m,
        "beam_flux_sdc": beam_flux,
        "beam_flux_rel_std": math.sqrt(beam.variance) / beam_flux,
        "incident_flux_sdc": phi_i,
        "exposure_ratio": exposure_ratio,
        "phi_s_low_sdc": phi_low,
        "phi_s_low_std_sdc": phi_low_std,
        "phi_s_high_sdc": phi_high,
        "noise_equivalent_brdf": neb,
        "noise_equivalent_brdf_std": neb_std,
        "max_measurable_brdf": f_max,
        "dynamic_range_decades": decades,
        "peak_brdf": peak,
        "artifact_floor": floor,
        "artifact_decades": float(artifact_decades),
        "saturation_fraction": float(saturation_fraction),
        "min_snr": float(min_snr),
        "taper_start": -1.0 if taper_start is None else float(taper_start),
        "nonlinearity_curve": curve.describe() if curve is not None and merge == "weighted" else "",
        "nonlinearity_corrected": int(bool(correct_nonlinearity) and merge == "weighted"),
        **{f"u_{k}": v for k, v in sorted(uniform.items())},
        "usable_fraction": float(mask.mean()),
        "saturated_pixels": int(saturated.sum()),
        "partly_saturated_pixels": int(partly.sum()),
        "channel_units": "brdf: sr^-1, theta_s: rad, phi_s: rad, omega: sr, "
        "noise_equivalent_brdf: sr^-1, sigma_rel and u_*: relative, mask: 1 usable / 0 excluded, "
        "flags: 1 saturated, 2 below noise, 4 below artifact floor, 8 not finite, 16 low SNR; "
        "u_* attributes: contributions equal on every pixel (also in the u_* channels)",
    }
    return ExrFrame(brdf, theta_s.astype(np.float32), phi_s.astype(np.float32),
                    omega.astype(np.float32), attrs, extra)


def _no_usable_pixel(sample: RawStack, flags: np.ndarray, saturation_fraction: float) -> None:
    """Raise the :class:`ReductionError` of a measurement whose mask is empty, saying why pixel by pixel."""
    n = flags.size
    why = {name: int(np.count_nonzero(flags & bit)) for name, bit in (
        ("saturated in every exposure", FLAG_SATURATED), ("below the noise-equivalent BRDF", FLAG_BELOW_NOISE),
        ("not finite", FLAG_NOT_FINITE), ("below the artifact floor", FLAG_BELOW_ARTIFACT_FLOOR),
        ("below min_snr", FLAG_LOW_SNR))}
    parts = ", ".join(f"{k} {v}" for k, v in why.items() if v)
    hint = (
        f"every pixel reaches {saturation_fraction:g} x full scale even in the shortest exposure "
        f"({float(sample.exposure_times[0]):g} s): take it again through a denser ND filter or with shorter exposures"
        if why["saturated in every exposure"] == n
        else "check the exposures, the ND filters and the background"
    )
    raise ReductionError(
        f"{sample.path or 'measurement'}: no usable pixel in the reduced frame ({n} pixels: {parts}); {hint}. "
        "Nothing was written for this measurement set"
    )


# --- frame files with extra channels --------------------------------------------------------------


def write_reduced_frame(path: str | os.PathLike, frame: ExrFrame) -> Path:
    """Write a reduced frame atomically: the frame format of :mod:`brdfjax.io.exr` plus its extra channels."""
    return write_frame_exr(
        path,
        frame.brdf,
        frame.theta_s,
        frame.phi_s,
        frame.omega,
        {"brdfjax_version": __version__, **frame.attrs},
        extra_channels=frame.extra,
    )


def read_reduced_frame(path: str | os.PathLike) -> ExrFrame:
    """Read a frame written by :func:`write_reduced_frame`, with its extra channels (:func:`brdfjax.io.read_frame_exr`)."""
    return read_frame_exr(path)


# --- measurement sets -----------------------------------------------------------------------------


def _read(path: Path, what: str) -> RawStack:
    try:
        return read_raw_exr(path)
    except RawFormatError:
        raise
    except FileNotFoundError as e:
        raise ReductionError(f"{path}: {what} file not found") from e


def reduce_measurement_set(
    manifest_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    merge: Literal["weighted", "replacement"] = "weighted",
    step: int = 1,
    progress: Callable[[int, int, str], None] | None = None,
    **options: Any,
) -> list[Path]:
    """Reduce every sample of a measurement set; returns the written frame paths (``<out_dir>/<name>.exr``).

    ``manifest_path`` is a ``manifest.toml`` (or its folder); ``merge`` is
    ``"weighted"`` (inverse-variance) or ``"replacement"`` (seed §3.6);
    ``step`` keeps every ``step``-th pixel of the output frames.  Other
    keyword options go to :func:`reduce_measurement` (``scatter_nonlinearity``,
    ``nd_tolerances``, ``dR``, ``dd``, ``dtheta_c``, ``saturation_fraction``,
    ``gain_e_per_count``, ``artifact_decades``, ``min_snr``,
    ``nonlinearity_curve``, ``correct_nonlinearity``, ``curve_residual``,
    ``taper_start``, ``detailed_uncertainty``); the weighted merge's options
    also stitch the beam signature.  The manifest's optional
    ``[calibration]`` table supplies ``scatter_nonlinearity``,
    ``nonlinearity_curve`` and extra ``nd_tolerances`` (added to the seed's
    table) unless given here.  Inputs are only read; each
    output is written to a temporary name and renamed into place only once
    every sample reduced, so an interrupted or refused run leaves the old
    outputs, never a part of the new ones.  ``progress(done, total, name)``
    is called after each sample.
    """
    if merge not in MERGES:
        raise ValueError(f"unknown merge {merge!r}; known: {', '.join(MERGES)}")
    if not (isinstance(step, int | np.integer) and step >= 1):
        raise ValueError(f"step must be a positive integer, got {step!r}")
    manifest: Manifest = read_manifest(manifest_path)
    cal = manifest.calibration
    if cal.scatter_nonlinearity is not None:
        options.setdefault("scatter_nonlinearity", cal.scatter_nonlinearity)
    if cal.nd_tolerances and options.get("nd_tolerances") is None:
        options["nd_tolerances"] = {**SEED_ND_TOLERANCES, **cal.nd_tolerances}
    if cal.nonlinearity_curve is not None:
        options.setdefault("nonlinearity_curve", NonlinearityCurve(cal.nonlinearity_curve))
    out_dir = Path(out_dir)
    inputs = {p.resolve() for p in manifest.files()} | {manifest.path}
    stitch_kw = {
        k: options[k]
        for k in ("saturation_fraction", "gain_e_per_count", "nonlinearity_curve", "correct_nonlinearity",
                  "curve_residual", "taper_start")
        if k in options
    }
    if merge == "replacement" and options.get("correct_nonlinearity"):
        raise ValueError("correct_nonlinearity needs merge='weighted' (the replacement scheme is the seed's, §3.6)")
    beam = beam_signature(
        _read(manifest.beam.file, "beam signature"),
        _read(manifest.beam.background, "beam background"),
        merge=merge,
        **stitch_kw,
    )
    targets = []
    for entry in manifest.samples:
        target = (out_dir / f"{entry.name}.exr").resolve()
        if target in inputs:
            raise ReductionError(
                f"{target}: the output would overwrite an input of {manifest.path}; choose another --out"
            )
        targets.append(target)
    # Every frame is first written under a hidden staging name and renamed into place only when all of
    # them reduced: a measurement that cannot be reduced (e.g. saturated everywhere) leaves nothing
    # half-written, and the old outputs stay as they were.
    staged: list[tuple[Path, Path]] = []
    try:
        for i, (entry, target) in enumerate(zip(manifest.samples, targets)):
            sample = _read(entry.file, f"sample '{entry.name}'")
            sample_bg = _read(entry.background, f"background of sample '{entry.name}'")
            reduced = reduce_measurement(sample, sample_bg, beam, merge=merge, step=int(step), **options)
            del sample, sample_bg
            tmp = target.with_name(f".{target.stem}.staged.exr")
            staged.append((write_reduced_frame(tmp, reduced), target))
            del reduced
            if progress is not None:
                progress(i + 1, len(targets), entry.name)
        for tmp, target in staged:
            os.replace(tmp, target)
    finally:
        for tmp, _ in staged:
            if tmp.exists():
                tmp.unlink()
    return targets


# --- figure ---------------------------------------------------------------------------------------


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
