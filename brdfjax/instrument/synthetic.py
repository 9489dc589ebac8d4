"""A synthetic CCD scatterometer: brdfjax models (or any BRDF frame) -> raw exposure stacks.

It plays the seed's instrument (Chapter III: the Thorlabs 8051 CCD on the
CASI arm, a 15 mW HeNe focused by the CASI optics) so that the reduction, the
fits and the sim-to-real diagnosis can be tested on data with known truth.
The output is exactly what the camera software writes: raw stacks in the
format of :mod:`brdfjax.io.raw`.

Signal chain, per measurement (units: counts are the camera's digital counts,
"counts/s" a rate of them; rates are per pixel):

1. **Light.**  For a sample, the scattered flux of every pixel is Eq 45
   inverted, ``Phi_s = (f_r * K) cos(theta_s) Omega_d Phi_i 10^-OD``: the
   BRDF frame rendered on the pixel grid (:func:`brdfjax.core.render`), convolved
   (FFT, zero padding) with the focused beam's footprint ``K`` -- the
   instrument function, effect ``footprint`` -- times the cosine and the
   pixel solid angle from the core mapping (misalignment included) and the
   incident flux ``Phi_i`` (counts/s reaching the array with no ND filter)
   attenuated by the ND filters' OD.  For a beam signature (no sample,
   ``theta_c = 0``) it is ``Phi_i 10^-OD K`` centred where the beam hits the
   array.  ``K`` is the pixel-integrated symmetric Gaussian of Eq 73,
   ``exp(-2 r^2 / w^2)``, normalised to 1, with the 1/e^2 radius ``w`` =
   25 pixels (seed §3.3/§4.3: the HeNe focuses to a 1/e^2 width of about 25
   pixels; a beam-signature peak of 3.82e6 sr^-1 (§3.8) implies w = 24 px).
2. **Stray light** (``stray_light``): faint displaced copies of the image (the
   sub-peaks of seed Fig 20-21, "more than 4.8 orders of magnitude below the
   main peak"; seed §4.6 suspects multiple reflections in the ND filters).
3. **Ambient** (``ambient``): room light leaking past the lens tube, a smooth
   per-pixel rate (not attenuated by the ND filters, seed §4.2).
4. **Source drift** (``source_drift``, off by default) scales ``Phi_i`` of each
   measurement by ``1 + N(0, rel_std)`` (seed Eq 96: 1.01 %); **ND error**
   (``nd_error``, off by default) gives each physical filter a true OD off its
   nominal value by a uniform draw within its tolerance (seed §4.3), the same
   for every measurement made with that filter.
5. **Exposure** ``t`` and **frame averaging** over ``n_frames`` frames
   (exposures one at a time, in row blocks, float32 out): photon **shot
   noise** (``shot_noise``; Poisson in electrons, gain 20000 e- / 16383
   counts: the published full well over the 14-bit range), per-pixel
   **non-linearity** (``nonlinearity``), **dark** signal and noise (``dark``),
   **black level** (``black_level``), **quantisation** to integer counts
   (``quantisation``) and **saturation** at ``2**adc_bits - 1``
   (``saturation``).

The average of ``n_frames`` frames is drawn directly rather than frame by
frame: the sum of N Poisson draws is one Poisson draw of N times the mean,
Gaussian terms shrink by sqrt(N), and saturation clips the mean. By default
the average is rounded to integer counts, as the seed's camera outputs its
internal average of up to 32 frames (§3.1) -- which also keeps the files small
(ZIP compresses integer-valued noise about 3x, float means of 32 frames hardly
at all); with ``round_average=False`` each frame is rounded before a software
average (variance 1/(12 N), values on the 1/N grid). ``counts_std`` is the
per-frame standard deviation (written when ``write_counts_std``; the seed's
camera does not report it) the software would report: the model's per-frame
noise times a chi draw with N - 1 degrees of freedom (Wilson-Hilferty),
rounded to float16 precision (an N = 32 estimate is uncertain by 13 %; the
rounding lets ZIP compress the channel).

Dark (lens-cap) calibration, seed §3.1 and §4.2. The ADC clips at 0, and at 1
s the dark noise (~23 counts) is comparable to the mean (~46 counts), so the
seed's figures -- array statistics of clipped frames -- are matched *after*
clipping (fitted with the moments of a clipped normal). Mean counts (black
level + dark signal) are linear in ``t`` through 29.29 counts at 1 ms and the
lens-cap stitched mean of 45.88 counts at 1 s (giving 29.52 at 15 ms; the seed
reads 29.62). The standard deviation of an ``n_ref``-frame (32) lens-cap
average before clipping is the empirical fit ``sigma(t) = sqrt(s_read^2 +
s_sat^2 tanh^2(t / tau))``, with ``s_read``, ``s_sat``, ``tau`` chosen so that
the clipped frames read 2.14 counts at 1 ms, 11.21 at 15 ms (seed §3.1) and,
with ambient light, the background stitched at 1 s reads 48.05 counts mean and
23.11 standard deviation (seed §4.2, ``Phi_s,low``); the lens cap then reads
45.88 at 1 s. The growth from 1 to 15 ms is faster than linear in variance and
then levels off, which no single power law fits. A fraction
``fixed_pattern_fraction`` of the variance is a fixed per-pixel pattern
(DSNU), the rest temporal noise per frame ``sigma(t) sqrt(n_ref)``.

Non-linearity, seed §4.2.  The seed's three characterisations say: the
array-average response deviates from linear by up to 1.72 % (baseline
method); each pixel deviates from its own linear fit by about the same, 1.74
+- 0.14 % (so the shape is common to all pixels); and each pixel deviates
from the array-wide fit by 2.18 +- 0.50 % on average, up to 16.32 %, with
0.021 % of pixels beyond 5.19 % (final method, the dNL_s of Eq 92).  The
model: a response ``S (1 + g + a (2 x - 1))`` with ``x = S / full_scale``, a
common term of amplitude ``a = 1.72 %`` and a per-pixel gain error ``g``
(random sign; ``|g|`` gamma-distributed with mean 0.46 % and std 0.50 %, so
that ``dNL_s = |g| + a`` has the seed's mean and std), and a fraction 2.1e-4
of outliers with ``dNL_s`` log-uniform in [5.19 %, 16.32 %].  The common term
differs between the exposures of one pixel (about +1.7 % near full scale,
-1.4 % at a tenth of it), which is what makes the replacement scheme's seams
(§3.6, Fig 18); :meth:`Camera.nonlinearity_map` gives each pixel's dNL_s.

Per-pixel maps (non-linearity, ambient pattern, dark pattern, ND filter
errors) belong to the synthetic camera and come from ``camera_seed``; the
noise of each measurement comes from the instrument's ``numpy`` Generator
(``seed``).  The same seeds give the same files.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import numpy as np
from pydantic import Field, field_validator

from ..config.base import StrictModel, read_toml, validate
from ..core.detector import Detector
from ..core.fft import fast_len
from ..core.render import Frame, render, render_geometry
from ..core.terms import AbstractTerm
from ..io.header import geometry_attrs
from ..io.raw import (
    Calibration,
    Exposure,
    RawAttrs,
    RawStack,
    write_manifest,
    write_raw_exr,
)
from .nd import ND_3_TOLERANCE, SEED_ND_TOLERANCES, choose_nd_filters, parse_nd_filters
from .radiometry import flux_from_brdf

__all__ = [
    "EFFECTS",
    "InstrumentConfig",
    "load_instrument_config",
    "Footprint",
    "StrayLight",
    "Ambient",
    "SourceDrift",
    "NDError",
    "Source",
    "ShotNoise",
    "NonLinearity",
    "Dark",
    "BlackLevel",
    "Quantisation",
    "Saturation",
    "Camera",
    "SyntheticInstrument",
    "footprint_kernel",
    "convolve_footprint",
    "scatter_flux_image",
    "beam_flux_image",
    "lens_cap_std",
    "SEED_BEAM_FLUX",
    "SEED_BEAM_OD",
    "SEED_BEAM_FILTERS",
]

#: Phi_b of the seed, sDC (scaled to 1 s exposure: counts per second) at OD_b = 5.2 (seed §4.2).
SEED_BEAM_FLUX = 9.828e9
#: The seed's beam-signature OD and its filter stack (seed §3.3, §4.3).
SEED_BEAM_OD = 5.2
SEED_BEAM_FILTERS = "4.0+1.0+0.2"


class Footprint(StrictModel):
    """Focused beam footprint, the instrument function (Eq 73): Gaussian with 1/e^2 radius ``w_px`` pixels."""

    enabled: bool = Field(True, description="convolve the scatter image with the beam footprint")
    w_px: float = Field(25.0, gt=0, description="1/e^2 radius of the Gaussian footprint, in pixels")


class ShotNoise(StrictModel):
    """Photon shot noise: Poisson in electrons; ``gain`` in electrons per count (full well 20000 e- / 16383)."""

    enabled: bool = Field(True, description="Poisson photon noise in electrons")
    gain_e_per_count: float = Field(20000.0 / 16383.0, gt=0, description="electrons per count (full well 20000 e- over 16383 counts)")


class Dark(StrictModel):
    """Dark signal and noise; counts.  Defaults fitted to the seed's lens-cap figures (module docstring).

    Mean dark signal ``rate_counts_per_s * t``; array std of an ``n_ref_frames``
    average ``sqrt(read_std^2 + sat_std^2 tanh^2(t / tau_s))``; a fraction
    ``fixed_pattern_fraction`` of its variance is a fixed per-pixel pattern.
    """

    enabled: bool = Field(True, description="add dark signal and its noise")
    rate_counts_per_s: float = Field(16.3714, ge=0, description="mean dark signal rate, counts per second")
    read_std: float = Field(1.96294, ge=0, description="read-noise std of an n_ref_frames average, counts")
    sat_std: float = Field(23.4554, ge=0, description="exposure-dependent noise std at long exposures, counts")
    tau_s: float = Field(0.0292368, gt=0, description="time constant of the exposure-dependent noise, seconds")
    n_ref_frames: int = Field(32, ge=1, description="frames averaged in the lens-cap reference the noise figures describe")
    fixed_pattern_fraction: float = Field(0.0, ge=0, le=1, description="fraction of the dark variance that is a fixed per-pixel pattern (0-1)")


class BlackLevel(StrictModel):
    """Black-level offset added by the camera, counts (29.29 at 1 ms minus 1 ms of dark signal)."""

    enabled: bool = Field(True, description="add the camera's black-level offset")
    counts: float = Field(29.2736, ge=0, description="black-level offset, counts")


class Ambient(StrictModel):
    """Ambient room light, counts/s per pixel, with a smooth pattern of relative std ``nonuniformity``."""

    enabled: bool = Field(True, description="add ambient room light")
    rate_counts_per_s: float = Field(2.2218, ge=0, description="ambient light per pixel, counts per second")
    nonuniformity: float = Field(0.3, ge=0, lt=0.5, description="relative std of the ambient light's smooth spatial pattern (< 0.5)")


class StrayLight(StrictModel):
    """Displaced faint copies of the image: ``(dh_px, dv_px, log10 of the copy's peak / main peak)`` each."""

    enabled: bool = Field(True, description="add displaced faint copies of the image")
    peaks: tuple[tuple[int, int, float], ...] = Field(((310, -140, -4.85), (-420, 95, -5.05), (150, 380, -5.3)), description="each copy as [dh_px, dv_px, log10 of its peak over the main peak]")


class NonLinearity(StrictModel):
    """Response ``S (1 + g + common_max (2 S / full_scale - 1))`` (seed §4.2; module docstring).

    ``common_max``: the array-average deviation from linear, fraction; the per-pixel
    gain error ``|g|`` has mean ``gain_mean`` and std ``gain_std`` (gamma
    distribution, random sign) below ``outlier_threshold - common_max``; a
    fraction ``outlier_fraction`` of pixels has a total error log-uniform in
    ``[outlier_threshold, outlier_max]``.
    """

    enabled: bool = Field(True, description="apply the camera's non-linear response")
    common_max: float = Field(0.0172, ge=0, description="array-average deviation from linear at full scale, a fraction")
    gain_mean: float = Field(0.0046, gt=0, description="mean of the per-pixel gain error |g|")
    gain_std: float = Field(0.0050, gt=0, description="std of the per-pixel gain error |g|")
    outlier_threshold: float = Field(0.0519, ge=0, description="total error beyond which a pixel is an outlier, a fraction")
    outlier_fraction: float = Field(2.1e-4, ge=0, le=1, description="fraction of pixels that are outliers (0-1)")
    outlier_max: float = Field(0.1632, ge=0, description="largest total error of an outlier pixel, a fraction")


class Quantisation(StrictModel):
    """Rounding to integer counts: of the averaged output (``round_average``, the camera's internal
    averaging, seed §3.1) or of every frame before a software average (``round_average=False``)."""

    enabled: bool = Field(True, description="round to integer counts")
    round_average: bool = Field(True, description="round the camera's averaged output (true) or every frame before a software average (false)")


class Saturation(StrictModel):
    """Clipping at the ADC's full scale ``2**adc_bits - 1`` counts (and at 0)."""

    enabled: bool = Field(True, description="clip at 0 and at the ADC's full scale 2**adc_bits - 1 counts")


class SourceDrift(StrictModel):
    """Incident flux of each measurement scaled by ``1 + N(0, rel_std)`` (seed Eq 96: 1.01 %)."""

    enabled: bool = Field(False, description="scale each measurement's incident flux by a random factor")
    rel_std: float = Field(0.0101, ge=0, description="relative std of that factor (seed Eq 96: 1.01 %)")


class Source(StrictModel):
    """The source's spectrum: a Gaussian line of relative rms width ``rel_width`` (sigma_lambda / lambda).

    0 (the default): the monochromatic HeNe.  A finite width (a broadband LED, a
    multimode laser) renders the model at ``n_nodes`` wavelengths (Gauss-Hermite
    nodes about the frame's wavelength) and averages them: diffraction orders
    smear into stripes.  ``spectrum`` instead gives explicit ``(wavelength_nm,
    relative power)`` samples (a ``colour.SpectralDistribution``'s pairs); the
    frame's wavelength is then ignored.  Not one of :data:`EFFECTS` (nothing
    to switch off in the seed's instrument).
    """

    rel_width: float = Field(0.0, ge=0, lt=0.5, description="relative rms width sigma_lambda / lambda of a Gaussian source line (0: monochromatic)")
    n_nodes: int = Field(15, ge=1, le=101, description="wavelengths (Gauss-Hermite nodes) a finite line is rendered at (1-101)")
    spectrum: tuple[tuple[float, float], ...] = Field((), description="explicit [wavelength_nm, relative power] samples instead of a line; the frame's wavelength is then ignored")

    def samples(self, wavelength: float) -> list[tuple[float, float]]:
        """``(wavelength in m, weight)`` pairs, weights summing to 1."""
        if self.spectrum:
            lam = np.array([w for w, _ in self.spectrum], float) * 1e-9
            val = np.clip(np.array([v for _, v in self.spectrum], float), 0.0, None)
            if not val.sum() > 0:
                raise ValueError("source.spectrum: no positive power")
            keep = val > 0
            return list(zip(lam[keep].tolist(), (val[keep] / val.sum()).tolist()))
        if self.rel_width == 0 or self.n_nodes == 1:
            return [(float(wavelength), 1.0)]
        x, w = np.polynomial.hermite_e.hermegauss(self.n_nodes)
        w = w / w.sum()
        return [(float(wavelength) * (1.0 + self.rel_width * xi), float(wi)) for xi, wi in zip(x, w)]


class NDError(StrictModel):
    """True OD of each physical filter = nominal + U(-tol, tol); tolerances by nominal OD (seed §4.3)."""

    enabled: bool = Field(False, description="draw each physical filter's true OD as nominal + U(-tol, tol)")
    tolerances: tuple[tuple[float, float], ...] = Field(tuple(sorted(SEED_ND_TOLERANCES.items())), description="[nominal OD, tolerance] pairs (seed §4.3)")


#: Effect name -> the :class:`InstrumentConfig` field holding its switch and parameters.
EFFECTS: tuple[str, ...] = (
    "footprint",
    "stray_light",
    "ambient",
    "source_drift",
    "nd_error",
    "shot_noise",
    "nonlinearity",
    "dark",
    "black_level",
    "quantisation",
    "saturation",
)


class InstrumentConfig(StrictModel):
    """Every effect of the synthetic instrument: a switch (``enabled``) and its parameters.

    Top-level: ``exposures_s`` (s, strictly increasing; seed: 1, 10, 100,
    1000 ms), ``n_frames`` (frames averaged per exposure), ``adc_bits``
    (full scale ``2**adc_bits - 1`` counts), ``incident_flux_cps`` (counts/s
    reaching the array from the unattenuated beam; the default gives the
    seed's Phi_b = 9.828e9 sDC at OD 5.2), ``camera_seed`` (per-pixel maps)
    and ``write_counts_std`` (add the optional ``counts_std`` channel).
    See :data:`EFFECTS` and the module docstring.
    """

    exposures_s: tuple[float, ...] = Field((1e-3, 1e-2, 1e-1, 1.0), description="exposure times in seconds, strictly increasing (seed: 1, 10, 100, 1000 ms)")
    n_frames: int = Field(32, ge=1, description="frames averaged per exposure")
    adc_bits: int = Field(14, ge=1, le=24, description="ADC resolution in bits: full scale 2**adc_bits - 1 counts")
    incident_flux_cps: float = Field(SEED_BEAM_FLUX * 10**SEED_BEAM_OD, gt=0, description="counts per second reaching the array from the unattenuated beam")
    camera_seed: int = Field(0, description="seed of the camera's fixed per-pixel maps (gain, dark pattern)")
    write_counts_std: bool = Field(False, description="write the optional per-pixel counts_std channel")
    footprint: Footprint = Field(Footprint(), description="the [footprint] table: beam footprint (instrument function)")
    stray_light: StrayLight = Field(StrayLight(), description="the [stray_light] table: displaced ghost copies")
    ambient: Ambient = Field(Ambient(), description="the [ambient] table: room light")
    source_drift: SourceDrift = Field(SourceDrift(), description="the [source_drift] table: incident-flux drift between measurements")
    nd_error: NDError = Field(NDError(), description="the [nd_error] table: ND filter OD errors")
    shot_noise: ShotNoise = Field(ShotNoise(), description="the [shot_noise] table: photon noise")
    nonlinearity: NonLinearity = Field(NonLinearity(), description="the [nonlinearity] table: the camera's response curve")
    dark: Dark = Field(Dark(), description="the [dark] table: dark signal and noise")
    black_level: BlackLevel = Field(BlackLevel(), description="the [black_level] table: offset added by the camera")
    quantisation: Quantisation = Field(Quantisation(), description="the [quantisation] table: integer counts")
    saturation: Saturation = Field(Saturation(), description="the [saturation] table: clipping at full scale")
    source: Source = Field(Source(), description="the [source] table: the source's spectrum")

    @field_validator("exposures_s")
    @classmethod
    def _increasing(cls, v):
        if not v or any(t <= 0 for t in v) or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"exposures_s must be positive and strictly increasing (s), got {v}")
        return v

    @property
    def full_scale(self) -> float:
        return float(2**self.adc_bits - 1)

    def _check_names(self, names: Sequence[str]) -> None:
        unknown = [n for n in names if n not in EFFECTS]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")

    def with_effects(self, **enabled: bool) -> "InstrumentConfig":
        """A copy with effects switched on or off by name: ``cfg.with_effects(shot_noise=False)``."""
        self._check_names(list(enabled))
        return self.model_copy(
            update={k: getattr(self, k).model_copy(update={"enabled": bool(v)}) for k, v in enabled.items()}
        )

    def without(self, *names: str) -> "InstrumentConfig":
        """A copy with the named effects switched off."""
        return self.with_effects(**{n: False for n in names})

    def ideal(self) -> "InstrumentConfig":
        """A copy with every effect off except the footprint: the noiseless, linear, unclipped instrument."""
        return self.without(*[e for e in EFFECTS if e != "footprint"])

    def enabled_effects(self) -> tuple[str, ...]:
        return tuple(e for e in EFFECTS if getattr(self, e).enabled)

    def for_pixel_pitch(self, pixel_pitch: float, seed_pitch: float = 5.5e-6) -> "InstrumentConfig":
        """The same physical instrument seen by a camera of another pixel pitch (metres).

        The beam footprint and the stray-light offsets are fixed on the array
        in metres, so their sizes in pixels scale by ``seed_pitch / pixel_pitch``;
        the incident flux is unchanged (larger pixels collect more light, as
        their solid angles say).  Compare :meth:`coarse`, which also keeps
        per-pixel counts for fast tests.
        """
        if not pixel_pitch > 0:
            raise ValueError(f"for_pixel_pitch: pixel_pitch must be a positive length in metres, got {pixel_pitch!r}")
        k = pixel_pitch / seed_pitch
        return self.coarse(k).model_copy(update={"incident_flux_cps": self.incident_flux_cps})

    def coarse(self, k: float) -> "InstrumentConfig":
        """The seed instrument on a camera whose pixels are ``k`` times larger (``k x k`` binning).

        Per-pixel counts are kept: footprint width and stray-light offsets
        shrink by ``k`` and the incident flux by ``k**2`` (pixel solid angles
        grow by ``k**2``), so the 1 ms beam peak stays near 1e4 counts and the
        §4.2 noise-equivalent BRDF stays the seed's.  For small, fast tests;
        use with ``Detector.seed(shape=..., pixel_pitch=5.5e-6 * k, pixel_pitch_v=5.5e-6 * k)``.
        """
        if not k > 0:
            raise ValueError(f"coarse: k must be positive, got {k!r}")
        peaks = tuple((int(round(h / k)), int(round(v / k)), r) for h, v, r in self.stray_light.peaks)
        return self.model_copy(
            update={
                "incident_flux_cps": self.incident_flux_cps / k**2,
                "footprint": self.footprint.model_copy(update={"w_px": self.footprint.w_px / k}),
                "stray_light": self.stray_light.model_copy(update={"peaks": peaks}),
            }
        )


