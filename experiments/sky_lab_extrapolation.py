"""Which model family extrapolates a lab table beyond its measured incidences: a lab-only cross-validation.

For each Starlink V2 Mini lab table (five in-plane tables, incidences 5, 41.4, 60 and 75 deg) and each
candidate family (every one + Lambertian):

- ``abg``: Harvey-Shack ABg;  ``abg2``: two ABg lobes (a narrow core and a wide halo);
- ``phong``: normalised Phong (lumos-sat's PHONG family);
- ``ggx``: GGX microfacet, Smith shadowing, Fresnel at the microfacet angle, index fixed (1.5 for films and
  coatings, aluminium 0.96 + 6.69i for the bare chassis);  ``ggx_n`` / ``beckmann_n``: the same with GGX or
  Beckmann and a fitted real index (Fresnel's grazing rise set by the data);
- ``spike_halo``: two GGX lobes (spike and halo) sharing one fixed index, Smith shadowing of each lobe;
- ``binomial``: Greynolds' binomial (lumos-sat's family; started at the ABg fit),

the family is fitted (a) on all but the steepest incidence and scored on the withheld 75-deg slice
(``steepest``: the extrapolation the sky needs, whose rows light the chassis beyond 75 deg) and (b) on every
leave-one-incidence-out fold (``loio``: the pooled held-out log-RMS of the four folds).  Scores are the RMS of
ln(model / measured) over the held-out rows.  No observation enters anything here: the choice per table is the
family with the smallest ``steepest`` score (``loio`` reported beside it), and model-averaging weights are
``w_k ∝ 1 / score_k^2`` (inverse held-out mean-square error, over the families whose out-of-plane shape
follows from the in-plane data by symmetry).  The full fits (every incidence) go to ``configs/v2mini/`` as
``<table>_<family>.result.json`` / ``.terms.toml`` (read by ``brdfjax observe``).

Results: ``experiments/results/sky_lab_extrapolation.json`` (resumable: finished (table, family, fold) entries
are kept; ``--fresh`` starts over).

    PYTHONPATH=$PWD python experiments/sky_lab_extrapolation.py [--fresh] [table ...]
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import brdfjax as bj
from brdfjax.core.terms import ABg, Binomial, Lobe, MultiLobeSpecular, Phong
from brdfjax.diagnose.engine import model_terms_config
from brdfjax.fit import fit
from brdfjax.io import toml, write_json_atomic

jax.config.update("jax_enable_x64", True)
warnings.filterwarnings("ignore")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
from sky_lab_fits import TABLES, read  # noqa: E402

OUT = ROOT / "configs" / "v2mini"
RESULTS = ROOT / "experiments" / "results" / "sky_lab_extrapolation.json"
FAMILIES = ("abg", "abg2", "phong", "ggx", "ggx_n", "beckmann_n", "spike_halo", "binomial")
#: families whose out-of-plane shape follows from in-plane data by symmetry (ABg: |beta - beta0|; Phong: the angle
#: from the mirror direction; microfacet: the half vector).  The binomial's powers of V = beta . beta0 are fitted on
#: collinear in-plane pairs only, so its out-of-plane shape is not determined by these tables.
SYMMETRIC = ("abg", "abg2", "phong", "ggx", "ggx_n", "beckmann_n", "spike_halo")


def copied_slices(table, rtol: float = 1e-6, share: float = 0.9) -> dict[float, float]:
    """Incidence slices that repeat a shallower one: ``{incidence: the incidence it copies}``.

    Two slices are the same scan when at least ``share`` of the BRDF values at equal signed offsets from the specular
    direction (1-deg bins) agree to ``rtol``.  A copied slice carries no information about how the BRDF changes with
    incidence, so withholding it tests nothing but shift-invariance in the angle from specular.
    """
    ti = np.round(np.degrees(np.asarray(table.theta_i, float)), 1)
    ts = np.degrees(np.asarray(table.theta_s, float))
    ps = np.degrees(np.asarray(table.phi_s, float))
    f = np.asarray(table.brdf, float)
    signed = np.where(np.abs(ps) > 90, ts, -ts)  # forward (specular) side positive
    curves = {}
    for a in sorted(set(ti)):
        s = ti == a
        curves[float(a)] = dict(zip(np.round(signed[s] - a).astype(int).tolist(), f[s]))
    out: dict[float, float] = {}
    angles = sorted(curves)
    for j, a in enumerate(angles):
        for b in angles[:j]:
            common = [k for k in curves[a] if k in curves[b]]
            same = sum(np.isclose(curves[a][k], curves[b][k], rtol=rtol) for k in common)
            if common and same >= share * len(common):
                out[a] = out.get(b, b)
                break
    return out


def build(family: str, f: np.ndarray, index: dict, abg_fit=None):
    """(model, params) of ``family`` started from the table's values ``f`` (``abg_fit`` starts the binomial)."""
    peak = float(np.quantile(f, 0.999))
    d0 = max(np.pi * float(np.quantile(f, 0.05)), 1e-5)
    lam = bj.Lambertian(d0)
    if family == "abg":
        return (bj.Model(terms={"spec": ABg(peak * 1e-3, 1e-3, 2.0), "diffuse": lam}),
                {"spec.A": "free", "spec.B": "free", "spec.g": "free", "diffuse.rho_d": "free"})
    if family == "abg2":
        # a narrow core where ABg starts and a wide halo at the table's median level (A / B = median)
        med = float(np.median(f))
        return (bj.Model(terms={"spec": ABg(peak * 1e-3, 1e-3, 2.0), "halo": ABg(med * 0.05, 0.05, 2.0), "diffuse": lam}),
                {"spec.A": "free", "spec.B": "free", "spec.g": "free", "halo.A": "free", "halo.B": "free",
                 "halo.g": "free", "diffuse.rho_d": "free"})
    if family == "phong":
        return (bj.Model(terms={"spec": Phong(0.3, 200.0), "diffuse": lam}),
                {"spec.rho": "free", "spec.k": "free", "diffuse.rho_d": "free"})
    if family == "ggx":
        return (bj.Model(terms={"spec": bj.Specular(bj.GGX(0.05), 0.3, **index), "diffuse": lam}),
                {"spec.alpha": "free", "spec.rho_s": "free", "diffuse.rho_d": "free"})
    if family in ("ggx_n", "beckmann_n"):
        dist = bj.GGX(0.05) if family == "ggx_n" else bj.Beckmann(0.05)
        w = "spec.alpha" if family == "ggx_n" else "spec.m"
        return (bj.Model(terms={"spec": bj.Specular(dist, 0.3, **index), "diffuse": lam}),
                {w: "free", "spec.rho_s": "free", "spec.n": "free", "diffuse.rho_d": "free"})
    if family == "spike_halo":
        lobes = {"spike": Lobe(bj.GGX(0.01), 0.2), "halo": Lobe(bj.GGX(0.2), 0.02)}
        return (bj.Model(terms={"spec": MultiLobeSpecular(lobes, **index), "diffuse": lam}),
                {"spec.spike.alpha": "free", "spec.spike.rho_s": "free", "spec.halo.alpha": "free",
                 "spec.halo.rho_s": "free", "diffuse.rho_d": "free"})
    if family == "binomial":
        A, B, g = (abg_fit.value(k) for k in ("spec.A", "spec.B", "spec.g"))
        model = bj.Model(terms={"spec": Binomial(np.array([[np.log10(A / B), 0.0, 0.0], [0.0, 0.0, 0.0]]),
                                                 np.array([[-g], [0.0]]), B ** (-2.0 / g), l1=1),
                                "diffuse": bj.Lambertian(max(abg_fit.value("diffuse.rho_d"), 1e-5))})
        sp = {f"spec.{k}": "free" for k in model.terms["spec"].coefficients}
        sp.update({"spec.d": "free", "diffuse.rho_d": "free"})
        return model, sp
    raise ValueError(family)


