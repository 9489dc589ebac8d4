"""Real-data fits: physically based models with shadowing and several lobes against empirical families (issue 14).

Data (``tests/data/real``, copied from ``../shared/data/real`` with their
licences): MERL aluminium in-plane slices (7 incident angles, 1785 points),
Cornell Krylon blue and Cayman metallic paint (8 incident angles, 1439
sparse samples each, mean over the 31 wavelengths).  None carries
uncertainties, so each point is weighted 1 in ``ln f`` and the quality measure
is the log-RMS, the rms of ``ln(f_model / f_data)``, per incident angle and
overall.

Models per dataset (index of refraction fixed at the prior of the shipped
configs unless said otherwise):

(a) ``today``: one microfacet lobe (the shipped config's distribution) +
    Lambertian, Eq 70 (seed normalisation, no shadowing), automatic start;
(b) ``smith_seed`` / ``smith_ts``: the same with Smith G2 shadowing and the
    seed's or the Torrance-Sparrow normalisation, started from (a);
(b') ``tail_hc``: one Hyper-Cauchy lobe (free tail exponent gamma > 1.5, where
    Smith's Lambda is finite) with Smith G2 + Lambertian;
(c) ``multi_lobe``: two lobes sharing the index (a spike of (a)'s family and a
    Beckmann or Hyper-Cauchy halo, the better kept), Smith G2, the better
    normalisation of (b), + Lambertian; ``multi_lobe_no_shadowing``: the same
    model refitted with G = 1 (the shadowing before/after per angle);
(c') ``three_lobes``: spike + mid + halo sharing the index (the spike of (c)'s
    family, a Hyper-Cauchy mid lobe and a Hyper-Cauchy halo, free tails), Smith
    G2, (c)'s normalisation, + Lambertian, started from (c) with two starts
    of the mid lobe's width (the geometric mean of the spike's and the halo's,
    and 4x the spike's; the better kept); ``three_lobes_no_shadowing``: the
    same refitted with G = 1;
(d) ``abg``: Harvey-Shack ABg + Lambertian; ``phong``: normalised Phong lobe
    + Lambertian (the lumos-sat PHONG family); ``binomial``: Greynolds'
    binomial (lumos-sat's BINOMIAL; n = 2 powers of V, m = 3 of D, one
    Gaussian term, l1 = 1) + Lambertian, started at ABg's fit (with
    ``c0_0 = -g``, ``d = B^(-2/g)`` it is ABg's form); all three empirical.

(e) ``mixture_shadowing``: the best multi-lobe model of (c)/(c') (lobes whose
    weight is below 1e-3 of the total dropped first: Krylon's three-lobe fit
    had parked its halo there, which kept that fit from converging) with
    ``shadowing = "smith_mixture"``: Smith G2 of the surface as one surface,
    the Lambda of the lobes' mixture masking every lobe, index fixed;
    ``mixture_index``: the same with the index free within the material's
    physical range (``INDEX_RANGE``), started from ``mixture_shadowing``;
    ``pruned_smith``: the pruned model refitted with each lobe's own Lambda
    (``smith``), as (c') (where a lobe was pruned); ``smith_index``: the
    pruned model (each lobe's own Lambda) with the index free in that range.

``--add`` runs only the named parts (``binomial``, (c') ``three_lobes``,
``abg``, ``refine``, (e) ``mixture``, ``continue``: (e) fits that stopped at
their iteration limit go on from there) from the starts stored in the dataset's
results json (the other fits are kept as they are there), and merges them in.
New fits store their model as a ``[model.terms]`` table (``terms``), from
which the figure and later ``--add`` runs rebuild them.

Prints a table of log-RMS per incident angle and overall per model, writes
``experiments/results/real_data_fits_<dataset>.json`` (atomically) and one figure per
dataset, ``experiments/figures/real_data_<dataset>.png`` (in-plane samples,
data and every model).

Run::

    python3 experiments/real_data_fits.py                 # all three datasets
    python3 experiments/real_data_fits.py --datasets merl_aluminium
    python3 experiments/real_data_fits.py --add three_lobes binomial --datasets merl_aluminium   # merged in
    python3 experiments/real_data_fits.py --add mixture            # (e) on every dataset, from the stored fits
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.config.model import ModelConfig, build_model  # noqa: E402
from brdfjax.core.terms import ABg, Binomial, Lobe, MultiLobeSpecular, Phong  # noqa: E402
from brdfjax.diagnose.engine import model_terms_config  # noqa: E402
from brdfjax.fit import fit, read_cornell_brdf, read_merl_inplane  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "tests" / "data" / "real"

#: dataset -> (file, reader, distribution of today's config, index prior)
DATASETS = {
    "merl_aluminium": ("merl_aluminium_inplane.txt", "merl", "ggx", {"n": 0.96, "k": 6.69}),
    "cornell_krylon_blue": ("cornell_krylon_blue.brdf", "cornell", "ggx", {"n": 1.5}),
    "cornell_cayman": ("cornell_cayman_metallic.brdf", "cornell", "beckmann", {"n": 1.5}),
}
WIDTH = {"ggx": "alpha", "beckmann": "m"}
DIST = {"ggx": bj.GGX, "beckmann": bj.Beckmann}
#: The physical range of the index where (e) frees it: aluminium at 550-650 nm (Rakic 1995: 0.96 + 6.69 i at
#: 550 nm, 1.37 + 7.62 i at 633 nm) with margin; a paint's binder (n = 1.3-2.0, no absorption).
INDEX_RANGE = {
    "merl_aluminium": {"n": (0.5, 2.0), "k": (5.0, 9.0)},
    "cornell_krylon_blue": {"n": (1.3, 2.0)},
    "cornell_cayman": {"n": (1.3, 2.0)},
}
#: Physically based model names (the rest are empirical).
PHYSICAL = ("today", "smith_seed", "smith_ts", "tail_hc", "multi_lobe", "multi_lobe_no_shadowing", "three_lobes",
            "three_lobes_no_shadowing", "pruned_smith", "mixture_shadowing", "mixture_index", "smith_index")
EMPIRICAL = ("abg", "phong", "binomial")
TAIL = {"value": 2.5, "lower": 1.5, "upper": 30.0}  # Smith's Lambda is finite for a Hyper-Cauchy gamma > 1.5


def read(name: str):
    file, reader, _, _ = DATASETS[name]
    return read_merl_inplane(REAL / file) if reader == "merl" else read_cornell_brdf(REAL / file)


def _summary(res, t0: float) -> dict:
    block = res.blocks[0]
    terms, _ = model_terms_config(res.models[0])
    return {
        "terms": terms,
        "log_rms": block.log_rms,
        "per_angle": {f"{g['theta_i_deg']:g}": g["log_rms"] for g in block.groups},
        "converged": bool(res.converged),
        "message": res.message,
        "n_free": len(res.free_names),
        "parameters": {k: res.value(k) for k in res.free_names},
        "wall_s": time.perf_counter() - t0,
    }


def single_lobe(distribution: str, width: float, rho_s: float, rho_d: float, index: dict, shadowing="none", normalisation="seed"):
    spec = bj.Specular(DIST[distribution](width), rho_s, shadowing=shadowing, normalisation=normalisation, fresnel="q_factor", **index)
    return bj.Model(terms={"spec": spec, "diffuse": bj.Lambertian(rho_d)})


def two_lobes(d1: str, w1: float, r1: float, d2: str, w2: float, r2: float, rho_d: float, index: dict, normalisation: str):
    lobes = {"spike": Lobe(DIST[d1](w1), r1), "halo": Lobe(DIST[d2](w2), r2)}
    spec = MultiLobeSpecular(lobes, shadowing="smith", normalisation=normalisation, fresnel="q_factor", **index)
    return bj.Model(terms={"spec": spec, "diffuse": bj.Lambertian(rho_d)})


def two_lobe_model(name: str, variant: str, params: dict, normalisation: str) -> bj.Model:
    """(c)'s fitted two-lobe model rebuilt from its free parameters (the index at the dataset's prior)."""
    _, _, dname, index = DATASETS[name]
    halo = bj.HyperCauchy(0.3, 3.0) if variant == "multi_lobe_hc" else bj.Beckmann(0.3)
    lobes = {"spike": Lobe(DIST[dname](0.01), 0.1), "halo": Lobe(halo, 0.1)}
    model = bj.Model(terms={"spec": MultiLobeSpecular(lobes, shadowing="smith", normalisation=normalisation, fresnel="q_factor", **index),
                            "diffuse": bj.Lambertian(0.01)})
    return model.with_params(params)


def three_lobe_runs(run, name: str, two: bj.Model) -> None:
    """(c'): spike + Hyper-Cauchy mid + Hyper-Cauchy halo from (c)'s fit, two starts of the mid width; G = 1 refit."""
    _, _, dname, _ = DATASETS[name]
    wname = WIDTH[dname]
    spec2 = two.terms["spec"]
    spike, halo = spec2.lobes["spike"], spec2.lobes["halo"]
    ws, rs = float(getattr(spike.distribution, wname)), float(spike.rho_s)
    if isinstance(halo.distribution, bj.HyperCauchy):
        wh, gh = float(halo.distribution.sigma), float(halo.distribution.gamma)
    else:
        wh, gh = float(halo.distribution.m), 3.6
    rh = float(halo.rho_s)
    rho_d = max(float(two.terms["diffuse"].rho_d), 1e-4)
    best = None
    for label, wm in (("three_lobes_geo", (ws * wh) ** 0.5), ("three_lobes_4x", 4.0 * ws)):
        lobes = {"spike": Lobe(DIST[dname](ws), 0.85 * rs), "mid": Lobe(bj.HyperCauchy(wm, 2.0), 0.2 * rs),
                 "halo": Lobe(bj.HyperCauchy(wh, gh), rh)}
        model = bj.Model(terms={"spec": MultiLobeSpecular(lobes, shadowing="smith", normalisation=spec2.normalisation, fresnel="q_factor",
                                                          n=spec2.n, k=spec2.k),
                                "diffuse": bj.Lambertian(rho_d)})
        spec = {f"spec.spike.{wname}": "free", "spec.spike.rho_s": "free", "spec.mid.sigma": "free",
                "spec.mid.gamma": dict(TAIL, value=2.0), "spec.mid.rho_s": "free", "spec.halo.sigma": "free",
                "spec.halo.gamma": dict(TAIL, value=gh), "spec.halo.rho_s": "free", "diffuse.rho_d": "free"}
        run(label, model, spec)
        if best is None or run.out[label]["log_rms"] < run.out[best]["log_rms"]:
            best = label
    run.out["three_lobes"] = dict(run.out[best], variant=best)
    run.models["three_lobes"] = run.models[best]
    m = run.models["three_lobes"]
    bare = dataclasses.replace(m.terms["spec"], shadowing="none")
    spec = {k: "free" for k in m.params() if k.startswith("spec.") and not k.endswith((".n", ".k"))}
    spec.update({k: dict(TAIL, value=float(m.params()[k])) for k in spec if k.endswith(".gamma")})
    spec["diffuse.rho_d"] = "free"
    run("three_lobes_no_shadowing", bj.Model(terms={"spec": bare, "diffuse": m.terms["diffuse"]}), spec)


def binomial_run(run, abg: dict, rho_d: float) -> None:
    """Greynolds' binomial (n = 2, m = 3, one Gaussian term, l1 = 1) + Lambertian, started at ABg's fit."""
    A, B, g = abg["spec.A"], abg["spec.B"], abg["spec.g"]
    Bm = np.array([[np.log10(A / B), 0.0, 0.0], [0.0, 0.0, 0.0]])
    Cm = np.array([[-g], [0.0]])
    model = bj.Model(terms={"spec": Binomial(Bm, Cm, B ** (-2.0 / g), l1=1), "diffuse": bj.Lambertian(max(rho_d, 1e-4))})
    spec = {f"spec.{k}": "free" for k in model.terms["spec"].coefficients}
    spec.update({"spec.d": "free", "diffuse.rho_d": "free"})
    run("binomial", model, spec)


def fit_dataset(name: str, verbose: bool = True) -> tuple[dict, dict]:
    """All model fits of one dataset: ``({model: summary}, {model: fitted Model})``."""
    table = read(name)
    _, _, dname, index = DATASETS[name]
    wname = WIDTH[dname]
    out, models = {}, {}

    run = Runner(table, out, models, verbose)

    # (a) today's model
    a = run("today", single_lobe(dname, 0.1, 0.5, 0.05, index),
            {f"spec.{wname}": "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"})
    w0, r0, d0 = a.value(f"spec.{wname}"), a.value("spec.rho_s"), a.value("diffuse.rho_d")
    # (b) shadowing, both normalisations, started from (a)
    free1 = {f"spec.{wname}": "free", "spec.rho_s": "free", "diffuse.rho_d": "free"}
    for label, norm in (("smith_seed", "seed"), ("smith_ts", "torrance_sparrow")):
        run(label, single_lobe(dname, w0, r0, d0, index, "smith", norm), free1)
    best_norm = "seed" if out["smith_seed"]["log_rms"] <= out["smith_ts"]["log_rms"] else "torrance_sparrow"
    b_label = "smith_seed" if best_norm == "seed" else "smith_ts"
    wb = float(getattr(models[b_label].terms["spec"].distribution, wname))
    rb = float(models[b_label].terms["spec"].rho_s)
    db = float(models[b_label].terms["diffuse"].rho_d)
    # (b') a distribution with a free tail (Hyper-Cauchy), Smith G2 (finite Lambda needs gamma > 1.5)
    tail = {"value": 2.5, "lower": 1.5, "upper": 30.0}
    run("tail_hc", bj.Model(terms={
        "spec": bj.Specular(bj.HyperCauchy(wb, 2.5), rb, shadowing="smith", normalisation=best_norm, fresnel="q_factor", **index),
        "diffuse": bj.Lambertian(db)}),
        {"spec.sigma": "free", "spec.gamma": tail, "spec.rho_s": "free", "diffuse.rho_d": "free"})
    # (c) two lobes sharing the index: a spike half as wide as (b) and a halo (Beckmann 5x wider, or
    # Hyper-Cauchy with a free tail); the better one is "multi_lobe"
    best = None
    for label, halo, hspec in (
        ("multi_lobe_beckmann", bj.Beckmann(5.0 * wb), {"spec.halo.m": "free"}),
        ("multi_lobe_hc", bj.HyperCauchy(2.0 * wb, 2.5), {"spec.halo.sigma": "free", "spec.halo.gamma": tail}),
    ):
        lobes = {"spike": Lobe(DIST[dname](0.5 * wb), 0.3 * rb), "halo": Lobe(halo, 0.7 * rb)}
        model = bj.Model(terms={"spec": MultiLobeSpecular(lobes, shadowing="smith", normalisation=best_norm, fresnel="q_factor", **index),
                                "diffuse": bj.Lambertian(db)})
        spec = {f"spec.spike.{wname}": "free", "spec.spike.rho_s": "free", "spec.halo.rho_s": "free",
                "diffuse.rho_d": "free", **hspec}
        run(label, model, spec)
        if best is None or out[label]["log_rms"] < out[best]["log_rms"]:
            best = label
    out["multi_lobe"] = dict(out[best], variant=best)
    models["multi_lobe"] = models[best]
    # shadowing before/after: the best multi-lobe model refitted without shadowing (same start, G = 1)
    m = models["multi_lobe"]
    bare = dataclasses.replace(m.terms["spec"], shadowing="none")
    spec = {k: "free" for k in m.params() if k.startswith("spec.") and not k.endswith((".n", ".k"))}
    spec.update({k: tail for k in spec if k.endswith(".gamma")})
    spec["diffuse.rho_d"] = "free"
    run("multi_lobe_no_shadowing", bj.Model(terms={"spec": bare, "diffuse": m.terms["diffuse"]}), spec)
    # (d) empirical families
    peak = float(np.quantile(np.asarray(table.brdf), 0.999))
    g0 = 2.0
    b0 = (wb * 2.0) ** g0
    run("abg", bj.Model(terms={"spec": ABg(peak * b0, b0, g0), "diffuse": bj.Lambertian(d0)}),
        {"spec.A": "free", "spec.B": "free", "spec.g": "free", "diffuse.rho_d": "free"})
    run("phong", bj.Model(terms={"spec": Phong(r0, 2.0 / wb**2), "diffuse": bj.Lambertian(d0)}),
        {"spec.rho": "free", "spec.k": "free", "diffuse.rho_d": "free"})
    binomial_run(run, out["abg"]["parameters"], d0)
    three_lobe_runs(run, name, models["multi_lobe"])
    mixture_runs(run, name, out)
    return out, models


ADD_PARTS = ("binomial", "three_lobes", "abg", "refine", "mixture", "continue")


def pruned(model: bj.Model, rel: float = 1e-3) -> tuple[bj.Model, list[str]]:
    """``model`` without the multi-lobe term's lobes whose weight is below ``rel`` of the total, and their names."""
    spec = model.terms["spec"]
    total = sum(float(lb.rho_s) for lb in spec.lobes.values())
    keep = {k: lb for k, lb in spec.lobes.items() if float(lb.rho_s) >= rel * total}
    dropped = [k for k in spec.lobes if k not in keep]
    return bj.Model(terms={**model.terms, "spec": dataclasses.replace(spec, lobes=keep)}), dropped


def _free_spec(model: bj.Model, index: dict | None = None) -> dict:
    """Every parameter free but the index (tails bounded as in TAIL); ``index``: {name: (lower, upper)} freed too."""
    params = model.params()
    spec = {k: "free" for k in params if not k.endswith((".n", ".k"))}
    spec.update({k: dict(TAIL, value=float(params[k])) for k in spec if k.endswith(".gamma")})
    for key, (lo, hi) in (index or {}).items():
        spec[f"spec.{key}"] = {"value": float(np.clip(float(params[f"spec.{key}"]), lo, hi)), "lower": lo, "upper": hi}
    return spec


def mixture_runs(run, name: str, fits: dict) -> None:
    """(e): the best multi-lobe model (pruned) with Smith G2 of the lobes' mixture, index fixed, then free."""
    base = "three_lobes" if fits.get("three_lobes", {}).get("log_rms", np.inf) < fits["multi_lobe"]["log_rms"] else "multi_lobe"
    model, dropped = pruned(_stored_model(base, name, fits))
    steps = 600  # the three-lobe fits had stopped at 256
    if dropped:
        run("pruned_smith", model, _free_spec(model), first_stage=None, solver_options={"max_steps": steps})
        run.out["pruned_smith"].update(base=base, dropped=dropped)
        model = run.models["pruned_smith"]
    mix = bj.Model(terms={**model.terms, "spec": dataclasses.replace(model.terms["spec"], shadowing="smith_mixture")})
    run("mixture_shadowing", mix, _free_spec(mix), first_stage=None, solver_options={"max_steps": steps})
    run.out["mixture_shadowing"].update(base=base, dropped=dropped)
    start = run.models["mixture_shadowing"]
    run("mixture_index", start, _free_spec(start, INDEX_RANGE[name]), first_stage=None, solver_options={"max_steps": steps})
    run.out["mixture_index"].update(base=base, dropped=dropped, index_range=INDEX_RANGE[name])
    run("smith_index", model, _free_spec(model, INDEX_RANGE[name]), first_stage=None, solver_options={"max_steps": steps})
    run.out["smith_index"].update(base=base, dropped=dropped, index_range=INDEX_RANGE[name])


def _stored_model(label: str, name: str, fits: dict) -> bj.Model:
    """A stored fit's model rebuilt from its stored ``[model.terms]`` table, or from its free parameters."""
    _, _, dname, index = DATASETS[name]
    if "terms" in fits.get(label, {}):
        return build_model(f"{label} (results json)", ModelConfig.model_validate({"terms": fits[label]["terms"]}))
    if label == "today":
        return single_lobe(dname, 0.1, 0.5, 0.05, index).with_params(fits["today"]["parameters"])
    if label == "multi_lobe":
        norm = "seed" if fits["smith_seed"]["log_rms"] <= fits["smith_ts"]["log_rms"] else "torrance_sparrow"
        variant = fits["multi_lobe"]["variant"]
        return two_lobe_model(name, variant, fits[variant]["parameters"], norm)
    if label == "abg":
        a = fits["abg"]["parameters"]
        return bj.Model(terms={"spec": ABg(a["spec.A"], a["spec.B"], a["spec.g"]), "diffuse": bj.Lambertian(a["diffuse.rho_d"])})
    if label == "three_lobes":
        two = _stored_model("multi_lobe", name, fits)
        lobes = {"spike": Lobe(DIST[dname](0.01), 0.1), "mid": Lobe(bj.HyperCauchy(0.05, 2.0), 0.1),
                 "halo": Lobe(bj.HyperCauchy(0.3, 3.0), 0.1)}
        spec = MultiLobeSpecular(lobes, shadowing="smith", normalisation=two.terms["spec"].normalisation, fresnel="q_factor", **index)
        return bj.Model(terms={"spec": spec, "diffuse": bj.Lambertian(0.01)}).with_params(fits["three_lobes"]["parameters"])
    if label == "binomial":
        model = bj.Model(terms={"spec": Binomial(np.zeros((2, 3)), np.zeros((2, 1)), 1.0, l1=1), "diffuse": bj.Lambertian(0.01)})
        return model.with_params(fits["binomial"]["parameters"])
    raise KeyError(label)


def add_to_dataset(name: str, stored: dict, parts=ADD_PARTS, verbose: bool = True) -> tuple[dict, dict]:
    """``--add``: the ``parts`` (``binomial``, (c') ``three_lobes``, ``abg``: ABg refitted from its stored
    optimum without the soft first stage, kept if lower; ``refine``: the same for the stored (c')) from the
    starts in ``stored`` (a results json)."""
    table = read(name)
    out, models = {}, {}
    run = Runner(table, out, models, verbose)
    fits = stored["fits"]
    two = _stored_model("multi_lobe", name, fits)
    if "binomial" in parts:
        binomial_run(run, fits["abg"]["parameters"], fits["today"]["parameters"]["diffuse.rho_d"])
    if "three_lobes" in parts:
        three_lobe_runs(run, name, two)
    abg = _stored_model("abg", name, fits)
    if "abg" in parts:
        spec = {"spec.A": "free", "spec.B": "free", "spec.g": "free", "diffuse.rho_d": "free"}
        start = abg.with_params({"diffuse.rho_d": max(float(abg.terms["diffuse"].rho_d), 1e-6)})  # inside its bound 0
        run("abg_refit", start, spec, first_stage=None)
        if out["abg_refit"]["log_rms"] < fits["abg"]["log_rms"]:
            out["abg"] = dict(out["abg_refit"], note="refitted from the stored optimum without the soft first stage")
            abg = models["abg_refit"]
        out.pop("abg_refit")
    if "mixture" in parts:
        mixture_runs(run, name, {**fits, **out})
    if "continue" in parts:
        # (e) fits that stopped at their iteration limit go on from where they stopped (600 more steps, the
        # same bounds); the continued fit replaces the stored one, with the steps of both in its note
        for label in ("mixture_index", "smith_index"):
            prev = {**fits, **out}.get(label)
            if prev is None or prev["converged"]:
                continue
            start = _stored_model(label, name, {**fits, **out})
            spec = _free_spec(start, prev.get("index_range") and {k: tuple(v) for k, v in prev["index_range"].items()})
            run(label, start, spec, first_stage=None, solver_options={"max_steps": 600})
            out[label].update({k: prev[k] for k in ("base", "dropped", "index_range") if k in prev},
                              note=f"continued from a fit that stopped at its iteration limit ({prev['message'][:40]}...)")
    if "refine" in parts and "three_lobes" in fits:
        # the stored three-lobe optimum refitted without the soft first stage (a fit that stopped at its
        # iteration limit goes on from there); kept if lower
        start = _stored_model("three_lobes", name, fits)
        spec = {k: "free" for k in fits["three_lobes"]["parameters"]}
        spec.update({k: dict(TAIL, value=float(start.params()[k])) for k in spec if k.endswith(".gamma")})
        run("three_lobes_refined", start, spec, first_stage=None)
        if out["three_lobes_refined"]["log_rms"] < fits["three_lobes"]["log_rms"]:
            out["three_lobes"] = dict(out["three_lobes_refined"], variant=fits["three_lobes"].get("variant"),
                                      note="refitted from the stored optimum without the soft first stage")
            models["three_lobes"] = models["three_lobes_refined"]
        out.pop("three_lobes_refined")
    models.setdefault("multi_lobe", two)
    for label in ("today", "three_lobes", "binomial", "mixture_index", "smith_index"):
        if label not in models and label in fits:
            models[label] = _stored_model(label, name, fits)
    models["abg"] = abg
    return out, models


class Runner:
    """One fit of a dataset's table: its summary in ``out[label]``, the fitted model in ``models[label]``."""

    def __init__(self, table, out: dict, models: dict, verbose: bool):
        self.table, self.out, self.models, self.verbose = table, out, models, verbose

    def __call__(self, label, model, spec, **kw):
        t0 = time.perf_counter()
        res = fit(model, self.table, spec, **kw)
        self.out[label] = _summary(res, t0)
        self.models[label] = res.models[0]
        if self.verbose:
            s = self.out[label]
            per = " ".join(f"{v:.2f}" for v in s["per_angle"].values())
            print(f"  {label:24s} log-RMS {s['log_rms']:.3f} | {per} | {s['wall_s']:.0f} s {'' if s['converged'] else '(not converged)'}",
                  flush=True)
        return res


def figure(name: str, models: dict, path: Path) -> None:
    # function-local: matplotlib only for the figure (the fits need none)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from brdfjax.plotting import save_figure_atomic

    table = read(name)
    ti, pi, ts, ps = (np.asarray(getattr(table, f), float) for f in ("theta_i", "phi_i", "theta_s", "phi_s"))
    f = np.asarray(table.brdf, float)
    plane = np.abs(np.sin(ps - pi)) < 0.05
    signed = np.degrees(np.where(np.cos(ps - pi) < 0, ts, -ts))  # + forward (specular side)
    angles = np.unique(np.round(np.degrees(ti), 4))
    ncol = 4
    nrow = int(np.ceil(len(angles) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 3.2 * nrow), squeeze=False)
    shown = ("today", "multi_lobe", "three_lobes", "mixture_index", "smith_index", "abg", "phong", "binomial")
    for ax, a in zip(axes.ravel(), angles):
        sel = plane & (np.round(np.degrees(ti), 4) == a) & (f > 0)
        order = np.argsort(signed[sel])
        ax.semilogy(signed[sel][order], f[sel][order], "k.", ms=3, label="data")
        dirs = bj.Directions.from_angles(ti[sel][order], pi[sel][order], ts[sel][order], ps[sel][order])
        for label in shown:
            if label in models:
                ax.semilogy(signed[sel][order], np.asarray(models[label](dirs, np.asarray(table.wavelength))), lw=1, label=label)
        ax.set_title(f"{name}: theta_i = {a:g} deg", fontsize=9)
        ax.set_xlabel("theta_s (deg, + on the specular side)")
        ax.set_ylabel("BRDF (sr^-1)")
    for ax in axes.ravel()[len(angles):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    save_figure_atomic(fig, path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results",
                   help="folder of the results: real_data_fits_<dataset>.json per dataset")
    p.add_argument("--figures", type=Path, default=ROOT / "experiments" / "figures")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--add", nargs="*", choices=ADD_PARTS, default=None,
                   help="run only these fits (default: all of them) from the stored results, merged in")
    args = p.parse_args(argv)
    for name in args.datasets:
        print(f"{name}: model, overall log-RMS | per incident angle | wall time", flush=True)
        stored_path = args.out / f"real_data_fits_{name}.json"
        if args.add is not None:
            import json  # function-local: only --add reads the stored results

            stored = json.loads(stored_path.read_text())
            new, models = add_to_dataset(name, stored, tuple(args.add) or ADD_PARTS)
            summary = {**stored["fits"], **new}
            best_models = dict(stored.get("best_models", {}))
        else:
            summary, models = fit_dataset(name)
            best_models = {}
        physical = min((k for k in summary if k in PHYSICAL), key=lambda k: summary[k]["log_rms"])
        empirical = min((k for k in EMPIRICAL if k in summary), key=lambda k: summary[k]["log_rms"])
        for k in (physical, empirical):
            if k in models:
                best_models[k] = {p: float(v) for p, v in models[k].params().items()}
        results = {"dataset": name, "fits": summary, "best_physical": physical, "best_empirical": empirical,
                   "best_models": {k: best_models[k] for k in (physical, empirical) if k in best_models}}
        print(f"  best physically based: {physical} ({summary[physical]['log_rms']:.3f}); "
              f"best empirical: {empirical} ({summary[empirical]['log_rms']:.3f})", flush=True)
        if not args.no_figures:
            figure(name, models, args.figures / f"real_data_{name}.png")
        path = write_json_atomic(args.out / f"real_data_fits_{name}.json", results, allow_nan=False)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
