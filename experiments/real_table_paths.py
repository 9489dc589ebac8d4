"""The diagnosis's whole search on the real goniometer tables (no uncertainties: sigma estimated), with the
library defaults: which explanation the search keeps and what it costs.  (``paths_compared`` is None since the
search replaced the two greedy paths; the key is kept so that older result files read alike.)

For each shipped real table (``tests/data/real``: MERL aluminium, Cornell Krylon blue and Cayman; every
``--step``-th row) the plain one-lobe + Lambertian base of ``tests/diagnose/test_tables_diagnosis.py`` is diagnosed with
the table-applicable library, ``max_steps`` steps at most.  Without sigma there is no noise level to stop at.
Printed and written per dataset: the kept
path, both paths' final ``-2 ln L``-based BIC and estimated ``sigma_ln``, and the timings.

    python experiments/real_table_paths.py [--json experiments/results/real_table_paths.json]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import brdfjax as bj  # noqa: E402
from brdfjax.diagnose import diagnose  # noqa: E402
from brdfjax.fit import prepare, read_cornell_brdf, read_merl_inplane  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "tests" / "data" / "real"
CASES = {
    "merl_aluminium": ("merl_aluminium_inplane.txt", dict(n=0.96, k=6.69)),
    "cornell_krylon_blue": ("cornell_krylon_blue.brdf", dict(n=1.5)),
    "cornell_cayman": ("cornell_cayman_metallic.brdf", dict(n=1.5)),
}
#: the table-applicable library less the floor (the base has its own Lambertian)
EFFECTS = ["second_lobe", "shadowing", "distribution_shape", "angular_sampling"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", default=None, help="write the figures here (atomically, after each dataset)")
    p.add_argument("--step", type=int, default=2, help="every STEP-th row of each table")
    p.add_argument("--max-steps", type=int, default=3)
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ", ".join(CASES))
    args = p.parse_args(argv)
    rows = []
    for name in args.cases.split(","):
        file, index = CASES[name]
        table = read_merl_inplane(REAL / file) if file.startswith("merl") else read_cornell_brdf(REAL / file)
        table = table.select(slice(None, None, args.step))
        model = bj.Model(terms={"spec": bj.Specular(bj.GGX(0.1), rho_s=0.5, **index, **bj.SEED_FORM), "diffuse": bj.Lambertian(0.05)})
        params = {"spec.alpha": "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"}
        t0 = time.perf_counter()
        d = diagnose(prepare(model, table, params, resolution_check=False), effects=EFFECTS, max_steps=args.max_steps)
        wall = time.perf_counter() - t0
        doc = d.to_dict()
        row = {
            "dataset": name, "rows": int(len(table.brdf)), "wall_s": wall, "timings_s": d.timings,
            "path": [[s.action, s.effect] for s in d.path], "stop_reason": d.stop_reason,
            "sigma_estimated": doc["sigma_estimated"], "sigma_ln": doc["gap"].get("sigma_ln"),
            "paths_compared": d.settings.get("paths_compared"),
            "fresh_refit_on_path": d.settings.get("fresh_refit_on_path"), "notes": d.notes,
            "rankings": [[{"effect": c.effect, "delta_bic": c.delta_bic, "flags": c.flags, "refit_start": c.refit_start}
                          for c in r] for r in d.path_rankings],
            "skipped": [{"effect": c.effect, "status": c.status, "note": c.note} for c in d.skipped],
        }
        rows.append(row)
        kept = " -> ".join(e for _, e in row["path"])
        print(f"{name}: {row['rows']} rows, path {kept}, sigma_ln {row['sigma_ln']:.4g}, {wall:.0f} s", flush=True)
        for pc in row["paths_compared"] or []:
            print(f"    fresh_top = {pc['fresh_top']}: {' -> '.join(e for _, e in pc['path'])}, BIC {pc['bic']:.6g}"
                  f"{' (kept)' if pc['kept'] else ''}", flush=True)
        if args.json:
            write_json_atomic(args.json, {"rows": rows, "step": args.step, "max_steps": args.max_steps,
                                          "cpu_count": os.cpu_count(), "load_average": os.getloadavg()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
