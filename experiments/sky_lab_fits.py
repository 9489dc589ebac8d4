"""Fits of the five Starlink V2 Mini lab tables (Kandula 2025) by three model families, for ``brdfjax observe``.

No observation enters any fit: each family is fitted to the in-plane lab table alone (the tables carry no
uncertainties: the noise of ln BRDF is estimated).  Families:

- ``abg``: Harvey-Shack ABg + Lambertian (empirical; the stray-light standard);
- ``ggx``: one GGX microfacet lobe with Smith shadowing and Fresnel (index fixed: 1.5 for the films and
  coatings, aluminium 0.96 + 6.69i for the bare chassis) + Lambertian (physically based);
- ``binomial``: Greynolds' binomial (2 powers of V, 3 of D, one Gaussian term, l1 = 1) + Lambertian,
  started at the ABg fit (lumos-sat's family).

Each fit's result.json and its model's terms (a TOML table the observe config names) go to
``configs/v2mini/``; the log-RMS per family and incidence to ``experiments/results/sky_lab_fits.json``.
Superseded by ``experiments/sky_lab_extrapolation.py``, which fits these three families and five more and
writes the fits the shipped observe configs use: running this script overwrites the ABg, GGX and binomial fits
there (with the same starts; the GGX now in the standard microfacet form, the default).

    PYTHONPATH=$PWD python experiments/sky_lab_fits.py [table ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import brdfjax as bj
from brdfjax.core.terms import ABg, Binomial
from brdfjax.diagnose.engine import model_terms_config
from brdfjax.fit import fit, read_merl_inplane
from brdfjax.io import toml, write_json_atomic

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "tests" / "data" / "satellites" / "starlink_v2mini_lab"
OUT = ROOT / "configs" / "v2mini"
COLUMNS = {"theta_i": "phi_i", "phi_i": "theta_i", "theta_s": "phi_o", "phi_s": "theta_o"}
TABLES = {
    "mirror": ("gen2_dialectric_mirror.csv", {"n": 1.5}),
    "bare_al": ("chassis_bare.csv", {"n": 0.96, "k": 6.69}),
    "black_c138": ("black_c138.csv", {"n": 1.5}),
    "lrb50xl2": ("LRB50XL2.csv", {"n": 1.5}),
    "a700": ("A700.csv", {"n": 1.5}),
}


def read(name: str):
    return read_merl_inplane(LAB / TABLES[name][0], columns=COLUMNS, name=name)


def save(name: str, family: str, res, t0: float, summary: dict) -> None:
    model = res.models[0]
    terms, _ = model_terms_config(model)
    stem = f"{name}_{family}"
    res.to_json(OUT / f"{stem}.result.json")
    toml.write(OUT / f"{stem}.terms.toml", {"terms": terms},
               header=f"{stem}: model terms of the fit in {stem}.result.json (written by experiments/sky_lab_fits.py)")
    block = res.blocks[0]
    summary.setdefault(name, {})[family] = {
        "log_rms": block.log_rms,
        "per_angle": {f"{g['theta_i_deg']:g}": g["log_rms"] for g in block.groups},
        "converged": bool(res.converged), "n_free": len(res.free_names), "wall_s": time.perf_counter() - t0,
        "parameters": {k: res.value(k) for k in res.free_names},
    }
    print(f"  {stem:22s} log-RMS {block.log_rms:.3f} | "
          + " ".join(f"{g['log_rms']:.2f}" for g in block.groups) + f" | {time.perf_counter() - t0:.0f} s", flush=True)


def fit_table(name: str, summary: dict) -> None:
    table = read(name)
    index = TABLES[name][1]
    f = np.asarray(table.brdf, float)
    peak = float(np.quantile(f, 0.999))
    floor = float(np.quantile(f, 0.05))
    d0 = max(np.pi * floor, 1e-5)
    # ABg + Lambertian
    t0 = time.perf_counter()
    g0, b0 = 2.0, 1e-3
    abg = fit(bj.Model(terms={"spec": ABg(peak * b0, b0, g0), "diffuse": bj.Lambertian(d0)}), table,
              {"spec.A": "free", "spec.B": "free", "spec.g": "free", "diffuse.rho_d": "free"})
    save(name, "abg", abg, t0, summary)
    # GGX + Smith + Fresnel + Lambertian
    t0 = time.perf_counter()
    spec = bj.Specular(bj.GGX(0.1), 0.5, shadowing="smith", **index)
    ggx = fit(bj.Model(terms={"spec": spec, "diffuse": bj.Lambertian(d0)}), table,
              {"spec.alpha": "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"})
    save(name, "ggx", ggx, t0, summary)
    # binomial + Lambertian from ABg
    t0 = time.perf_counter()
    A, B, g = (abg.value(k) for k in ("spec.A", "spec.B", "spec.g"))
    Bm = np.array([[np.log10(A / B), 0.0, 0.0], [0.0, 0.0, 0.0]])
    Cm = np.array([[-g], [0.0]])
    model = bj.Model(terms={"spec": Binomial(Bm, Cm, B ** (-2.0 / g), l1=1),
                            "diffuse": bj.Lambertian(max(abg.value("diffuse.rho_d"), 1e-5))})
    sp = {f"spec.{k}": "free" for k in model.terms["spec"].coefficients}
    sp.update({"spec.d": "free", "diffuse.rho_d": "free"})
    save(name, "binomial", fit(model, table, sp), t0, summary)


def main(argv: list[str]) -> None:
    names = argv or list(TABLES)
    OUT.mkdir(parents=True, exist_ok=True)
    path = ROOT / "experiments" / "results" / "sky_lab_fits.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    for name in names:
        print(name, flush=True)
        fit_table(name, summary)
        write_json_atomic(path, summary)


if __name__ == "__main__":
    main(sys.argv[1:])
