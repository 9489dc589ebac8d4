"""Noise-free (Asimov) fits of the shipped synthetic solar-cell config: where does the bias of ``c`` come from?

The frames of ``configs/fit_synthetic_solar_cell.toml`` are generated once (one noise seed) to give the fit its
grids, masks, weights and nuisance setup; then each frame's BRDF is replaced by a noise-free version and the
config's fit is rerun, started at the truth.  The fitted offset ``(c_hat - c_true) / sigma_c`` of a noise-free
fit is the bias itself.  Variants (``--variants``):

- ``f64``: the model rendered in float64 on the binned camera, convolved with the footprint in float64;
- ``f32``: the synthetic instrument's own ``expected_brdf(render_brdf(...))`` (its float32 render and float32
  convolution output): exactly the light the synthetic instrument puts on the array, before the camera;
- ``noisy``: one noise realisation (``--seed``) as the shipped fit sees it (started at the truth; its noise
  weights re-evaluated at the first fit's model and refitted, ``[data] noise_weights = "model"``);
  ``noisypix``: the same with the weights of each pixel's own reading (``noise_weights = "pixel"``);
- ``noisy-gain0``, ``noisypix-gain0``: the same with a camera without per-pixel gain errors;
- ``swap``: its BRDF with the weights and mask of another realisation (``--seed`` + 1000);
- ``gauss``: the ``f64`` light times ``1 + u N(0, 1)``, ``u`` each pixel's noise level, with weights that do
  not depend on that noise: the bias of the log residual alone (``E[log d] != log E[d]``); ``gausscorr``: the
  same data multiplied by ``exp(u^2 / 2)``;
- ``pipeline``: the synthetic instrument with its noise switched off (no shot noise, no dark noise, no
  quantisation), reduced by the reduction: the camera chain and the reduction without noise;
  ``pipeline-<effect>-<effect>``: the same with those effects of the instrument switched off too;
  tokens ``nocorr`` (no non-linearity correction in the reduction), ``gain0`` (no per-pixel gain errors in
  the camera), ``cam<N>`` (camera seed N).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dataclasses import replace  # noqa: E402

import brdfjax.fit.job as job_mod  # noqa: E402
from brdfjax.core.detector import Detector  # noqa: E402
from brdfjax.core.render import Conditions, render  # noqa: E402
from brdfjax.fit._params import Param  # noqa: E402
from brdfjax.fit.config import load_fit_config  # noqa: E402
from brdfjax.fit.job import build_fit_job  # noqa: E402
from brdfjax.instrument.optics import footprint_kernel  # noqa: E402
from brdfjax.instrument.synthetic import SyntheticInstrument, load_instrument_config  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

CONFIG = ROOT / "configs" / "fit_synthetic_solar_cell.toml"
WATCH = ("c", "a", "b", "m1", "rho_s3")


def base_job(bin_: int, seed: int, work: Path, without=(), *, camera_seed=None, correct=True, gain0=False):
    """The config's job at ``bin_`` with noise seed ``seed`` and the instrument's ``without`` effects off.

    ``camera_seed``: another synthetic camera (its per-pixel maps); ``correct``: the reduction's
    non-linearity correction; ``gain0``: the camera's per-pixel gain errors (and outliers) removed, its
    array-wide response curve kept.
    """
    cfg = load_fit_config(CONFIG)
    upd = {"seed": seed, "bin": bin_, "without": list(without)}
    if camera_seed is not None:
        upd["camera_seed"] = camera_seed
    syn = cfg.data.synthetic.model_copy(update=upd)
    red = cfg.data.reduce.model_copy(update={"correct_nonlinearity": bool(correct)})
    cfg = cfg.model_copy(update={"data": cfg.data.model_copy(update={"synthetic": syn, "reduce": red})})
    orig = job_mod.load_instrument_config

    def patched(path, cam):
        c = orig(path, cam)
        if gain0:
            nl = c.nonlinearity.model_copy(update={"gain_mean": 1e-12, "gain_std": 1e-12, "outlier_fraction": 0.0})
            c = c.model_copy(update={"nonlinearity": nl})
        return c

    job_mod.load_instrument_config = patched
    try:
        return cfg, build_fit_job(cfg, work_dir=work)
    finally:
        job_mod.load_instrument_config = orig


def instrument_for(cfg):
    s = cfg.data.synthetic
    inst_cfg = load_instrument_config(None, s.camera_seed).without(*s.without)
    det = Detector.seed(shape=(2472 // s.bin, 3296 // s.bin), pixel_pitch=5.5e-6 * s.bin, pixel_pitch_v=5.5e-6 * s.bin)
    inst_cfg = inst_cfg.for_pixel_pitch(float(det.pixel_pitch))
    return SyntheticInstrument(det, inst_cfg, seed=0)


def noise_free(job, cfg, how: str, noise_seed=None, log_correct=False):
    """Each frame's BRDF replaced by the noise-free light of the synthetic instrument (``how``: f64 / f32).

    ``noise_seed``: plus Gaussian noise of each pixel's relative noise (its ``sigma_rel`` without the config's
    ``sigma_floor``), independent of the weights; ``log_correct``: the data then multiplied by
    ``exp(u^2 / 2)`` so that ``E[log d] = log m`` to second order.
    """
    rng = np.random.default_rng(noise_seed)
    floor = float(cfg.data.sigma_floor or 0.0)
    inst = instrument_for(cfg)
    det = inst.detector
    h_min, _, v_min, _ = det.index_range
    w = inst.config.footprint.w_px
    blocks = []
    for b in job.blocks:
        frame = Conditions(b.theta_i, b.phi_ref, b.wavelength)
        if how == "f64":
            img = np.asarray(render(job.model, frame, det, precision="float64"), np.float64)
            img = _conv64(img, footprint_kernel(w))
        elif how == "f32":
            img = inst.expected_brdf(inst.render_brdf(job.model, frame)).astype(np.float64)
        else:
            raise ValueError(how)
        rows = np.asarray(b.grid.n_v) - v_min
        cols = np.asarray(b.grid.n_h) - h_min
        img = img[np.ix_(rows, cols)]
        if noise_seed is not None:  # additive-in-linear noise of the frame's own noise level (the floor taken out)
            u = np.sqrt(np.clip(np.asarray(b.sigma_rel, float) ** 2 - floor**2, 0.0, None))
            img = img * (1.0 + u * rng.standard_normal(img.shape))
            img = np.where(img > 0, img, np.nan)
            if log_correct:
                img = img * np.exp(0.5 * u**2)
        blocks.append(replace(b, brdf=img))
    job.blocks = blocks
    return job


def _conv64(image, kernel):
    from scipy.signal import fftconvolve

    return fftconvolve(image, kernel, mode="same")


def start_at_truth(job):
    params = {}
    for k, p in job.params.items():
        if isinstance(p, Param):
            params[k] = replace(p, value=None) if p.value == "auto" else p
        elif p == "auto":
            params[k] = Param(value=None)
        else:
            params[k] = p
    job.params = params
    job.fit_kwargs["initializer"] = None
    job.fit_kwargs["absolute_sigma"] = True  # a noise-free fit has chi^2 ~ 0: the sigmas must not scale with it
    return job


def report(job, r, t0):
    out = {"chi2_reduced": float(r.chi2_reduced), "converged": bool(r.converged), "wall_s": time.perf_counter() - t0}
    for name in WATCH:
        p = r.parameters[name]
        t = job.truth[name]
        out[name] = {"value": p.value, "sigma": p.sigma, "truth": t, "rel": p.value / t - 1,
                     "pull": (p.value - t) / p.sigma if p.sigma and math.isfinite(p.sigma) else math.nan}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", type=int, default=8)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--variants", default="f64,f32")
    ap.add_argument("--work", default="runs/c_asimov")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    work = Path(args.work) / f"bin{args.bin}"
    res = {"settings": vars(args), "variants": {}}
    for v in args.variants.split(","):
        t0 = time.perf_counter()
        if v.startswith("pipeline"):
            toks = [x for x in v.split("-")[1:] if x]
            cam = next((int(x[3:]) for x in toks if x.startswith("cam")), None)
            extra = tuple(x for x in toks if x not in ("nocorr", "gain0") and not x.startswith("cam"))
            cfg, job = base_job(args.bin, args.seed, work / v, without=("shot_noise", "dark", "quantisation", *extra),
                                camera_seed=cam, correct="nocorr" not in toks, gain0="gain0" in toks)
        elif v in ("noisy-gain0", "noisypix-gain0"):
            # the same without the camera's per-pixel gain errors: what is left besides the fixed gain map
            cfg, job = base_job(args.bin, args.seed, work / f"noisy{args.seed}-gain0", gain0=True)
        elif v in ("noisy", "noisypix", "swap"):
            # a noisy realisation as the shipped fit sees it; "swap": its BRDF, but the weights and the mask of
            # another realisation (seed + 1000), so that neither depends on the noise of the pixel it weighs
            cfg, job = base_job(args.bin, args.seed, work / f"noisy{args.seed}")
            if v == "swap":
                _, other = base_job(args.bin, args.seed + 1000, work / f"noisy{args.seed + 1000}")
                job.blocks = [replace(b, sigma_rel=o.sigma_rel, mask=o.mask) for b, o in zip(job.blocks, other.blocks)]
        elif v in ("gauss", "gausscorr"):
            cfg, job = base_job(args.bin, args.seed, work / f"noisy{args.seed}")
            job = noise_free(job, cfg, "f64", noise_seed=args.seed + 1, log_correct=v == "gausscorr")
        else:
            cfg, job = base_job(args.bin, args.seed, work / f"noisy{args.seed}")
            job = noise_free(job, cfg, v)
        if not v.startswith("noisy-") and v != "noisy":
            job.reweight = None  # the data and weights as built here: no refit at the model (it rereads the data)
        job = start_at_truth(job)
        r = job.run()
        res["variants"][v] = rep = report(job, r, t0)
        if job.first_result is not None:  # the fit with the readings' own weights, before the refit
            rep["pixel_weights"] = first = report(job, job.first_result, t0)
            print(f"[{v} first fit] " + " ".join(f"{n} pull {first[n]['pull']:+.2f}" for n in WATCH), flush=True)
        print(f"[{v}] chi2_red {rep['chi2_reduced']:.4g} " + " ".join(
            f"{n}: rel {rep[n]['rel']:+.2e} pull {rep[n]['pull']:+.2f}" for n in WATCH) + f" [{rep['wall_s']:.0f} s]", flush=True)
        if args.out:
            write_json_atomic(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
