"""Solar-cell recovery on frames from the synthetic instrument (issue 4, "What it must show").

Data: the seed's solar-cell model (§6.4 parameters, the truth) measured by the
synthetic instrument with the full effect set of ``configs/instrument_seed.toml``
(beam footprint, stray light, ambient light, shot noise, camera
non-linearity, dark signal, black level, 14-bit quantisation, saturation),
noise on, at theta_i = 20, 40 and 60 deg, phi_ref = 0; each measurement
reduced by :func:`brdfjax.instrument.reduce.reduce_measurement` (weighted
merge) on a 4x-decimated grid and read back as :class:`~brdfjax.fit.FrameData`
with :func:`brdfjax.fit.frame_data_from_reduced` (through the reduced-frame
EXR files, which are cached and reused: the run is resumable).

For speed the camera is the seed camera binned ``--bin`` x ``--bin`` (default
2: 1648 x 1236 pixels of 11 um) with the seed instrument scaled to it by
:meth:`InstrumentConfig.coarse` (per-pixel counts, and so per-pixel noise,
are the seed's); a 4x-decimated grid of that camera samples every 8th seed
pixel, 412 x 309 points per frame.  ``--bin 1`` runs the full seed camera.

What the fit uses from each reduced frame (the choices this experiment
found necessary; see the README section "Fitting: measured recovery"):

- weights: ``u_scatter_flux``, the per-pixel independent part of the
  uncertainty (stitched noise and the camera's per-pixel non-linearity), not
  the total ``sigma_rel``: the total also holds contributions common to every
  pixel of a frame (ND filters, 59 % with the 3.0 filter's 0.15 OD tolerance;
  the distance R, 3.1 %; the source's temporal drift, 1 %) which only scale
  the frame and must not be counted once per pixel;
- the reduction corrects the readings by the camera's calibrated response
  curve (``correct_nonlinearity``) and is told the camera's per-pixel
  non-linearity as a standard deviation (the RMS of the camera's gain map),
  not the seed's maximum error ``|g| + common_max`` (2.18 %);
- mask: the reduction's mask and BRDF above 5 times the pixel's
  noise-equivalent BRDF (removes the stray-light sub-peaks that pass the
  artifact floor and the truncation bias of pixels at the noise floor);
- instrument function: the Gaussian beam footprint (1/e^2 radius 25 seed
  pixels) sampled on the grid's spacing (:func:`grid_footprint`), convolved
  with the model.

Parts: ``recovery`` (auto-init + fit; targets: every parameter within 3 sigma,
a within 1 %, m1 and m2 within 5 %, dtheta, dphi0, phi_ref within 0.05 deg,
reduced chi^2 in 0.8-1.3), ``robustness`` (20 random starts, auto disabled;
target >= 19 reach the same optimum), ``coverage`` (30 noise seeds; target:
truth within 1 sigma for 55-80 % of (dataset, parameter) pairs).  The
coverage fits use masks fixed in advance from the truth (:func:`truth_masks`),
so that the selection of pixels does not depend on the noise and one compiled
fit serves every dataset.

Run::

    python3 experiments/fit_recovery.py --out runs/fit_recovery                  # all parts
    python3 experiments/fit_recovery.py --out runs/fit_recovery --parts recovery  # one part

Prints a table and writes ``<out>/fit_recovery.json`` (atomically); per-seed
coverage fits are kept in ``<out>/coverage/`` so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.fit import Param, fit, frame_data_from_reduced  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
INSTRUMENT_TOML = ROOT / "configs" / "instrument_seed.toml"
THETA_I = (20.0, 40.0, 60.0)
NAMES = ["m1", "rho_s1", "n1", "m2", "rho_s2", "n2", "dtheta", "dphi0", "a", "b", "c", "rho_s3"]
TRUTH = dict(bj.SOLAR_CELL_SEED)
ANGLES = ("dtheta", "dphi0")
INDEX = dict(lower=1.0, upper=6.0)
B_BOUNDS = dict(lower=1e-6, upper=4e-5)
MODEL = bj.solar_cell()
NEB_FACTOR = 5.0


# --- data ---------------------------------------------------------------------------------------


def instrument(bin_: int, seed: int):
    from brdfjax.instrument.synthetic import SyntheticInstrument, load_instrument_config

    det = bj.Detector.seed(shape=(2472 // bin_, 3296 // bin_), pixel_pitch=5.5e-6 * bin_, pixel_pitch_v=5.5e-6 * bin_)
    cfg = load_instrument_config(INSTRUMENT_TOML)
    if bin_ != 1:
        cfg = cfg.coarse(bin_)
    return SyntheticInstrument(det, cfg, seed=seed)


def measure(out: Path, seed: int, bin_: int, step: int) -> list[Path]:
    """Synthesize and reduce the three measurements of one noise seed (cached reduced-frame EXRs)."""
    from brdfjax.instrument.nd import ND_3_TOLERANCE, SEED_ND_TOLERANCES, choose_nd_filters
    from brdfjax.instrument.reduce import beam_signature, reduce_measurement, write_reduced_frame

    folder = out / "frames" / f"bin{bin_}_step{step}_seed{seed}"
    paths = [folder / f"ti{ti:g}.exr" for ti in THETA_I]
    if all(p.exists() for p in paths):
        return paths
    ins = instrument(bin_, seed)
    # The camera's calibration: its per-pixel non-linearity as a standard deviation (the RMS of the gain
    # map a characterisation would measure) and its response curve, by which the readings are corrected.
    g = ins.camera.nonlinearity
    nl_rms = float(np.sqrt(np.mean(np.square(g, dtype=np.float64)))) if g is not None else 0.0
    beam = ins.measure_beam(choose_nd_filters(ins.beam_flux, ins))
    sig = beam_signature(beam, ins.measure_background(beam.attrs), correct_nonlinearity=True)
    del beam
    for ti, path in zip(THETA_I, paths):
        frame = bj.Conditions.from_degrees(ti, 0.0)
        brdf = ins.render_brdf(MODEL, frame)
        nd = choose_nd_filters(lambda s, b=brdf, f=frame: ins.sample_flux(b, f, s), ins)
        st = ins.measure_sample(brdf, frame, nd, sample=f"ti{ti:g}")
        bg = ins.measure_background(st.attrs)
        red = reduce_measurement(
            st, bg, sig, step=step, correct_nonlinearity=True, scatter_nonlinearity=nl_rms,
            nd_tolerances={**SEED_ND_TOLERANCES, 3.0: ND_3_TOLERANCE},
        )
        red = dataclasses.replace(red, attrs={**red.attrs, "footprint_w_px": ins.config.footprint.w_px})
        write_reduced_frame(path, red)
        del st, bg, red, brdf
    return paths


def grid_footprint(w_px: float, step: int, tail: float = 1e-9) -> np.ndarray:
    """The beam footprint on a grid of every ``step``-th pixel: the raw-pixel kernel *sampled* every
    ``step`` pixels (``footprint_kernel(..., step=step)``; integrating over the grid's ``step``-wide cells
    adds ``step^2 / 12`` pixel^2 of variance: at step 4 on the 2x-binned camera that made the fitted m1,
    m2 1 % and c 2 % too small)."""
    from brdfjax.instrument.synthetic import footprint_kernel

    return footprint_kernel(w_px, tail=tail, step=step)


def truth_masks(paths: list[Path], bin_: int) -> list[np.ndarray]:
    """Masks fixed in advance from the truth: the noiseless expected frame (model convolved with the
    footprint, on the reduced grid) above 5 x the noise-equivalent BRDF of the given frames.  The selection
    then does not depend on the noise, and every dataset has the same shapes (one compiled fit serves all)."""
    from brdfjax.instrument.reduce import read_reduced_frame

    ins = instrument(bin_, 0)
    out = []
    for ti, p in zip(THETA_I, paths):
        red = read_reduced_frame(p)
        step = int(red.attrs["step"])
        expected = ins.expected_brdf(ins.render_brdf(MODEL, bj.Conditions.from_degrees(ti, 0.0)))[::step, ::step]
        out.append(np.asarray(expected, float) > NEB_FACTOR * np.asarray(red.extra["noise_equivalent_brdf"], float))
    return out


def load_frames(paths: list[Path], sigma: str = "pixel", masks: list[np.ndarray] | None = None) -> list[bj.fit.FrameData]:
    """FrameData with the per-pixel weights and the noise-equivalent mask described in the module docstring
    (``masks``: fixed masks instead, :func:`truth_masks`)."""
    from brdfjax.instrument.reduce import read_reduced_frame

    out = []
    for i, p in enumerate(paths):
        red = read_reduced_frame(p)
        keep = np.asarray(red.brdf, float) > NEB_FACTOR * np.asarray(red.extra["noise_equivalent_brdf"], float)
        if masks is not None:
            keep = masks[i]
        kernel = grid_footprint(float(red.attrs["footprint_w_px"]), int(red.attrs["step"]))
        fd = frame_data_from_reduced(red, name=p.stem, mask=keep, footprint=kernel)
        if masks is not None:  # the fixed mask alone (not AND-ed with the reduction's data-dependent mask)
            fd = dataclasses.replace(fd, mask=keep)
        if sigma == "pixel":
            fd = dataclasses.replace(fd, sigma_rel=np.asarray(red.extra["u_scatter_flux"], np.float64))
        out.append(fd)
    return out


# --- fits ---------------------------------------------------------------------------------------


def spec(values=None, phi_ref=None):
    v = values or {}
    s = {k: Param(v.get(k, "auto")) for k in NAMES}
    s["n1"] = Param(v.get("n1", "auto"), **INDEX)
    s["n2"] = Param(v.get("n2", "auto"), **INDEX)
    s["b"] = Param(v.get("b", "auto"), **B_BOUNDS)
    s["phi_ref"] = Param("auto" if phi_ref is None else phi_ref)
    return s


def recovery_row(res, frames) -> dict:
    rows = {}
    for k in NAMES:
        v, s = res.value(k), res.sigma(k)
        t = TRUTH[k]
        rows[k] = dict(truth=t, value=v, sigma=s, pull=(v - t) / s, rel_err=(v - t) / t)
    for f in frames:
        n = f"phi_ref[{f.name}]"
        v, s = res.value(n), res.sigma(n)
        rows[n] = dict(truth=0.0, value=v, sigma=s, pull=v / s, rel_err=None)
    return rows


def check_recovery(res, rows) -> dict[str, bool]:
    deg = math.degrees
    return {
        "converged": bool(res.converged),
        "all within 3 sigma": all(abs(r["pull"]) < 3 for r in rows.values()),
        "a within 1 %": abs(rows["a"]["rel_err"]) < 0.01,
        "m1, m2 within 5 %": abs(rows["m1"]["rel_err"]) < 0.05 and abs(rows["m2"]["rel_err"]) < 0.05,
        "dtheta, dphi0, phi_ref within 0.05 deg": all(
            abs(deg(rows[k]["value"] - rows[k]["truth"])) < 0.05 for k in rows if k in ANGLES or k.startswith("phi_ref")
        ),
        "reduced chi2 in 0.8-1.3": 0.8 <= res.chi2_reduced <= 1.3,
    }


def print_recovery(res, rows, checks) -> None:
    print(f"\n{'parameter':16s} {'truth':>12s} {'fitted':>12s} {'sigma':>10s} {'pull':>6s} {'error':>10s}")
    for k, r in rows.items():
        is_angle = k in ANGLES or k.startswith("phi_ref")
        if is_angle:
            t, v, s = (math.degrees(r[x]) for x in ("truth", "value", "sigma"))
            err = f"{v - t:+.4f} deg"
        else:
            t, v, s = r["truth"], r["value"], r["sigma"]
            err = f"{100 * r['rel_err']:+.3f} %"
        print(f"{k:16s} {t:12.6g} {v:12.6g} {s:10.3g} {r['pull']:+6.2f} {err:>10s}")
    print(f"chi2 {res.chi2:.1f}, dof {res.dof}, {res.n_points} points, reduced chi2 {res.chi2_reduced:.4f}; "
          f"{res.n_iterations} steps, {res.wall_s:.1f} s ({res.message})")
    for k, ok in checks.items():
        print(f"  [{'x' if ok else ' '}] {k}")


def robustness(reference, frames, n_starts: int, seed: int = 2026) -> dict:
    """Random starts around the reference optimum (module docstring of tests/fit/test_fit_solar_cell.py)."""
    x = {k: reference.value(k) for k in NAMES}
    phis = [reference.value(f"phi_ref[{f.name}]") for f in frames]
    m2, dth = x["m2"], x["dtheta"]
    rng = np.random.default_rng(seed)
    same, runs = 0, []
    for i in range(n_starts):
        v = {k: x[k] * rng.uniform(0.5, 1.5) for k in ("m1", "rho_s1", "m2", "rho_s2", "c", "rho_s3", "b")}
        v["n1"] = float(np.clip(x["n1"] * rng.uniform(0.5, 1.5), 1.05, 5.9))
        v["n2"] = float(np.clip(x["n2"] * rng.uniform(0.5, 1.5), 1.05, 5.9))
        v["b"] = float(np.clip(v["b"], 1.1e-6, 3.9e-5))
        v["a"] = x["a"] * (1 + rng.uniform(-0.01, 0.01))
        v["dtheta"] = x["dtheta"] + rng.uniform(-2, 2) * m2
        v["dphi0"] = x["dphi0"] + rng.uniform(-2, 2) * m2 / dth
        phi = [p + rng.uniform(-2, 2) * m2 / dth for p in phis]
        r = fit(MODEL, frames, spec(v, phi))
        worst = max(abs(r.value(k) - x[k]) / reference.sigma(k) for k in NAMES)
        ok = bool(r.converged and abs(r.chi2 - reference.chi2) < 1e-6 * reference.chi2 and worst < 0.1)
        same += ok
        runs.append(dict(start=i, converged=bool(r.converged), chi2=r.chi2, worst_shift_sigma=worst, same=ok,
                         steps=r.n_iterations, wall_s=r.wall_s))
        print(f"  start {i:2d}: {'same optimum' if ok else 'DIFFERENT'}  chi2 {r.chi2:.3f} "
              f"(ref {reference.chi2:.3f}), max shift {worst:.2g} sigma, {r.n_iterations} steps, {r.wall_s:.1f} s",
              flush=True)
    return dict(n_starts=n_starts, n_same=same, runs=runs)


def coverage(out: Path, seeds: list[int], bin_: int, step: int, fixed_mask: bool = True,
             deadline: float | None = None) -> dict:
    inside = total = 0
    per = []
    masks = truth_masks(measure(out, seeds[0], bin_, step), bin_) if fixed_mask else None
    for s in seeds:
        cache = out / "coverage" / f"seed{s}.json"
        if deadline is not None and time.time() > deadline and not cache.exists():
            print(f"  stopping at the deadline: {len(per)} datasets done", flush=True)
            break
        if cache.exists():
            rec = json.loads(cache.read_text())
        else:
            t0 = time.perf_counter()
            frames = load_frames(measure(out, s, bin_, step), masks=masks)
            t1, c1 = time.perf_counter(), time.process_time()
            r = fit(MODEL, frames, spec())
            cpu = time.process_time() - c1
            rows = recovery_row(r, frames)
            rec = dict(seed=s, converged=bool(r.converged), chi2_reduced=r.chi2_reduced,
                       inside={k: bool(abs(v["value"] - v["truth"]) <= v["sigma"]) for k, v in rows.items()},
                       pulls={k: v["pull"] for k, v in rows.items()}, data_s=t1 - t0, fit_s=r.wall_s, fit_cpu_s=cpu)
            write_json_atomic(cache, rec)
        n_in = sum(rec["inside"].values())
        inside += n_in
        total += len(rec["inside"])
        per.append(rec)
        print(f"  seed {s}: {n_in}/{len(rec['inside'])} within 1 sigma, reduced chi2 {rec['chi2_reduced']:.3f}, "
              f"converged {rec['converged']}", flush=True)
    pulls = np.array([p for rec in per for p in rec["pulls"].values()])
    return dict(n_datasets=len(per), mask="fixed from the truth" if fixed_mask else "from each dataset",
                inside=inside, total=total, fraction=inside / total,
                pull_std=float(np.std(pulls)), pull_mean=float(np.mean(pulls)),
                all_converged=all(r["converged"] for r in per),
                chi2_reduced=[r["chi2_reduced"] for r in per], datasets=per)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--parts", default="recovery,robustness,coverage")
    ap.add_argument("--bin", type=int, default=2, help="camera binning (1: the full seed camera)")
    ap.add_argument("--step", type=int, default=4, help="grid decimation of the reduced frames")
    ap.add_argument("--seed", type=int, default=1, help="noise seed of the recovery dataset")
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--datasets", type=int, default=30)
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="coverage: start no new dataset after this many minutes (resume later: seeds are cached)")
    ap.add_argument("--sigma", choices=("pixel", "total"), default="pixel",
                    help="weights: per-pixel independent uncertainty (u_scatter_flux) or the total sigma_rel")
    args = ap.parse_args(argv)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    result_path = out / "fit_recovery.json"
    report = json.loads(result_path.read_text()) if result_path.exists() else {}
    report["setup"] = dict(
        camera=f"seed camera binned {args.bin}x{args.bin}: {3296 // args.bin} x {2472 // args.bin} px of "
        f"{5.5 * args.bin:g} um, InstrumentConfig.coarse({args.bin})" if args.bin != 1 else "full seed camera",
        grid_step=args.step, theta_i_deg=list(THETA_I), instrument=str(INSTRUMENT_TOML.relative_to(ROOT)),
        weights=args.sigma, mask=f"reduction mask and brdf > {NEB_FACTOR:g} x noise_equivalent_brdf",
        instrument_function="Gaussian footprint, w = 25 seed px", cpu_count=os.cpu_count(),
        jax=jax.__version__, device=str(jax.devices()[0]),
    )
    t_all = time.perf_counter()
    reference = frames = None
    if "recovery" in parts or "robustness" in parts:
        t0 = time.perf_counter()
        frames = load_frames(measure(out, args.seed, args.bin, args.step), args.sigma)
        t_data = time.perf_counter() - t0
        print(f"data: seed {args.seed}, {', '.join(f'{f.name} {int(f.usable().sum())} px' for f in frames)} "
              f"({t_data:.1f} s)", flush=True)
        c0 = time.process_time()
        reference = fit(MODEL, frames, spec())
        cpu_fit = time.process_time() - c0
        rows = recovery_row(reference, frames)
        checks = check_recovery(reference, rows)
        print_recovery(reference, rows, checks)
        report["recovery"] = dict(
            seed=args.seed, rows=rows, checks=checks, chi2=reference.chi2, dof=reference.dof,
            chi2_reduced=reference.chi2_reduced, n_points=reference.n_points, n_iterations=reference.n_iterations,
            converged=reference.converged, message=reference.message, timings=reference.timings,
            wall_s=reference.wall_s, cpu_s=cpu_fit, data_s=t_data, warnings=list(reference.warnings),
        )
        write_json_atomic(result_path, report)
    if "robustness" in parts:
        print(f"\nrobustness: {args.starts} random starts (auto disabled)", flush=True)
        t0 = time.perf_counter()
        rob = robustness(reference, frames, args.starts)
        rob["wall_s"] = time.perf_counter() - t0
        print(f"robustness: {rob['n_same']}/{rob['n_starts']} starts reach the reference optimum (target >= 19/20)")
        report["robustness"] = rob
        write_json_atomic(result_path, report)
    if "coverage" in parts:
        print(f"\ncoverage: {args.datasets} noise seeds", flush=True)
        t0 = time.perf_counter()
        deadline = None if args.max_minutes is None else time.time() + 60 * args.max_minutes
        cov = coverage(out, list(range(100, 100 + args.datasets)), args.bin, args.step, deadline=deadline)
        cov["wall_s"] = time.perf_counter() - t0
        print(f"coverage: truth within 1 sigma for {cov['inside']}/{cov['total']} = {cov['fraction']:.3f} of "
              f"(dataset, parameter) pairs (target 0.55-0.80); pulls mean {cov['pull_mean']:+.3f}, "
              f"std {cov['pull_std']:.3f}")
        report["coverage"] = cov
        write_json_atomic(result_path, report)
    report["wall_s_last_run"] = time.perf_counter() - t_all
    write_json_atomic(result_path, report)
    print(f"\nwrote {result_path} ({report['wall_s_last_run']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
