"""One name -> object registry shared by configs, the CLI and error messages.

``lookup("distribution", "ggxx")`` raises ``unknown distribution 'ggxx'; known:
ashikhmin_shirley, beard_maxwell, beckmann, ...``.  Terms are built from
plain dictionaries with :func:`build_term` (what a TOML config holds), with
parameter values in the units the term stores (radians, metres).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from . import distributions as _d, presets as _presets
from .terms import AbstractTerm, Diffraction, Lambertian, Model, OffsetNormal, Specular, solar_cell

__all__ = ["DISTRIBUTIONS", "TERMS", "PRESETS", "lookup", "parameter_names", "build_term", "build_model"]

DISTRIBUTIONS: dict[str, type[_d.AbstractDistribution]] = {
    cls.name: cls
    for cls in (
        _d.Beckmann,
        _d.BeckmannAniso,
        _d.GGX,
        _d.GGXAniso,
        _d.GTR,
        _d.HyperCauchy,
        _d.Ribardiere,
        _d.StudentT,
        _d.StudentTAniso,
        _d.CosineLobe,
        _d.AshikhminShirley,
        _d.BeardMaxwell,
    )
}
# Common aliases for the same distributions.
DISTRIBUTIONS["trowbridge_reitz"] = _d.GGX
DISTRIBUTIONS["blinn_phong"] = _d.CosineLobe

#: Term kinds.  ``offset_specular`` is a :class:`Specular` inside :class:`OffsetNormal`.
TERMS: dict[str, Any] = {
    "specular": Specular,
    "offset_specular": OffsetNormal,
    "lambertian": Lambertian,
    "diffraction": Diffraction,
}

#: Model presets: the seed's solar cell and its other materials (``brdfjax.presets``: mirror, polished
#: aluminium, Kapton; plausible values, see that module).
PRESETS: dict[str, Any] = {
    "solar_cell": solar_cell,
    "mirror": _presets.mirror,
    "polished_aluminium": _presets.polished_aluminium,
    "kapton": _presets.kapton,
}

_REGISTRIES = {"distribution": DISTRIBUTIONS, "term": TERMS, "preset": PRESETS}


def lookup(kind: str, name: str) -> Any:
    """The registered object ``name`` of ``kind`` ('distribution', 'term', 'preset')."""
    table = _REGISTRIES[kind]
    if name not in table:
        raise KeyError(f"unknown {kind} '{name}'; known: {', '.join(sorted(table))}")
    return table[name]


def parameter_names(cls: type) -> dict[str, str]:
    """Parameter name -> unit of a distribution or term class (from field metadata)."""
    return {f.name: f.metadata["unit"] for f in dataclasses.fields(cls) if "unit" in f.metadata}


def _take(owner: str, cls: type, params: dict[str, Any], required: bool = True) -> dict[str, Any]:
    names = parameter_names(cls)
    out = {}
    for name, f in ((f.name, f) for f in dataclasses.fields(cls) if f.name in names):
        if name in params:
            out[name] = params.pop(name)
        elif required and f.default is dataclasses.MISSING:
            raise KeyError(f"{owner}: missing parameter '{name}' ({names[name]}); needs: {', '.join(names)}")
    return out


def build_term(kind: str, params: Mapping[str, Any], distribution: str | None = None, owner: str = "term") -> AbstractTerm:
    """Build a term from its kind, a flat parameter dict (stored units) and, for specular kinds, a D name."""
    cls = lookup("term", kind)
    p = dict(params)
    if kind in ("specular", "offset_specular"):
        if distribution is None:
            raise KeyError(f"{owner}: a '{kind}' term needs 'distribution'; known: {', '.join(sorted(DISTRIBUTIONS))}")
        dcls = lookup("distribution", distribution)
        d = dcls(**_take(owner, dcls, p))
        spec_args = _take(owner, Specular, p)
        if kind == "specular":
            term = Specular(d, **spec_args)
        else:
            term = OffsetNormal(Specular(d, **spec_args), **_take(owner, OffsetNormal, p))
    else:
        if distribution is not None:
            raise KeyError(f"{owner}: a '{kind}' term takes no 'distribution'")
        term = cls(**_take(owner, cls, p))
    if p:
        raise KeyError(f"{owner}: unknown parameter(s) {sorted(p)} for a '{kind}' term")
    return term


def build_model(terms: Mapping[str, AbstractTerm], aliases: Mapping[str, str] | None = None) -> Model:
    return Model(terms=dict(terms), aliases=tuple((aliases or {}).items()))
