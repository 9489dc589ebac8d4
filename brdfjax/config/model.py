"""The ``[model]`` table shared by every command (simulate, fit, sample, diagnose, capture).

:class:`ModelConfig` is a preset with overrides (``preset = "solar_cell"``,
``[model.params]``) or named terms (``[model.terms.<name>]``, a
:class:`TermConfig` each); :func:`build_model` turns it into a
:class:`~brdfjax.core.terms.Model`.  Parameter keys carry the unit of the stored
value (:func:`parameter_keys`: ``<name>_deg`` for angles, ``<name>_m`` for
lengths), and every problem names the dotted key (``model.terms.spec.params.m``).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from ..core import registry
from ..core.shadowing import SHADOWING
from ..core.terms import (
    FRESNELS,
    NORMALISATIONS,
    AbstractTerm,
    Diffraction,
    Lobe,
    Model,
    MultiLobeSpecular,
    OffsetNormal,
    Oriented,
    Specular,
)
from .base import ConfigError, StrictModel, raise_unknown, unknown_key_message

# the microfacet terms' string options and their allowed values (one validator checks all three)
_TERM_OPTIONS = {"shadowing": SHADOWING, "normalisation": NORMALISATIONS, "fresnel": FRESNELS}

__all__ = [
    "TermConfig",
    "ModelConfig",
    "build_model",
    "build_preset",
    "term_from_config",
    "describe_model",
    "parameter_keys",
]

#: Config-key suffix and scale to stored units, by the unit a parameter is stored in.
_UNIT_KEYS: dict[str, tuple[str, float]] = {
    "rad": ("_deg", np.pi / 180.0),
    "m": ("_m", 1.0),
    "px": ("_px", 1.0),
}


def _flatten_params(v: Any) -> Any:
    """``{center = {k = 0.1}}`` (a TOML dotted key) -> ``{"center.k": 0.1}``."""
    if not isinstance(v, Mapping):
        return v
    out: dict[str, Any] = {}
    for k, x in v.items():
        if isinstance(x, Mapping):
            for k2, x2 in _flatten_params(x).items():
                out[f"{k}.{k2}"] = x2
        else:
            out[k] = x
    return out




class TermConfig(StrictModel):
    """``[model.terms.<name>]``: one term built from the registry."""

    kind: str = Field(description=f"a term kind; known: {', '.join(sorted(registry.TERMS))}")
    distribution: str | None = Field(
        None, description=f"microfacet distribution of a specular kind; known: {', '.join(sorted(registry.DISTRIBUTIONS))}"
    )
    params: dict[str, float] = Field(
        default_factory=dict,
        description="parameter values: angles as <name>_deg, lengths as <name>_m, others as <name>",
    )
    grating_factor: bool | None = Field(
        None, description="diffraction only: keep the seed's 2 cos(theta_i) factor (default true)"
    )
    distance_m: float | None = Field(
        None, gt=0, description="diffraction only: nominal distance in the Gaussian, metres (default 0.325)"
    )
    lobes: dict[str, str] | None = Field(
        None, description="multi_lobe only: lobe name -> distribution, e.g. {spike = 'beckmann', halo = 'ggx'}"
    )
    l1: int | None = Field(
        None, description="binomial only: the lowest Gaussian index l1 (an integer, default 0): d^(i + l1) in the i-th c term"
    )
    shadowing: str | None = Field(
        None, description=f"microfacet kinds only: masking-shadowing, one of {', '.join(SHADOWING)} (default smith: "
        "height-correlated Smith G2; none: the seed's G = 1)"
    )
    normalisation: str | None = Field(
        None,
        description=f"microfacet kinds only: one of {', '.join(NORMALISATIONS)} (default torrance_sparrow: "
        "1 / (4 cos ti cos ts), Walter et al. 2007; seed: the seed's Eq 70, 1 / (2 (cos ti + cos ts)^2))",
    )
    fresnel: str | None = Field(
        None,
        description=f"microfacet kinds only: one of {', '.join(FRESNELS)} (default microfacet: F_s + F_p at the "
        "microfacet angle, Cook-Torrance / Walter; q_factor: the seed's Eq 69 Q at the macro angles)",
    )
    oriented: bool | None = Field(
        None,
        description="turn the term about the sample normal by its parameter psi (params psi_deg, default 0): the "
        "orientation of a bar grating or of an anisotropic distribution's axes (core.terms.Oriented)",
    )

    @field_validator("params", mode="before")
    @classmethod
    def _dotted_keys(cls, v: Any) -> Any:
        return _flatten_params(v)

    @field_validator("shadowing", "normalisation", "fresnel")
    @classmethod
    def _known_option(cls, v: str | None, info: ValidationInfo) -> str | None:
        choices = _TERM_OPTIONS[info.field_name]
        if v is not None and v not in choices:
            raise_unknown(info.field_name, v, choices)
        return v

    @field_validator("lobes")
    @classmethod
    def _known_lobes(cls, v: dict[str, str] | None) -> dict[str, str] | None:
        if v is not None:
            if not v:
                raise ValueError("'lobes' needs at least one lobe (name -> distribution)")
            bad = [k for k in v if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k)]
            if bad:
                raise ValueError(f"lobe names must be identifiers (letters, digits, '_'), got {bad}")
            for d in v.values():
                if d not in registry.DISTRIBUTIONS:
                    raise_unknown("distribution", d, registry.DISTRIBUTIONS)
        return v

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        if v not in registry.TERMS:
            raise_unknown("term kind", v, registry.TERMS)
        return v

    @field_validator("distribution")
    @classmethod
    def _known_distribution(cls, v: str | None) -> str | None:
        if v is not None and v not in registry.DISTRIBUTIONS:
            raise_unknown("distribution", v, registry.DISTRIBUTIONS)
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "TermConfig":
        if self.kind != "multi_lobe" and self.lobes is not None:
            raise ValueError("'lobes' applies only to a 'multi_lobe' term")
        if self.kind == "multi_lobe" and self.lobes is None:
            raise ValueError(
                "a 'multi_lobe' term needs 'lobes' (lobe name -> distribution; known: "
                f"{', '.join(sorted(registry.DISTRIBUTIONS))})"
            )
        if self.kind not in registry.MICROFACET_KINDS and (
            self.shadowing is not None or self.normalisation is not None or self.fresnel is not None
        ):
            raise ValueError(
                f"'shadowing', 'normalisation' and 'fresnel' apply only to microfacet terms "
                f"({', '.join(registry.MICROFACET_KINDS)})"
            )
        specular = self.kind in ("specular", "offset_specular")
        if specular and self.distribution is None:
            raise ValueError(
                f"a '{self.kind}' term needs 'distribution'; known: {', '.join(sorted(registry.DISTRIBUTIONS))}"
            )
        if not specular and self.distribution is not None:
            raise ValueError(f"a '{self.kind}' term takes no 'distribution' (only specular and offset_specular do)")
        if self.kind != "binomial" and self.l1 is not None:
            raise ValueError("'l1' applies only to a 'binomial' term")
        if self.kind != "diffraction" and (self.grating_factor is not None or self.distance_m is not None):
            raise ValueError("'grating_factor' and 'distance_m' apply only to a 'diffraction' term")
        return self


class ModelConfig(StrictModel):
    """``[model]``: a preset with optional parameter overrides, or named terms."""

    preset: str | None = Field(None, description=f"a model preset; known: {', '.join(sorted(registry.PRESETS))}")
    params: dict[str, float] = Field(
        default_factory=dict,
        description="overrides of the preset's parameters: angles as <name>_deg, lengths as <name>_m",
    )
    terms: dict[str, TermConfig] | None = Field(None, description="named terms (instead of a preset)")

    @field_validator("params", mode="before")
    @classmethod
    def _dotted_keys(cls, v: Any) -> Any:
        return _flatten_params(v)

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, v: str | None) -> str | None:
        if v is not None and v not in registry.PRESETS:
            raise_unknown("model preset", v, registry.PRESETS)
        return v

    @field_validator("terms")
    @classmethod
    def _term_names(cls, v: dict[str, TermConfig] | None) -> dict[str, TermConfig] | None:
        if v is not None:
            if not v:
                raise ValueError("needs at least one term")
            bad = [k for k in v if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k)]
            if bad:
                raise ValueError(f"term names must be identifiers (letters, digits, '_'), got {bad}")
        return v

    @model_validator(mode="after")
    def _one_of(self) -> "ModelConfig":
        if (self.preset is None) == (self.terms is None):
            raise ValueError(
                "give exactly one of 'preset' (known: "
                f"{', '.join(sorted(registry.PRESETS))}) or 'terms' ([model.terms.<name>] tables)"
            )
        if self.terms is not None and self.params:
            raise ValueError("'params' overrides go with a 'preset'; with 'terms' put params in each term")
        return self




# --- parameter keys with units ---------------------------------------------------------------


def _config_key(name: str, unit: str) -> tuple[str, float]:
    suffix, scale = _UNIT_KEYS.get(unit, ("", 1.0))
    return name + suffix, scale


def parameter_keys(units: Mapping[str, str]) -> dict[str, tuple[str, float, str]]:
    """Config key -> (stored name, scale to stored units, unit) for parameters with ``units``.

    Angles (stored in 'rad') are given in degrees as ``<name>_deg``, lengths as
    ``<name>_m``; dimensionless and sr^-1 parameters keep their name.
    """
    out = {}
    for name, unit in units.items():
        key, scale = _config_key(name, unit)
        out[key] = (name, scale, unit)
    return out


def _rebuild(obj: Any) -> Any:
    """Re-run the constructors (and so the parameter checks) of a module tree."""
    if isinstance(obj, dict):
        return {k: _rebuild(v) for k, v in obj.items()}
    if not isinstance(obj, eqx.Module):
        return obj
    kwargs = {f.name: _rebuild(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    return type(obj)(**kwargs)


def build_preset(source: str, preset: str, params: Mapping[str, float]) -> Model:
    model = registry.lookup("preset", preset)()
    keys = parameter_keys(model.parameter_units())
    problems: list[tuple[str, str]] = []
    values: dict[str, Any] = {}
    for key, value in params.items():
        loc = f"model.params.{key}"
        if key not in keys:
            problems.append((loc, unknown_key_message(key, keys, f"preset '{preset}'")))
            continue
        name, scale, unit = keys[key]
        try:  # check each override on its own so that the message names the key
            _rebuild(model.with_params({name: value * scale}))
        except ValueError as e:
            problems.append((loc, f"{e}{_given_in(unit)}"))
            continue
        values[name] = value * scale
    if problems:
        raise ConfigError(source, problems)
    return model.with_params(values) if values else model


def _given_in(unit: str) -> str:
    """A note for core messages about angles, which show radians while the config gives degrees."""
    return " (the value shown is in radians; the config gives degrees)" if unit == "rad" else ""


def _class_units(cls: type, prefix: str = "") -> tuple[dict[str, str], set[str]]:
    units: dict[str, str] = {}
    required: set[str] = set()
    for f in dataclasses.fields(cls):
        if "unit" in f.metadata:
            units[prefix + f.name] = f.metadata["unit"]
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                required.add(prefix + f.name)
    return units, required


def _term_units(
    kind: str, distribution: str | None, lobes: Mapping[str, str] | None = None, given: Any = ()
) -> tuple[dict[str, str], set[str]]:
    """Parameter units of a term kind (and its distribution or lobes), and the required ones.

    A ``binomial`` term's coefficients ``b<k>_<i>``, ``c<k>_<i>`` are whatever of ``given`` has that form
    (the matrix shape follows from them); it needs ``d`` and ``b0_0``.
    """
    if kind == "binomial":
        units = {"d": "1", "b0_0": "log10"}  # the coefficients are signed (unit 'log10': no positive bound)
        units.update({k: "log10" for k in given if registry.BINOMIAL_KEY.fullmatch(k)})
        return units, {"d", "b0_0"}
    if kind == "multi_lobe":
        units, required = _class_units(MultiLobeSpecular)
        for lname, dname in (lobes or {}).items():
            for cls in (registry.lookup("distribution", dname), Lobe):
                u, r = _class_units(cls, f"{lname}.")
                units.update(u)
                required |= r
        return units, required
    classes: list[type] = []
    if kind in ("specular", "offset_specular"):
        classes.append(registry.lookup("distribution", distribution or ""))
        classes.append(Specular)
        if kind == "offset_specular":
            classes.append(OffsetNormal)
    else:
        classes.append(registry.lookup("term", kind))
    units: dict[str, str] = {}
    required: set[str] = set()
    for cls in classes:
        for f in dataclasses.fields(cls):
            if "unit" in f.metadata:
                units[f.name] = f.metadata["unit"]
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    required.add(f.name)
    return units, required


def term_from_config(source: str, loc: str, t: TermConfig) -> AbstractTerm:
    units, required = _term_units(t.kind, t.distribution, t.lobes, t.params)
    if t.oriented:
        units["psi"] = "rad"  # Oriented's turn, not required (default 0)
    keys = parameter_keys(units)
    what = f"a '{t.kind}' term" + (f" with distribution '{t.distribution}'" if t.distribution else "")
    problems = [
        (f"{loc}.params.{k}", unknown_key_message(k, keys, what)) for k in t.params if k not in keys
    ]
    given = {keys[k][0] for k in t.params if k in keys}
    for key, (name, _, _unit) in keys.items():
        if name in required and name not in given:
            needs = ", ".join(k for k, (n, _, _) in keys.items() if n in required)
            problems.append((f"{loc}.params", f"missing parameter '{key}' for {what}; needs: {needs}"))
    if problems:
        raise ConfigError(source, problems)
    stored = {keys[k][0]: v * keys[k][1] for k, v in t.params.items()}
    psi = stored.pop("psi", 0.0) if t.oriented else None
    try:
        term = registry.term_from_params(
            t.kind, stored, t.distribution, owner=loc, lobes=t.lobes, shadowing=t.shadowing, normalisation=t.normalisation,
            l1=t.l1, fresnel=t.fresnel,
        )
        if isinstance(term, Diffraction) and (t.grating_factor is not None or t.distance_m is not None):
            opts: dict[str, Any] = {}
            if t.grating_factor is not None:
                opts["grating_factor"] = t.grating_factor
            if t.distance_m is not None:
                opts["distance"] = float(t.distance_m)
            term = dataclasses.replace(term, **opts)
        if psi is not None:
            term = Oriented(term, psi=np.asarray(psi, float))
    except (ValueError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        # Name the config key when the core's message names the parameter ("parameter 'c' = ...").
        where = f"{loc}.params"
        hit = re.search(r"parameter '([^']+)'", msg)
        if hit:
            for key in t.params:
                if keys[key][0] == hit.group(1):
                    where, msg = f"{loc}.params.{key}", msg + _given_in(keys[key][2])
        raise ConfigError(source, [(where, msg)]) from None
    return term


def build_model(source: str, m: ModelConfig) -> Model:
    """The BRDF :class:`~brdfjax.core.terms.Model` of a ``[model]`` table (parameters in SI units and radians).

    Raises :class:`ConfigError` naming ``source`` and the dotted key.
    """
    if m.preset is not None:
        return build_preset(source, m.preset, m.params)
    terms = {name: term_from_config(source, f"model.terms.{name}", t) for name, t in (m.terms or {}).items()}
    return Model(terms=terms)


def describe_model(m: ModelConfig) -> str:
    """A one-line description of a ``[model]`` table for file headers, e.g. ``preset solar_cell (m1=...)``."""
    if m.preset is not None:
        extra = ", ".join(f"{k}={v:g}" for k, v in m.params.items())
        return f"preset {m.preset}" + (f" ({extra})" if extra else "")
    parts = []
    for name, t in (m.terms or {}).items():
        ps = ", ".join(f"{k}={v:g}" for k, v in t.params.items())
        dist = f"/{t.distribution}" if t.distribution else ""
        opts = "".join(
            f", {k}={getattr(t, k)}"
            for k in ("grating_factor", "distance_m", "lobes", "shadowing", "normalisation", "fresnel", "l1", "oriented")
            if getattr(t, k) is not None
        )
        parts.append(f"{name}: {t.kind}{dist}({ps}{opts})")
    return "; ".join(parts)
