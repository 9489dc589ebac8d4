"""Withheld-effect benchmark on the sky: does the sky gap diagnosis name the effect a synthetic set was made with?

Observation sets are synthesised by brdfjax's forward model (:mod:`brdfjax.lightcurve.skyfit`) at the geometry
of the real V2 Mini rows (the Slingshot set's relative rows: no uncertainties, Gaussian noise of 0.15 mag, the
scatter profiled; the SCORE set's absolute rows: noise drawn with each row's own uncertainty) from a three-facet
model (a nadir chassis, a canted side panel, a Sun-tracking array; lumos-sat Phong materials) with one effect
added to the truth and withheld from the base: earthshine (albedo 0.3), an array offset (its axis turned 15 deg),
a missing Lambertian facet, a wide lobe beyond the chassis' measured incidence (60 deg), an out-of-plane offset
peak on the chassis; plus null sets (nothing added).  The diagnosis (:func:`brdfjax.lightcurve.skygap.diagnose_sky`)
refits the base (facet areas free) with each candidate; a trial passes when the withheld effect's kind is named
first on the path and the path's held-out RMS (whole nights for SCORE, blocks of rows for Slingshot) is within
20 % of the truth's own RMS; a null trial passes when the path is empty.

    PYTHONPATH=$PWD python experiments/sky_withheld.py [--trials 3] [--nulls 6] [--rows 300]
    PYTHONPATH=$PWD python experiments/sky_withheld.py --sizes --trials 4   # each effect's size at the rows, no fit

Writes experiments/results/sky_withheld.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from brdfjax.io.observations import read_observations  # noqa: E402
from brdfjax.lightcurve.models import lumos_phong  # noqa: E402
from brdfjax.lightcurve.observe import FacetSpec  # noqa: E402
from brdfjax.lightcurve.skyfit import SkyProblem, block_groups, group_folds, night_groups, sky_data  # noqa: E402
from brdfjax.lightcurve.skygap import add_effects, diagnose_sky  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OBS = ROOT / "tests/data/satellites/observations"

#: the withheld effect -> the truth's parameter values (natural units)
EFFECTS = {
    "earthshine": {"es.albedo": 0.3},
    # a bright (cloud-covered) Earth: twice lumos-sat's default albedo
    "earthshine@bright": {"es.albedo": 0.6},
    # the same on all of the trial's rows (not only those near the terminator): the rows where earthshine is nil
    # are where an effect that mimics it near the terminator (a chassis cant) shows
    "earthshine@bright_all_rows": {"es.albedo": 0.6},
    "offset": {"yaw.array": np.deg2rad(15.0)},
    "missing_facet": {"miss.arho": 1.5, "miss.tilt": np.deg2rad(50.0), "miss.az": np.deg2rad(90.0)},
    "wide_lobe": {"wide.chassis.k": 0.4, "wide.chassis.w": np.deg2rad(20.0)},
    "out_of_plane": {"oop.chassis.k": 0.6, "oop.chassis.delta": np.deg2rad(15.0)},
    # the same offset peak 2.5 times as bright (a variant: "kind@label" is scored on its kind)
    "out_of_plane@strong": {"oop.chassis.k": 1.5, "oop.chassis.delta": np.deg2rad(15.0)},
    # grating orders of the chassis out of its lab scan plane (grooves along its x axis)
    "diffraction": {"diff.chassis.k": 0.6, "diff.chassis.s": 0.15},
    # the finite Sun on a glinting side panel (its model sharp in both truth and base: see SHARP_SIDE)
    "solar_disk": {"disk.on": 1.0},
}

#: the side panel's material in the solar-disk trials: a bright Phong lobe about 0.3 deg wide (exponent 3.6e4), so
#: that the Sun's 0.27-deg radius changes the glint; the SCORE rows within a few degrees of that panel's specular
#: direction are the only real rows where a disk can show (no Slingshot row comes within 10 deg of any facet's)
SHARP_SIDE = (0.1, 0.5, 3.6e4)
#: the rows of each trial: the solar-disk trials take SCORE nights holding rows within this angle of the side
#: panel's specular direction first; the earthshine trials take only rows where the Sun is less than
#: EARTHSHINE_SUN_BELOW_DEG below the satellite's horizontal (the nadir faces then see the Sun at grazing incidence
#: and more of the lit Earth: earthshine is largest there, 10-100 times its size elsewhere;
#: experiments/sky_earthshine_size.py)
DISK_NEAR_DEG = 5.0
EARTHSHINE_SUN_BELOW_DEG = 10.0


def facets_and_models(sharp_side: bool = False):
    models = {"chassis": lumos_phong(0.05, 0.4, 8.0),
              "side": lumos_phong(*SHARP_SIDE) if sharp_side else lumos_phong(0.1, 0.2, 4.0),
              "array": lumos_phong(0.02, 0.3, 20.0)}
    facets = [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"], max_theta_i_deg=60.0),
              FacetSpec("side", 3.0, (0, 0.7071, -0.7071), ["side"], max_theta_i_deg=60.0),
              FacetSpec("array", 5.0, (0, 1.0, 0.0), ["array"], x_axis=(1.0, 0, 0), tracking=True)]
    return facets, models


def _load(which: str):
    if which == "slingshot":
        obs = read_observations(OBS / "slingshot_v2mini.csv", "slingshot")
        return obs, sky_data("slingshot", obs, convention="lumos", earth_radius=6378000.0)
    obs = read_observations(OBS / "score_v2mini.csv", "score")
    return obs, sky_data("score", obs, convention="physical", band_map={"CLEAR": "V"})


def _near_side_specular(d) -> np.ndarray:
    """Rows (kept rows of ``d``) within DISK_NEAR_DEG of the side panel's specular direction."""
    facets, models = facets_and_models()
    P = SkyProblem.build(d, facets, models, normals="lumos")
    w_c, w_s, _, _ = P.facet_terms(P.x_of_u(jnp.asarray(P.u0())), jnp.asarray(d.s_b), jnp.asarray(d.o_b))
    w_c, w_s = np.asarray(w_c)[:, 1], np.asarray(w_s)[:, 1]
    ang = np.degrees(np.arccos(np.clip(np.sum(w_c * np.array([-1, -1, 1.0]) * w_s, -1), -1, 1)))
    return (w_c[:, 2] > 0) & (w_s[:, 2] > 0) & (ang < DISK_NEAR_DEG)


