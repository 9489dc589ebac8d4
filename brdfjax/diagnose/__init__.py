"""Sim-to-real gap diagnosis: where a model misses the data, which unmodelled effect causes it, how far it shrinks.

``diagnose(base_model, blocks, params)`` (:mod:`brdfjax.diagnose.engine`) fits
the base model, finds the significant residual structures and their zones
(:mod:`brdfjax.diagnose.zones`), refits with every candidate effect of the
library (:mod:`brdfjax.diagnose.effects`), ranks them by BIC and builds the
explanation path by greedy forward selection; :meth:`Diagnosis.write` writes
``diagnosis.json``, ``report.md`` and ``report.html``.  ``brdfjax diagnose
CONFIG --out DIR`` (:mod:`brdfjax.diagnose.cli`) runs it from a fit config
with a ``[diagnose]`` table.

The effect library's names (``EFFECTS``, ``Effect``, ``Context``, ...) are
re-exported lazily, so that the engine imports without it.
"""

from __future__ import annotations

from typing import Any

from .engine import (
    Candidate as Candidate,
    DiagnoseInputError as DiagnoseInputError,
    Diagnosis as Diagnosis,
    Step as Step,
    build_context as build_context,
    diagnose as diagnose,
    gap_measures as gap_measures,
    residual_maps as residual_maps,
    warm_params as warm_params,
)
from .zones import Region as Region, find_regions as find_regions, specular_coordinates as specular_coordinates

_EFFECTS_NAMES = (
    "EFFECTS", "Effect", "Extension", "Context", "Signature", "Scenario", "inject", "base_scenario", "synthesize",
)


def __getattr__(name: str) -> Any:
    if name in _EFFECTS_NAMES:
        from . import effects

        return getattr(effects, name)
    raise AttributeError(f"module 'brdfjax.diagnose' has no attribute '{name}'")
