"""The gap on the sky: which unmodelled effect explains where a facet model misses observed magnitudes.

Given a :class:`~.skyfit.SkyProblem` (a base facet model over one
observation set), the diagnosis is a search over *candidate effects*
(:class:`SkyGapProblem`, implementing the search protocol shared with the
frame and table diagnosis: :class:`SearchProblem`, :func:`search`):

1. the base is fitted (facet areas free; the scatter profiled or the rows'
   uncertainties);
2. the search of :mod:`brdfjax.diagnose.search` (the rule in its docstring):
   at each step every candidate not yet in the set is refitted on top of the
   current model (its parameters physically bounded, several starts where
   the likelihood is multimodal, the current fit as the warm start), the
   ``pair_top`` best in pairs; a refit whose candidate parameter ends on a
   bound (an amplitude at zero, a width at its limit) or whose effect changes
   no row by 1 mmag (dead) is flagged for that effect, which never enters, as
   on tables; the best admissible move improving BIC (``-2 ln L + k ln N``)
   by more than ``bic_threshold`` enters (a *generic* effect, the missing
   facet, not where a specific one explains its residual on their joint
   refit), and after each entry every effect of the set is taken out in turn
   and stays only if its removal costs more than the threshold;
3. each set on the path is cross-validated on held-out groups (whole nights,
   satellites or blocks of rows: :func:`~.skyfit.group_folds`) and
   :func:`zones` says *where* each move changed the residuals (phase angle,
   each facet's incidence and scattering angle, the Sun-observer azimuth
   about body z).

Candidates (:func:`add_effects`; the effect kinds, their fluxes in
:mod:`.skyeffects`):

``earthshine``
    a Lambertian Earth of albedo ``a`` in [0, 1]: ``a`` times each facet's
    earthshine per unit albedo (:func:`~.earthshine.earthshine_flux` on an
    8 x 16 Earth grid with the configured facets and models, computed once),
    scaled with each facet's fitted area.
``offset``
    a facet's normal canted about its x axis (a fixed facet) or a tracking
    array's axis turned about body z (``yaw``), +- 30 deg.
``missing_facet``
    a Lambertian plate the model lacks: ``A rho`` in [0, 5] m^2, its normal at
    ``tilt`` in [0, 180] deg from body +z and azimuth ``az`` about z (generic).
``wide_lobe``
    a lobe beyond the lab's steepest measured incidence on a facet: ``k`` in
    [0, 2] sr^-1, width ``w`` in [5, 45] deg, switched on beyond the facet's
    lab table's largest incidence (75 deg when unknown).
``out_of_plane``
    an offset peak out of the plane of incidence (anisotropy an in-plane lab
    scan cannot see): ``k`` in [0, 2], ``delta`` in [5, 40] deg.
``diffraction``
    a facet-fixed out-of-plane term of the material: the first orders of a
    grating with grooves along the facet's x axis, ``k`` in [0, 2], order
    spacing ``s = lambda / Lambda`` in [0.02, 0.5].
``solar_disk``
    the finite Sun instead of a point Sun: each facet's BRDF integrated over
    the solar disk (:class:`~.engine.SunDisk` ``rings(disk_rings,
    limb_darkening)``, as ``brdfjax observe`` with ``[sun] disk = "rings"``);
    no free parameter.  It matters only where a lobe is not much wider than
    the Sun (0.27 deg radius); with lobes degrees wide it is dead.

A diagnosed model is written as an observe config by
:func:`write_diagnosed_config` (offsets as facet cants and yaws, earthshine
as ``[earthshine]``, the disk as ``[sun]``, the others as ``[effects]``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from ..diagnose.search import SearchProblem, SearchResult, Trial, search
from ..runtime.errors import InputError
from .earthshine import earthshine_flux
from .engine import Attitude, Satellite, SunDisk
from .skyeffects import effects_flux
from .skyfit import Param, SkyFit, SkyProblem, cross_validate

__all__ = ["Candidate", "KINDS", "SkyGapProblem", "Trial", "SearchProblem", "SearchResult", "search", "add_effects",
           "candidates", "diagnose_sky", "zones"]

KINDS = ("earthshine", "offset", "missing_facet", "wide_lobe", "out_of_plane", "diffraction", "solar_disk")
GENERIC = ("missing_facet",)
DEAD_MAG = 1e-3  # an effect changing no row by more than this (mag) is dead
#: the flag of a dead effect (its refit changes no row by DEAD_MAG)
DEAD_FLAG = f"dead (changes no row by {DEAD_MAG * 1e3:g} mmag)"


# --- candidates --------------------------------------------------------------------------------------------------


@dataclass
class Candidate:
    """An effect: its name, kind, the facet it acts on ('' for the satellite), its free parameter keys, starting
    values, and fixed values it sets without freeing them (the solar disk's switch)."""

    name: str
    kind: str
    facet: str
    keys: list[str]
    starts: list[dict[str, float]] = field(default_factory=list)
    fixed: dict[str, float] = field(default_factory=dict)


def _earthshine_unit(problem: SkyProblem, n_psi: int, n_chi: int, earth_radius: float) -> np.ndarray:
    """Each facet's earthshine at albedo 1 per m^2 of its area (N, J), with the base model at its configured values."""
    x0 = problem.x_of_u(jnp.asarray(problem.u0()))
    fac = problem._facets(x0)
    fams = list(dict.fromkeys(f.families[0] for f in problem.facets))
    sat = Satellite(fac, tuple(problem.models[m] for m in fams), Attitude.nadir(*np.deg2rad(problem.data.rpy)),
                    tuple(fams.index(f.families[0]) for f in problem.facets))
    es = np.asarray(earthshine_flux(sat, problem.data.engine, 1.0, n_psi=n_psi, n_chi=n_chi, earth_radius=earth_radius,
                                    wavelength=problem.wavelength))
    return es / np.asarray(fac.area)[None, :]


#: The effects with a strength ``k`` (0 = absent, bounded 0-2) and one shape parameter, per facet: kind ->
#: (parameter prefix and flux target, shape name, shape start, lower, upper bound, the shape's second starts).
_SHAPED = {
    "wide_lobe": ("wide", "w", np.deg2rad(15.0), np.deg2rad(5.0), np.deg2rad(45.0),
                  (np.deg2rad(10.0), np.deg2rad(25.0))),
    "out_of_plane": ("oop", "delta", np.deg2rad(15.0), np.deg2rad(5.0), np.deg2rad(40.0),
                     (np.deg2rad(12.0), np.deg2rad(25.0))),
    "diffraction": ("diff", "s", 0.1, 0.02, 0.5, (0.06, 0.15, 0.3)),
}


def add_effects(problem: SkyProblem, *, kinds=KINDS, facets: list[str] | None = None, earthshine_grid=(8, 16),
                earth_radius: float | None = None, disk_rings: int = 4, limb_darkening: float = 0.6
                ) -> list[Candidate]:
    """Add every candidate's parameters to ``problem`` (each off: zero amplitude, no offset, a point Sun) and its flux
    function; returns the candidates (also kept as ``problem.candidates_``).

    ``facets``: the facets that get facet candidates (default: all).  ``earthshine_grid``: the Earth cap's polar x
    azimuthal elements.  ``earth_radius``: default the rows' own.  ``disk_rings``, ``limb_darkening``: the solar
    disk's rule.
    """
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise InputError(f"effect kinds {unknown} unknown; known: {', '.join(KINDS)}")
    earth_radius = problem.data.geometry.earth_radius if earth_radius is None else earth_radius
    names = [f.name for f in problem.facets]
    facets = names if facets is None else list(facets)
    out: list[Candidate] = []
    new: list[Param] = []
    have = {p.key for p in problem.params}
    if "earthshine" in kinds:
        problem._es_unit = _earthshine_unit(problem, *earthshine_grid, earth_radius)
        problem._es_grid = tuple(earthshine_grid)
        problem._es_radius = float(earth_radius)
        new.append(Param("es.albedo", "effect", 0.0, 0.0, 1.0, target="earthshine", name="albedo"))
        out.append(Candidate("earthshine", "earthshine", "", ["es.albedo"], [{"es.albedo": 0.3}]))
    if "solar_disk" in kinds:
        problem.data = problem.data.with_disk(SunDisk.rings(disk_rings, limb_darkening=limb_darkening))
        problem._disk_rule = (int(disk_rings), float(limb_darkening))
        new.append(Param("disk.on", "effect", 0.0, 0.0, 1.0, target="disk", name="on"))
        out.append(Candidate("solar_disk", "solar_disk", "", [], [{}], fixed={"disk.on": 1.0}))
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
        for kind, (pre, shape, v0, lo, hi, tries) in _SHAPED.items():
            if kind not in kinds:
                continue
            ks, kx = f"{pre}.{f.name}.k", f"{pre}.{f.name}.{shape}"
            new += [Param(ks, "effect", 0.0, 0.0, 2.0, index=j, target=pre, name="k"),
                    Param(kx, "effect", v0, lo, hi, index=j, target=pre, name=shape)]
            out.append(Candidate(f"{kind}.{f.name}", kind, f.name, [ks, kx], [{ks: 0.1, kx: t} for t in tries]))
    problem.add(new)
    problem.effect_flux = _effect_flux
    problem._theta_max = np.deg2rad([75.0 if f.max_theta_i_deg is None else f.max_theta_i_deg for f in problem.facets])
    problem.candidates_ = out
    return out


def _effect_flux(problem: SkyProblem, x, d, w_c, w_s):
    """The candidate effects' flux (N,) at parameters ``x`` (facet-frame directions ``w_c``, ``w_s`` (N, J, 3))."""
    vals = {p.key: x[i] for i, p in enumerate(problem.params)
            if p.kind == "effect" and p.key not in ("es.albedo", "disk.on")}
    area = problem._facets(x).area
    total = effects_flux(vals, [f.name for f in problem.facets], w_c, w_s, d.s_b, d.o_b, d.scale, area,
                         problem._theta_max)
    if any(p.key == "es.albedo" for p in problem.params):
        # each facet's earthshine per m^2 at albedo 1, computed once with the configured facets and models, scaled by
        # the fitted areas: evaluating the Earth grid inside the fit (differentiable in cants and model parameters)
        # made every compiled fit 3-4 times slower to compile; a model diagnosed with earthshine *and* a refitted
        # facet orientation or model therefore reruns in observe to within the earthshine's change with them
        # (skygap.json's rerun_check says how close)
        es = jnp.sum(jnp.asarray(problem._es_unit) * area[None, :], -1)
        total = total + x[problem.index("es.albedo")] * es
    return total


def candidates(problem: SkyProblem) -> list[Candidate]:
    """The candidates :func:`add_effects` registered (kept on the problem)."""
    return list(getattr(problem, "candidates_", []))


# --- the candidates' refits as a search problem ------------------------------------------------------------------


class SkyGapProblem:
    """The sky diagnosis's refits behind :class:`SearchProblem`: effects are :class:`Candidate` names.

    ``folds``: held-out masks (:func:`~.skyfit.group_folds`); the held-out
    figure of a trial (:meth:`heldout`) is the RMS of observed minus
    predicted magnitude over every row, each predicted by the refit on the
    other folds.  ``base_free``: the base's free mask (default: the areas and,
    if asked, the scatter).
    """

    def __init__(self, problem: SkyProblem, cands: list[Candidate] | None = None,
                 folds: list[np.ndarray] | None = None, base_free: np.ndarray | None = None, max_starts: int = 8):
        self.problem = problem
        self.cands = {c.name: c for c in (cands if cands is not None else candidates(problem))}
        self.folds = folds
        self.base_free = problem.default_free() if base_free is None else np.asarray(base_free, bool)
        self.max_starts = max_starts
        self.cv: dict[tuple[str, ...], dict] = {}
        self.n_refits = 0
        self._last: dict[str, dict[str, float]] = {}  # each effect's fitted u of its keys in its latest refit

    def candidates(self) -> list[str]:
        return list(self.cands)

    def generic(self, effect: str) -> bool:
        return self.cands[effect].kind in GENERIC

    def mask(self, effects) -> np.ndarray:
        m = self.base_free.copy()
        for e in effects:
            for k in self.cands[e].keys:
                m[self.problem.index(k)] = True
        return m

    def _trial(self, effects: tuple[str, ...], fit: SkyFit | None, failure: str | None = None) -> Trial:
        if fit is None:
            return Trial(effects, False, failure, np.inf, np.inf, int(self.mask(effects).sum()), None, {})
        P = self.problem
        d = P.data
        pred = fit.predict()
        r = d.mag - pred
        has = np.isfinite(d.mag_err) & (d.mag_err > 0)
        s = fit.values()["scatter"]
        var = np.where(has, np.where(has, d.mag_err, 1.0) ** 2 + s**2, np.mean(r[~has] ** 2) if (~has).any() else 1.0)
        chi2 = float(np.sum(r**2 / var) / max(len(d) - fit.k, 1))
        on = set(fit.on_bound())
        flags: dict[str, list[str]] = {}
        for e in effects:
            c = self.cands[e]
            flags[e] = [f"{k} on its bound" for k in c.keys if k in on]
            # an effect that changes no row: the fit with its parameters set back to off predicts the same
            u = fit.u.copy()
            for k in [*c.keys, *c.fixed]:
                u[P.index(k)] = P.params[P.index(k)].to_u(P.params[P.index(k)].value)
            if np.max(np.abs(P.predict(u) - pred)) < DEAD_MAG:
                flags[e].append(DEAD_FLAG)
        return Trial(effects, True, None, float(fit.bic), chi2, fit.k, None, flags, fit)

    def base(self) -> Trial:
        return self._trial((), self.problem.fit(self.base_free))

    def refit(self, effects: tuple[str, ...], warm: Trial | None) -> Trial:
        P = self.problem
        self.n_refits += 1
        u = (warm.state.u if warm is not None and warm.state is not None else P.u0()).copy()
        have = set(warm.effects) if warm is not None else set()
        new = [self.cands[e] for e in effects if e not in have]
        for c in self.cands.values():  # effects not in this trial are off (a warm start of another branch)
            if c.name not in effects:
                for k in [*c.keys, *c.fixed]:
                    u[P.index(k)] = P.params[P.index(k)].to_u(P.params[P.index(k)].value)
        for c in new:
            for k, v in c.fixed.items():
                u[P.index(k)] = P.params[P.index(k)].to_u(v)
        # an effect refitted before (an earlier step or a single before a pair) starts where it ended and from its
        # first listed start; a new one from each listed start (multimodal: the missing facet's orientation)
        starts = []
        opts = [[("u", self._last[c.name]), ("x", (c.starts or [{}])[0])] if c.name in self._last and c.keys
                else [("x", st) for st in (c.starts or [{}])] for c in new]
        for combo in itertools.islice(itertools.product(*opts), self.max_starts):
            v = u.copy()
            for how, st in combo:
                for k, val in st.items():
                    v[P.index(k)] = val if how == "u" else P.params[P.index(k)].to_u(val)
            starts.append(v)
        starts = starts or [u]
        if warm is not None and warm.ok and len(new) == 1 and not new[0].keys:
            # an effect without free parameters (the solar disk) that changes no row at the warm start is dead
            # there: no refit (the disk's rule costs its node count in every evaluation)
            if np.max(np.abs(P.predict(starts[0]) - warm.state.predict())) < DEAD_MAG:
                w = warm.state
                f0 = SkyFit(P, starts[0], w.free, P.m2ll(starts[0], w.w, w.joint), w.n, 0, w.w, w.joint)
                t = self._trial(effects, f0)
                if DEAD_FLAG not in t.flags[new[0].name]:
                    t.flags[new[0].name].append(DEAD_FLAG)
                return t
        try:
            fit = P.fit(self.mask(effects), u0=starts[0], starts=starts[1:])
        except Exception as e:  # noqa: BLE001 -- a refit that cannot be evaluated is a failed trial, counted
            return self._trial(effects, None, f"{type(e).__name__}: {e}")
        for e in effects:
            self._last[e] = {k: float(fit.u[P.index(k)]) for k in self.cands[e].keys}
        return self._trial(effects, fit)

    def heldout(self, trial: Trial) -> float | None:
        """Cross-validated RMS (mag) of the trial's model (its free mask, refitted on each training fold)."""
        if self.folds is None or not trial.ok:
            return None
        cv = cross_validate(self.problem, trial.state.free, self.folds, u0=trial.state.u)
        self.cv[trial.effects] = cv
        return float(cv["rms"])


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


def _step_entry(gp: SkyGapProblem, prev: Trial, t: Trial, action: str = "add") -> dict:
    """One move of the path: the effects it added (one, or a pair jointly) or removed, its BIC change, the values
    of the added effects' parameters, where it changed the residuals and the held-out figure of the set after it."""
    P = gp.problem
    moved = [e for e in t.effects if e not in prev.effects] if action == "add" else \
        [e for e in prev.effects if e not in t.effects]
    vals = t.state.values()
    before, after = prev.state.predict(), t.state.predict()
    sign = "" if action == "add" else "-"
    return {"action": action, "effect": sign + "+".join(moved), "effects": moved,
            "kind": "+".join(gp.cands[e].kind for e in moved), "facet": "+".join(gp.cands[e].facet for e in moved),
            "set": list(t.effects), "delta_bic": t.bic - prev.bic, "chi2_reduced": t.chi2_reduced,
            "values": {k: vals[k] for e in moved for k in gp.cands[e].keys} if action == "add" else {},
            "fixed": {k: v for e in moved for k, v in gp.cands[e].fixed.items()} if action == "add" else {},
            "zones": zones(P, before, after),
            "rms_after": float(np.sqrt(np.mean((P.data.mag - after) ** 2))), "heldout_rms": t.heldout}


def diagnose_sky(problem: SkyProblem, cands: list[Candidate] | None = None, folds: list[np.ndarray] | None = None, *,
                 base_free: np.ndarray | None = None, threshold: float = 10.0, max_steps: int = 3,
                 pair_top: int = 3, log=lambda s: None) -> dict:
    """The diagnosis (see the module docstring) through :func:`search`: ranking of the first step, path (each
    accepted move: an effect or a pair added, an effect taken out), zones and held-out figures (JSON-ready;
    ``_search``, ``_path`` (the base and the set after each move), ``_final_fit`` and ``_heldout_pred`` are for
    callers)."""
    t0 = time.perf_counter()
    gp = SkyGapProblem(problem, cands, folds, base_free)
    res = search(gp, bic_threshold=threshold, max_steps=max_steps, pair_top=pair_top, progress=log)
    base = res.base
    if not base.ok:
        raise InputError(f"sky diagnosis: the base fit failed ({base.failure})")
    trials = [base] + [m.trial for m in res.moves]
    for t in trials:  # the held-out figure of every set on the path (the search itself ranks by BIC)
        if t.heldout is None:
            t.heldout = gp.heldout(t)
    ranking = []
    for t in (res.singles[0] if res.singles else []):
        c = gp.cands[t.effects[-1]]
        ranking.append({"name": c.name, "kind": c.kind, "facet": c.facet, "ok": t.ok, "failure": t.failure,
                        "delta_bic": t.bic - base.bic, "k": len(c.keys),
                        "on_bound": [k for k in c.keys if t.ok and k in t.state.on_bound()],
                        "dead": any(f.startswith("dead") for f in t.flags.get(c.name, [])),
                        "flags": list(t.flags.get(c.name, [])),
                        "values": {k: t.state.values()[k] for k in c.keys} if t.ok else {}})
    ranking.sort(key=lambda r: r["delta_bic"])
    path = [_step_entry(gp, a, m.trial, m.action) for a, m in zip(trials[:-1], res.moves)]
    current = res.final
    first = res.moves[0].effects[0] if res.moves else None
    d = problem.data
    out = {"n": len(d), "base": {"m2ll": base.state.m2ll, "bic": base.bic, "k": base.n_params,
                                 "rms": float(np.sqrt(np.mean((d.mag - base.state.predict()) ** 2))),
                                 "chi2_reduced": base.chi2_reduced, "heldout_rms": base.heldout,
                                 "values": base.state.values()},
           "ranking": ranking, "path": path, "named": gp.cands[first].kind if first else None,
           "effects": list(current.effects), "threshold": threshold, "stopped": res.stop_reason,
           "refits": len(res.trials) - 1, "failed_refits": res.n_failed}
    if folds is not None:
        out["heldout"] = {"base_rms": base.heldout, "base_bias": gp.cv[()]["bias"], "folds": len(folds)}
        if path:
            out["heldout"].update(path_rms=current.heldout, path_bias=gp.cv[current.effects]["bias"])
        out["_heldout_pred"] = {"base": gp.cv[()]["pred"], "path": gp.cv[current.effects]["pred"]}
    out["final"] = {"values": current.state.values(),
                    "free": [p.key for i, p in enumerate(problem.params) if current.state.free[i]]}
    out["_final_fit"] = current.state
    out["_search"] = res
    out["_path"] = trials
    out["_gap_problem"] = gp
    out["seconds"] = time.perf_counter() - t0
    log(f"diagnosis done ({out['seconds']:.1f} s): path {[p['effect'] for p in path]}")
    return out
