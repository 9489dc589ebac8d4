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
    "offset": {"yaw.array": np.deg2rad(15.0)},
    "missing_facet": {"miss.arho": 1.5, "miss.tilt": np.deg2rad(50.0), "miss.az": np.deg2rad(90.0)},
    "wide_lobe": {"wide.chassis.k": 0.4, "wide.chassis.w": np.deg2rad(20.0)},
    "out_of_plane": {"oop.chassis.k": 0.6, "oop.chassis.delta": np.deg2rad(15.0)},
    # the same offset peak 2.5 times as bright (a variant: "kind@label" is scored on its kind)
    "out_of_plane@strong": {"oop.chassis.k": 1.5, "oop.chassis.delta": np.deg2rad(15.0)},
}


def facets_and_models():
    models = {"chassis": lumos_phong(0.05, 0.4, 8.0), "side": lumos_phong(0.1, 0.2, 4.0),
              "array": lumos_phong(0.02, 0.3, 20.0)}
    facets = [FacetSpec("chassis", 12.0, (0, 0, -1.0), ["chassis"], max_theta_i_deg=60.0),
              FacetSpec("side", 3.0, (0, 0.7071, -0.7071), ["side"], max_theta_i_deg=60.0),
              FacetSpec("array", 5.0, (0, 1.0, 0.0), ["array"], x_axis=(1.0, 0, 0), tracking=True)]
    return facets, models


def geometry(which: str, rows: int, seed: int):
    rng = np.random.default_rng(seed)
    if which == "slingshot":
        obs = read_observations(OBS / "slingshot_v2mini.csv", "slingshot")
        start = rng.integers(0, max(1, len(obs) - rows * 4))
        obs = obs.take(np.arange(start, len(obs), 4)[:rows])  # every 4th row: passes stay contiguous
        d = sky_data("slingshot", obs, convention="lumos", earth_radius=6378000.0)
        groups = block_groups(len(d), 10)
    else:
        obs = read_observations(OBS / "score_v2mini.csv", "score")
        nights = night_groups(obs)
        pick = rng.permutation(np.unique(nights))
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


def trial(which: str, effect: str | None, rows: int, seed: int, log) -> dict:
    d, groups = geometry(which, rows, seed)
    facets, models = facets_and_models()
    P = SkyProblem.build(d, facets, models, normals="lumos")
    cands = add_effects(P, earth_radius=6378000.0 if which == "slingshot" else 6378137.0)
    truth = P.u0()
    for k, v in (EFFECTS[effect] if effect else {}).items():
        truth[P.index(k)] = P.params[P.index(k)].to_u(v)
    clean = P.predict(truth)
    rng = np.random.default_rng(1000 + seed)
    if which == "slingshot":
        err = np.full(len(d), np.nan)
        noise = 0.15 * rng.standard_normal(len(d))
    else:
        err = np.where(np.isfinite(d.mag_err) & (d.mag_err > 0), d.mag_err, 0.2)
        noise = err * rng.standard_normal(len(d))
    P.data = d.with_mag(clean + noise, err)
    P._fns.clear()
    folds = group_folds(groups, 5, seed=seed)
    res = diagnose_sky(P, cands, folds, log=log)
    truth_rms = float(np.sqrt(np.mean(noise**2)))
    h = res["heldout"]
    path_rms = h.get("path_rms", h["base_rms"])
    named = res["named"]
    kind = None if effect is None else effect.split("@")[0]
    ok = (named is None) if effect is None else (named == kind and path_rms <= 1.2 * truth_rms)
    return {"set": which, "withheld": effect, "seed": seed, "n": res["n"], "named": named,
            "path": [p["effect"] for p in res["path"]], "truth_rms": truth_rms, "base_heldout_rms": h["base_rms"],
            "path_heldout_rms": path_rms, "pass": bool(ok), "seconds": res["seconds"],
            "ranking_top3": [{k: r[k] for k in ("name", "delta_bic", "on_bound")} for r in res["ranking"][:3]],
            "zones_first_step": res["path"][0]["zones"][:3] if res["path"] else []}


