"""Coverage of brdfjax's uncertainties on measurements through the synthetic instrument, with and without nuisance parameters.

Each realisation: the seed's solar cell (truth: the §6.4 values) measured at
theta_i = 20 deg by the synthetic instrument with every default effect on
(footprint, stray light, ambient light, shot noise, non-linearity, dark, black
level, quantisation, saturation) on a 16 x 16 binned camera, its own noise
seed and camera seed, and an ND-filter error drawn per realisation: each
physical filter's true OD is its nominal one plus N(0, tol) (the seed's
tolerances, §4.3, read as standard uncertainties as Eq 97 does; the
instrument's own ``nd_error`` effect draws uniformly within the tolerance,
see ``--uniform``).  The raw set is reduced (weighted merge, non-linearity
corrected), read back (``sigma = "noise"`` with the 0.68 % per-pixel gain
floor, as the shipped configs) and fitted (m1, rho_s1, rho_s3, c free;
the rest at the truth):

- **without** nuisance parameters (what brdfjax did before issue 15);
- **with** them (ND filters, incident flux, non-linearity level;
  :mod:`brdfjax.fit._nuisance`).

Intervals are the Laplace approximation's (fit +- z sigma; marginal sigma for
the runs with nuisance parameters); ``--footprint`` adds a third fit with the
footprint width free (4 % prior), and ``--sample-steps N`` also samples the last
fit's likelihood with emcee (N steps from the fit; equal-tailed intervals),
``--log-uniform-weights`` with log-uniform priors on the weights spanning two
decades either side of the fit's optimum (what a user has; the truth enters
only the coverage count).  Coverage of the 68 % and 95 % intervals is counted
per parameter group -- shape (m1, c) and flux-scaled weights (rho_s1, rho_s3)
-- and overall, each with its standard error and a 95 % Wilson interval counted
by realisation (rho_s1 and rho_s3 share the ND error: one draw, not two).

Resumable: per-realisation results go to ``OUT/realisations.jsonl`` and are
skipped on a rerun; ``--n`` sets how many (default 50).

    python3 experiments/posterior_calibration_instrument.py --out runs/calib_instrument --n 50
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.core.detector import Detector  # noqa: E402
from brdfjax.core.render import Conditions  # noqa: E402
from brdfjax.fit import fit, prepare, read_frame_data  # noqa: E402
from brdfjax.fit._nuisance import NuisanceOptions  # noqa: E402
from brdfjax.instrument.nd import ND_3_TOLERANCE, SEED_ND_TOLERANCES  # noqa: E402
from brdfjax.instrument.reduce import ReductionError, reduce_measurement_set  # noqa: E402
from brdfjax.instrument.synthetic import InstrumentConfig, SyntheticInstrument  # noqa: E402
from brdfjax.sample import Emcee, Prior, sample  # noqa: E402

FREE = ("m1", "rho_s1", "rho_s3", "c")
GROUPS = {"shape": ("m1", "c"), "weights": ("rho_s1", "rho_s3")}
BIN = 16
ROI_DEG = 0.3
Z68, Z95 = 0.994457883, 1.959963985
_REF_MASK = None


class DrawnNDInstrument(SyntheticInstrument):
    """The synthetic instrument with given OD offsets of its physical filters (``nd_error`` on)."""

    def __init__(self, *args, nd_offsets, **kw):
        super().__init__(*args, **kw)
        self._offsets = dict(nd_offsets)
        self._drawn = None

    @property
    def camera(self):
        if self._drawn is None:
            self._drawn = dataclasses.replace(super().camera, nd_offsets=self._offsets)
        return self._drawn


def _draw_offsets(rng: np.random.Generator, uniform: bool) -> dict:
    tol = {**{round(k, 6): v for k, v in SEED_ND_TOLERANCES.items()}, 3.0: ND_3_TOLERANCE}
    out = {}
    for od, t in sorted(tol.items()):
        for occ in range(4):
            out[(od, occ)] = float(rng.uniform(-t, t) if uniform else rng.normal(0.0, t))
    return out


def realise(i: int, work: Path, uniform: bool, step: int, footprint: bool = False, sample_steps: int = 0,
            log_weights_prior: bool = False) -> dict:
    model = bj.solar_cell()
    truth = {k: float(np.asarray(v)) for k, v in model.params().items()}
    det = Detector.seed(shape=(2472 // BIN, 3296 // BIN), pixel_pitch=5.5e-6 * BIN, pixel_pitch_v=5.5e-6 * BIN)
    cfg = InstrumentConfig(camera_seed=1000 + i).for_pixel_pitch(float(det.pixel_pitch)).with_effects(nd_error=True)
    offsets = _draw_offsets(np.random.default_rng([2026, i]), uniform)
    inst = DrawnNDInstrument(det, cfg, seed=i, nd_offsets=offsets)
    folder = work / f"r{i}"
    t0 = time.perf_counter()
    manifest = inst.measure_set(folder / "raw", model, {"ti20": Conditions.from_degrees(20.0, 0.0, 632.8)})
    (path,) = reduce_measurement_set(manifest, folder / "reduced", merge="weighted", correct_nonlinearity=True)
    t_data = time.perf_counter() - t0
    R = float(np.asarray(det.distance))
    h = math.ceil(math.tan(math.radians(ROI_DEG)) * R / float(det.pixel_pitch))
    frame = read_frame_data(path, step=step, roi=(-h, h, -h, h), footprint_w_px=cfg.footprint.w_px, sigma="noise",
                            sigma_floor=0.0068)
    # One fixed set of pixels for every realisation (the truth above 1 sr^-1, SNR >> 10 there), so that every fit has
    # the same shapes and reuses the compiled program (a new point count would recompile, ~1 min on the busy box).
    global _REF_MASK
    if _REF_MASK is None:
        truth_img = np.asarray(bj.render(model, Conditions.from_degrees(20.0, 0.0, 632.8), frame.arm_detector(), grid=frame.grid))
        _REF_MASK = np.asarray(frame.mask) & (truth_img > 1.0)
    usable = np.asarray(frame.usable())
    lost = int((_REF_MASK & ~usable).sum())
    frame = dataclasses.replace(frame, mask=_REF_MASK & usable)
    spec = {"m1": truth["m1"] * 1.05, "rho_s1": truth["rho_s1"] * 0.95, "rho_s3": truth["rho_s3"] * 1.05,
            "c": truth["c"] * 0.95}
    out = {"i": i, "nd_beam": frame.systematics.nd_beam, "nd_sample": frame.systematics.nd_sample,
           "n_points": int(frame.usable().sum()), "n_lost": lost, "data_s": t_data, "truth": {k: truth[k] for k in FREE}}
    # the true flux error of this realisation's stacks: log(d / f) = ln10 (delta_beam - delta_sample)
    from brdfjax.fit._nuisance import build_nuisance

    ns = build_nuisance([frame], ["ti20"], NuisanceOptions(flux=False, nonlinearity=False))
    true_log_scale = 0.0
    for name, col in zip(ns.names, ns.design.T):
        od = float(name[3:-1].split("#")[0])
        true_log_scale += float(col[0]) * offsets[(round(od, 6), 0)]
    out["true_log_scale"] = true_log_scale
    runs = [("without", None), ("with", NuisanceOptions())]
    if footprint:  # the footprint width free too (4 % prior), as configs/sample_synthetic_solar_cell.toml does
        runs.append(("with_footprint", NuisanceOptions(footprint=True)))
    for label, nuis in runs:
        t0 = time.perf_counter()
        r = fit(model, [frame], spec, nuisance=nuis)
        est = {}
        for k in FREE:
            est[k] = {"value": r.value(k), "sigma": r.sigma(k)}
        out[label] = {"converged": r.converged, "chi2_reduced": r.chi2_reduced, "params": est,
                      "wall_s": time.perf_counter() - t0}
        if sample_steps and label == runs[-1][0]:
            # the same likelihood sampled (emcee, started from this fit): equal-tailed 68 % / 95 % intervals
            t0 = time.perf_counter()
            # log-uniform priors on the weights: the ND error is log-normal, and a prior flat in rho pushes the
            # flux-scaled weights' posterior up by the ridge's length. They span two decades either side of the fit's
            # optimum (the value the sampler starts from), which a user has without knowing the truth; the truth
            # enters only the coverage count.
            centre = {k: r.value(k) for k in GROUPS["weights"]}
            priors = ({k: Prior.log_uniform(centre[k] / 100, centre[k] * 100) for k in GROUPS["weights"]}
                      if log_weights_prior else None)
            post = sample(prepare(model, [frame], spec, nuisance=nuis), priors, start=r,
                          sampler=Emcee(n_steps=sample_steps), seed=i, figures=False, predictive_draws=0)
            iv = {k: {"i68": post.interval(k, 0.68), "i95": post.interval(k, 0.95)} for k in FREE}
            out["sampled"] = {"of": label, "prior": "log_uniform weights" if log_weights_prior else "flat",
                              **({"prior_centre": "fit optimum", "prior_bounds": {k: [centre[k] / 100, centre[k] * 100]
                                                                                 for k in GROUPS["weights"]}}
                                 if log_weights_prior else {}),
                              "params": iv, "tau_max": float(np.max(post.diagnostics.tau)),
                              "n_steps": sample_steps, "wall_s": time.perf_counter() - t0}
    return out


def coverage_stats(hits: list[list[bool]], z: float = 1.959963985) -> dict:
    """A coverage fraction with its standard error and a Wilson interval, counting realisations, not pairs.

    ``hits[r]`` holds one entry per parameter of the group in realisation ``r``.  The parameters of one realisation
    are not independent draws (rho_s1 and rho_s3 share the ND error and move together), so the standard error is the
    cluster (by realisation) one, ``sqrt(sum_r m_r^2 (h_r - p)^2) / M`` (``h_r`` the realisation's fraction, ``m_r``
    its count, ``M`` all entries); for one parameter per realisation it is the binomial ``sqrt(p (1 - p) / N)``.
    The Wilson interval (level of ``z``, default 95 %) uses the effective count ``p (1 - p) / se^2`` (``N``
    realisations when the standard error is 0), which is ``N`` for one parameter, ``N`` for two that always move
    together and ``2 N`` for two independent ones.
    """
    hits = [h for h in hits if len(h)]
    m = np.array([len(h) for h in hits], dtype=float)
    if not len(m):
        return {"n": 0, "n_realisations": 0, "cover": None, "se": None, "n_eff": None, "wilson": None}
    k = np.array([sum(bool(x) for x in h) for h in hits], dtype=float)
    total = float(m.sum())
    p = float(k.sum() / total)
    se = float(math.sqrt(float(np.sum((k - m * p) ** 2))) / total)
    n_eff = p * (1 - p) / se**2 if se > 0 else float(len(m))
    denom = 1 + z**2 / n_eff
    centre = (p + z**2 / (2 * n_eff)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n_eff + z**2 / (4 * n_eff**2))
    return {"n": int(total), "n_realisations": len(m), "cover": p, "se": se, "n_eff": n_eff,
            "wilson": [max(0.0, centre - half), min(1.0, centre + half)]}


def _group_stats(per_row: list[dict]) -> dict:
    """``per_row[r][k]`` = {"68": bool, "95": bool} (a parameter missing: no entry) -> coverage per group and level."""
    res = {}
    for group, names in {**GROUPS, "overall": FREE, **{k: [k] for k in FREE}}.items():
        entry = {}
        for lev in ("68", "95"):
            st = coverage_stats([[row[k][lev] for k in names if k in row] for row in per_row])
            entry.update({"n": st["n"], "n_realisations": st["n_realisations"], f"cover{lev}": st["cover"],
                          f"se{lev}": st["se"], f"n_eff{lev}": st["n_eff"], f"wilson{lev}": st["wilson"]})
        res[group] = entry
    return res


def sampled_coverage(rows: list[dict]) -> dict:
    """Coverage of the sampler's equal-tailed intervals (the realisations that were sampled)."""
    per_row = []
    for row in rows:
        if "sampled" not in row:
            continue
        hits = {}
        for k in FREE:
            iv = row["sampled"]["params"][k]
            hits[k] = {lev: iv["i" + lev][0] <= row["truth"][k] <= iv["i" + lev][1] for lev in ("68", "95")}
        per_row.append(hits)
    return _group_stats(per_row)


