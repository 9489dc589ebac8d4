"""emcee against NUTS on one posterior: wall time and effective samples per second, in one run.

Loads a sample config (default: the 12-parameter two-angle solar-cell posterior
with nuisance parameters, ``configs/sample_synthetic_solar_cell_full.toml``),
generates and reduces its synthetic data, fits once (or reads ``--fit-result``;
the fit is written to ``OUT/fit_result.json`` for the next run), then samples
the same log-posterior with emcee (the config's walkers) and with NUTS
(``--chains`` chains after ``--warmup`` adaptation steps), each for the same
wall-clock budget ``--budget-s`` (the chain is extended piece by piece with
``resume`` until the budget is spent, or until ``--emcee-steps`` /
``--nuts-steps``), and reports per sampler the wall time (total, and the
sampling alone), the steps drawn, the largest tau, the smallest ESS over the
parameters (emcee: walkers x kept / tau; NUTS: blackjax's ESS across chains),
ESS per second, R-hat and divergences (NUTS) and the acceptance.  A chain
shorter than 50 tau has an unreliable ESS: ``converged`` and
``chain_over_tau`` say so.  Written to ``OUT/benchmark.json`` after each sampler.

    python3 experiments/benchmark_nuts.py --out runs/bench_nuts [--budget-s 420] [--fit-result FIT.json]
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

from brdfjax.fit.config import load_fit_config  # noqa: E402
from brdfjax.fit.job import build_fit_job  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.sample import sample  # noqa: E402
from brdfjax.sample.config import SampleSection, priors_from_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _record(s: dict, wall: float, sampling: float) -> dict:
    ess = np.array([p["ess"] if p["ess"] is not None else np.nan for p in s["parameters"].values()], float)
    names = list(s["parameters"])
    ok = np.any(np.isfinite(ess))
    worst = int(np.nanargmin(ess)) if ok else 0
    kept = s["n_steps"] - s["burn"]
    return {
        "wall_s": wall,
        "sampling_s": sampling,
        "n_steps": s["n_steps"],
        "n_walkers_or_chains": s["n_walkers"],
        "min_ess": float(np.nanmin(ess)) if ok else None,
        "min_ess_parameter": names[worst],
        "ess_per_s_total": float(np.nanmin(ess) / wall) if ok else None,
        "ess_per_s_sampling": float(np.nanmin(ess) / sampling) if ok and sampling > 0 else None,
        "tau_max": s["tau_max"],
        "chain_over_tau": None if not s["tau_max"] else kept / s["tau_max"],
        "converged": s["converged"],
        "acceptance_mean": s["acceptance_fraction_mean"],
        "warnings": s["warnings"],
        "nuts": s.get("nuts"),
    }


def evaluation_costs(job, priors, start, n_walkers: int, repeats: int = 5) -> dict:
    """Seconds per log-posterior evaluation in emcee's vectorised batch (per walker) and per value-and-gradient
    of NUTS's whitened log-density (one point), medians of ``repeats`` after a compiling call."""
    import jax.numpy as jnp

    from brdfjax.fit import get_solver
    from brdfjax.fit.internal import prepare_problem
    from brdfjax.sample._api import _PREPARE_KEYS, _spec_from_result, weight_mask
    from brdfjax.sample._nuts import _logdensity
    from brdfjax.sample._posterior import build_log_posterior

    fk = job.fit_kwargs
    values = {k: p["value"] * (np.pi / 180 if p.get("unit") == "deg" else 1.0)
              for k, p in start["parameters"].items() if p.get("free")}
    prep = prepare_problem(job.model, job.blocks, _spec_from_result(job.params, values, [b.name for b in job.blocks]),
                   solver=get_solver(fk.get("solver", "levenberg_marquardt")),
                   **{k: fk[k] for k in _PREPARE_KEYS if k in fk and k not in ("initializer", "init_options")})
    post = build_log_posterior(prep, priors)
    post = post.with_log(weight_mask(post))
    x0 = np.array([values.get(n, 0.0) for n in post.names])
    X = x0 + 1e-9 * np.abs(x0) * np.random.default_rng(0).standard_normal((n_walkers, x0.size))
    post.sampler_log_prob(post.to_sampler(X))
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        post.sampler_log_prob(post.to_sampler(X))
        t.append(time.perf_counter() - t0)
    y0 = jnp.asarray(post.to_sampler(x0))
    ld = jax.jit(jax.value_and_grad(_logdensity(post.problem, post.priors, post.est, y0, jnp.eye(x0.size),
                                                jnp.asarray(post.logged))))
    z = jnp.zeros(x0.size)
    jax.block_until_ready(ld(z))
    tg = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(ld(z))
        tg.append(time.perf_counter() - t0)
    return {"emcee_s_per_walker_evaluation": float(np.median(t)) / n_walkers, "n_walkers": n_walkers,
            "nuts_s_per_gradient": float(np.median(tg)), "n_points": post.n_points, "n_dim": post.ndim,
            "gradient_over_evaluation": float(np.median(tg)) / (float(np.median(t)) / n_walkers)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/bench_nuts")
    ap.add_argument("--config", default=str(ROOT / "configs" / "sample_synthetic_solar_cell_full.toml"))
    ap.add_argument("--fit-result", default=None, help="a fit result JSON of this problem (default: fit here)")
    ap.add_argument("--budget-s", type=float, default=420.0, help="wall-clock budget per sampler, seconds")
    ap.add_argument("--emcee-steps", type=int, default=100000)
    ap.add_argument("--emcee-piece", type=int, default=100)
    ap.add_argument("--walkers", type=int, default=None)
    ap.add_argument("--nuts-steps", type=int, default=100000)
    ap.add_argument("--nuts-piece", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--only", choices=("emcee", "nuts", "none"), default=None)
    ap.add_argument("--costs", action="store_true", help="measure the cost of an evaluation and of a gradient first")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_fit_config(args.config, sections={"sample": SampleSection})
    sec: SampleSection = cfg.sections.get("sample") or SampleSection()
    job = build_fit_job(cfg, work_dir=out)
    print("\n".join(job.notes), file=sys.stderr)
    t0 = time.perf_counter()
    if args.fit_result:
        start = json.loads(Path(args.fit_result).read_text())
        n_free = sum(1 for p in start["parameters"].values() if p.get("free"))
    else:
        res = job.run()
        print(res.summary(), file=sys.stderr)
        start = json.loads(res.to_json())
        write_json_atomic(out / "fit_result.json", start)
        n_free = len(res.free_names)
    t_fit = time.perf_counter() - t0
    priors = priors_from_config(str(cfg.source), sec, job.model)
    report = {"config": args.config, "fit_s": t_fit, "n_free": n_free, "budget_s_per_sampler": args.budget_s,
              "loadavg_start": os.getloadavg()}
    common = dict(priors=priors, start=start, fit_kwargs=job.fit_kwargs, figures=False, seed=1, predictive_draws=0)
    if args.costs:
        nw = args.walkers or sec.n_walkers or max(32, 4 * n_free)
        report["costs"] = evaluation_costs(job, priors, start, nw + nw % 2)
        print(f"costs: {report['costs']}", file=sys.stderr, flush=True)
        write_json_atomic(out / "benchmark.json", json.loads(json.dumps(report, default=str)))
    runs = (
        ("emcee", dict(sampler="emcee", n_walkers=args.walkers or sec.n_walkers), args.emcee_steps, args.emcee_piece),
        ("nuts", dict(sampler="nuts", n_chains=args.chains, n_warmup=args.warmup), args.nuts_steps, args.nuts_piece),
    )
    for name, kw, max_steps, piece in runs:
        if args.only and name != args.only:  # "none": the costs only
            continue
        d = out / name
        t0 = time.perf_counter()
        sampling = 0.0
        n = piece
        while True:
            r = sample(job.model, job.blocks, job.params, out_dir=d, resume=(d / "chain.h5").exists(), n_steps=n,
                       **common, **kw)
            sampling += r.summary["run_wall_s"]
            wall = time.perf_counter() - t0
            print(f"{name}: {n} steps, {wall:.0f} s, tau_max {r.summary['tau_max']}", file=sys.stderr, flush=True)
            if wall > args.budget_s or n >= max_steps:
                break
            n = min(max_steps, n + piece)
        report[name] = _record(r.summary, wall, sampling)
        print(f"{name}: {json.dumps(report[name], default=str)[:800]}", file=sys.stderr, flush=True)
        report["loadavg_now"] = os.getloadavg()
        write_json_atomic(out / "benchmark.json", json.loads(json.dumps(report, default=str)))  # survives a kill
    report["loadavg_end"] = os.getloadavg()
    e = (report.get("emcee") or {}).get("ess_per_s_total")
    n_ = (report.get("nuts") or {}).get("ess_per_s_total")
    report["nuts_over_emcee_ess_per_s"] = None if not (e and n_) else n_ / e
    write_json_atomic(out / "benchmark.json", json.loads(json.dumps(report, default=str)))
    print(json.dumps({k: report.get(k) for k in ("nuts_over_emcee_ess_per_s", "fit_s", "n_free")}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