def _log_ratio(res, table, rows: np.ndarray) -> np.ndarray:
    dirs = bj.Directions.from_angles(*(jnp.asarray(np.asarray(getattr(table, k), float)[rows])
                                       for k in ("theta_i", "phi_i", "theta_s", "phi_s")))
    wl = float(np.asarray(table.wavelength).ravel()[0])
    pred = np.asarray(res.models[0](dirs, wl))
    return np.log(np.maximum(pred, 1e-300)) - np.log(np.asarray(table.brdf, float)[rows])


def run_table(name: str, out: dict, steepest_only: bool = False) -> None:
    table = read(name)
    index = TABLES[name][1]
    ti = np.round(np.degrees(np.asarray(table.theta_i, float)), 1)
    base = np.ones(len(table), bool) if table.mask is None else np.asarray(table.mask, bool)
    f = np.asarray(table.brdf, float)
    angles = sorted(set(ti[base]))
    entry = out.setdefault(name, {"incidences_deg": [float(a) for a in angles], "families": {}})
    copies = copied_slices(table)
    entry["copied_slices"] = {f"{a:g}": b for a, b in copies.items()}
    distinct = [a for a in angles if a not in copies]
    folds = ["full"] + ([f"without_{max(angles):g}"] if steepest_only else [f"without_{a:g}" for a in angles])
    if len(distinct) > 1 and max(angles) in copies:
        # the steepest slice repeats a shallower one: withhold the steepest distinct scan and its copies instead
        folds.append(f"without_distinct_{max(distinct):g}")
    abg_fits: dict[str, object] = {}
    for fam in FAMILIES:
        fe = entry["families"].setdefault(fam, {"folds": {}})
        for fold in folds:
            done = fold in fe["folds"] and "error" not in fe["folds"][fold]
            need_abg = fam == "abg" and fold not in entry["families"].get("binomial", {}).get("folds", {})
            if done and not need_abg:
                continue
            if fold.startswith("without_distinct_"):
                a = float(fold.rsplit("_", 1)[1])
                train = base & (ti != a) & ~np.isin(ti, [c for c, src in copies.items() if src == a])
                test = base & (ti == a)
            else:
                train = base.copy() if fold == "full" else base & (ti != float(fold.split("_")[1]))
                test = None if fold == "full" else base & ~train
            sub = dataclasses.replace(table, mask=train)
            t0 = time.perf_counter()
            try:
                model, spec = build(fam, f[train], index, abg_fits.get(fold))
                res = fit(model, sub, spec)
            except Exception as e:  # noqa: BLE001 - a family that cannot be fitted is recorded, not fatal
                fe["folds"][fold] = {"error": f"{type(e).__name__}: {e}"}
                print(f"  {name:10s} {fam:10s} {fold:14s} FAILED {e}", flush=True)
                continue
            if fam == "abg":
                abg_fits[fold] = res
            if done:
                continue
            rec = {"converged": bool(res.converged), "wall_s": time.perf_counter() - t0,
                   "train_log_rms": float(np.sqrt(np.mean(_log_ratio(res, table, train) ** 2)))}
            if test is not None:
                lr = _log_ratio(res, table, test)
                rec.update(heldout_log_rms=float(np.sqrt(np.mean(lr**2))), heldout_log_bias=float(np.mean(lr)),
                           heldout_n=int(test.sum()), heldout_sq_sum=float(np.sum(lr**2)))
            else:
                rec["parameters"] = {k: res.value(k) for k in res.free_names}
                rec["per_incidence_log_rms"] = {
                    f"{a:g}": float(np.sqrt(np.mean(_log_ratio(res, table, base & (ti == a)) ** 2))) for a in angles}
                stem = f"{name}_{fam}"
                res.to_json(OUT / f"{stem}.result.json")
                terms, _ = model_terms_config(res.models[0])
                toml.write(OUT / f"{stem}.terms.toml", {"terms": terms},
                           header=f"{stem}: model terms of the fit in {stem}.result.json "
                                  "(written by experiments/sky_lab_extrapolation.py)")
            fe["folds"][fold] = rec
            print(f"  {name:10s} {fam:10s} {fold:14s} train {rec['train_log_rms']:.3f}"
                  + (f" held-out {rec['heldout_log_rms']:.3f} (bias {rec['heldout_log_bias']:+.2f})" if test is not None
                     else "") + f" {rec['wall_s']:.0f} s", flush=True)
            write_json_atomic(RESULTS, out)
    summarise(name, entry)
    write_json_atomic(RESULTS, out)


