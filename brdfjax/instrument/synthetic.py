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
from collections.abc import Callable, Mapping
from pathlib import Path

import equinox as eqx
import numpy as np

from ..core.detector import Detector
from ..core.render import Conditions, render, render_geometry
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
from .camera import Camera
from .config import (
    EFFECTS,
    SEED_BEAM_FILTERS,
    SEED_BEAM_FLUX,
    SEED_BEAM_OD,
    Ambient,
    BlackLevel,
    Dark,
    Footprint,
    InstrumentConfig,
    NDError,
    NonLinearity,
    Quantisation,
    Saturation,
    ShotNoise,
    Source,
    SourceDrift,
    StrayLight,
    load_instrument_config,
)
from .nd import ND_3_TOLERANCE, choose_nd_filters, parse_nd_filters
from .optics import (
    beam_flux_image,
    convolve_footprint,
    footprint_kernel,
    lens_cap_std,
    scatter_flux_image,
    shift_add,
)

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
    def raw_attrs(self, kind: str, nd_filters: str, frame: Conditions, sample: str, *, theta_c: float | None = None) -> RawAttrs:
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

    def render_brdf(self, model: AbstractTerm, frame: Conditions, *, precision: str = "float32") -> np.ndarray:
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

    def sample_flux(self, brdf: np.ndarray, frame: Conditions, nd_filters: str) -> np.ndarray:
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
        frame: Conditions,
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
        frame = Conditions(0.0, 0.0, wavelength)
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
        frames: Mapping[str, Conditions],
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
        samples: Mapping[str, tuple[AbstractTerm | np.ndarray, Conditions, str]],
        *,
        beam_filters: str = SEED_BEAM_FILTERS,
        wavelength: float = 632.8e-9,
        calibration: Calibration | None = None,
        progress: Callable[[int, int, str], None] | None = None,
    ) -> Path:
        """Write a measurement set (beam + background, each sample + background, ``manifest.toml``).

        ``samples`` maps a sample name (file stem) to ``(model or BRDF frame,
        Conditions, nd_filters)``; ``calibration`` goes into the manifest's
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