# --- deterministic forward operators (NumPy, float64 internally) ------------------------------------


def load_instrument_config(path: str | Path | None, camera_seed: int | None = None) -> InstrumentConfig:
    """Read an instrument TOML (``configs/instrument_seed.toml`` layout) into :class:`InstrumentConfig`.

    ``None`` gives the defaults (the seed instrument); ``camera_seed`` replaces the file's.
    Raises :class:`~brdfjax.config.ConfigError` naming the file and the dotted key.
    """
    source = str(path) if path is not None else "<default instrument>"
    data = read_toml(path, "instrument config") if path is not None else {}
    if camera_seed is not None:
        data["camera_seed"] = camera_seed
    return validate(InstrumentConfig, data, source)


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


# --- the camera's per-pixel maps -------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """Per-pixel properties of one synthetic CCD (from ``camera_seed``), float32 ``(n_v, n_h)`` maps or None.

    ``nonlinearity``: signed per-pixel gain error g (fraction);
    ``ambient``: ambient rate map, counts/s; ``dark_pattern``: standard-normal
    fixed pattern; ``nd_offsets``: true minus nominal OD of each physical
    filter, keyed by ``(nominal OD, occurrence in a stack)``.
    """

    shape: tuple[int, int]
    nonlinearity: np.ndarray | None
    ambient: np.ndarray | None
    dark_pattern: np.ndarray | None
    nd_offsets: Mapping[tuple[float, int], float]

    @classmethod
    def build(cls, config: InstrumentConfig, shape: tuple[int, int]) -> "Camera":
        rng = np.random.default_rng([config.camera_seed, 0x5EED])
        rows, cols = shape
        nl = amb = dark = None
        c = config.nonlinearity
        if c.enabled:
            k_shape, theta = (c.gain_mean / c.gain_std) ** 2, c.gain_std**2 / c.gain_mean
            cap = max(c.outlier_threshold - c.common_max, 0.0)
            mag = rng.gamma(k_shape, theta, size=shape)
            bad = mag > cap
            while np.any(bad):  # truncated gamma by rejection: the tail beyond the threshold is the outliers'
                mag[bad] = rng.gamma(k_shape, theta, size=int(bad.sum()))
                bad = mag > cap
            outlier = rng.random(shape) < c.outlier_fraction
            n_out = int(outlier.sum())
            if n_out and c.outlier_max > c.outlier_threshold > 0:
                total = np.exp(rng.uniform(np.log(c.outlier_threshold), np.log(c.outlier_max), n_out))
                mag[outlier] = total - c.common_max
            sign = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
            nl = (sign * mag).astype(np.float32)
        a = config.ambient
        if a.enabled:
            v = np.linspace(-1.0, 1.0, rows)[:, None]
            h = np.linspace(-1.0, 1.0, cols)[None, :]
            field = np.zeros(shape)
            for _ in range(4):  # a few smooth random waves across the array
                fx, fy = rng.uniform(0.2, 1.5, 2)
                ph1, ph2 = rng.uniform(0, 2 * np.pi, 2)
                field += np.cos(np.pi * fx * h + ph1) * np.cos(np.pi * fy * v + ph2)
            field = (field - field.mean()) / (field.std() or 1.0)
            pattern = np.clip(1.0 + a.nonuniformity * field, 0.0, None)
            amb = (a.rate_counts_per_s * pattern / pattern.mean()).astype(np.float32)
        if config.dark.enabled and config.dark.fixed_pattern_fraction > 0:
            dark = rng.standard_normal(shape).astype(np.float32)
        offsets: dict[tuple[float, int], float] = {}
        if config.nd_error.enabled:
            nd_rng = np.random.default_rng([config.camera_seed, 0x0D])
            for od, tol in sorted(config.nd_error.tolerances):
                for occ in range(4):
                    offsets[(round(od, 6), occ)] = float(nd_rng.uniform(-tol, tol))
        return cls((rows, cols), nl, amb, dark, offsets)

    def nonlinearity_map(self, config: InstrumentConfig) -> np.ndarray:
        """Each pixel's maximum response error relative to the array-average linear response, ``|g| + common_max``.

        This is the seed's ``dNL_s`` (§4.2, final method; Eq 92): what a
        characterised camera would hand the reduction as ``scatter_nonlinearity``.
        """
        if self.nonlinearity is None:
            return np.zeros(self.shape, np.float32)
        return (np.abs(self.nonlinearity) + np.float32(config.nonlinearity.common_max)).astype(np.float32)

    def true_od(self, nd_filters: str, config: InstrumentConfig) -> float:
        """The actual OD of a filter stack (nominal unless ``nd_error`` is on)."""
        filters = parse_nd_filters(nd_filters)
        if not config.nd_error.enabled:
            return float(sum(filters))
        seen: dict[float, int] = {}
        total = 0.0
        for od in filters:
            key = round(od, 6)
            occ = seen.get(key, 0)
            seen[key] = occ + 1
            if (key, occ) not in self.nd_offsets:
                known = sorted({k for k, _ in self.nd_offsets})
                raise ValueError(
                    f"nd_error: no tolerance for the {od:g} OD filter; known: {known}; add it to nd_error.tolerances"
                )
            total += od + self.nd_offsets[(key, occ)]
        return total


# --- the instrument -------------------------------------------------------------------------------


class SyntheticInstrument:
    """The synthetic scatterometer: a detector, an :class:`InstrumentConfig` and a seeded noise generator.

    ``detector`` is the true geometry (misalignment included); its array
    shape is the raw frames' shape.  ``nominal_detector`` (default: the same)
    is the geometry written to the files, i.e. what the reduction believes:
    a true camera that differs from it is an unknown misalignment.  ``seed`` seeds the noise Generator
    (NumPy ``default_rng``); measurements made in the same order give the
    same stacks.
    """

    def __init__(
        self,
        detector: Detector | None = None,
        config: InstrumentConfig | None = None,
        *,
        seed: int | None = 0,
        block_rows: int = 256,
        nominal_detector: Detector | None = None,
    ):
        self.detector = Detector.seed() if detector is None else detector
        self.nominal_detector = self.detector if nominal_detector is None else nominal_detector
        if self.nominal_detector.shape != self.detector.shape:
            raise ValueError(
                f"nominal_detector has shape {self.nominal_detector.shape}, the detector {self.detector.shape}; "
                "they must describe the same array"
            )
        self.config = InstrumentConfig() if config is None else config
        self.rng = np.random.default_rng(seed)
        self.block_rows = int(block_rows)
        self._camera: Camera | None = None

    @property
    def camera(self) -> Camera:
        if self._camera is None:
            self._camera = Camera.build(self.config, self.detector.shape)
        return self._camera

    @property
    def shape(self) -> tuple[int, int]:
        return self.detector.shape

    # -- attributes ------------------------------------------------------------------------------
    def raw_attrs(self, kind: str, nd_filters: str, frame: Frame, sample: str, *, theta_c: float | None = None) -> RawAttrs:
        """The raw file attributes of a ``kind`` measurement of ``frame`` through ``nd_filters``.

        The geometry is the frame header (:func:`brdfjax.io.header.geometry_attrs`)
        of the nominal detector, with the arm at ``theta_c`` (default: the
        true detector's, :meth:`~brdfjax.Detector.arm_angle`).
        """
        if theta_c is None:
            theta_c = self.detector.arm_angle(frame.theta_i)
        filters = parse_nd_filters(nd_filters)
        return RawAttrs(
            kind=kind,
            optical_density=round(float(sum(filters)), 10),
            nd_filters=nd_filters,
            **geometry_attrs(self.nominal_detector, frame, theta_c=theta_c),
            black_level=self.config.black_level.counts if self.config.black_level.enabled else 0.0,
            full_scale=self.config.full_scale,
            sample=sample,
            software="brdfjax.instrument.synthetic",
            extra={"synthetic_effects": ",".join(self.config.enabled_effects())},
        )

    # -- light -----------------------------------------------------------------------------------
    def incident_flux(self, nd_filters: str) -> float:
        """Incident flux reaching the array through the ND stack, counts/s (drift not included)."""
        return self.config.incident_flux_cps * 10.0 ** (-self.camera.true_od(nd_filters, self.config))

    def drift(self) -> float:
        """A source-drift factor for one measurement (1 when drift is off); draws from :attr:`rng`."""
        c = self.config.source_drift
        return float(1.0 + self.rng.normal(0.0, c.rel_std)) if c.enabled else 1.0

    def expected_brdf(self, brdf: np.ndarray) -> np.ndarray:
        """The BRDF frame a perfect reduction recovers: ``brdf`` convolved with the beam footprint (float32)."""
        brdf = np.asarray(brdf, dtype=np.float32)
        if not self.config.footprint.enabled:
            return brdf
        return convolve_footprint(brdf, footprint_kernel(self.config.footprint.w_px))

    def render_brdf(self, model: AbstractTerm, frame: Frame, *, precision: str = "float32") -> np.ndarray:
        """The model's BRDF on every pixel of the (true) detector, sr^-1, float32 ``(n_v, n_h)``.

        With a spectral source (``config.source``) the average over its wavelengths.
        """
        samples = self.config.source.samples(float(np.asarray(frame.wavelength)))
        if len(samples) == 1 and samples[0][0] == float(np.asarray(frame.wavelength)):
            return np.asarray(render(model, frame, self.detector, precision=precision), dtype=np.float32)
        out = np.zeros(self.shape, np.float64)
        for wl, w in samples:
            f = eqx.tree_at(lambda fr: fr.wavelength, frame, np.float64(wl))
            out += w * np.asarray(render(model, f, self.detector, precision=precision), dtype=np.float64)
        return out.astype(np.float32)

    def sample_flux(self, brdf: np.ndarray, frame: Frame, nd_filters: str) -> np.ndarray:
        """Light rate on every pixel of a sample measurement, counts/s, float32 (steps 1-3 of the module doc)."""
        brdf = np.asarray(brdf)
        if brdf.shape != self.shape:
            raise ValueError(f"BRDF frame has shape {brdf.shape}; the detector's array is {self.shape} (rows, cols)")
        geom = render_geometry(frame, self.detector)
        phi = scatter_flux_image(
            self.expected_brdf(brdf),
            np.asarray(geom["theta_s"]),
            np.asarray(geom["omega"]),
            self.incident_flux(nd_filters) * self.drift(),
        )
        del geom
        return self.add_stray_and_ambient(phi)

    def beam_flux(self, nd_filters: str) -> np.ndarray:
        """Light rate on every pixel of a beam-signature measurement (no sample, theta_c = 0), counts/s."""
        det0 = self.detector.at(0.0)
        n_h0, n_v0 = (float(np.asarray(x)) for x in det0.pixel_of(0.0, 0.0))
        h_min, _, v_min, _ = self.detector.index_range
        flux = self.incident_flux(nd_filters) * self.drift()
        centre = (n_v0 - v_min, n_h0 - h_min)
        if self.config.footprint.enabled:
            phi = beam_flux_image(self.shape, centre, self.config.footprint.w_px, flux)
        else:
            phi = np.zeros(self.shape, np.float32)
            r, c = int(round(centre[0])), int(round(centre[1]))
            if 0 <= r < self.shape[0] and 0 <= c < self.shape[1]:
                phi[r, c] = flux
        return self.add_stray_and_ambient(phi)

    def add_stray_and_ambient(self, phi: np.ndarray) -> np.ndarray:
        """``phi`` (counts/s on every pixel) plus the stray light and the ambient light that are enabled."""
        if self.config.stray_light.enabled:
            main = phi.copy()
            for dh, dv, log_ratio in self.config.stray_light.peaks:
                shift_add(phi, main, dv, dh, 10.0**log_ratio)
            del main
        if self.config.ambient.enabled:
            phi += self.camera.ambient
        return phi

    # -- exposure --------------------------------------------------------------------------------
    def expose(self, flux: np.ndarray, exposure_s: float, *, light: bool = True) -> Exposure:
        """One averaged exposure of a light-rate image (counts/s): steps 5 of the module doc, float32 out."""
        cfg = self.config
        cam = self.camera
        n = cfg.n_frames
        fs = cfg.full_scale
        t = float(exposure_s)
        counts = np.empty(self.shape, np.float32)
        std = np.empty(self.shape, np.float32) if cfg.write_counts_std else None
        sigma_lc = float(lens_cap_std(cfg.dark, t)) if cfg.dark.enabled else 0.0
        fpn = cfg.dark.fixed_pattern_fraction if cfg.dark.enabled else 0.0
        temporal_frame = sigma_lc * math.sqrt((1.0 - fpn) * cfg.dark.n_ref_frames)  # per-frame temporal std
        gain = cfg.shot_noise.gain_e_per_count
        nl = cfg.nonlinearity
        for r0 in range(0, self.shape[0], self.block_rows):
            r1 = min(self.shape[0], r0 + self.block_rows)
            s = flux[r0:r1].astype(np.float64) * t if light else np.zeros((r1 - r0, self.shape[1]))
            if cfg.saturation.enabled:
                s = np.minimum(s, 4.0 * fs)  # saturated either way; keeps Poisson draws cheap
            if cfg.shot_noise.enabled:
                x = self.rng.poisson(s * (gain * n)) / (gain * n)
            else:
                x = s.copy()
            if nl.enabled and cam.nonlinearity is not None:
                g = cam.nonlinearity[r0:r1].astype(np.float64)
                x *= 1.0 + g + nl.common_max * (2.0 * np.clip(x / fs, 0.0, 1.0) - 1.0)
            if cfg.dark.enabled:
                x += cfg.dark.rate_counts_per_s * t
                x += (temporal_frame / math.sqrt(n)) * self.rng.standard_normal(x.shape)
                if cam.dark_pattern is not None:
                    x += math.sqrt(fpn) * sigma_lc * cam.dark_pattern[r0:r1]
            if cfg.black_level.enabled:
                x += cfg.black_level.counts
            if cfg.quantisation.enabled:
                if n == 1 or cfg.quantisation.round_average:
                    x = np.round(x)
                else:
                    x = np.round(n * x + math.sqrt((n - 1) / 12.0) * self.rng.standard_normal(x.shape)) / n
            saturated = np.zeros(x.shape, bool)
            if cfg.saturation.enabled:
                saturated = x >= fs
                np.clip(x, 0.0, fs, out=x)
            counts[r0:r1] = x
            if std is not None:
                var = temporal_frame**2 + (1.0 / 12.0 if cfg.quantisation.enabled else 0.0)
                if cfg.shot_noise.enabled:
                    var = var + s / gain
                chi = 1.0
                if n > 1:  # sqrt(chi^2_(n-1) / (n-1)) by the Wilson-Hilferty approximation (cheaper than gamma draws)
                    a = 2.0 / (9.0 * (n - 1))
                    chi = np.maximum(1.0 - a + math.sqrt(a) * self.rng.standard_normal(x.shape), 0.0) ** 1.5
                # A 32-frame std is itself uncertain by ~13 %: float16 precision (11 bits) lets ZIP compress it.
                std[r0:r1] = np.where(saturated, 0.0, np.sqrt(var) * chi).astype(np.float16)
        return Exposure(t, n, counts, std)

    def stack(self, flux: np.ndarray | None, attrs: RawAttrs) -> RawStack:
        """A raw stack with ``attrs``: one :meth:`expose` of ``flux`` (counts/s; None: no light) per exposure time."""
        exposures = []
        for t in self.config.exposures_s:
            exposures.append(self.expose(flux, t, light=flux is not None))
        return RawStack(attrs, tuple(exposures))

    # -- measurements ----------------------------------------------------------------------------
    def measure_sample(
        self,
        brdf: AbstractTerm | np.ndarray,
        frame: Frame,
        nd_filters: str,
        *,
        sample: str = "",
    ) -> RawStack:
        """A sample measurement centred on the specular peak (``theta_c`` = the detector's, or ``theta_i``).

        ``brdf`` is a brdfjax model (rendered on the true detector) or a BRDF
        frame (sr^-1, the detector's array shape).
        """
        if isinstance(brdf, AbstractTerm):
            brdf = self.render_brdf(brdf, frame)
        flux = self.sample_flux(brdf, frame, nd_filters)
        return self.stack(flux, self.raw_attrs("sample", nd_filters, frame, sample))

    def measure_beam(self, nd_filters: str = SEED_BEAM_FILTERS, *, wavelength: float = 632.8e-9) -> RawStack:
        """A beam signature: the focused beam straight onto the array, no sample, ``theta_c = 0``."""
        frame = Frame(0.0, 0.0, wavelength)
        flux = self.beam_flux(nd_filters)
        return self.stack(flux, self.raw_attrs("beam", nd_filters, frame, "beam signature", theta_c=0.0))

    def measure_background(self, like: RawAttrs) -> RawStack:
        """Background for a measurement: laser on but blocked (ambient light only), same geometry attributes."""
        flux = np.zeros(self.shape, np.float32)
        if self.config.ambient.enabled:
            flux += self.camera.ambient
        attrs = dataclasses.replace(like, kind="background", sample=f"background for: {like.sample}")
        return self.stack(flux, attrs)

    def measure_dark(self, like: RawAttrs) -> RawStack:
        """A lens-cap (dark) stack: no light at all."""
        attrs = dataclasses.replace(like, kind="dark", sample="lens cap")
        return self.stack(None, attrs)

    def measure_set(
        self,
        folder: str | Path,
        model: AbstractTerm,
        frames: Mapping[str, Frame],
        *,
        nd_filters: str | None = None,
        beam_filters: str | None = None,
        wavelength: float = 632.8e-9,
        calibration: Calibration | None = None,
        log: Callable[[str], None] | None = None,
        progress: Callable[[int, int, str], None] | None = None,
    ) -> Path:
        """Measure ``model`` at every ``frames[name]`` and write the measurement set: the one synthetic pipeline.

        Each sample's BRDF is rendered (:meth:`render_brdf`) and its ND stack
        chosen by the seed's rule (:func:`~brdfjax.instrument.nd.choose_nd_filters`)
        unless ``nd_filters`` fixes it; the beam's stack likewise unless
        ``beam_filters`` is given.  ``calibration`` defaults to the seed's ND
        tolerances plus the inferred 3.0 OD one; ``log`` receives one line per
        choice; ``progress(done, total, what)`` is called per step (each
        sample rendered, each file written).  Returns the manifest path (:meth:`write_set`).
        """
        total = 3 * len(frames) + 2
        tick = progress or (lambda done, total, what: None)
        samples = {}
        for name, frame in frames.items():
            brdf = self.render_brdf(model, frame)
            nd = nd_filters if nd_filters is not None else choose_nd_filters(
                lambda stack, b=brdf, f=frame: self.sample_flux(b, f, stack), self
            )
            samples[name] = (brdf, frame, nd)
            tick(len(samples), total, f"rendered {name}")
            if log is not None:
                log(f"{name}: sample ND filters '{nd or 'none'}'")
        if beam_filters is None:
            beam_filters = choose_nd_filters(self.beam_flux, self)
            if log is not None:
                log(f"beam signature: ND filters '{beam_filters}'")
        if calibration is None:
            calibration = Calibration(nd_tolerances={3.0: ND_3_TOLERANCE})
        return self.write_set(
            folder, samples, beam_filters=beam_filters, wavelength=wavelength, calibration=calibration,
            progress=None if progress is None else (lambda d, t, w: progress(len(frames) + d, total, w)),
        )

    def write_set(
        self,
        folder: str | Path,
        samples: Mapping[str, tuple[AbstractTerm | np.ndarray, Frame, str]],
        *,
        beam_filters: str = SEED_BEAM_FILTERS,
        wavelength: float = 632.8e-9,
        calibration: Calibration | None = None,
        progress: Callable[[int, int, str], None] | None = None,
    ) -> Path:
        """Write a measurement set (beam + background, each sample + background, ``manifest.toml``).

        ``samples`` maps a sample name (file stem) to ``(model or BRDF frame,
        Frame, nd_filters)``; ``calibration`` goes into the manifest's
        ``[calibration]`` table.  Files are written one at a time
        (atomically), ``progress(done, total, file name)`` after each; returns the manifest path.
        """
        tick = progress or (lambda done, total, what: None)
        n_files = 2 + 2 * len(samples)
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        beam = self.measure_beam(beam_filters, wavelength=wavelength)
        write_raw_exr(folder / "beam.exr", beam.attrs, beam.exposures)
        tick(1, n_files, "beam.exr")
        bg = self.measure_background(beam.attrs)
        del beam
        write_raw_exr(folder / "beam_background.exr", bg.attrs, bg.exposures)
        tick(2, n_files, "beam_background.exr")
        del bg
        entries = []
        for name, (brdf, frame, nd) in samples.items():
            st = self.measure_sample(brdf, frame, nd, sample=name)
            write_raw_exr(folder / f"{name}.exr", st.attrs, st.exposures)
            tick(3 + 2 * len(entries), n_files, f"{name}.exr")
            attrs = st.attrs
            del st
            bg = self.measure_background(attrs)
            write_raw_exr(folder / f"{name}_background.exr", bg.attrs, bg.exposures)
            tick(4 + 2 * len(entries), n_files, f"{name}_background.exr")
            del bg
            entries.append((name, f"{name}.exr", f"{name}_background.exr"))
        return write_manifest(folder / "manifest.toml", ("beam.exr", "beam_background.exr"), entries, calibration)