def geometry(which: str, rows: int, seed: int, select: str | None = None):
    """The rows of one trial.  ``select``: ``"earthshine"`` keeps only rows with the Sun less than
    EARTHSHINE_SUN_BELOW_DEG below the satellite's horizontal; ``"solar_disk"`` takes the SCORE nights holding rows
    near the side panel's specular direction first."""
    rng = np.random.default_rng(seed)
    obs, full = _load(which)
    if select == "earthshine":
        ok = full.geometry.sun_elevation_at_satellite_deg() > -EARTHSHINE_SUN_BELOW_DEG
        obs = obs.take(full.geometry.keep[ok])
    if which == "slingshot":
        k = max(1, len(obs) // rows)
        start = rng.integers(0, k)
        obs = obs.take(np.arange(start, len(obs), k)[:rows])  # every k-th row: passes stay contiguous
        d = sky_data("slingshot", obs, convention="lumos", earth_radius=6378000.0)
        groups = block_groups(len(d), 10)
    else:
        nights = night_groups(obs)
        pick = list(rng.permutation(np.unique(nights)))
        if select == "solar_disk":
            near = np.zeros(len(obs), bool)
            near[full.geometry.keep[_near_side_specular(full)]] = True
            first = [g for g in pick if near[nights == g].any()]
            pick = first + [g for g in pick if g not in first]
        keep, n = [], 0
        for g in pick:  # whole nights until ``rows``
            idx = np.flatnonzero(nights == g)
            keep.extend(idx.tolist())
            n += idx.size
            if n >= rows:
                break
        obs = obs.take(np.sort(np.asarray(keep)))
        d = sky_data("score", obs, convention="physical", band_map={"CLEAR": "V"})
        groups = night_groups(d.obs)
    return d, groups


def setup(which: str, effect: str | None, rows: int, seed: int):
    """The problem of one trial (candidates added), the truth's ``u``, the row groups and the set actually used."""
    kind = None if effect is None else effect.split("@")[0]
    if kind == "solar_disk":
        which = "score"  # only SCORE rows come near a facet's specular direction
    select = kind if kind in ("earthshine", "solar_disk") and not effect.endswith("all_rows") else None
    d, groups = geometry(which, rows, seed, select=select)
    facets, models = facets_and_models(sharp_side=kind == "solar_disk")
    P = SkyProblem.build(d, facets, models, normals="lumos")
    cands = add_effects(P, earth_radius=6378000.0 if which == "slingshot" else 6378137.0)
    truth = P.u0()
    for k, v in (EFFECTS[effect] if effect else {}).items():
        truth[P.index(k)] = P.params[P.index(k)].to_u(v)
    return P, cands, truth, groups, which


def trial(which: str, effect: str | None, rows: int, seed: int, log) -> dict:
    kind = None if effect is None else effect.split("@")[0]
    P, cands, truth, groups, which = setup(which, effect, rows, seed)
    d = P.data
    clean = P.predict(truth)
    rng = np.random.default_rng(1000 + seed)
    if which == "slingshot":
        err = np.full(len(d), np.nan)
        noise = 0.15 * rng.standard_normal(len(d))
    else:
        err = np.where(np.isfinite(d.mag_err) & (d.mag_err > 0), d.mag_err, 0.2)
        noise = err * rng.standard_normal(len(d))
    P.data = d.with_mag(clean + noise, err)  # d: the rows with the solar-disk nodes
    P._fns.clear()
    folds = group_folds(groups, 5, seed=seed)
    res = diagnose_sky(P, cands, folds, log=log)
    truth_rms = float(np.sqrt(np.mean(noise**2)))
    # how detectable the withheld effect is at these rows and this noise: its noiseless change of the magnitudes
    # in units of the noise (chi^2 of truth - base), against what it must gain to enter (the threshold plus its
    # parameters' BIC penalty); an effect below that cannot be named by any test on these rows
    dm = clean - P.predict(P.u0())
    sig = np.where(np.isfinite(err), err, 0.15)
    signal_chi2 = float(np.sum((dm / sig) ** 2))
    k_eff = max(len(EFFECTS[effect]) if effect else 0, 1)
    needed = float(res["threshold"] + k_eff * np.log(len(d)))
    h = res["heldout"]
    path_rms = h.get("path_rms", h["base_rms"])
    named = res["named"]
    ok = (named is None) if effect is None else (named == kind and path_rms <= 1.2 * truth_rms)
    return {"set": which, "withheld": effect, "seed": seed, "n": res["n"], "named": named,
            "path": [p["effect"] for p in res["path"]], "truth_rms": truth_rms, "base_heldout_rms": h["base_rms"],
            "path_heldout_rms": path_rms, "pass": bool(ok), "seconds": res["seconds"],
            "refits": res["refits"], "failed_refits": res["failed_refits"],
            "effect_rms_mag": float(np.sqrt(np.mean(dm**2))), "noise_rms_mag": float(np.sqrt(np.mean(noise**2))),
            "signal_chi2": signal_chi2, "signal_chi2_needed": needed,
            "detectable": bool(effect is None or signal_chi2 > needed),
            "gap_ratio": float(path_rms / truth_rms), "stopped": res["stopped"],
            "ranking_top3": [{k: r[k] for k in ("name", "delta_bic", "on_bound", "dead")} for r in res["ranking"][:3]],
            "zones_first_step": res["path"][0]["zones"][:3] if res["path"] else []}


def effect_sizes(rows: int, seeds, log, effects=tuple(EFFECTS)) -> list[dict]:
    """How much each withheld effect changes the noiseless magnitudes at its trial's rows (no fit): RMS and the 90th
    percentile of |truth - base| (mag), and for earthshine its share of the flux."""
    out = []
    for seed in seeds:
        for eff in effects:
            P, _, truth, _, which = setup(("slingshot", "score")[seed % 2], eff, rows, seed)
            base = P.predict(P.u0())
            dm = np.abs(P.predict(truth) - base)
            row = {"set": which, "seed": seed, "effect": eff, "rows": len(base),
                   "rms_mag": float(np.sqrt(np.mean(dm**2))), "p90_mag": float(np.percentile(dm, 90)),
                   "max_mag": float(np.max(dm))}
            if eff == "earthshine":
                per, _ = P.flux(P.x_of_u(P.u0()))
                es = 0.3 * np.sum(P._es_unit * np.asarray([f.area for f in P.facets])[None, :], -1)
                row["flux_share_p50_p90"] = [float(x) for x in np.percentile(es / np.asarray(per).sum(-1), [50, 90])]
            out.append(row)
            log(f"{which:9s} seed {seed} {eff:20s} {len(base)} rows |truth - base| RMS {row['rms_mag']:.4f} mag, "
                f"p90 {row['p90_mag']:.4f}, max {row['max_mag']:.3f}"
                + (f", flux share p50/p90 {row['flux_share_p50_p90']}" if "flux_share_p50_p90" in row else ""))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--nulls", type=int, default=6)
    ap.add_argument("--rows", type=int, default=1583, help="rows per trial (1583: every Slingshot row; SCORE: whole "
                    "nights until this many)")
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--set", choices=("alternate", "slingshot", "score"), default="alternate",
                    help="the real set whose geometry the trials take (alternate: Slingshot on even seeds, SCORE on odd)")
    ap.add_argument("--out", default=str(ROOT / "experiments/results/sky_withheld_full_rows.json"))
    ap.add_argument("--until", default=None, help="stop starting trials after this UTC time (HH:MM)")
    ap.add_argument("--sizes", action="store_true", help="only measure each effect's size at the rows (no diagnosis)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.sizes:
        data = json.loads(out.read_text()) if out.exists() else {}
        data["effect_sizes"] = effect_sizes(a.rows, range(a.first_seed, a.first_seed + a.trials), print,
                                           [e for e in a.effects.split(",") if e])
        write_json_atomic(out, data)
        return 0
    done = json.loads(out.read_text())["trials"] if out.exists() else []
    seen = {(t["set"], t["withheld"], t["seed"]) for t in done}
    seeds = range(a.first_seed, a.first_seed + a.trials)
    # seed by seed (every effect gets its first trial before any gets its second), nulls in between
    plan = []

    def which_of(s: int) -> str:
        return ("slingshot", "score")[s % 2] if a.set == "alternate" else a.set

    for s in range(a.first_seed, a.first_seed + max(a.trials, a.nulls)):
        if s in seeds:
            plan += [(which_of(s), e, s) for e in a.effects.split(",") if e]
        if s < a.first_seed + a.nulls:
            plan.append((which_of(s), None, s))
    t0 = time.perf_counter()
    for which, eff, seed in plan:
        if (which, eff, seed) in seen:
            continue
        if a.until and time.strftime("%H:%M", time.gmtime()) >= a.until:
            print(f"stopped at {a.until} UTC: trials not run from ({which}, {eff}, seed {seed}) on")
            break
        r = trial(which, eff, a.rows, seed, log=lambda s: None)
        done.append(r)
        print(f"{which:9s} {str(eff):14s} seed {seed} {r['n']} rows: named {r['named']} path {r['path']} held-out "
              f"{r['path_heldout_rms']:.3f} (base {r['base_heldout_rms']:.3f}, truth {r['truth_rms']:.3f}); effect "
              f"RMS {r['effect_rms_mag']:.3f} mag, signal chi2 {r['signal_chi2']:.0f} (needs {r['signal_chi2_needed']:.0f}) "
              f"{'PASS' if r['pass'] else 'FAIL'} {r['seconds']:.0f} s", flush=True)
        summary = {}
        for t in done:
            s = summary.setdefault(str(t["withheld"]), {"trials": 0, "passed": 0, "named_first": 0, "detectable": 0})
            s["trials"] += 1
            s["passed"] += t["pass"]
            s["detectable"] += bool(t.get("detectable", True))
            s["named_first"] += ((t["named"] == t["withheld"].split("@")[0]) if t["withheld"]
                                 else (t["named"] is None))
        old = json.loads(out.read_text()) if out.exists() else {}
        write_json_atomic(out, json.loads(json.dumps({**old, "summary": summary, "trials": done,
                                                      "elapsed_s_this_run": time.perf_counter() - t0}, default=float)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
