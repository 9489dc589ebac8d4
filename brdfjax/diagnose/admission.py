"""The admission rules of the path: why a ranked candidate may not enter (a parameter on its bound, a term
of the model driven to zero, a weak signature, its own terms dead or undetermined), and when a weak
signature gives way to a dominant refit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..fit import TableData
from ..fit.internal import as_param, natural_unit, to_natural
from .effects.base import weight_names
from .refits import _State
from .results import Candidate


def _natural(name: str, x: float, unit: str) -> str:
    """A value in the unit reports and configs use (degrees for angles)."""
    u = natural_unit(unit)
    return f"{x * to_natural(unit):.6g}" + ("" if u in ("", "1") else f" {u}")


#: the words of the weak-signature flag (:func:`_admission_flags`), by which :func:`_weak_only` knows it
_WEAK = "presence threshold"


def _weak_only(c: Candidate) -> bool:
    """Whether ``c`` is held off the path by a weak signature and nothing else."""
    return bool(c.flags) and all(_WEAK in f for f in c.flags)


def _admission_flags(c: Candidate, eff: Any, before: _State, presence: bool) -> list[str]:
    """Why a ranked candidate may not enter the path; empty when it may.

    - its own new parameter ended on a bound (the fit pushed the effect out of its physical range, or off);
    - it drove a term of the model it extends to zero (it replaced that term rather than adding to it);
    - its signature is below its presence threshold (``Effect.presence``): its own evidence is too weak.
    """
    out = []
    score = c.signature.get("score")
    if presence and score is not None and score < getattr(eff, "presence", 3.0):
        out.append(f"its signature score {score:.3g} is below its {_WEAK} {getattr(eff, 'presence', 3.0):g}")
    after = c.state
    if after is None:
        return out
    before_free = set(before.result.free_names)
    for name in after.result.free_names:
        base = name[:-1].split("[", 1)[0] if name.endswith("]") else name
        if name in before_free or base in before_free or base not in after.params:
            continue
        p = as_param(base, after.params[base])
        est = after.result.parameters[name]
        for bound in (p.lower, p.upper):
            if bound is None or not math.isfinite(float(bound)):
                continue
            tol = 1e-6 * max(abs(est.initial - bound), abs(bound), 1e-300)
            if abs(est.value - bound) <= tol:
                out.append(f"its parameter {name} ended on its bound {_natural(name, float(bound), est.unit)}")
    out += _own_terms_flags(c, before, after)
    for tname, w in weight_names(before.model):
        if w is None or w not in before.result.parameters or w not in after.result.parameters:
            continue
        if not before.result.parameters[w].free:
            continue
        v0, v1 = before.result.value(w), after.result.value(w)
        if v0 > 0 and v1 < 1e-6 * v0:
            out.append(f"it drives the term '{tname}' to zero ({w} {v0:.3g} -> {v1:.3g})")
    return out


#: the distribution parameters that are a lobe's width (an rms slope or its like; radians of facet tilt)
WIDTH_FIELDS = ("m", "mx", "my", "alpha", "alpha_x", "alpha_y", "sigma", "sigma_x", "sigma_y")
#: an effect's own parameter is "dead" when it ends below this fraction of its start (a weight or a width at ~0)
DEAD_FRACTION = 1e-3
#: the words of the flags of :func:`_own_terms_flags` (a dead or undetermined effect never enters)
_DEAD, _UNDETERMINED = "dead", "not determined"


def _sampling_rad(blocks: Sequence[Any]) -> float:
    """The coarsest angular sampling step of the fitted data (radians): a goniometer table's median step between
    neighbouring scatter angles of one incidence, a frame's median pixel step in scatter angle."""
    steps = []
    for b in blocks:
        if isinstance(b, TableData):
            ts, ti = np.asarray(b.theta_s, float).ravel(), np.round(np.asarray(b.theta_i, float).ravel(), 6)
            ps = np.asarray(b.phi_s, float).ravel()
            for t in np.unique(ti):
                sel = ti == t
                # in-plane and out-of-plane angles on one axis: signed scatter angle
                x = np.unique(np.round(np.where(np.cos(ps[sel]) >= 0, ts[sel], -ts[sel]), 9))
                d = np.diff(np.sort(x))
                d = d[d > 0]
                if d.size:
                    steps.append(float(np.median(d)))
    return max(steps) if steps else 0.0


