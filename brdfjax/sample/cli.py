"""``brdfjax sample CONFIG --out DIR [--resume]``: parameter posteriors with emcee from a fit config.

The config is a fit config (:mod:`brdfjax.fit.config`: data, model, [params],
[fit]) plus an optional ``[sample]`` table (:class:`SampleSection`)::

    [sample]
    sampler = "emcee"               # or "nuts" (blackjax's No-U-Turn sampler; n_chains, n_warmup)
    n_walkers = 32                  # default max(32, 4 x free parameters); >= 2 x free parameters, even
    n_steps = 2000                  # total chain length (a resumed run continues to this length)
    burn = "auto"                   # discarded steps: an integer or "auto" (2 x the largest tau, <= half)
    thin = 1
    seed = 0
    ball = 0.1                      # walkers start within ball x the fit's sigma around the optimum
    stop_when_converged = false     # stop once the chain is > 50 tau and tau is stable to 1 %
    check_every = 100               # steps between convergence checks
    # fit_result = "runs/fit/result.json"   # the least-squares optimum (default: fit first)
    # step = 2                      # sample on every step-th point of the fit's grid ...
    # roi = [-60, 60, -60, 60]      # ... inside this region [h0, h1, v0, v1] (seed pixel indices)
    predictive_draws = 100          # posterior draws for the predictive bands
    # log_weights = true            # sample rho* as log rho (default: on with nuisance parameters)
    # start_covariance = true       # start along the fit's full covariance (default: on with nuisance parameters)

    [sample.priors]                 # keys and units as in [params] (angles <name>_deg, lengths <name>_m)
    rho_s3 = { kind = "uniform", lower = 100.0, upper = 600.0 }
    m1 = { kind = "log_uniform", lower = 5e-5, upper = 1e-3 }
    dtheta_deg = { kind = "normal", mu = 0.5, sigma = 0.1 }
    n1 = { kind = "truncated_normal", mu = 3.6, sigma = 0.5, lower = 1.0, upper = 6.0 }
    "phi_ref_deg[ti20]" = { kind = "normal", mu = 0.0, sigma = 0.05 }   # one frame's entry

Writes ``DIR/chain.h5`` (emcee's HDF5 backend, written as drawn),
``posterior.json``, ``corner.png``, ``trace.png``, ``predictive_<frame>.png``
and, when it fitted first, ``fit_result.json``.  ``--resume`` continues the
chain in ``DIR/chain.h5`` to ``n_steps`` (``--steps`` to extend it).  Ctrl-C
stops after the step in flight; what was drawn is kept and summarised.

The chain records the problem's fingerprint (the model, priors, data
values, grid, masks, sigma settings, sampler settings: see
:func:`brdfjax.sample.problem_fingerprint`) plus, from the config, the
checksum of every data file and every ``[data]`` setting; ``--resume``
refuses a chain drawn under any other problem and names what differs.

Exit codes (:mod:`brdfjax.runtime.errors`): 0 done, 130 interrupted (resumable), 2
bad config, priors, walkers, chain file, a resume of another problem or an
output folder that cannot be written (the message names the file and key),
1 an internal error.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator

from ..config import (
    ConfigError,
    StrictModel,
    check_choice,
    parameter_keys,
    quoted_choices,
    unknown_key_message,
)
from ..fit.config import enable_config_precision, load_fit_config
from ..fit.internal import FRAME_PARAMETERS
from ..fit.job import build_fit_job
from ..io import check_output_dir
from ..io.fingerprint import file_digest, value_digest
from ..runtime.progress import make_console
from ._api import SAMPLERS, check_sampling, sample
from ._posterior import check_walkers
from ._priors import PRIOR_KINDS, Prior, SampleError
from ._store import ChainStore

__all__ = ["SampleSection", "PriorConfig", "add_arguments", "run", "priors_from_config"]


#: The prior kinds a config may name (``flat`` is what a parameter without a prior gets).
_PRIOR_CHOICES = tuple(k for k in PRIOR_KINDS if k != "flat")


class PriorConfig(StrictModel):
    """One entry of ``[sample.priors]``, numbers in the key's unit (degrees for ``<name>_deg``)."""

    kind: str = Field(description=quoted_choices(_PRIOR_CHOICES))
    lower: float | None = Field(None, allow_inf_nan=True, description="lower end (uniform, log_uniform, truncated_normal)")
    upper: float | None = Field(None, allow_inf_nan=True, description="upper end (uniform, log_uniform, truncated_normal)")
    mu: float | None = Field(None, allow_inf_nan=True, description="mean (normal, truncated_normal)")
    sigma: float | None = Field(None, allow_inf_nan=True, description="standard deviation > 0 (normal, truncated_normal)")

    @field_validator("kind")
    @classmethod
    def _kind(cls, v: str) -> str:
        return check_choice("prior kind", v, _PRIOR_CHOICES)