def effect_sizes(rows: int, seeds, log) -> list[dict]:
    """How much each withheld effect changes the noiseless magnitudes at the real rows (no fit): RMS and the 90th
    percentile of |truth - base| (mag), and for earthshine its share of the flux."""
    out = []
    for seed in seeds:
        which = ("slingshot", "score")[seed % 2]
        d, _ = geometry(which, rows, seed)
        facets, models = facets_and_models()
        P = SkyProblem.build(d, facets, models, normals="lumos")
        add_effects(P, earth_radius=6378000.0 if which == "slingshot" else 6378137.0)
        base = P.predict(P.u0())
        per, _ = P.flux(P.x_of_u(P.u0()))
        direct = np.asarray(per).sum(-1)
        for eff, vals in EFFECTS.items():
            u = P.u0()
            for k, v in vals.items():
                u[P.index(k)] = P.params[P.index(k)].to_u(v)
            dm = np.abs(P.predict(u) - base)
            row = {"set": which, "seed": seed, "effect": eff, "rms_mag": float(np.sqrt(np.mean(dm**2))),
                   "p90_mag": float(np.percentile(dm, 90))}
            if eff == "earthshine":
                es = 0.3 * np.sum(P._es_unit * np.asarray([f.area for f in facets])[None, :], -1)
                row["flux_share_p50_p90"] = [float(x) for x in np.percentile(es / direct, [50, 90])]
            out.append(row)
            log(f"{which:9s} seed {seed} {eff:20s} |truth - base| RMS {row['rms_mag']:.4f} mag, p90 {row['p90_mag']:.4f}"
                + (f", flux share p50/p90 {row['flux_share_p50_p90']}" if "flux_share_p50_p90" in row else ""))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--nulls", type=int, default=6)
    ap.add_argument("--rows", type=int, default=300)
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "experiments/results/sky_withheld.json"))
    ap.add_argument("--sizes", action="store_true", help="only measure each effect's size at the rows (no diagnosis)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.sizes:
        data = json.loads(out.read_text()) if out.exists() else {}
        data["effect_sizes"] = effect_sizes(a.rows, range(a.first_seed, a.first_seed + a.trials), print)
        write_json_atomic(out, data)
        return 0
    done = json.loads(out.read_text())["trials"] if out.exists() else []
    seen = {(t["set"], t["withheld"], t["seed"]) for t in done}
    seeds = range(a.first_seed, a.first_seed + a.trials)
    plan = [(("slingshot", "score")[s % 2], e, s) for e in a.effects.split(",") if e for s in seeds]
    plan += [(("slingshot", "score")[s % 2], None, s) for s in range(a.first_seed, a.first_seed + a.nulls)]
    t0 = time.perf_counter()
    for which, eff, seed in plan:
        if (which, eff, seed) in seen:
            continue
        r = trial(which, eff, a.rows, seed, log=lambda s: None)
        done.append(r)
        print(f"{which:9s} {str(eff):14s} seed {seed}: named {r['named']} path {r['path']} held-out "
              f"{r['path_heldout_rms']:.3f} (base {r['base_heldout_rms']:.3f}, truth {r['truth_rms']:.3f}) "
              f"{'PASS' if r['pass'] else 'FAIL'} {r['seconds']:.0f} s", flush=True)
        summary = {}
        for t in done:
            s = summary.setdefault(str(t["withheld"]), {"trials": 0, "passed": 0, "named_first": 0})
            s["trials"] += 1
            s["passed"] += t["pass"]
            s["named_first"] += ((t["named"] == t["withheld"].split("@")[0]) if t["withheld"]
                                 else (t["named"] is None))
        old = json.loads(out.read_text()) if out.exists() else {}
        write_json_atomic(out, json.loads(json.dumps({**old, "summary": summary, "trials": done,
                                                      "elapsed_s_this_run": time.perf_counter() - t0}, default=float)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
