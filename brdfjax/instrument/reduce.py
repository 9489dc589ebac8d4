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
from ..io import ExrFrame, frame_attrs, read_frame_exr, write_frame_exr
from ..io.raw import (
    Manifest,
    RawAttrs,
    RawFormatError,
    RawStack,
    read_manifest,
    read_raw_exr,
)
from .figures import plot_merge_comparison
from .nd import SEED_ND_TOLERANCES
from .radiometry import brdf_from_flux, incident_flux
from .stitch import (
    MERGES,
    SEED_CURVE_RESIDUAL,
    SEED_GAIN,
    SYNTHETIC_NONLINEARITY_CURVE,
    NonlinearityCurve,
    ReductionError,
    Stitched,
    _check_pair,
    _curve,
    stitch,
    stitch_raw,
    stitch_replacement,
    stitch_weighted,
)
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


