"""TOML configs of every brdfjax command, parsed at the edge into frozen, validated objects.

Every config table is a :class:`StrictModel` (:mod:`brdfjax.config.base`):
frozen, unknown keys are errors, no type coercion, no inf/NaN unless a field
says so.  Every file is read by :func:`read_toml` and validated by
:func:`validate`, so every message names the file and the dotted key
(``frames[1].theta_i_deg``; an unknown key lists the allowed ones,
:func:`describe_validation_error`), raised as :class:`ConfigError` (an
:class:`~brdfjax.runtime.errors.InputError`: the commands exit 2 with its message).
Choices (losses, solvers, merge schemes, ...) are checked against the registry
that owns them (:func:`check_choice`).

Where a newcomer finds each config key:

=====================================  ==================================================  =====================================
keys                                   class                                               file
=====================================  ==================================================  =====================================
``[model]``, ``[model.params]``        :class:`ModelConfig`                                ``brdfjax/config/model.py``
``[model.terms.<name>]``               :class:`TermConfig`                                 ``brdfjax/config/model.py``
simulate: ``precision``                :class:`SimulateConfig`                             ``brdfjax/config/simulate.py``
simulate: ``[detector]``, ``[grid]``   :class:`DetectorConfig`, :class:`GridConfig`        ``brdfjax/config/simulate.py``
simulate: ``[[frames]]``               :class:`FrameConfig`                                ``brdfjax/config/simulate.py``
fit: top level, ``[params]``           ``FitConfig`` (``_resolve_params``)                 ``brdfjax/fit/config.py``
fit: ``[data]``, ``[data.reduce]``     ``FitDataConfig``, ``ReduceConfig``                 ``brdfjax/fit/config.py``
fit: ``[[data.tables]]``               ``TableConfig``                                     ``brdfjax/fit/config.py``
fit: ``[data.synthetic]``              ``SyntheticConfig``                                 ``brdfjax/fit/config.py``
fit: ``[fit]``, ``[output]``           ``FitSection``, ``OutputConfig``                    ``brdfjax/fit/config.py``
sample: ``[sample]``, ``.priors``      ``SampleSection``, ``PriorConfig``                  ``brdfjax/sample/config.py``
diagnose: ``[diagnose]``               ``DiagnoseSection``                                 ``brdfjax/diagnose/config.py``
capture: every table                   ``CaptureConfig`` and its sections                  ``brdfjax/devices/config.py``
instrument TOML (synthetic camera)     ``InstrumentConfig`` (``load_instrument_config``)   ``brdfjax/instrument/config.py``
=====================================  ==================================================  =====================================

The simulate config's layout is in :mod:`brdfjax.config.simulate`, the fit
config's in :mod:`brdfjax.fit.config`.
"""

from __future__ import annotations

from .base import (
    ConfigError as ConfigError,
    StrictModel as StrictModel,
    check_choice as check_choice,
    describe_validation_error as describe_validation_error,
    quoted_choices as quoted_choices,
    read_toml as read_toml,
    unknown_key_message as unknown_key_message,
    validate as validate,
)
from .model import (
    ModelConfig as ModelConfig,
    TermConfig as TermConfig,
    build_model as build_model,
    build_preset as build_preset,
    describe_model as describe_model,
    parameter_keys as parameter_keys,
    term_from_config as term_from_config,
)
from .simulate import (
    DETECTOR_PRESETS as DETECTOR_PRESETS,
    DetectorConfig as DetectorConfig,
    FrameConfig as FrameConfig,
    GridConfig as GridConfig,
    SimulateConfig as SimulateConfig,
    default_config_path as default_config_path,
    load_simulate_config as load_simulate_config,
    parse_simulate_config as parse_simulate_config,
)

__all__ = [
    "ConfigError",
    "StrictModel",
    "read_toml",
    "validate",
    "describe_validation_error",
    "check_choice",
    "quoted_choices",
    "unknown_key_message",
    "DetectorConfig",
    "GridConfig",
    "TermConfig",
    "ModelConfig",
    "FrameConfig",
    "SimulateConfig",
    "DETECTOR_PRESETS",
    "build_model",
    "build_preset",
    "term_from_config",
    "describe_model",
    "load_simulate_config",
    "parse_simulate_config",
    "default_config_path",
    "parameter_keys",
]
