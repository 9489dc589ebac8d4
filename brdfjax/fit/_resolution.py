"""Unresolved peaks: a lobe narrower than a table's angular sampling (or the aperture) is not determined.

When the fitted specular lobe's angular FWHM (measured on the fitted term
along the plane of incidence through the mirror direction) is below the
table's angular step at the peak -- or the fitted aperture of an
``InstrumentResponse`` when one is there -- the data hold the peak in one
sample: its width and its weight trade off and the covariance's sigmas
describe nothing.  :func:`check_resolution` then profiles the likelihood over
the width (the lobe width held at each of a log grid of values, every other
free parameter refitted) and reports the widths whose ``-2 ln L`` lies
within ``threshold`` (1: the 68 % profile interval of one parameter) of the
best, and the weights found at those widths, in place of the sigmas.  The
grid spans FWHMs from 1/30 of the step to 2 steps; a range that reaches
the grid's narrow end is reported open (``lower = 0``: any narrower width is
allowed too).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..core.geometry import Directions
from ..core.terms import MultiLobeSpecular
from ..io.blocks import TableData
from ._params import Param, as_param

__all__ = ["lobe_parameters", "lobe_term", "table_step", "lobe_fwhm", "check_resolution"]


def _width_field(dist: Any) -> str | None:
    return getattr(type(dist), "width_field", None) if dist is not None else None


def lobe_parameters(model: Any) -> list[tuple[str, str, str]]:
    """``(term, width parameter, weight parameter)`` of every microfacet lobe of a model.

    Parameter names are the model's public ones, as a fit reports them: an
    alias where the model declares one (a preset's ``m`` for
    ``specular.m``), else the full name.  A
    :class:`~brdfjax.core.terms.MultiLobeSpecular` term gives one entry per
    lobe (``<term>.<lobe>.<width>``, ``<term>.<lobe>.rho_s``): a narrow spike
    beside a wide halo is checked on its own (:func:`lobe_term`).
    """
    public = {flat: alias for alias, flat in getattr(model, "aliases", ())}
    out = []
    for name, term in getattr(model, "terms", {}).items():
        if isinstance(term, MultiLobeSpecular):
            for key, lobe in term.lobes.items():
                field = _width_field(lobe.distribution)
                if field is not None:
                    w, a = f"{name}.{key}.{field}", f"{name}.{key}.rho_s"
                    out.append((name, public.get(w, w), public.get(a, a)))
            continue
        field = _width_field(getattr(term, "distribution", None))
        if field is not None and hasattr(term, "rho_s"):
            w, a = f"{name}.{field}", f"{name}.rho_s"
            out.append((name, public.get(w, w), public.get(a, a)))
    return out


def lobe_term(model: Any, term_name: str, width_name: str) -> Any:
    """The term whose peak :func:`lobe_fwhm` measures for a :func:`lobe_parameters` entry: the term itself, or,
    for one lobe of a :class:`~brdfjax.core.terms.MultiLobeSpecular`, that term with this lobe alone (the other
    lobes would hide a narrow spike's width under a halo's)."""
    term = model.terms[term_name]
    if isinstance(term, MultiLobeSpecular):
        flat = dict(getattr(model, "aliases", ())).get(width_name, width_name)
        key = flat[len(term_name) + 1 :].split(".")[0]
        return dataclasses.replace(term, lobes={key: term.lobes[key]})
    return term


def _signed_inplane(b: TableData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """theta_i, the signed in-plane scatter angle (positive: the mirror side) and whether a row is in-plane."""
    ti = np.asarray(b.theta_i, float)
    ts = np.asarray(b.theta_s, float)
    dphi = np.mod(np.asarray(b.phi_s, float) - np.asarray(b.phi_i, float), 2 * math.pi)
    fwd = np.abs(dphi - math.pi) < 1e-3
    back = (np.abs(dphi) < 1e-3) | (np.abs(dphi - 2 * math.pi) < 1e-3)
    return ti, np.where(fwd, ts, -ts), fwd | back | (ts < 1e-9)


def table_step(b: TableData) -> tuple[float, float] | None:
    """``(step, theta_i)`` in radians: the in-plane sampling step next to the mirror direction of the slice
    with the highest BRDF sample (None: the table has no in-plane slice there)."""
    ti, s, inplane = _signed_inplane(b)
    d = np.asarray(b.brdf, float)
    ok = inplane & np.isfinite(d) & (d > 0)
    if not ok.any():
        return None
    k = np.flatnonzero(ok)[int(np.argmax(d[ok]))]
    sl = ok & (np.abs(ti - ti[k]) < 1e-6)
    near = np.sort(s[sl][np.abs(s[sl] - ti[k]) < math.radians(10.0)])
    steps = np.diff(near)
    steps = steps[steps > 1e-9]
    if steps.size == 0:
        return None
    return float(np.median(steps)), float(ti[k])


def lobe_fwhm(term: Any, theta_i: float, wavelength: float, span: float) -> float:
    """The lobe's full width at half maximum (rad) along the plane of incidence through the mirror direction,
    on a grid of 4001 points over +-``span`` (rad); below the grid's spacing: that spacing."""
    t = theta_i + np.linspace(-span, span, 4001)
    t = t[(t > -math.pi / 2 + 1e-6) & (t < math.pi / 2 - 1e-6)]
    dirs = Directions.from_angles(np.full(t.shape, theta_i), np.zeros(t.shape), np.abs(t), np.where(t < 0, 0.0, math.pi))
    f = np.asarray(term(dirs, wavelength), float)
    if not np.all(np.isfinite(f)) or f.max() <= 0:
        return math.nan
    above = t[f >= 0.5 * f.max()]
    return float(max(above.max() - above.min(), t[1] - t[0]))


