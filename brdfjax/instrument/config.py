"""The synthetic instrument's config: every effect of the seed's camera and source, each with its switch and
parameters (``configs/instrument_seed.toml``), and the seed's beam constants.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from ..config.base import StrictModel, read_toml, validate
from ..runtime.choices import check_choices
from .nd import SEED_ND_TOLERANCES

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
        check_choices("effect", names, EFFECTS)

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
