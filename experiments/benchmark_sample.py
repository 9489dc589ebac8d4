"""Throughput of the posterior sampler: log-probability evaluations per second, vectorised vs per walker.

The same emcee ``EnsembleSampler`` (64 walkers, stretch move) runs on the same
log-posterior of a noisy solar-cell frame (theta_i = 20 deg, every 4th pixel of
the seed camera, pixels above 0.1 sr^-1, 3 % noise; 12 free parameters, the
seed's values as the start), once with ``vectorize=True`` and the jit-compiled
vmapped log-posterior (one batched call per half-step) and once with
``vectorize=False`` and a plain per-walker Python log-probability (the same
jit-compiled single-walker function called once per walker).  Compilation is
excluded (both are warmed up).  Prints evaluations per second and their ratio,
per device (``jax.devices()``; CPU always, GPU when present), and with
``--roi`` the same on a region of interest where the per-call overhead
dominates.

    python3 experiments/benchmark_sample.py [--step 4] [--steps 3] [--walkers 64] [--roi 120] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import emcee  # noqa: E402
import numpy as np  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.fit import Param, get_solver, render_noisy_frames  # noqa: E402
from brdfjax.fit.internal import prepare_problem  # noqa: E402
from brdfjax.sample import build_log_posterior  # noqa: E402

FREE = ["m1", "rho_s1", "n1", "m2", "rho_s2", "n2", "dtheta", "dphi0", "a", "b", "c", "rho_s3"]


def build(step: int, roi: int | None, device) -> tuple:
    model = bj.solar_cell()
    r = None if roi is None else (-roi, roi, -roi, roi)
    frames = render_noisy_frames(model, [20.0], step=step, roi=r, seed=1, noise_rel=0.03, floor=0.1)
    spec = {k: Param(float(np.asarray(v))) for k, v in model.params().items() if k in FREE}
    spec["n1"] = Param(3.6, lower=1.0, upper=6.0)
    spec["n2"] = Param(1.4, lower=1.0, upper=6.0)
    spec["b"] = Param(1e-5, lower=1e-6, upper=4e-5)
    with jax.default_device(device):
        prep = prepare_problem(model, frames, spec, solver=get_solver("levenberg_marquardt"))
        post = build_log_posterior(prep)
        post.problem = jax.device_put(post.problem, device)
        post.priors = jax.device_put(post.priors, device)
    x0 = np.array([e.x0 for e in prep.layout.free])
    return post, x0, int(frames[0].usable().sum()), frames[0].grid.shape


def time_sampler(log_prob, vectorize: bool, p0: np.ndarray, n_steps: int) -> tuple[float, int]:
    calls = {"n": 0}

    def counted(x):
        calls["n"] += len(x) if vectorize else 1
        return log_prob(x)

    sampler = emcee.EnsembleSampler(p0.shape[0], p0.shape[1], counted, vectorize=vectorize)
    state = sampler.run_mcmc(p0, 1, progress=False)  # warm-up: compiles the (n/2, p) shape too
    calls["n"] = 0
    t0 = time.perf_counter()
    sampler.run_mcmc(state, n_steps, progress=False)
    return time.perf_counter() - t0, calls["n"]


def run(step: int, roi: int | None, n_walkers: int, n_steps: int, device) -> dict:
    post, x0, n_points, shape = build(step, roi, device)
    rng = np.random.default_rng(0)
    p0 = x0 * (1 + 1e-4 * rng.standard_normal((n_walkers, x0.size)))
    with jax.default_device(device):
        post(p0)  # compile (n, p)
        post.log_prob_one(p0[0])  # compile the single-walker function
        t_vec, n_vec = time_sampler(post, True, p0, n_steps)
        t_one, n_one = time_sampler(post.log_prob_one, False, p0, n_steps)
    out = {
        "device": str(device),
        "grid_shape": list(shape),
        "step": step,
        "roi_px": roi,
        "n_points": n_points,
        "n_walkers": n_walkers,
        "n_dim": int(x0.size),
        "n_steps": n_steps,
        "vectorised_evals_per_s": n_vec / t_vec,
        "per_walker_evals_per_s": n_one / t_one,
    }
    out["ratio"] = out["vectorised_evals_per_s"] / out["per_walker_evals_per_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--step", type=int, default=4)
    ap.add_argument("--steps", type=int, default=3, help="timed sampler steps per variant")
    ap.add_argument("--walkers", type=int, default=64)
    ap.add_argument("--roi", type=int, default=None, help="also run on a (2 roi + 1)^2 pixel region, every pixel")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    devices = [jax.devices("cpu")[0]]
    try:
        devices += jax.devices("gpu")[:1]
    except RuntimeError:
        pass
    results = []
    cases = [(args.step, None)] + ([(1, args.roi)] if args.roi else [])
    for dev in devices:
        for step, roi in cases:
            r = run(step, roi, args.walkers, args.steps, dev)
            results.append(r)
            where = f"every {step}th pixel" + (f" of a {2 * roi + 1} px square" if roi else " of the frame")
            print(
                f"{r['device']}: {where} ({r['grid_shape'][0]} x {r['grid_shape'][1]} grid, {r['n_points']} usable points), "
                f"{r['n_walkers']} walkers x {r['n_dim']} parameters: vectorised {r['vectorised_evals_per_s']:.1f} evals/s, "
                f"per-walker Python {r['per_walker_evals_per_s']:.1f} evals/s, ratio {r['ratio']:.2f}",
                flush=True,
            )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
