"""brdfjax's fit against a scipy finite-difference fit of the same data, both measured in one run (issue 19).

The problem: ``configs/fit_synthetic_solar_cell.toml`` (the solar-cell model
measured by the synthetic instrument at theta_i = 20, 40, 60 deg, reduced,
3 frames, footprint convolved, 15 free parameters from the automatic
initialisation).  The frames are generated once into ``--data`` and reused.

Sides, each in its own process, alternating, ``--repeats`` times:

- ``brdfjax``: ``fit()`` as the CLI runs it (cold: the process's first fit,
  compilation included; warm: the same fit again in the same process).  The
  warm process also times one residual evaluation and one Jacobian (medians).
  With ``--cache DIR`` the persistent compilation cache is on (the second
  process starts warm).
- ``scipy``: ``scipy.optimize.least_squares(method="trf", jac="2-point",
  x_scale="jac")`` on a NumPy model of the same residuals: the seed model of
  ``brdfjax/reference.py`` (float64 NumPy) at each frame's support pixels
  (scatter angles computed once; they depend on no parameter), convolved
  with the footprint by ``scipy.signal.fftconvolve``, the same log residuals,
  weights, floor, bounds and start (the brdfjax side's automatic
  initialisation, passed over in a file).

Whole-process time includes the interpreter, imports and loading the frames.
Run::

    python3 experiments/benchmark_fit.py --repeats 1
    python3 experiments/benchmark_fit.py --repeats 3 --json runs/benchmark_fit.json

Targets (issue 19): brdfjax >= 3x faster whole-process cold, >= 5x warm, the
same final chi^2; the Jacobian <= 4x a residual evaluation.  The brdfjax side
fits without the config's nuisance parameters (the scipy side has none: both
fit the same 15 parameters).  The residual and Jacobian are timed in CPU
seconds of the process (less distorted by other jobs on a shared box than wall
time, which is printed beside them); ``--jacfwd`` also times the plain
``jax.jacfwd`` Jacobian.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

T_START = time.perf_counter()
ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "fit_synthetic_solar_cell.toml"


def _job(data: Path):
    import jax

    jax.config.update("jax_enable_x64", True)
    from brdfjax.fit.config import load_fit_config
    from brdfjax.fit.job import build_fit_job

    return build_fit_job(load_fit_config(CONFIG), work_dir=data)


def _brdfjax(data: Path, start_out: Path, first_stage: str, with_jacfwd: bool = False) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from brdfjax.fit import fit
    from brdfjax.fit._problem import jacobian, jacobian_jacfwd, residuals
    from brdfjax.fit._solvers import get_solver
    from brdfjax.fit.internal import prepare_problem

    job = _job(data)
    t_loaded = time.perf_counter()
    kw = dict(job.fit_kwargs)
    # The scipy side models no nuisance parameters (the config's [nuisance] adds 7): both sides fit the
    # same 15 free parameters to the same residuals.
    kw["nuisance"] = None
    if first_stage != "config":
        kw["first_stage"] = None if first_stage == "none" else first_stage
    runs = []
    for label in ("cold", "warm"):
        t0 = time.perf_counter()
        res = fit(job.model, job.blocks, job.params, **kw)
        runs.append(dict(run=label, fit_s=time.perf_counter() - t0, process_s=time.perf_counter() - T_START,
                         chi2=res.chi2, steps=res.n_iterations, converged=res.converged, message=res.message,
                         timings=dict(res.timings)))
    # the start (automatic initialisation) and the layout, for the scipy side
    prep = prepare_problem(job.model, job.blocks, job.params, solver=get_solver(kw["solver"]), loss=kw["loss"],
                   initializer=kw["initializer"], precision=kw["precision"], use_footprint=kw["use_footprint"])
    lay = prep.layout
    free = [dict(name=e.name, base=e.base, kind=e.kind, blocks=list(e.blocks), x0=float(e.x0), lower=float(e.lower),
                 upper=float(e.upper)) for e in lay.free]
    fixed = [dict(base=e.base, kind=e.kind, blocks=list(e.blocks), value=float(e.value)) for e in lay.fixed]
    start_out.write_text(json.dumps(dict(free=free, fixed=fixed)))
    # one residual vs one Jacobian (the solver's pieces), medians of alternating calls
    from brdfjax.fit._fit import _scales, with_scale

    problem = with_scale(prep.problem, lay.u0(), np.ones(len(free)))
    problem = with_scale(problem, lay.u0(), _scales(problem, lay, []))
    v = jnp.zeros(len(free))
    f_r = jax.jit(residuals)
    jax.block_until_ready(f_r(v, problem))
    jax.block_until_ready(jacobian(v, problem))
    if with_jacfwd:
        jax.block_until_ready(jacobian_jacfwd(v, problem))
    # CPU seconds of this process (all its threads), alternating; wall seconds beside them
    tr, tj, tf, wr, wj = [], [], [], [], []
    for _ in range(7):
        for f, cpu, wall in ((f_r, tr, wr), (jacobian, tj, wj)) + (((jacobian_jacfwd, tf, []),) if with_jacfwd else ()):
            t, c = time.perf_counter(), time.process_time()
            jax.block_until_ready(f(v, problem))
            cpu.append(time.process_time() - c)
            wall.append(time.perf_counter() - t)
    return dict(side="brdfjax", load_s=t_loaded - T_START, runs=runs, residual_s=float(np.median(tr)),
                jacobian_s=float(np.median(tj)), jacfwd_s=float(np.median(tf)) if tf else None,
                residual_wall_s=float(np.median(wr)), jacobian_wall_s=float(np.median(wj)),
                n_free=len(free), n_points=sum(prep.problem.counts), device=str(jax.devices()[0]))


def _scipy(data: Path, start_in: Path) -> dict:
    import numpy as np
    from numpy.lib.stride_tricks import sliding_window_view
    from scipy.optimize import least_squares
    from scipy.signal import fftconvolve

    from brdfjax import reference as ref

    job = _job(data)
    t_loaded = time.perf_counter()
    spec = json.loads(start_in.read_text())
    free, fixed = spec["free"], spec["fixed"]
    blocks = []
    for k, b in enumerate(job.blocks):
        usable = b.usable()
        brdf = np.asarray(b.brdf, float)
        sigma = np.broadcast_to(np.asarray(b.sigma_rel, float), brdf.shape)
        kern = np.asarray(b.footprint, float)
        kern = kern / kern.sum()
        r, c = kern.shape[0] // 2, kern.shape[1] // 2
        m = np.pad(usable, ((r, r), (0, 0)))
        m = sliding_window_view(m, 2 * r + 1, axis=0).any(-1)
        m = np.pad(m, ((0, 0), (c, c)))
        reach = sliding_window_view(m, 2 * c + 1, axis=1).any(-1)
        rows, cols = np.nonzero(reach)
        det = b.arm_detector()
        ts, ps = (np.asarray(a, float) for a in det.angles(np.asarray(b.grid.n_h, float)[cols],
                                                           np.asarray(b.grid.n_v, float)[rows],
                                                           det.arm_angle(np.float64(b.theta_i))))
        d = brdf[usable]
        blocks.append(dict(k=k, shape=brdf.shape, reach=reach, ts=ts, ps=ps, kern=kern, usable=usable, d=d,
                           inv_sigma=1.0 / sigma[usable], floor=1e-6 * d.min(), theta_i=float(b.theta_i),
                           phi_ref=float(b.phi_ref), wl=float(b.wavelength)))
    x0 = np.array([f["x0"] for f in free])
    lo = np.array([f["lower"] for f in free])
    hi = np.array([f["upper"] for f in free])
    x0 = np.clip(x0, np.nextafter(lo, np.inf), np.nextafter(hi, -np.inf))
    base = {e["base"]: e["value"] for e in fixed if e["kind"] == "model"}

    def residuals(x):
        out = []
        for blk in blocks:
            p = dict(base)
            phi_ref = blk["phi_ref"]
            for f, xi in zip(free, x):
                if blk["k"] in f["blocks"]:
                    if f["kind"] == "model":
                        p[f["base"]] = xi
                    elif f["base"] == "phi_ref":
                        phi_ref = xi
            p = {k_: v for k_, v in p.items() if k_ in ref.solar_cell.__code__.co_varnames}
            vals = ref.solar_cell(blk["theta_i"], blk["ts"], blk["ps"], phi_ref, blk["wl"], **p)
            img = np.zeros(blk["shape"])
            img[blk["reach"]] = vals
            g = fftconvolve(img, blk["kern"], mode="same")[blk["usable"]]
            out.append((np.log(g + blk["floor"]) - np.log(blk["d"])) * blk["inv_sigma"])
        return np.concatenate(out)

    t0 = time.perf_counter()
    r0 = residuals(x0)
    t_res = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = least_squares(residuals, x0, bounds=(lo, hi), method="trf", jac="2-point", x_scale="jac")
    fit_s = time.perf_counter() - t0
    return dict(side="scipy", load_s=t_loaded - T_START, fit_s=fit_s, process_s=time.perf_counter() - T_START,
                chi2=float(np.sum(sol.fun**2)), chi2_start=float(np.sum(r0**2)), nfev=int(sol.nfev),
                njev=int(sol.njev or 0), status=int(sol.status), message=sol.message, residual_s=t_res)


def _child(args) -> int:
    data, io = Path(args.data), Path(args.child_io)
    if args.child == "brdfjax":
        out = _brdfjax(data, io, args.first_stage, args.jacfwd)
    else:
        out = _scipy(data, io)
    out["process_s"] = time.perf_counter() - T_START
    Path(args.child_out).write_text(json.dumps(out))
    return 0


def _run(side: str, args, start: Path, cache: str | None) -> dict:
    env = dict(os.environ)
    env.pop("BRDFJAX_NO_CACHE", None)
    if side == "brdfjax" and cache:
        env["BRDFJAX_CACHE_DIR"] = cache
    with tempfile.NamedTemporaryFile("r", suffix=".json") as tmp:
        code = "import runpy, sys; sys.argv = sys.argv[1:]; "
        if side == "brdfjax" and cache:
            code += "from brdfjax.runtime.compile_cache import enable_compilation_cache; enable_compilation_cache(); "
        code += "runpy.run_path(sys.argv[0], run_name='__main__')"
        cmd = [sys.executable, "-c", code, __file__, "--child", side, "--child-out", tmp.name, "--child-io", str(start),
               "--data", str(args.data), "--first-stage", args.first_stage] + (["--jacfwd"] if args.jacfwd else [])
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env)
        out = json.loads(Path(tmp.name).read_text())
        out["wall_s"] = time.perf_counter() - t0
        return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(ROOT / "runs" / "benchmark_fit_data"), help="synthetic frames (made once)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--first-stage", default="config", help="config (the config's: soft), none, soft, huber, cauchy")
    ap.add_argument("--cache", default=None, help="persistent compilation cache folder for the brdfjax side")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--jacfwd", action="store_true", help="also time jax.jacfwd's Jacobian (the reference)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-out", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-io", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args)
    import statistics

    start = Path(tempfile.mkdtemp()) / "start.json"
    rows = {"brdfjax": [], "scipy": []}
    for _ in range(args.repeats):  # alternating sides
        rows["brdfjax"].append(_run("brdfjax", args, start, args.cache))
        rows["scipy"].append(_run("scipy", args, start, args.cache))
    med = statistics.median
    bj, sp = rows["brdfjax"], rows["scipy"]
    cold = med(r["runs"][0]["process_s"] for r in bj)  # process start to the end of its first fit
    warm = med(r["runs"][1]["fit_s"] for r in bj)
    sp_wall, sp_fit = med(r["process_s"] for r in sp), med(r["fit_s"] for r in sp)
    res_s, jac_s = med(r["residual_s"] for r in bj), med(r["jacobian_s"] for r in bj)
    print(f"\nsynthetic solar-cell fit ({bj[0]['n_points']} points, {bj[0]['n_free']} free), {os.cpu_count()} CPU(s), "
          f"load {os.getloadavg()[0]:.1f}, device {bj[0]['device']}, medians of {args.repeats}, first stage {args.first_stage}")
    print(f"{'measure':44s} {'brdfjax':>10s} {'scipy':>10s} {'ratio':>7s} target")
    if args.cache and len(bj) > 1:
        # one cache folder for every repeat: the first process fills it, the later ones start with it (a
        # user's second run); a median over both kinds would mean neither
        first = bj[0]["runs"][0]["process_s"]
        later = med(r["runs"][0]["process_s"] for r in bj[1:])
        print(f"{'whole process, 1st (empty cache) (s)':44s} {first:10.2f} {sp_wall:10.2f} {sp_wall / first:6.2f}x")
        print(f"{'whole process, later (cache filled) (s)':44s} {later:10.2f} {sp_wall:10.2f} {sp_wall / later:6.2f}x >= 3x"
              f"  (median of {len(bj) - 1})")
    else:
        print(f"{'whole process, cold fit (s)':44s} {cold:10.2f} {sp_wall:10.2f} {sp_wall / cold:6.2f}x >= 3x")
    print(f"{'fit in process, warm (s)':44s} {warm:10.2f} {sp_fit:10.2f} {sp_fit / warm:6.2f}x >= 5x")
    solve = med(r["runs"][1]["timings"]["solve_s"] for r in bj)
    print(f"{'  of which the solve (s), vs least_squares':44s} {solve:10.2f} {sp_fit:10.2f} {sp_fit / solve:6.2f}x")
    print(f"{'final chi^2':44s} {bj[0]['runs'][1]['chi2']:10.2f} {sp[0]['chi2']:10.2f} "
          f"{bj[0]['runs'][1]['chi2'] / sp[0]['chi2']:6.4f}  same")
    print(f"{'steps (brdfjax) / residual evals (scipy)':44s} {bj[0]['runs'][1]['steps']:10d} {sp[0]['nfev']:10d}")
    print(f"{'one residual (CPU s)':44s} {res_s:10.4f} {sp[0]['residual_s']:10.4f}")
    print(f"{'one Jacobian (CPU s), / residual':44s} {jac_s:10.4f} {'':>10s} {jac_s / res_s:6.2f}x <= 4x")
    wr, wj = med(r["residual_wall_s"] for r in bj), med(r["jacobian_wall_s"] for r in bj)
    print(f"{'same, wall s: residual, Jacobian':44s} {wr:10.4f} {wj:10.4f} {wj / wr:6.2f}x")
    if bj[0].get("jacfwd_s"):
        jf = med(r["jacfwd_s"] for r in bj)
        print(f"{'jax.jacfwd Jacobian (CPU s), / residual':44s} {jf:10.4f} {'':>10s} {jf / res_s:6.2f}x")
    if args.json:
        from brdfjax.runtime.atomic import write_json_atomic  # noqa: PLC0415 -- the timed children import brdfjax, not this parent

        write_json_atomic(args.json, dict(rows=rows, load=os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
