"""``diagnose(likelihood, effects=...)``: the public entry of the gap diagnosis.

The likelihood (:func:`brdfjax.fit.prepare`) is the one a fit and a posterior of the same data use;
the diagnosis refits it with each candidate effect (:mod:`brdfjax.diagnose.engine`).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

from ..core.terms import Model
from ..fit import FrameData, Likelihood, TableData
from .engine import DiagnoseInputError, diagnose as _diagnose
from .results import Diagnosis

__all__ = ["diagnose"]


def diagnose(
    likelihood: Likelihood | Model,
    blocks: FrameData | TableData | Sequence[FrameData | TableData] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    effects: Sequence[str] | None = None,
    heldout: Sequence[FrameData | TableData] | None = None,
    heldout_blocks: Sequence[FrameData | TableData] | None = None,
    fit_kwargs: Mapping[str, Any] | None = None,
    **options: Any,
) -> Diagnosis:
    """Diagnose the gap between a likelihood's model and its data.

    ``diagnose(likelihood, effects=[...], heldout=[...], **options)``: ``likelihood`` from
    :func:`brdfjax.fit.prepare` (its model is the base, its params the base fit's spec, its options every
    refit's); ``effects``: candidate names (default: the whole library); ``heldout``: frames or tables
    predicted, never fitted; ``options``: the search's settings (``bic_threshold``, ``max_steps``,
    ``pair_top``, ``fresh_top``, ``threshold``, ``smooth``, ``presence``, ``noise_stop``, ``library``,
    ``progress``, ``workers``; see :func:`brdfjax.diagnose.engine.diagnose`).
    ``diagnose(base_model, blocks, params, fit_kwargs=...)`` is the older spelling (``fit_kwargs``
    deprecated).
    """
    if heldout is not None and heldout_blocks is not None:
        raise DiagnoseInputError("give the held-out blocks once: heldout=...")
    held = heldout if heldout is not None else heldout_blocks
    if isinstance(likelihood, Likelihood):
        if blocks is not None or params is not None or fit_kwargs is not None:
            raise DiagnoseInputError("diagnose(likelihood): blocks, params and fit_kwargs are the likelihood's; set "
                                     "them with brdfjax.fit.prepare(...) or likelihood.replace(...)")
        return _diagnose(likelihood.model, list(likelihood.blocks), dict(likelihood.params), effects=effects,
                         heldout_blocks=held, fit_kwargs=likelihood.options(), **options)
    if blocks is None or params is None:
        raise DiagnoseInputError("diagnose(base_model, blocks, params): blocks or params missing (or pass a "
                                 "Likelihood from brdfjax.fit.prepare)")
    if fit_kwargs is not None:
        warnings.warn("diagnose(..., fit_kwargs=...) is deprecated: build the likelihood with brdfjax.fit.prepare("
                      "model, data, params, **options) and call diagnose(likelihood, ...)", DeprecationWarning,
                      stacklevel=2)
    return _diagnose(likelihood, blocks, params, effects=effects, heldout_blocks=held, fit_kwargs=fit_kwargs, **options)