def coverage(rows: list[dict], label: str) -> dict:
    per_row = []
    for row in rows:
        hits = {}
        for k in FREE:
            p = row[label]["params"][k]
            if p["sigma"] is None or not math.isfinite(p["sigma"]):
                continue
            z = abs(p["value"] - row["truth"][k]) / p["sigma"]
            hits[k] = {"68": bool(z <= Z68), "95": bool(z <= Z95)}
        per_row.append(hits)
    return _group_stats(per_row)


def _fmt(c: dict) -> str:
    """``76.3 +- 5.5 / 89.8 +- 3.9``: the coverages of the 68 % and 95 % intervals, in %, with their standard errors."""
    return " / ".join(f"{100 * c['cover' + lev]:.1f} +- {100 * c['se' + lev]:.1f}" for lev in ("68", "95"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/calib_instrument")
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--step", type=int, default=1, help="every step-th pixel of the reduced 16x16-binned frame")
    ap.add_argument("--uniform", action="store_true", help="draw OD errors uniformly within the tolerance (the instrument's own)")
    ap.add_argument("--footprint", action="store_true",
                    help="a third fit per realisation with the footprint width free as well (4 %% prior)")
    ap.add_argument("--sample-steps", type=int, default=0,
                    help="also sample each realisation's last likelihood with emcee for this many steps (0: off)")
    ap.add_argument("--log-uniform-weights", action="store_true",
                    help="with --sample-steps: log-uniform priors on rho_s1, rho_s3, two decades either side of the "
                         "fit's optimum (else flat in rho)")
    ap.add_argument("--budget-s", type=float, default=math.inf, help="stop starting new realisations after this long")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "realisations.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []
    done = {r["i"] for r in rows}
    t0 = time.perf_counter()
    skipped: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="calib-") as tmp:
        for i in range(args.n):
            if i in done:
                continue
            if time.perf_counter() - t0 > args.budget_s:
                print(f"budget reached after {len(rows)} realisations", file=sys.stderr)
                break
            try:
                row = realise(i, Path(tmp), args.uniform, args.step, args.footprint, args.sample_steps,
                          args.log_uniform_weights)
            except ReductionError as e:  # an OD error so large that the beam saturates: the lab would refilter
                print(f"[{i}] skipped: {e}", file=sys.stderr)
                skipped.append({"i": i, "why": str(e).split(": ", 1)[-1]})
                continue
            rows.append(row)
            with open(log, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"[{i}] {row['nd_beam']} / {row['nd_sample']}: true log-scale {row['true_log_scale']:+.3f}; "
                  f"rho_s1 without {row['without']['params']['rho_s1']['value']:.5g} +- "
                  f"{row['without']['params']['rho_s1']['sigma']:.2g}, with {row['with']['params']['rho_s1']['value']:.5g} +- "
                  f"{row['with']['params']['rho_s1']['sigma']:.2g} (truth 0.015); "
                  f"{row['data_s']:.0f} s data, {row['with']['wall_s']:.0f} s fit", file=sys.stderr, flush=True)
            import shutil

            shutil.rmtree(Path(tmp) / f"r{i}", ignore_errors=True)
    summary = {"n_realisations": len(rows), "skipped_this_run": skipped, "uniform_nd": bool(args.uniform), "bin": BIN, "step": args.step,
               "without": coverage(rows, "without"), "with": coverage(rows, "with"),
               **({"with_footprint": coverage(rows, "with_footprint")} if args.footprint else {}),
               **({"sampled": sampled_coverage(rows)} if any("sampled" in r for r in rows) else {}),
               "loadavg": os.getloadavg(), "wall_s": time.perf_counter() - t0}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{len(rows)} realisations; coverage of the 68 % / 95 % intervals in %, +- the standard error counted by "
          f"realisation (asked: 60-76 % / 90-98 %):")
    for g in (*GROUPS, "overall", *FREE):
        a, b = summary["without"][g], summary["with"][g]
        line = f"  {g:<8s} without nuisance {_fmt(a)}   with nuisance {_fmt(b)}"
        if args.footprint:
            line += f"   with nuisance + footprint {_fmt(summary['with_footprint'][g])}"
        if "sampled" in summary:
            d = summary["sampled"][g]
            w68, w95 = (f"{100 * d[f'wilson{lev}'][0]:.0f}-{100 * d[f'wilson{lev}'][1]:.0f}" for lev in ("68", "95"))
            line += (f"   sampled (emcee) {_fmt(d)} (Wilson 95 %: {w68} / {w95}; "
                     f"{d['n']} pairs, {d['n_realisations']} realisations)")
        print(line + f"   ({b['n']} pairs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
