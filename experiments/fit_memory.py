"""Peak memory of a float32 solar-cell fit and the resident memory over repeated fits in one process (issue 19).

Fits the solar-cell model to a noisy rendered frame (``render_noisy_frames``,
theta_i = 20 deg) ``--repeats`` times in one process, float32, and reports the
process's resident set size (RSS, from /proc) after each fit and the peak RSS
(``getrusage``).  Growth over the repeats would be a leak (the compiled
programs are cached after the first fit; nothing else should accumulate).

    python3 experiments/fit_memory.py --step 1 --repeats 20      # full resolution (minutes on 2 cores)
    python3 experiments/fit_memory.py --step 8 --repeats 20      # decimated

``--json PATH`` writes the figures (per-fit wall time, chi^2 and RSS, the peak) atomically.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--step", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", default=None, help="write the figures here (atomically)")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # the data in float64, as the CLI reads them; the model in float32
    import numpy as np

    import brdfjax as bj
    from brdfjax.fit import Param, fit, render_noisy_frames

    model = bj.solar_cell()
    frames = render_noisy_frames(model, [20.0], step=args.step, noise_rel=0.03, floor=0.1, seed=1)
    truth = model.params()
    # starts 10 % off the truth, the bar spacing 0.2 % (its basin is narrow: 10 % moves the high orders by
    # several fringes, and the fit would end in a side minimum; this experiment is about memory, not starts)
    off = {"m1": 1.1, "rho_s1": 1.1, "a": 1.002, "c": 1.1, "rho_s3": 1.1}
    spec = {k: Param(float(np.asarray(truth[k])) * f) for k, f in off.items()}
    rss, walls, chi2 = [], [], []
    for i in range(args.repeats):
        t0 = time.perf_counter()
        res = fit(model, frames, spec, precision="float32")
        walls.append(time.perf_counter() - t0)
        rss.append(_rss_mib())
        chi2.append(float(res.chi2_reduced))
        print(f"fit {i + 1:2d}: {walls[-1]:6.2f} s, chi2_red {res.chi2_reduced:.4f}, RSS {rss[-1]:7.1f} MiB", flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n = frames[0].usable().sum()
    later = rss[1:] if len(rss) > 1 else rss
    slope = np.polyfit(np.arange(len(later)), later, 1)[0] if len(later) > 2 else float("nan")
    print(f"\nstep {args.step} ({frames[0].shape[1]} x {frames[0].shape[0]} px, {n} fitted), float32, load "
          f"{os.getloadavg()[0]:.1f}: peak RSS {peak:.0f} MiB; RSS after fit 2..{args.repeats}: "
          f"{min(later):.1f}..{max(later):.1f} MiB, trend {slope:+.2f} MiB/fit")
    if args.json:
        from brdfjax.runtime.atomic import write_json_atomic

        out = {"step": args.step, "shape": list(frames[0].shape), "fitted_pixels": int(n), "precision": "float32",
               "free": sorted(spec), "wall_s": walls, "chi2_reduced": chi2, "rss_mib": rss, "peak_rss_mib": peak,
               "rss_trend_mib_per_fit": float(slope), "load_average": list(os.getloadavg()),
               "cpu_count": os.cpu_count()}
        write_json_atomic(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
