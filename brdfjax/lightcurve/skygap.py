"""The gap on the sky: which unmodelled effect explains where a facet model misses observed magnitudes.

Given a :class:`~.skyfit.SkyProblem` (a base facet model over one
observation set), the diagnosis

1. fits the base (facet areas free; the scatter profiled or the rows'
   uncertainties);
2. refits the base with each *candidate effect* added (its parameters
   physically bounded, several starts where the likelihood is multimodal) and
   ranks the candidates by BIC (``-2 ln L + k ln N``); a candidate whose
   fitted parameters end on a bound (an amplitude at zero, a width at its
   limit) is kept off the path, as on tables;
3. builds the path: the best candidate improving BIC by more than
   ``threshold`` joins, the remaining leading candidates are refitted on top,
   until none does or ``max_steps``;
4. reports *where* each step changes the residuals (zones in phase angle,
   in each facet's incidence and scattering angle, in the Sun-observer
   azimuth about the body's z axis at the satellite) and *how far* the gap
   shrinks on held-out groups (whole nights, satellites or blocks of rows:
   :func:`~.skyfit.group_folds`), base against path.

Candidates (:func:`candidates`; the names are the effect kinds):

``earthshine``
    a Lambertian Earth of albedo ``a`` in [0, 0.6]: ``a`` times each facet's
    earthshine per unit albedo (:func:`~.earthshine.earthshine_flux` with the
    base model, scaled with each facet's fitted area).
``offset``
    a facet's normal canted about its x axis (a fixed facet) or a tracking
    array's axis turned about body z (``yaw``), +- 30 deg.
``missing_facet``
    a Lambertian plate the model lacks: ``A rho`` in [0, 5] m^2, its normal at
    ``tilt`` in [0, 180] deg from body +z (nadir) and azimuth ``az`` about z.
``wide_lobe``
    a lobe beyond the lab's steepest measured incidence on a facet: ``k
    exp(-(1 - h_z) / w^2)`` (sr^-1; ``h`` the half vector in the facet frame,
    ~ a Gaussian of width ``w`` in the half-angle), ``k`` in [0, 2], ``w`` in
    [5, 45] deg, switched on by ``sigmoid((theta_i - theta_max) / 2 deg)``
    with ``theta_max`` the facet's lab table's largest incidence (75 deg when
    unknown).
``out_of_plane``
    an offset peak out of the plane of incidence (anisotropy an in-plane lab
    scan cannot see): two lobes ``k/2 exp(-(1 - h . h0) / w^2)`` around ``h0 =
    cos(delta) z +- sin(delta) p`` (``p`` the normal of the plane of
    incidence), ``k`` in [0, 2], ``delta`` in [5, 40] deg, ``w`` = 6 deg.

The solar disk is not a candidate: with lobes degrees wide (the V2 Mini's
lab fits) the disk changes nothing measurable (``sun.disk = "point"`` in the
shipped configs).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from .earthshine import earthshine_flux
from .engine import Attitude, Satellite
from .skyfit import Param, SkyFit, SkyProblem, cross_validate

__all__ = ["Candidate", "KINDS", "add_effects", "candidates", "diagnose_sky", "zones"]

KINDS = ("earthshine", "offset", "missing_facet", "wide_lobe", "out_of_plane")
_OOP_WIDTH = np.deg2rad(6.0)
_GATE = np.deg2rad(2.0)


@dataclass
class Candidate:
    """An effect: its kind, the facet it acts on ('' for the satellite), its parameter keys and starting values."""

    name: str
    kind: str
    facet: str
    keys: list[str]
    starts: list[dict[str, float]] = field(default_factory=list)


def _earthshine_unit(problem: SkyProblem, n_psi: int, n_chi: int, earth_radius: float) -> np.ndarray:
    """Each facet's earthshine at albedo 1 per m^2 of its area (N, J), with the base model at its configured values."""
    x0 = problem.x_of_u(jnp.asarray(problem.u0()))
    fac = problem._facets(x0)
    fams = list(dict.fromkeys(f.families[0] for f in problem.facets))
    sat = Satellite(fac, tuple(problem.models[m] for m in fams), Attitude.nadir(),
                    tuple(fams.index(f.families[0]) for f in problem.facets))
    es = np.asarray(earthshine_flux(sat, problem.data.engine, 1.0, n_psi=n_psi, n_chi=n_chi, earth_radius=earth_radius,
                                    wavelength=problem.wavelength))
    return es / np.asarray(fac.area)[None, :]