#: the family a facet takes when its table has a single distinct incidence (no extrapolation test possible): ABg,
#: whose scatter is shift-invariant in direction cosines (Harvey 1976; Harvey-Shack surface scatter theory), the
#: established incidence scaling of scatter from smooth optical surfaces and the stray-light standard
PRIOR_FAMILY = "abg"


def choose(entry: dict) -> tuple[str, str]:
    """(family, reason): the symmetric family that best predicts the steepest *distinct* incidence withheld (a copied
    steepest slice tests nothing); with one distinct incidence only, :data:`PRIOR_FAMILY`."""
    copies = {float(k): v for k, v in entry.get("copied_slices", {}).items()}
    angles = entry["incidences_deg"]
    distinct = [a for a in angles if a not in copies]
    fams = {k: v for k, v in entry["families"].items() if k in SYMMETRIC}
    if len(distinct) == 1:
        return PRIOR_FAMILY, (f"every slice repeats the {distinct[0]:g}-deg scan: no incidence information; "
                              f"prior family {PRIOR_FAMILY}")
    if max(angles) not in copies:
        key, what = f"without_{max(angles):g}", f"withheld {max(angles):g}-deg slice"
    else:
        key = f"without_distinct_{max(distinct):g}"
        what = (f"withheld {max(distinct):g}-deg slice (the steepest distinct scan; "
                + ", ".join(f"{a:g}" for a in angles if copies.get(a) == max(distinct)) + " deg repeat it)")
    sc = {k: e["folds"][key]["heldout_log_rms"] for k, e in fams.items()
          if key in e.get("folds", {}) and "heldout_log_rms" in e["folds"][key]}
    best = min(sc, key=sc.get)
    return best, f"best log-RMS on the {what}: {sc[best]:.2f}"