def _warm(params: Mapping[str, Any], result: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, spec in params.items():
        p = as_param(name, spec)
        if p.free and name in result.parameters and result.parameters[name].free:
            x = result.value(name)
            lo = -math.inf if p.lower is None else p.lower
            hi = math.inf if p.upper is None else p.upper
            if math.isfinite(lo) and math.isfinite(hi):
                x = min(max(x, lo + 1e-9 * (hi - lo)), hi - 1e-9 * (hi - lo))
            p = dataclasses.replace(p, value=float(x))
        out[name] = p
    return out


def check_resolution(
    model: Any,
    blocks: list[Any],
    params: Mapping[str, Any],
    result: Any,
    refit: Callable[[Any, Mapping[str, Any]], Any],
    threshold: float = 1.0,
    n_grid: int = 10,
) -> dict[str, Any]:
    """The undetermined lobe parameters of a fit (see the module docstring): name -> record; {} when resolved.

    ``refit(model, params)`` runs the fit with the same data and options (and no resolution check).
    """
    tables = [k for k, b in enumerate(blocks) if isinstance(b, TableData)]
    if not tables or not result.models:
        return {}
    found: dict[str, Any] = {}
    for term_name, wname, aname in lobe_parameters(model):
        if wname not in result.parameters or not result.parameters[wname].free:
            continue
        k = max(tables, key=lambda j: float(np.nanmax(np.where(np.asarray(blocks[j].brdf) > 0, blocks[j].brdf, np.nan))))
        st = table_step(blocks[k])
        if st is None:
            continue
        step, ti = st
        aperture = result.parameters.get("instrument.aperture")
        limit = max(step, float(aperture.value) if aperture is not None else 0.0)
        wl = float(np.mean(np.asarray(blocks[k].wavelength, float)))
        term = lobe_term(result.models[k], term_name, wname)
        fwhm = lobe_fwhm(term, ti, wl, 3.0 * limit)
        if not (math.isfinite(fwhm) and fwhm < limit):
            continue
        w_fit = result.value(wname)
        # FWHM is proportional to the width for narrow lobes: the grid spans FWHMs of limit/30 .. 2 limit
        base = w_fit * limit / fwhm
        grid = base * np.geomspace(1.0 / 30.0, 2.0, n_grid)
        warm = _warm(params, result)
        spec0 = as_param(wname, params.get(wname, "free"))
        lo_b = -math.inf if spec0.lower is None else spec0.lower
        hi_b = math.inf if spec0.upper is None else spec0.upper
        rows = [(w_fit, float(result.m2ll), result.value(aname) if aname in result.parameters else math.nan)]
        for w in grid:
            if not (lo_b < w < hi_b):
                continue
            spec = dict(warm)
            spec[wname] = Param.fixed(float(w))
            try:
                r = refit(model, spec)
            except Exception:  # noqa: BLE001 - a width the model cannot take is simply not in the profile
                continue
            if math.isfinite(r.m2ll):
                rows.append((float(w), float(r.m2ll), r.value(aname) if aname in r.parameters else math.nan))
        rows.sort()
        ws = np.array([r[0] for r in rows])
        m2 = np.array([r[1] for r in rows])
        amp = np.array([r[2] for r in rows])
        ok = m2 - m2.min() <= threshold
        open_low = bool(ok[0] and ws[0] <= grid[0] * 1.0001)
        w_lo = 0.0 if open_low else float(ws[ok].min())
        w_hi = float(ws[ok].max())
        if not open_low and w_hi <= 2.0 * w_lo:
            # pinned within a factor 2 although narrower than the sampling: by the lobe's tails, i.e. by the
            # assumed distribution's shape; the covariance stands, with that caveat
            found.setdefault("_notes", []).append(
                f"{wname}: the lobe's FWHM ({math.degrees(fwhm):.3g} deg) is below the sampling "
                f"({math.degrees(limit):.3g} deg); its width is fixed by the tails of the assumed distribution "
                f"(profile range {w_lo:.3g} .. {w_hi:.3g})"
            )
            continue
        scale_fwhm = fwhm / w_fit
        rec_w = {
            "reason": (
                f"the fitted lobe's FWHM ({math.degrees(fwhm):.3g} deg) is below the angular sampling "
                f"({math.degrees(limit):.3g} deg{' (aperture)' if limit > step else ''}): the peak is unresolved"
            ),
            "range": [w_lo, w_hi],
            "fwhm_deg_range": [math.degrees(w_lo * scale_fwhm), math.degrees(w_hi * scale_fwhm)],
            "open_below": open_low,
            "sampling_deg": math.degrees(step),
            "threshold_delta_m2ll": threshold,
            "profile": [[float(a), float(b)] for a, b in zip(ws, m2)],
        }
        found[wname] = rec_w
        if aname in result.parameters and result.parameters[aname].free:
            found[aname] = {
                "reason": f"trades off against {wname} (unresolved peak)",
                "range": [float(np.nanmin(amp[ok])), float(np.nanmax(amp[ok]))],
            }
    return found
