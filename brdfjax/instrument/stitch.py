"""The HDR merge of an exposure stack (seed §3.6): the non-linearity calibration and the two merges.

:func:`stitch` merges a stack of exposures (with its background stack) into one count-rate image with
its variance: ``"weighted"`` (inverse-variance weights over every unsaturated exposure, with an
optional non-linearity correction) or ``"replacement"`` (the seed's scheme: the longest unsaturated
exposure per pixel).  :class:`NonlinearityCurve` is the detector's measured response curve.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..io.raw import RawStack
from ..runtime.errors import InputError

__all__ = ["MERGES", "SEED_GAIN", "ReductionError", "NonlinearityCurve", "SYNTHETIC_NONLINEARITY_CURVE",
           "SEED_CURVE_RESIDUAL", "Stitched", "stitch", "stitch_replacement", "stitch_weighted", "stitch_raw"]

MERGES = ("weighted", "replacement")
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