def _choice_fold(entry: dict) -> str | None:
    """The fold whose held-out score chooses (None: no test possible, the averaging weights use the steepest slice)."""
    copies = {float(k) for k in entry.get("copied_slices", {})}
    angles = entry["incidences_deg"]
    distinct = [a for a in angles if a not in copies]
    if len(distinct) == 1:
        return None
    return f"without_{max(angles):g}" if max(angles) not in copies else f"without_distinct_{max(distinct):g}"


def summarise(name: str, entry: dict) -> None:
    """Scores per family, the choice and the averaging weights of one table."""
    steep = f"without_{max(entry['incidences_deg']):g}"
    scores = {}
    for fam, fe in entry["families"].items():
        fo = fe["folds"]
        key = _choice_fold(entry) or steep
        if any("error" in fo.get(k, {"error": 1}) for k in {"full", steep, key}):
            continue
        held = [v for k, v in fo.items() if k.startswith("without_") and not k.startswith("without_distinct_")]
        if any("error" in v for v in held):
            held = []
        fe["steepest_log_rms"] = fo[steep]["heldout_log_rms"]
        fe["steepest_log_bias"] = fo[steep]["heldout_log_bias"]
        if len(held) == len(entry["incidences_deg"]):
            fe["loio_log_rms"] = float(np.sqrt(sum(v["heldout_sq_sum"] for v in held) / sum(v["heldout_n"] for v in held)))
        fe["in_sample_log_rms"] = fo["full"]["train_log_rms"]
        scores[fam] = fe["steepest_log_rms"]
    entry["chosen_any"] = min(scores, key=scores.get)
    sym = {k: v for k, v in scores.items() if k in SYMMETRIC}
    entry["chosen_by_steepest"] = min(sym, key=sym.get)
    entry["chosen"], entry["chosen_reason"] = choose(entry)
    loio = {k: entry["families"][k]["loio_log_rms"] for k in sym if "loio_log_rms" in entry["families"][k]}
    entry["chosen_loio"] = min(loio, key=loio.get) if len(loio) == len(sym) else None
    key = _choice_fold(entry)
    basis = {k: entry["families"][k]["folds"][key]["heldout_log_rms"] for k in sym
             if key in entry["families"][k]["folds"]} if key else sym
    w = {k: 1.0 / v**2 for k, v in (basis or sym).items()}
    tot = sum(w.values())
    entry["average_weights"] = {k: v / tot for k, v in sorted(w.items(), key=lambda kv: -kv[1])}
    print(f"{name}: steepest " + " ".join(f"{k} {v:.2f}" for k, v in scores.items()) + f" -> {entry['chosen']}"
          f" ({entry['chosen_reason']}; by the steepest slice: {entry['chosen_by_steepest']}; any family: "
          f"{entry['chosen_any']}; by loio: {entry['chosen_loio']})", flush=True)


def markdown(out: dict) -> str:
    """Table rows: per table and family full-fit / withheld-steepest (bias) [/ steepest distinct] [/ leave-one-out]
    log-RMS, and the chosen family."""
    rows = []
    for t, e in out.items():
        key = _choice_fold(e)
        cells = []
        for fam in FAMILIES:
            x = e["families"].get(fam, {})
            if "steepest_log_rms" not in x:
                cells.append("failed")
                continue
            c = f"{x['in_sample_log_rms']:.2f} / {x['steepest_log_rms']:.2f} ({x['steepest_log_bias']:+.2f})"
            if key and key.startswith("without_distinct_") and key in x["folds"]:
                c += f" / {x['folds'][key]['heldout_log_rms']:.2f}"
            if "loio_log_rms" in x:
                c += f" / LOIO {x['loio_log_rms']:.2f}"
            cells.append(c)
        rows.append(f"| {t} | " + " | ".join(cells) + f" | {e['chosen']} |")
    return "\n".join(rows)


def main(argv: list[str]) -> None:
    if "--markdown" in argv:
        print(markdown(json.loads(RESULTS.read_text())))
        return
    if "--summarise" in argv:
        out = json.loads(RESULTS.read_text())
        for name in out:
            entry = out[name]
            if "copied_slices" not in entry:
                entry["copied_slices"] = {f"{a:g}": b for a, b in copied_slices(read(name)).items()}
            summarise(name, entry)
        write_json_atomic(RESULTS, out)
        return
    fresh = "--fresh" in argv
    names = [a for a in argv if not a.startswith("--")] or list(TABLES)
    out = {} if fresh or not RESULTS.exists() else json.loads(RESULTS.read_text())
    # first every table's full fit and its steepest-incidence fold (the choice), then the other folds
    for steepest_only in (True, False):
        for name in names:
            print(name, "(steepest incidence withheld)" if steepest_only else "(every incidence withheld in turn)",
                  flush=True)
            run_table(name, out, steepest_only)


if __name__ == "__main__":
    main(sys.argv[1:])