def _own_terms_flags(c: Candidate, before: _State, after: _State) -> list[str]:
    """An effect whose own terms end dead or undetermined is not admitted, whatever the BIC gain.

    Its own new free parameters (those the model it extends lacks) must have a finite sigma; a weight of a term it
    added, or a lobe width, must not end below ``DEAD_FRACTION`` of its start; a lobe it added must not be
    narrower (its angular width ~ 2 x its slope width) than half the angular sampling of goniometer tables.
    Measured on a real lab table: ``second_lobe`` entered at step 1 with weight 2.7e-6 and width 5e-6, no sigma:
    its delta BIC of 55 came from the refit of the first lobe, not from the lobe it added.
    """
    out: list[str] = []
    res = after.result
    before_free = set(before.result.free_names)
    for name in res.free_names:
        base = name[:-1].split("[", 1)[0] if name.endswith("]") else name
        if name in before_free or base in before_free:
            continue
        sg = res.parameters[name].sigma
        if sg is None or not math.isfinite(float(sg)) or float(sg) <= 0:
            out.append(f"its parameter {name} is {_UNDETERMINED} by the data (no finite sigma)")
    added = after.added_terms.get(c.effect) if after.added_terms else None
    if not added:
        return out
    back = dict(after.model.aliases)
    inv = {v: k for k, v in back.items()}
    step = _sampling_rad(after.blocks)
    for flat, (_path, _unit) in after.model._paths().items():
        tname, field = flat.split(".", 1)[0], flat.rsplit(".", 1)[-1]
        if tname not in added:
            continue
        pub = inv.get(flat, flat)
        if pub not in res.parameters or not res.parameters[pub].free:
            continue
        est = res.parameters[pub]
        is_weight = any(w == pub for t, w in weight_names(after.model) if t == tname)
        if (is_weight or field in WIDTH_FIELDS) and est.initial > 0 and est.value < DEAD_FRACTION * est.initial:
            out.append(f"its term '{tname}' ends {_DEAD}: {pub} {est.initial:.3g} -> {est.value:.3g}")
        elif field in WIDTH_FIELDS and step > 0 and 2.0 * est.value < 0.5 * step:
            out.append(f"its lobe '{tname}' is {_UNDETERMINED}: {pub} = {est.value:.3g} (about "
                       f"{math.degrees(2 * est.value):.3g} deg wide) is narrower than half the sampling "
                       f"({math.degrees(step):.3g} deg)")
    return out


#: A candidate held off only by a weak signature enters when its refit gains at least this many times the best
#: admissible candidate's delta BIC (its refit is then the stronger evidence).
DOMINANCE = 5.0


def _admit_dominant(ranked: list[Candidate]) -> None:
    """Clear the weak-signature flag of a candidate whose refit dominates every admissible one (``DOMINANCE``).

    Measured on the project's own generator (flux scale withheld, weights calibrated): the base widened its
    lobe to soak up the flux error, so the bright and faint halves of the residual moved apart and the flux
    signature was 0, yet its refit gained delta BIC 45118 against the floor's 4060; the path took the floor and
    a response curve instead.  Only the presence flag is cleared (a parameter on its bound or a term driven to
    zero still keep a candidate off), and only beside an admissible candidate to compare with.
    """
    gains = [c.delta_bic for c in ranked if not c.flags and math.isfinite(c.delta_bic)]
    if not gains:
        return
    best = max(gains)
    for c in ranked:
        if _weak_only(c) and best > 0 and c.delta_bic >= DOMINANCE * best:
            c.note = (f"admitted although {c.flags[0]}: its refit gains delta BIC {c.delta_bic:.4g}, "
                      f"{c.delta_bic / best:.3g}x the best admissible candidate's ({best:.4g})"
                      + (f"; {c.note}" if c.note else ""))
            c.flags = []

