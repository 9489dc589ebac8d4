"""The LM solve's ``ftol`` stop on data brdfjax did not make: the shipped real-data fits with ``ftol`` = 1e-8
(the default) and 0 (off), side by side in one process.

For each config (``configs/fit_cornell_krylon_blue.toml``, ``fit_cornell_cayman.toml``,
``fit_merl_aluminium.toml``: real goniometer tables without uncertainties, so the noise scale is estimated and
``chi2`` is the count of points by construction) it prints and writes the steps, whether the solve converged,
the estimated noise ``sigma_ln`` and ``-2 ln L``: the stop must not change the optimum.

    python experiments/ftol_real_data.py [--json experiments/results/ftol_real_data.json]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from brdfjax.fit import fit  # noqa: E402
from brdfjax.fit.config import load_fit_config  # noqa: E402
from brdfjax.fit.job import build_fit_job  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ("fit_cornell_krylon_blue", "fit_cornell_cayman", "fit_merl_aluminium")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", default=None, help="write the figures here")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="brdfjax-ftol-") as work:
        for name in CONFIGS:
            job = build_fit_job(load_fit_config(ROOT / "configs" / f"{name}.toml"), work_dir=Path(work) / name)
            for ftol in (1e-8, 0.0):
                kw = dict(job.fit_kwargs)
                kw["solver_options"] = {**dict(kw.get("solver_options") or {}), "ftol": ftol}
                t = time.perf_counter()
                r = fit(job.model, job.blocks, job.params, **kw)
                row = dict(config=name, ftol=ftol, steps=int(r.n_iterations), converged=bool(r.converged),
                           sigma_ln=r.noise.get("sigma_ln"), m2ll=float(r.m2ll), fit_s=time.perf_counter() - t)
                rows.append(row)
                print(f"{name:26s} ftol={ftol:<6g} steps {row['steps']:4d} converged {row['converged']!s:5s} "
                      f"sigma_ln {row['sigma_ln']:.10g}  -2lnL {row['m2ll']:.6f}  ({row['fit_s']:.1f} s)", flush=True)
    for name in CONFIGS:
        on, off = (r for r in rows if r["config"] == name)
        print(f"{name}: sigma_ln relative change {abs(on['sigma_ln'] - off['sigma_ln']) / off['sigma_ln']:.2e}, "
              f"-2lnL change {on['m2ll'] - off['m2ll']:+.2e}, steps {on['steps']} vs {off['steps']}")
    if args.json:
        write_json_atomic(args.json, {"rows": rows, "cpu_count": os.cpu_count()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