class SampleSection(StrictModel):
    """The ``[sample]`` table of a fit config (see the module docstring)."""

    sampler: str = Field("emcee", description=f"the sampler: {quoted_choices(SAMPLERS)}")
    n_chains: int = Field(4, ge=1, description="NUTS: independent chains (R-hat needs >= 2)")
    n_warmup: int = Field(500, ge=1, description="NUTS: window-adaptation steps per chain (not kept)")
    n_walkers: int | None = Field(None, ge=2, description="number of walkers, even, >= 2 x the free parameters")
    n_steps: int = Field(2000, ge=1, description="total chain length in steps, >= 1")
    burn: int | Literal["auto"] = Field("auto", description="steps discarded as burn-in: an integer >= 0 or 'auto'")
    thin: int = Field(1, ge=1, description="keep every thin-th step of the chain for the summary")
    seed: int = Field(0, description="seed of the walkers' start and of the sampler")
    ball: float = Field(0.1, gt=0, description="start ball radius in units of the fit's sigma, > 0")
    stop_when_converged: bool = Field(False, description="stop early once converged (> 50 tau, tau stable to 1 %)")
    check_every: int = Field(100, ge=10, description="steps between convergence checks, >= 10")
    progress: bool = Field(True, description="show a progress bar")
    fit_result: str | None = Field(None, description="a fit result JSON (brdfjax fit's result.json), relative to the config")
    step: int | None = Field(None, ge=1, description="sample on every step-th point of the fit's grid")
    roi: list[int] | None = Field(None, min_length=4, max_length=4, description="[h0, h1, v0, v1] seed pixel indices")
    predictive_draws: int = Field(100, ge=0, description="posterior draws for the predictive bands (0: none)")
    log_weights: bool | None = Field(
        None, description="sample the weights (rho*) as logarithms (default: on with nuisance parameters)"
    )
    start_covariance: bool | None = Field(
        None, description="start from the fit's full covariance, not its sigmas (default: on with nuisance parameters)"
    )
    priors: dict[str, PriorConfig] = Field(default_factory=dict, description="parameter key -> prior table")

    @field_validator("sampler")
    @classmethod
    def _sampler(cls, v: str) -> str:
        return check_choice("sampler", v, SAMPLERS)

    @field_validator("burn")
    @classmethod
    def _burn(cls, v: Any) -> Any:
        if isinstance(v, int) and v < 0:
            raise ValueError(f"burn must be >= 0 or 'auto', got {v}")
        return v

    @field_validator("roi")
    @classmethod
    def _roi(cls, v: Any) -> Any:
        if v is not None and not (v[0] <= v[1] and v[2] <= v[3]):
            raise ValueError(f"{list(v)} is not ordered; expected [h0, h1, v0, v1] with h0 <= h1 and v0 <= v1")
        return v


_ENTRY = re.compile(r"^(?P<key>[^\[\]]+)\[(?P<block>[^\[\]]+)\]$")


