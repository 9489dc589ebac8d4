"""The shipped sample config's posterior against the truth and the seed's Chapter IV budget.

Reads ``RUN/posterior.json`` of ``brdfjax sample configs/sample_synthetic_solar_cell.toml --out RUN`` and
the reduced frame's header (``RUN/synthetic/reduced/ti20.exr``, or ``--frame``), and prints per sampled
parameter the truth, the 95 % interval and whether it holds the truth; for the flux-scaled weights (rho_s1,
rho_s3) the relative posterior width (half the 68 % interval over the median) beside the seed's combined ND +
non-linearity uncertainty of that frame's stacks, computed with :mod:`brdfjax.instrument.uncertainty`
(Eq 97 for the beam-signature and sample stacks, with the manifest's tolerances, in quadrature with the
per-pixel scatter non-linearity of Eq 92 the reduction used).  Writes ``RUN/check.json``.

    python3 experiments/check_shipped_sample.py runs/sample
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import brdfjax as bj
from brdfjax.fit._nuisance import default_nd_tolerances
from brdfjax.instrument.reduce import read_reduced_frame
from brdfjax.instrument.uncertainty import optical_density_uncertainty
from brdfjax.io.raw import read_manifest

WEIGHTS = ("rho_s1", "rho_s2", "rho_s3")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--frame", default=None)
    ap.add_argument("--synthetic", default=None, help="the synthetic folder (default RUN/synthetic)")
    args = ap.parse_args(argv)
    run = Path(args.run)
    doc = json.loads((run / "posterior.json").read_text())
    syn = Path(args.synthetic) if args.synthetic else run / "synthetic"
    frame = read_reduced_frame(args.frame or syn / "reduced" / "ti20.exr")
    a = frame.attrs
    table = {**default_nd_tolerances(), **read_manifest(syn / "raw" / "manifest.toml", check_files=False).calibration.nd_tolerances}
    nd = optical_density_uncertainty(a["nd_beam"], a["nd_sample"], table)
    nl = float(a["u_scatter_nonlinearity"])
    combined = math.hypot(nd, nl)
    truth = dict(bj.SOLAR_CELL_SEED)
    truth_nat = truth
    out = {"nd_beam": a["nd_beam"], "nd_sample": a["nd_sample"], "u_nd": nd, "u_scatter_nonlinearity": nl,
           "combined_nd_nonlinearity": combined, "parameters": {}, "converged": doc["converged"],
           "n_steps": doc["n_steps"], "tau_max": doc["tau_max"], "sampler": doc.get("sampler", "emcee")}
    print(f"stacks beam {a['nd_beam']} / sample {a['nd_sample']}: ND (Eq 97) {nd:.4f}, scatter non-linearity "
          f"{nl:.4f}, combined {combined:.4f}")
    ok_all = True
    for name, p in doc["parameters"].items():
        if name not in truth_nat:
            continue
        t = truth_nat[name]
        inside = p["q025"] <= t <= p["q975"]
        ok_all &= inside
        row = {"truth": t, "q025": p["q025"], "q975": p["q975"], "median": p["median"], "inside95": inside}
        line = f"{name:<8s} truth {t:.6g}  95 % [{p['q025']:.6g}, {p['q975']:.6g}]  {'inside' if inside else 'OUTSIDE'}"
        if name in WEIGHTS:
            rel = 0.5 * (p["q84"] - p["q16"]) / p["median"]
            row.update(rel_width=rel, ratio_to_budget=rel / combined)
            line += f"; relative width {rel:.4f} = {rel / combined:.3f} x the combined ND + NL {combined:.4f}"
        if p.get("sigma_conditional") is not None:
            row["sigma_conditional"] = p["sigma_conditional"]
            row["sigma_marginal"] = p["sigma_marginal"]
            line += f" (sigma with systematics {p['sigma_marginal']:.3g}, without {p['sigma_conditional']:.3g})"
        out["parameters"][name] = row
        print(line)
    out["all_inside95"] = bool(ok_all)
    (run / "check.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
