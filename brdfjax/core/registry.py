"""One name -> object registry shared by configs, the CLI and error messages.

``lookup("distribution", "ggxx")`` raises ``unknown distribution 'ggxx'; known:
ashikhmin_shirley, beard_maxwell, beckmann, ...``.  Terms are built from
plain dictionaries with :func:`term_from_params` (what a TOML config holds), with
parameter values in the units the term stores (radians, metres).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from . import distributions as _d, presets as _presets
from .terms import (
    _BINOMIAL_KEY as BINOMIAL_KEY,
    ABg,
    AbstractTerm,
    Binomial,
    Diffraction,
    Lambertian,
    Lobe,
    MultiLobeSpecular,
    OffsetNormal,
    Phong,
    Specular,
    solar_cell,
)

__all__ = ["DISTRIBUTIONS", "TERMS", "MICROFACET_KINDS", "PRESETS", "lookup", "parameter_names", "term_from_params"]

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

#: Term kinds.  ``offset_specular`` is a :class:`Specular` inside :class:`OffsetNormal`;
#: ``multi_lobe`` several microfacet lobes sharing an index; ``abg``, ``phong`` and ``binomial`` empirical lobes.
TERMS: dict[str, Any] = {
    "specular": Specular,
    "offset_specular": OffsetNormal,
    "multi_lobe": MultiLobeSpecular,
    "lambertian": Lambertian,
    "diffraction": Diffraction,
    "abg": ABg,
    "phong": Phong,
    "binomial": Binomial,
}

#: Term kinds built around microfacet distributions, which take the ``shadowing``, ``normalisation`` and
#: ``fresnel`` options (:data:`brdfjax.core.shadowing.SHADOWING`, :data:`brdfjax.core.terms.NORMALISATIONS`,
#: :data:`brdfjax.core.terms.FRESNELS`).
MICROFACET_KINDS = ("specular", "offset_specular", "multi_lobe")

#: Model presets: the seed's solar cell and its other materials (``brdfjax.core.presets``: mirror, polished
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


def term_from_params(
    kind: str,
    params: Mapping[str, Any],
    distribution: str | None = None,
    owner: str = "term",
    *,
    lobes: Mapping[str, str] | None = None,
    shadowing: str | None = None,
    normalisation: str | None = None,
    l1: int | None = None,
    fresnel: str | None = None,
) -> AbstractTerm:
    """Build a term from its kind and a flat parameter dict (stored units).

    Specular kinds take a distribution name; ``multi_lobe`` takes ``lobes``
    (lobe name -> distribution name) and parameters ``<lobe>.<name>`` plus the
    shared ``n``, ``k``; the microfacet kinds take the ``shadowing``,
    ``normalisation`` and ``fresnel`` options (``None``: the seed's defaults); ``binomial``
    takes its coefficients ``b<k>_<i>``, ``c<k>_<i>``, ``d`` and the integer ``l1``
    (default 0).
    """
    cls = lookup("term", kind)
    p = dict(params)
    options = {k: v for k, v in (("shadowing", shadowing), ("normalisation", normalisation), ("fresnel", fresnel))
               if v is not None}
    if options and kind not in MICROFACET_KINDS:
        raise KeyError(f"{owner}: a '{kind}' term takes no {' or '.join(repr(k) for k in options)} "
                       f"(only {', '.join(MICROFACET_KINDS)} do)")
    if l1 is not None and kind != "binomial":
        raise KeyError(f"{owner}: a '{kind}' term takes no 'l1' (only binomial does)")
    if lobes is not None and kind != "multi_lobe":
        raise KeyError(f"{owner}: a '{kind}' term takes no 'lobes' (only multi_lobe does)")
    if kind in ("specular", "offset_specular"):
        if distribution is None:
            raise KeyError(f"{owner}: a '{kind}' term needs 'distribution'; known: {', '.join(sorted(DISTRIBUTIONS))}")
        dcls = lookup("distribution", distribution)
        d = dcls(**_take(owner, dcls, p))
        spec_args = _take(owner, Specular, p)
        if kind == "specular":
            term = Specular(d, **spec_args, **options)
        else:
            term = OffsetNormal(Specular(d, **spec_args, **options), **_take(owner, OffsetNormal, p))
    elif kind == "multi_lobe":
        if distribution is not None:
            raise KeyError(f"{owner}: a 'multi_lobe' term takes 'lobes' (name -> distribution), not 'distribution'")
        if not lobes:
            raise KeyError(f"{owner}: a 'multi_lobe' term needs 'lobes' (lobe name -> distribution; known: "
                           f"{', '.join(sorted(DISTRIBUTIONS))})")
        built = {}
        for lname, dname in lobes.items():
            dcls = lookup("distribution", dname)
            sub = {k.split(".", 1)[1]: p.pop(k) for k in list(p) if k.startswith(lname + ".")}
            d = dcls(**_take(f"{owner}.{lname}", dcls, sub))
            built[lname] = Lobe(d, **_take(f"{owner}.{lname}", Lobe, sub))
            if sub:
                raise KeyError(f"{owner}: unknown parameter(s) {sorted(f'{lname}.{k}' for k in sub)} for lobe '{lname}'")
        term = MultiLobeSpecular(built, **_take(owner, MultiLobeSpecular, p), **options)
    elif kind == "binomial":
        if distribution is not None:
            raise KeyError(f"{owner}: a 'binomial' term takes no 'distribution'")
        coefficients = {k: p.pop(k) for k in list(p) if BINOMIAL_KEY.fullmatch(k)}
        if "d" not in p:
            raise KeyError(f"{owner}: missing parameter 'd' (specularity constant); needs: d, b0_0, ...")
        try:
            term = Binomial(coefficients=coefficients, d=p.pop("d"), l1=0 if l1 is None else l1)
        except ValueError as e:
            raise KeyError(f"{owner}: {e}") from None
    else:
        if distribution is not None:
            raise KeyError(f"{owner}: a '{kind}' term takes no 'distribution'")
        term = cls(**_take(owner, cls, p))
    if p:
        raise KeyError(f"{owner}: unknown parameter(s) {sorted(p)} for a '{kind}' term")
    return term