def priors_from_config(source: str, sec: SampleSection, model: Any) -> dict[str, Any]:
    """``[sample.priors]`` -> {parameter name: Prior (stored units)}; unknown keys raise ConfigError."""
    keys = parameter_keys({**model.parameter_units(), **FRAME_PARAMETERS})
    out: dict[str, Any] = {}
    problems = []
    for key, p in sec.priors.items():
        m = _ENTRY.match(key)
        base_key, block = (m.group("key"), m.group("block")) if m else (key, None)
        if base_key not in keys:
            problems.append((f"sample.priors.{key}", "prior on unknown parameter: " + unknown_key_message(base_key, keys, "this model")))
            continue
        name, scale, _ = keys[base_key]
        full = name if block is None else f"{name}[{block}]"
        prior = Prior(p.kind, **{f: (None if getattr(p, f) is None else getattr(p, f) * scale) for f in ("lower", "upper", "mu", "sigma")})
        try:
            prior.check(full)
        except SampleError as e:
            problems.append((f"sample.priors.{key}", str(e)))
            continue
        out[full] = prior
    if problems:
        raise ConfigError(source, problems)
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="a fit config with an optional [sample] table (configs/sample_*.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: chain.h5, posterior.json, figures")
    p.add_argument("--resume", action="store_true", help="continue the chain in DIR/chain.h5")
    p.add_argument("--steps", type=int, default=None, metavar="N", help="total chain length (overrides sample.n_steps)")
    p.add_argument("--walkers", type=int, default=None, metavar="N", help="number of walkers (overrides sample.n_walkers)")
    p.add_argument("--fit-result", default=None, metavar="JSON", help="least-squares result to start from (brdfjax fit's result.json)")
    p.add_argument("--no-figures", action="store_true", help="write chain.h5 and posterior.json only")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


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


def config_fingerprint(cfg: Any) -> dict[str, Any]:
    """The config's part of a chain's fingerprint: every data file's checksum and every ``[data]`` setting."""
    fp: dict[str, Any] = {}
    d = cfg.data
    for f in d.frames:
        fp[f"file[{f}]"] = file_digest(cfg.resolve(f))
    for t in d.tables:
        fp[f"file[{t.path}]"] = file_digest(cfg.resolve(t.path))
    if d.manifest is not None:
        m = cfg.resolve(d.manifest)
        m = m / "manifest.toml" if m.is_dir() else m
        fp[f"file[{d.manifest}]"] = file_digest(m)
        for raw in sorted(m.parent.glob("*.exr")):
            fp[f"file[{raw.name}]"] = file_digest(raw)
    for k, v in d.model_dump(mode="json", exclude={"frames", "tables", "manifest"}).items():
        fp[f"config.data.{k}"] = value_digest(v)
    return fp


def run(args: argparse.Namespace) -> int:
    console = make_console(args.quiet)
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
    elif not (args.resume and chain_exists):
        console.print("fitting first (no fit result given) ...", markup=False)
        start = job.run()
        start.to_json(out / "fit_result.json")
        console.print(start.summary(), markup=False)
        fit_path = str(out / "fit_result.json")
    record = {"config": str(cfg.source), "fit_result": fit_path, "data_step": cfg.data.step, "data_roi": cfg.data.roi,
              "data_roi_deg": cfg.data.roi_deg}
    res = sample(
        job.model,
        job.blocks,
        job.params,
        priors=priors,
        n_walkers=n_walkers,
        n_steps=args.steps if args.steps is not None else sec.n_steps,
        out_dir=out,
        resume=args.resume,
        start=start,
        fit_kwargs=job.fit_kwargs,
        seed=sec.seed,
        ball=sec.ball,
        burn=sec.burn,
        thin=sec.thin,
        stop_when_converged=sec.stop_when_converged,
        check_every=sec.check_every,
        progress=sec.progress and not args.no_progress and not args.quiet,
        figures=cfg.output.figures and not args.no_figures,
        predictive_draws=sec.predictive_draws,
        step=sec.step,
        roi=None if sec.roi is None else tuple(sec.roi),
        log=lambda m: console.print(m, markup=False),
        extra_record=record,
        extra_fingerprint=config_fingerprint(cfg),
        sampler=sec.sampler,
        n_chains=sec.n_chains,
        n_warmup=sec.n_warmup,
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
