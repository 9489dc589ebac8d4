"""emcee against NUTS on one posterior: wall time and effective samples per second, in one run.

Loads a sample config (default: the 12-parameter two-angle solar-cell posterior
with nuisance parameters, ``configs/sample_synthetic_solar_cell_full.toml``),
generates and reduces its synthetic data, fits once, then samples the same
log-posterior with emcee (``--emcee-steps`` x the config's walkers) and with
NUTS (``--nuts-steps`` per chain after ``--warmup``), and reports per sampler
the wall time (total, and the sampling alone), the smallest ESS over the
parameters (emcee: walkers x kept / tau; NUTS: blackjax's ESS across
chains), ESS per second, R-hat (NUTS) and the acceptance.  Written to
``OUT/benchmark.json``.

    python3 experiments/benchmark_nuts.py --out runs/bench_nuts [--config CFG] [--emcee-steps 2000] [--nuts-steps 500]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from brdfjax.fit.config import build_fit_job, load_fit_config  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.sample import sample  # noqa: E402
from brdfjax.sample.cli import SampleSection, priors_from_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/bench_nuts")
    ap.add_argument("--config", default=str(ROOT / "configs" / "sample_synthetic_solar_cell_full.toml"))
    ap.add_argument("--emcee-steps", type=int, default=2000)
    ap.add_argument("--walkers", type=int, default=None)
    ap.add_argument("--nuts-steps", type=int, default=500)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--chains", type=int, default=4)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_fit_config(args.config, sections={"sample": SampleSection})
    sec: SampleSection = cfg.sections.get("sample") or SampleSection()
    job = build_fit_job(cfg, work_dir=out)
    print("\n".join(job.notes), file=sys.stderr)
    t0 = time.perf_counter()
    res = job.run()
    t_fit = time.perf_counter() - t0
    print(res.summary(), file=sys.stderr)
    priors = priors_from_config(str(cfg.source), sec, job.model)
    report = {"config": args.config, "fit_s": t_fit, "n_free": len(res.free_names), "loadavg_start": os.getloadavg()}
    common = dict(priors=priors, start=res, fit_kwargs=job.fit_kwargs, figures=False, seed=1, predictive_draws=0)
    for name, kw in (
        ("emcee", dict(sampler="emcee", n_steps=args.emcee_steps, n_walkers=args.walkers or sec.n_walkers)),
        ("nuts", dict(sampler="nuts", n_steps=args.nuts_steps, n_chains=args.chains, n_warmup=args.warmup)),
    ):
        d = out / name
        t0 = time.perf_counter()
        r = sample(job.model, job.blocks, job.params, out_dir=d, resume=(d / "chain.h5").exists(), **common, **kw)
        wall = time.perf_counter() - t0
        s = r.summary
        ess = np.array([p["ess"] if p["ess"] is not None else np.nan for p in s["parameters"].values()], float)
        worst = int(np.nanargmin(ess)) if np.any(np.isfinite(ess)) else 0
        names = list(s["parameters"])
        report[name] = {
            "wall_s": wall,
            "sampling_s": s["run_wall_s"],
            "n_steps": s["n_steps"],
            "n_walkers_or_chains": s["n_walkers"],
            "min_ess": float(np.nanmin(ess)) if np.any(np.isfinite(ess)) else None,
            "min_ess_parameter": names[worst],
            "ess_per_s_total": float(np.nanmin(ess) / wall) if np.any(np.isfinite(ess)) else None,
            "ess_per_s_sampling": float(np.nanmin(ess) / s["run_wall_s"]) if np.any(np.isfinite(ess)) else None,
            "tau_max": s["tau_max"],
            "converged": s["converged"],
            "acceptance_mean": s["acceptance_fraction_mean"],
            "nuts": s.get("nuts"),
        }
        print(f"{name}: {json.dumps(report[name], default=str)[:600]}", file=sys.stderr, flush=True)
        report["loadavg_now"] = os.getloadavg()
        write_json_atomic(out / "benchmark.json", json.loads(json.dumps(report, default=str)))  # what is measured so far survives a kill
    report["loadavg_end"] = os.getloadavg()
    e, n = report["emcee"]["ess_per_s_total"], report["nuts"]["ess_per_s_total"]
    report["nuts_over_emcee_ess_per_s"] = None if not (e and n) else n / e
    write_json_atomic(out / "benchmark.json", json.loads(json.dumps(report, default=str)))
    print(json.dumps({k: report[k] for k in ("nuts_over_emcee_ess_per_s", "fit_s", "n_free")}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
