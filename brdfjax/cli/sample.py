"""``brdfjax sample CONFIG --out DIR [--resume]``: parameter posteriors (emcee or NUTS) from a fit config.

The config is a fit config plus an optional ``[sample]`` table
(:class:`brdfjax.sample.config.SampleSection`). The command builds the config's
likelihood (:meth:`brdfjax.fit.job.FitJob.likelihood`) and its sampler object
(:meth:`~brdfjax.sample.config.SampleSection.sampler`) and runs
:func:`brdfjax.sample.sample` on them; see :mod:`brdfjax.sample.config` for the
table, the outputs and the resume rules.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ..fit.config import enable_config_precision, load_fit_config
from ..fit.job import build_fit_job
from ..io import check_output_dir
from ..runtime.cli_args import CONFIG, DIR, add_no_figures, positive_int
from ..runtime.progress import make_console
from ..sample import sample
from ..sample.config import SampleSection, config_fingerprint, priors_from_config
from ..sample.internal import ChainStore, SampleError, check_sampling, check_walkers, spec_from_fit_json

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar=CONFIG, help="a fit config with an optional [sample] table (configs/sample_*.toml); "
                   "its sample.sampler picks emcee (affine-invariant ensemble) or nuts (blackjax's No-U-Turn sampler)")
    p.add_argument("--out", required=True, metavar=DIR, help="output folder: chain.h5, posterior.json, figures")
    p.add_argument("--resume", action="store_true", help="continue the chain in DIR/chain.h5")
    p.add_argument("--steps", type=positive_int, default=None, metavar="N",
                   help="total chain length: steps per walker (emcee) or draws per chain (NUTS) (overrides sample.n_steps)")
    p.add_argument("--walkers", type=positive_int, default=None, metavar="N",
                   help="number of emcee walkers (overrides sample.n_walkers; NUTS runs sample.n_chains chains)")
    p.add_argument("--fit-result", default=None, metavar="JSON", help="least-squares result to start from (brdfjax fit's result.json)")
    add_no_figures(p, "write chain.h5 and posterior.json only")
    p.add_argument("--no-progress", action="store_true", help="no progress bar or progress lines")


def _print_summary(console: Any, s: dict[str, Any]) -> None:
    fmt = lambda v: "-" if v is None else f"{v:.5g}"  # noqa: E731
    lines = [
        f"posterior ({s.get('sampler', 'emcee')}): {s['n_steps']} steps x {s['n_walkers']} "
        f"{'chains' if s.get('sampler') == 'nuts' else 'walkers'}, burn-in {s['burn']}, {s['n_samples']} samples",
        f"{'parameter':<18s} {'median':>12s} {'-1 sigma':>11s} {'+1 sigma':>11s} {'unit':<6s} {'tau':>7s} {'ESS':>8s} {'fit':>12s}",
    ]
    for name, p in s["parameters"].items():
        lines.append(
            f"{name:<18s} {fmt(p['median']):>12s} {fmt(p['median'] - p['q16']):>11s} {fmt(p['q84'] - p['median']):>11s} "
            f"{p['unit']:<6s} {fmt(p['tau']):>7s} {fmt(p['ess']):>8s} {fmt(p.get('fit_value')):>12s}"
        )
    lines.append(
        f"acceptance fraction: mean {s['acceptance_fraction_mean']:.3f} (per walker "
        f"{min(s['acceptance_fraction']):.3f} .. {max(s['acceptance_fraction']):.3f}); converged: {s['converged']}"
    )
    if "nuts" in s:
        n = s["nuts"]
        lines.append(f"NUTS: R-hat max {n['rhat_max']}, {n['divergences']} divergences, mean {n['mean_leapfrog_steps']} leapfrog steps")
    for name, p in s["parameters"].items():
        if p.get("sigma_conditional") is not None:
            lines.append(f"{name}: sigma {fmt(p['sigma_marginal'])} with the systematics, {fmt(p['sigma_conditional'])} without")
    lines.extend(f"warning: {w}" for w in s["warnings"])
    console.print("\n".join(lines), markup=False)


def run(args: argparse.Namespace) -> int:
    console = make_console(args.quiet, args.no_progress)
    prog = "brdfjax sample"
    enable_config_precision(args.config)
    out = Path(args.out)
    check_output_dir(out)
    cfg = load_fit_config(args.config, sections={"sample": SampleSection})
    sec: SampleSection = cfg.sections.get("sample") or SampleSection()
    model = cfg.build_model()
    priors = priors_from_config(str(cfg.source), sec, model)
    if args.steps is not None and args.steps < 1:
        raise SampleError(f"--steps must be a positive integer, got {args.steps}")
    chain_exists = ChainStore.check_open(out / "chain.h5", resume=args.resume)  # refusals before any fitting
    if args.walkers is not None and args.walkers < 2:
        raise SampleError(f"--walkers must be an even number >= 2 x the free parameters, got {args.walkers}")
    # a prior on a parameter the config holds fixed: before any data are generated or read
    spec = cfg.build_params()
    held = sorted(k for k in priors if k.split("[")[0] in spec and not spec[k.split("[")[0]].free)
    unlisted = sorted(k for k in priors if k.split("[")[0] not in spec)
    if held or unlisted:
        name = (held or unlisted)[0]
        raise SampleError(
            f"{cfg.source}: sample.priors: prior on '{name}', which is held fixed; make it free in [params] to sample it"
        )
    n_walkers = args.walkers if args.walkers is not None else sec.n_walkers
    if sec.sampler == "emcee" and n_walkers is not None:
        # before any data are generated or read: the free parameters the config names are a lower bound on the
        # sampled ones (frames add per-frame parameters and, through the instrument, nuisance parameters)
        check_walkers(n_walkers, sum(1 for p in spec.values() if p.free))
    out.mkdir(parents=True, exist_ok=True)
    job = build_fit_job(cfg, work_dir=out)
    step_roi = dict(step=sec.step, roi=None if sec.roi is None else tuple(sec.roi))
    # priors on fixed or unknown parameters and the walker count: before the fit
    check_sampling(job.model, job.blocks, job.params, priors=priors, n_walkers=n_walkers,
                   fit_kwargs=job.fit_kwargs, **step_roi)
    for note in job.notes:
        console.print(note, markup=False)
    start: Any = None
    weights_note: str | None = None
    fit_path = args.fit_result or (None if sec.fit_result is None else str(cfg.resolve(sec.fit_result)))
    if fit_path is None and (out / "fit_result.json").is_file():
        fit_path = str(out / "fit_result.json")
    if fit_path is not None:
        try:
            start = json.loads(Path(fit_path).read_text())
        except FileNotFoundError:
            raise SampleError(f"{fit_path}: fit result not found (sample.fit_result / --fit-result)") from None
        except (OSError, ValueError) as e:
            raise SampleError(f"{fit_path}: cannot read the fit result JSON: {e}") from None
        console.print(f"starting from the fit result {fit_path}", markup=False)
        if (job.reweight and any(job.reweight) and isinstance(start, dict)
                and isinstance(start.get("noise"), dict) and start["noise"].get("reweighted")):
            # that fit weighed the pixels' noise at its model (noise_weights = "model"); the posterior must use the
            # same weights, not the readings': the fit is repeated from the result's values, which re-evaluates them
            # (two short fits that start at the optimum)
            console.print("its noise weights were evaluated at its model: repeating that fit from its values to "
                          "weigh the pixels the same way", markup=False)
            job.params = spec_from_fit_json(job.params, start, [b.name for b in job.blocks])
            start = job.run()
            start.to_json(out / "fit_result.json")
            weights_note = "noise weights at the model of the fit result (its fit repeated from its values)"
    elif not (args.resume and chain_exists):
        console.print("fitting first (no fit result given) ...", markup=False)
        start = job.run()
        start.to_json(out / "fit_result.json")
        console.print(start.summary(), markup=False)
        fit_path = str(out / "fit_result.json")
    record = {"config": str(cfg.source), "fit_result": fit_path, "data_step": cfg.data.step, "data_roi": cfg.data.roi,
              "data_roi_deg": cfg.data.roi_deg}
    if job.first_result is not None:
        record["noise_weights"] = weights_note or "noise weights at the model of the fit (noise_weights = \"model\")"
    res = sample(
        job.likelihood(),
        priors,
        sampler=sec.sampler_object(n_walkers=n_walkers, n_steps=args.steps if args.steps is not None else sec.n_steps),
        out_dir=out,
        resume=args.resume,
        start=start,
        seed=sec.seed,
        progress=sec.progress and not args.no_progress and not args.quiet,
        figures=cfg.output.figures and not args.no_figures,
        predictive_draws=sec.predictive_draws,
        step=sec.step,
        roi=None if sec.roi is None else tuple(sec.roi),
        log=lambda m: console.print(m, markup=False),
        extra_record=record,
        extra_fingerprint=config_fingerprint(cfg),
        log_weights=sec.log_weights,
        start_covariance=sec.start_covariance,
    )
    _print_summary(console, res.summary)
    console.print(f"wrote {', '.join(sorted(Path(f).name for f in res.files.values()))} in {out}", markup=False)
    if res.run.interrupted:
        console.print(
            f"{prog}: interrupted after {res.run.iterations} steps; the chain is saved: continue with --resume",
            markup=False,
        )
        return 130
    return 0
