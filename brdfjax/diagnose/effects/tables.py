"""Model-side effects that goniometer tables (wide angular ranges, grazing angles) show: a second lobe and
shadowing-masking; and the rule that instrument responses are ranked on detector frames only.

- ``second_lobe``: a second microfacet lobe of the main lobe's family (a wider halo or a narrower spike)
  sharing its index;
- ``shadowing``: the Smith (height-correlated) masking-shadowing factor G2 switched on in every microfacet
  term (:mod:`brdfjax.core.shadowing`; exact Lambda for Beckmann/GGX, tabulated otherwise) -- no new
  parameter, so its BIC gain is its chi^2 decrease;
- the distribution's tail is ``distribution_shape`` (:mod:`.model`: the family swap among Beckmann, GGX,
  Student-t and Hyper-Cauchy, applicable to tables).

:func:`tables_only` is the reason an instrument-response effect (a response curve, a flux scale) is not
ranked on tables: a table carries no pixel-level signature of the instrument, so such a curve would only
absorb a model-shape error (as measured: ``pixel_nonlinearity`` ranked first on two real tables with
its exponent on its bound).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

from ...core.terms import Model, Specular
from ...fit import FrameData, Param, TableData
from .base import (
    Effect,
    Extension,
    Signature,
    best_by_linear_chi2,
    log_sf_normal,
    score_from_logp,
    template_z,
    unique_name,
    with_terms,
)

__all__ = ["SecondLobeEffect", "ShadowingEffect", "tables_only"]


def tables_only(blocks: Sequence[Any], effect: str) -> str | None:
    """Why an instrument-response effect is not ranked on these data (None: some block is a detector frame)."""
    if blocks and not any(isinstance(b, FrameData) for b in blocks) and all(isinstance(b, TableData) for b in blocks):
        return (
            f"{effect} is an instrument response: it is ranked only on detector frames, whose pixels carry the "
            "instrument's signature; these data are goniometer tables, where a response curve would absorb a "
            "model-shape error (second lobe, shadowing, distribution tail)"
        )
    return None


def _lobes(model: Model) -> list[str]:
    return [n for n, t in model.terms.items() if isinstance(t, Specular) and getattr(type(t.distribution), "width_field", None)]


def _with_lobe(model: Model, main: str, ratio: float, frac: float) -> tuple[Model, str, str]:
    t = model.terms[main]
    field = type(t.distribution).width_field
    w = float(getattr(t.distribution, field))
    dist = dataclasses.replace(t.distribution, **{field: w * ratio})
    lobe = dataclasses.replace(t, distribution=dist, rho_s=float(t.rho_s) * frac)
    name = unique_name(model, "lobe2")
    return with_terms(model, {**model.terms, name: lobe}), name, field


class SecondLobeEffect(Effect):
    # Generic: a lobe of free width and weight takes the shape of a floor, a halo or a changed distribution as
    # readily as a second physical lobe (measured on reference frames with a floor withheld and one incidence
    # fitted: the second lobe and the floor fitted within 1.2 and 12 of each other in BIC, and as a "specific"
    # effect the lobe kept the floor out; the held-out frame at another incidence missed by 0.25 decades with it).
    # Between two generic effects the BIC decides; a specific effect that explains its residual keeps it out.
    generic = True
    name = "second_lobe"
    title = "a second microfacet lobe (halo or spike)"
    needs_2d = False
    doc = (
        "Adds a second Specular term of the main lobe's distribution family and index (n, k held at the main "
        "lobe's; its shadowing and normalisation too) with its own width and weight (2 new parameters): a "
        "wide halo under a glossy peak or a narrow spike on a broad one.  Signature: the score test (matched "
        "filter, the base's free parameters projected out) of the change in ln f such a lobe makes, at width "
        "ratios 0.3, 3 and 10 with weights 0.3, 0.1 and 0.03 of the main lobe's, look-elsewhere over the "
        "three; the best ratio initialises the lobe."
    )
    candidates = ((0.3, 0.3), (3.0, 0.1), (10.0, 0.03))

    def present_in(self, model):
        return len(_lobes(model)) >= 2

    def identifiable(self, model, params, blocks):
        if not _lobes(model):
            return "no microfacet (Specular) lobe to add a second one beside"
        return None

    def _best(self, ctx):
        main = _lobes(ctx.model)[0]

        def make(c):
            return (lambda m, c=c: _with_lobe(m, main, *c)[0],)

        z, best, _ = best_by_linear_chi2(ctx, self.candidates, make)
        return z, best, main

    def signature(self, ctx):
        z, (ratio, frac), _ = self._best(ctx)
        logp = math.log(len(self.candidates) / 2.0) + log_sf_normal(abs(z))
        return Signature(z, score_from_logp(logp), f"score test z = {z:.1f} for a lobe x{ratio:g} as wide at {frac:g} of the weight")

    def extend(self, ctx):
        _, (ratio, frac), main = self._best(ctx)
        model, name, field = _with_lobe(ctx.model, main, ratio, frac)
        t = model.terms[name]
        params = dict(ctx.params)
        params[f"{name}.{field}"] = Param(float(getattr(t.distribution, field)), lower=1e-6, upper=10.0)
        params[f"{name}.rho_s"] = Param(float(t.rho_s), lower=0.0)
        return Extension(model, params, 2, note=f"second lobe '{name}': x{ratio:g} the width of '{main}', {frac:g} of its weight")


def _shadowed(model: Model, kind: str = "smith") -> Model:
    terms = {n: (dataclasses.replace(t, shadowing=kind) if n in _lobes(model) else t) for n, t in model.terms.items()}
    return with_terms(model, terms)


class ShadowingEffect(Effect):
    name = "shadowing"
    title = "shadowing-masking of the microfacets (Smith G2)"
    needs_2d = False
    doc = (
        "Switches every microfacet (Specular) term from G = 1 to the height-correlated Smith "
        "masking-shadowing factor G2 of its own distribution (brdfjax.core.shadowing: the exact Lambda of "
        "Beckmann and GGX, a tabulated Lambda otherwise).  No new parameter: the BIC gain is the chi^2 "
        "decrease.  G < 1 lowers the model towards grazing incidence and scatter, where a microfacet lobe "
        "without it rises above goniometer data.  Signature: the score test of the change in ln f that G2 "
        "makes at the base's widths (one-sided: G lowers the model)."
    )

    def present_in(self, model):
        lobes = _lobes(model)
        return bool(lobes) and all(model.terms[n].shadowing != "none" for n in lobes)

    def identifiable(self, model, params, blocks):
        if not _lobes(model):
            return "no microfacet (Specular) term to shadow"
        return None

    def signature(self, ctx):
        z = template_z(ctx, _shadowed)
        return Signature(z, score_from_logp(log_sf_normal(z)), f"score test z = {z:.1f} for Smith G2")

    def extend(self, ctx):
        return Extension(_shadowed(ctx.model), dict(ctx.params), 0, note="Smith G2 (height-correlated) in " + ", ".join(_lobes(ctx.model)))