def add_effects(problem: SkyProblem, *, kinds=KINDS, facets: list[str] | None = None, earthshine_grid=(8, 16),
                earth_radius: float = 6378137.0) -> list[Candidate]:
    """Add every candidate's parameters to ``problem`` (each off: zero amplitude, no offset) and its flux function.

    ``facets``: the facets that get facet candidates (default: all).
    """
    names = [f.name for f in problem.facets]
    facets = names if facets is None else list(facets)
    out: list[Candidate] = []
    new: list[Param] = []
    have = {p.key for p in problem.params}
    if "earthshine" in kinds:
        problem._es_unit = _earthshine_unit(problem, *earthshine_grid, earth_radius)
        new.append(Param("es.albedo", "effect", 0.0, 0.0, 0.6, target="earthshine", name="albedo"))
        out.append(Candidate("earthshine", "earthshine", "", ["es.albedo"], [{"es.albedo": 0.3}]))
    if "missing_facet" in kinds:
        new += [Param("miss.arho", "effect", 0.0, 0.0, 5.0, target="missing", name="arho"),
                Param("miss.tilt", "effect", np.pi / 3, 0.0, np.pi, target="missing", name="tilt"),
                Param("miss.az", "effect", 0.0, -np.pi, np.pi, target="missing", name="az")]
        starts = [{"miss.arho": 0.5, "miss.tilt": t, "miss.az": a} for t in (np.pi / 4, 3 * np.pi / 4)
                  for a in (-np.pi / 2, 0.0, np.pi / 2, 0.99 * np.pi)]
        out.append(Candidate("missing_facet", "missing_facet", "", ["miss.arho", "miss.tilt", "miss.az"], starts))
    lim = np.deg2rad(30.0)
    for j, f in enumerate(problem.facets):
        if f.name not in facets:
            continue
        if "offset" in kinds:
            kind = "yaw" if f.tracking else "cant"
            key = f"{kind}.{f.name}"
            if key not in have:
                v = np.deg2rad(f.yaw_deg if f.tracking else f.cant_deg)
                new.append(Param(key, kind, float(v), v - lim, v + lim, index=j))
            out.append(Candidate(f"offset.{f.name}", "offset", f.name, [key],
                                 [{key: np.deg2rad(10.0)}, {key: -np.deg2rad(10.0)}]))
        if "wide_lobe" in kinds:
            ks, kw = f"wide.{f.name}.k", f"wide.{f.name}.w"
            new += [Param(ks, "effect", 0.0, 0.0, 2.0, index=j, target="wide", name="k"),
                    Param(kw, "effect", np.deg2rad(15.0), np.deg2rad(5.0), np.deg2rad(45.0), index=j, target="wide",
                          name="w")]
            out.append(Candidate(f"wide_lobe.{f.name}", "wide_lobe", f.name, [ks, kw],
                                 [{ks: 0.1, kw: np.deg2rad(w)} for w in (10.0, 25.0)]))
        if "out_of_plane" in kinds:
            ks, kd = f"oop.{f.name}.k", f"oop.{f.name}.delta"
            new += [Param(ks, "effect", 0.0, 0.0, 2.0, index=j, target="oop", name="k"),
                    Param(kd, "effect", np.deg2rad(15.0), np.deg2rad(5.0), np.deg2rad(40.0), index=j, target="oop",
                          name="delta")]
            out.append(Candidate(f"out_of_plane.{f.name}", "out_of_plane", f.name, [ks, kd],
                                 [{ks: 0.1, kd: np.deg2rad(d)} for d in (12.0, 25.0)]))
    problem.add(new)
    problem.effect_flux = _effect_flux
    problem._theta_max = np.deg2rad([75.0 if f.max_theta_i_deg is None else f.max_theta_i_deg for f in problem.facets])
    return out


