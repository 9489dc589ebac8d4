"""Sim-to-real gap diagnosis: where a model misses the data, which unmodelled effect causes it, how far it shrinks.

``diagnose(likelihood, effects=...)`` (the likelihood from
:func:`brdfjax.fit.prepare`, the one a fit and a posterior use) fits the base model, finds the
significant residual structures and their zones, refits with every candidate
effect of the library, ranks them by BIC and builds the explanation path by
greedy forward selection; :meth:`Diagnosis.write` writes ``diagnosis.json``,
``report.md`` and ``report.html``.  ``brdfjax diagnose CONFIG --out DIR``
runs it from a fit config with a ``[diagnose]`` table.

Where to find what (each module imports only those above it):

- :mod:`~brdfjax.diagnose.zones`: WHERE: significant residual regions and their zones;
- :mod:`~brdfjax.diagnose.context`: the base fit as the effects see it
  (:class:`Context`, :func:`build_context`, :func:`warm_params`,
  :func:`gap_measures`);
- :mod:`~brdfjax.diagnose.effects`: WHICH: the effect library
  (:data:`EFFECT_LIBRARY`); the interface and the score-test engine in
  ``effects/base.py``, an effect in ``effects/model.py`` (surface side) or
  ``effects/instrument.py`` (measurement side), the terms they add in
  ``effects/terms.py``, a generator of synthetic truth with an effect in
  ``effects/generators.py`` (:class:`Scenario`, :func:`inject`,
  :func:`base_scenario`, :func:`synthesize`);
- :mod:`~brdfjax.diagnose.report` and :mod:`~brdfjax.diagnose.results`: the
  results (:class:`Diagnosis`, :class:`Candidate`, :class:`Step`) and their
  Markdown/HTML reports;
- :mod:`~brdfjax.diagnose.refits`: a fit state, a candidate's refit (retried
  from a second start), the refits from fresh starts, taking an effect out,
  the held-out and the truth's gaps, the ranking;
- :mod:`~brdfjax.diagnose.admission`: the admission rules (an effect's own
  parameters on a bound or undetermined, its own terms dead or narrower than
  the sampling, a term driven to zero, and where asked a weak signature);
- :mod:`~brdfjax.diagnose.search`: the search over sets of effects (every
  candidate refitted at every step, pairs, generic against specific, backward
  elimination with the same threshold), generic over a ``SearchProblem``;
- :mod:`~brdfjax.diagnose.engine`: :func:`diagnose` itself and the frame/table
  problem (``FrameProblem``) the search runs on;
- :mod:`~brdfjax.diagnose.model_config`: the final model as a fit config;
- :mod:`~brdfjax.diagnose.config`: the ``[diagnose]`` table and the run of ``brdfjax diagnose``.
"""

from __future__ import annotations

from .api import diagnose as diagnose
from .context import (
    Context as Context,
    build_context as build_context,
    gap_measures as gap_measures,
    residual_maps as residual_maps,
    warm_params as warm_params,
)
from .effects import (
    EFFECT_LIBRARY as EFFECT_LIBRARY,
    Effect as Effect,
    Extension as Extension,
    Scenario as Scenario,
    Signature as Signature,
    base_scenario as base_scenario,
    inject as inject,
    synthesize as synthesize,
)
from .engine import DiagnoseInputError as DiagnoseInputError
from .results import Candidate as Candidate, Diagnosis as Diagnosis, Step as Step
from .zones import Region as Region, find_regions as find_regions, specular_coordinates as specular_coordinates
