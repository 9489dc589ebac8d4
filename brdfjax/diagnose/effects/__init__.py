"""The library of candidate unmodelled effects, on both sides of the sim-to-real gap.

Diagnosis side (used by :func:`brdfjax.diagnose.diagnose`): every
:class:`Effect` is a named, documented extension of a base model (or of the
data's instrument function) with

- :meth:`Effect.present_in` -- the base model already has it;
- :meth:`Effect.identifiable` -- ``None``, or the reason the data cannot tell
  it apart from the base's free parameters (e.g. ``flux_scale`` when every
  term's weight is free);
- :meth:`Effect.signature` -- a residual statistic computed from the base
  fit's normalised residual ``r = (ln d - ln f) / sigma`` alone (no refit),
  reported as ``score`` in sigma-like units (the two-sided normal quantile of
  its p-value under pure noise, look-elsewhere included; ``> 3``: present);
- :meth:`Effect.extend` -- the base model plus the effect, warm-started at
  the base fit's optimum, with the effect's new parameters initialised from
  the residual (:class:`Extension`).

Generator side (synthetic truth with any effect, :mod:`.generators`): :func:`base_scenario`
draws a plausible single-peak base (random theta_i in 20-60 deg, phi_ref in
0-180 deg), :func:`inject` adds an effect with random plausible parameters
to a :class:`Scenario`, and :func:`synthesize` produces the measured frames
(:class:`~brdfjax.fit.FrameData`) or goniometer tables.

Effects (see each class's ``doc``), keyed by name in :data:`EFFECT_LIBRARY`:
model side (:mod:`.model`) ``offset_normal_peak``, ``diffraction``,
``lambertian``, ``anisotropic_roughness``, ``distribution_shape``; tables (:mod:`.tables`)
``second_lobe``, ``shadowing``;
instrument side (:mod:`.instrument`) ``instrument_function``,
``misalignment``, ``flux_scale``, ``pixel_nonlinearity``,
``spectral_bandwidth``, ``stray_light``, ``angular_sampling``.

Modules: :mod:`.base` (the interface, the statistics and the score-test
engine the effects share), :mod:`.model`, :mod:`.instrument`,
:mod:`.terms` (the terms and the instrument-response wrapper the effects
add: ``Oriented``, ``SpectralDiffraction``, ``InstrumentResponse``) and
:mod:`.generators`.  A new effect is a subclass of :class:`Effect` in
``model.py`` or ``instrument.py``, listed in :data:`EFFECT_LIBRARY`, with a
generator in ``generators.GENERATORS``.
"""

from __future__ import annotations

from .base import Context as Context, Effect as Effect, Extension as Extension, Signature as Signature
from .generators import (
    EXCLUSIVE as EXCLUSIVE,
    GENERATORS as GENERATORS,
    REFERENCE_EFFECTS as REFERENCE_EFFECTS,
    Scenario as Scenario,
    base_scenario as base_scenario,
    inject as inject,
    reference_frames as reference_frames,
    synthesize as synthesize,
    table_scenario as table_scenario,
    wide_table_scenario as wide_table_scenario,
)
from .instrument import (
    AngularSamplingEffect as AngularSamplingEffect,
    FluxScaleEffect as FluxScaleEffect,
    InstrumentFunctionEffect as InstrumentFunctionEffect,
    MisalignmentEffect as MisalignmentEffect,
    PixelNonlinearityEffect as PixelNonlinearityEffect,
    SpectralBandwidthEffect as SpectralBandwidthEffect,
    StrayLightEffect as StrayLightEffect,
)
from .model import (
    AnisotropicRoughnessEffect as AnisotropicRoughnessEffect,
    DiffractionEffect as DiffractionEffect,
    DistributionShapeEffect as DistributionShapeEffect,
    LambertianEffect as LambertianEffect,
    OffsetNormalPeakEffect as OffsetNormalPeakEffect,
)
from .tables import SecondLobeEffect as SecondLobeEffect, ShadowingEffect as ShadowingEffect, tables_only as tables_only
from .terms import (
    InstrumentResponse as InstrumentResponse,
    Oriented as Oriented,
    SpectralDiffraction as SpectralDiffraction,
    camera_params as camera_params,
    response_features as response_features,
)

__all__ = [
    "Extension",
    "Effect",
    "Context",
    "Signature",
    "EFFECT_LIBRARY",
    "Scenario",
    "base_scenario",
    "table_scenario",
    "wide_table_scenario",
    "inject",
    "synthesize",
    "GENERATORS",
    "EXCLUSIVE",
    "reference_frames",
    "REFERENCE_EFFECTS",
]

#: The candidate effects, by name, in the order the engine tries them.
EFFECT_LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        OffsetNormalPeakEffect(),
        DiffractionEffect(),
        InstrumentFunctionEffect(),
        LambertianEffect(),
        AnisotropicRoughnessEffect(),
        DistributionShapeEffect(),
        SecondLobeEffect(),
        ShadowingEffect(),
        MisalignmentEffect(),
        FluxScaleEffect(),
        PixelNonlinearityEffect(),
        SpectralBandwidthEffect(),
        StrayLightEffect(),
        AngularSamplingEffect(),
    )
}