def _effect_flux(problem: SkyProblem, x, d, w_c, w_s):
    """The candidate effects' flux (N,) at parameters ``x`` (facet-frame directions ``w_c``, ``w_s`` (N, J, 3))."""
    idx = {p.key: i for i, p in enumerate(problem.params)}
    scale = jnp.asarray(d.scale)
    area = problem._facets(x).area
    total = jnp.zeros(scale.shape[0])
    if "es.albedo" in idx:
        total = total + x[idx["es.albedo"]] * jnp.sum(jnp.asarray(problem._es_unit) * area[None, :], -1)
    if "miss.arho" in idx:
        t, a = x[idx["miss.tilt"]], x[idx["miss.az"]]
        n = jnp.stack([jnp.sin(t) * jnp.cos(a), jnp.sin(t) * jnp.sin(a), jnp.cos(t)])
        cs = jnp.maximum(jnp.asarray(d.s_b) @ n, 0.0)
        co = jnp.maximum(jnp.asarray(d.o_b) @ n, 0.0)
        total = total + x[idx["miss.arho"]] / np.pi * cs * co * scale
    cos = jnp.maximum(w_c[..., 2], 0.0) * jnp.maximum(w_s[..., 2], 0.0)  # (N, J)
    h = w_c + w_s
    h = h / jnp.maximum(jnp.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    ti = jnp.arctan2(jnp.hypot(w_c[..., 0], w_c[..., 1]), w_c[..., 2])
    pn = jnp.stack([w_c[..., 1], -w_c[..., 0], jnp.zeros_like(w_c[..., 0])], -1)
    pn = pn / jnp.maximum(jnp.linalg.norm(pn, axis=-1, keepdims=True), 1e-12)
    for j, f in enumerate(problem.facets):
        geo = cos[:, j] * area[j] * scale
        kw = f"wide.{f.name}.k"
        if kw in idx:
            k, w = x[idx[kw]], x[idx[f"wide.{f.name}.w"]]
            gate = jnp.asarray(1.0 / (1.0 + jnp.exp(-(ti[:, j] - problem._theta_max[j]) / _GATE)))
            total = total + k * jnp.exp(-(1.0 - h[:, j, 2]) / jnp.square(w)) * gate * geo
        ko = f"oop.{f.name}.k"
        if ko in idx:
            k, dl = x[idx[ko]], x[idx[f"oop.{f.name}.delta"]]
            hz, hp = h[:, j, 2], jnp.sum(h[:, j] * pn[:, j], -1)
            lobe = 0.0
            for sgn in (1.0, -1.0):
                c = jnp.cos(dl) * hz + sgn * jnp.sin(dl) * hp
                lobe = lobe + 0.5 * jnp.exp(-(1.0 - c) / _OOP_WIDTH**2)
            total = total + k * lobe * geo
    return total


def candidates(problem: SkyProblem) -> list[Candidate]:
    """The candidates :func:`add_effects` registered (kept on the problem)."""
    return list(getattr(problem, "_candidates", []))


def _mask(problem: SkyProblem, base: np.ndarray, keys) -> np.ndarray:
    m = base.copy()
    for k in keys:
        m[problem.index(k)] = True
    return m


def _starts(problem: SkyProblem, u: np.ndarray, cand: Candidate) -> list[np.ndarray]:
    out = []
    for st in cand.starts or [{}]:
        v = u.copy()
        for k, val in st.items():
            v[problem.index(k)] = problem.params[problem.index(k)].to_u(val)
        out.append(v)
    return out


def _edge_keys(fit: SkyFit, keys) -> list[str]:
    on = set(fit.on_bound())
    return [k for k in keys if k in on]


def zones(problem: SkyProblem, before: np.ndarray, after: np.ndarray, min_rows: int = 10, top: int = 8) -> list[dict]:
    """Where the residuals changed: per zone (phase angle, each facet's incidence and scattering angle, Sun-observer
    azimuth) the rows, the RMS before and after and the share of the whole RSS reduction; largest shares first.
    Zones with fewer than ``min_rows`` rows or more than 90 % of them are left out."""
    d = problem.data
    rb, ra = d.mag - before, d.mag - after
    total = float(np.sum(rb**2) - np.sum(ra**2))
    x0 = problem.x_of_u(jnp.asarray(problem.u0()))  # the angles of the configured facets
    w_c, w_s, _, _ = problem.facet_terms(x0, jnp.asarray(d.s_b), jnp.asarray(d.o_b))
    ti = np.degrees(np.arctan2(np.hypot(w_c[..., 0], w_c[..., 1]), w_c[..., 2]))
    ts = np.degrees(np.arctan2(np.hypot(w_s[..., 0], w_s[..., 1]), w_s[..., 2]))
    axes = [("phase_deg", d.phase_deg, [0, 30, 60, 90, 120, 180]),
            ("sun_observer_az_deg", d.sun_obs_az_deg, [-180, -120, -60, 0, 60, 120, 180])]
    for j, f in enumerate(problem.facets):
        axes.append((f"theta_i.{f.name}", ti[:, j], [0, 30, 60, 75, 90, 180]))
        axes.append((f"theta_s.{f.name}", ts[:, j], [0, 30, 60, 75, 90, 180]))
    out = []
    for name, v, edges in axes:
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (v >= lo) & (v < hi)
            if m.sum() < min_rows or m.sum() > 0.9 * m.size:  # a zone holding (nearly) every row says nothing
                continue
            red = float(np.sum(rb[m] ** 2) - np.sum(ra[m] ** 2))
            out.append({"axis": name, "range": [lo, hi], "n": int(m.sum()),
                        "rms_before": float(np.sqrt(np.mean(rb[m] ** 2))),
                        "rms_after": float(np.sqrt(np.mean(ra[m] ** 2))),
                        "bias_before": float(np.mean(rb[m])), "bias_after": float(np.mean(ra[m])),
                        "share": red / total if total > 0 else 0.0})
    out.sort(key=lambda z: -z["share"])
    return out[:top]


def diagnose_sky(problem: SkyProblem, cands: list[Candidate], folds: list[np.ndarray] | None = None, *,
                 base_free: np.ndarray | None = None, threshold: float = 10.0, max_steps: int = 3,
                 refit_top: int = 4, log=lambda s: None) -> dict:
    """The diagnosis (see the module docstring): ranking, path, zones and held-out figures (JSON-ready)."""
    t0 = time.perf_counter()
    base_free = problem.default_free() if base_free is None else base_free
    base = problem.fit(base_free)
    log(f"base: -2lnL {base.m2ll:.2f} ({time.perf_counter() - t0:.1f} s)")
    ranking = []
    fits = {}
    for c in cands:
        f = problem.fit(_mask(problem, base_free, c.keys), starts=_starts(problem, base.u, c)[1:],
                        u0=_starts(problem, base.u, c)[0])
        fits[c.name] = f
        edge = _edge_keys(f, c.keys)
        ranking.append({"name": c.name, "kind": c.kind, "facet": c.facet, "delta_bic": f.bic - base.bic,
                        "delta_m2ll": f.m2ll - base.m2ll, "k": len(c.keys), "on_bound": edge,
                        "values": {k: f.values()[k] for k in c.keys}})
    ranking.sort(key=lambda r: r["delta_bic"])
    log(f"ranked {len(cands)} candidates ({time.perf_counter() - t0:.1f} s)")
    path = []
    current, cur_free = base, base_free
    remaining = [r for r in ranking if not r["on_bound"]]
    step_cands = remaining
    for _ in range(max_steps):
        ok = [r for r in step_cands if not r["on_bound"] and r["delta_bic"] < -threshold]
        if not ok:
            break
        best = ok[0]
        c = next(c for c in cands if c.name == best["name"])
        f = fits[c.name] if not path else fits[("step", c.name)]
        before = current.predict()
        after = f.predict()
        path.append({"effect": c.name, "kind": c.kind, "facet": c.facet, "delta_bic": best["delta_bic"],
                     "values": {k: f.values()[k] for k in c.keys}, "zones": zones(problem, before, after),
                     "rms_after": float(np.sqrt(np.mean((problem.data.mag - after) ** 2)))})
        current, cur_free = f, _mask(problem, cur_free, c.keys)
        used = {p["effect"] for p in path}
        step_cands = []
        for r in [r for r in remaining if r["name"] not in used][:refit_top]:
            c2 = next(c for c in cands if c.name == r["name"])
            f2 = problem.fit(_mask(problem, cur_free, c2.keys), u0=_starts(problem, current.u, c2)[0],
                             starts=_starts(problem, current.u, c2)[1:])
            fits[("step", c2.name)] = f2
            step_cands.append({**r, "delta_bic": f2.bic - current.bic, "on_bound": _edge_keys(f2, c2.keys)})
        step_cands.sort(key=lambda r: r["delta_bic"])
    out = {"n": len(problem.data), "base": {"m2ll": base.m2ll, "bic": base.bic, "k": base.k,
                                            "rms": float(np.sqrt(np.mean((problem.data.mag - base.predict()) ** 2))),
                                            "values": base.values()},
           "ranking": ranking, "path": path, "named": path[0]["kind"] if path else None,
           "threshold": threshold}
    if folds is not None:
        cvb = cross_validate(problem, base_free, folds, u0=base.u)
        out["heldout"] = {"base_rms": cvb["rms"], "base_bias": cvb["bias"], "folds": len(folds)}
        if path:
            cvp = cross_validate(problem, cur_free, folds, u0=current.u)
            out["heldout"].update(path_rms=cvp["rms"], path_bias=cvp["bias"])
        out["_heldout_pred"] = {"base": cvb["pred"], "path": cvp["pred"] if path else cvb["pred"]}
    out["final"] = {"values": current.values(), "free": [p.key for i, p in enumerate(problem.params) if cur_free[i]]}
    out["_final_fit"] = current
    out["seconds"] = time.perf_counter() - t0
    log(f"diagnosis done ({out['seconds']:.1f} s): path {[p['effect'] for p in path]}")
    return out
