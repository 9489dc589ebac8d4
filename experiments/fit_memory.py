"""Peak memory of a float32 solar-cell fit and the resident memory over repeated fits in one process (issue 19).

Fits the solar-cell model to a noisy rendered frame (``render_noisy_frames``,
theta_i = 20 deg) ``--repeats`` times in one process, float32, and reports the
process's resident set size (RSS, from /proc) after each fit and the peak RSS
(``getrusage``).  Growth over the repeats would be a leak (the compiled
programs are cached after the first fit; nothing else should accumulate).

    python3 experiments/fit_memory.py --step 1 --repeats 20      # full resolution (minutes on 2 cores)
    python3 experiments/fit_memory.py --step 8 --repeats 20      # decimated
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
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # the data in float64, as the CLI reads them; the model in float32
    import numpy as np

    import brdfjax as bj
    from brdfjax.fit import Param, fit, render_noisy_frames

    model = bj.solar_cell()
    frames = render_noisy_frames(model, [20.0], step=args.step, noise_rel=0.03, floor=0.1, seed=1)
    truth = model.params()
    spec = {k: Param(float(np.asarray(truth[k])) * 1.1) for k in ("m1", "rho_s1", "a", "c", "rho_s3")}
    rss, walls = [], []
    for i in range(args.repeats):
        t0 = time.perf_counter()
        res = fit(model, frames, spec, precision="float32")
        walls.append(time.perf_counter() - t0)
        rss.append(_rss_mib())
        print(f"fit {i + 1:2d}: {walls[-1]:6.2f} s, chi2_red {res.chi2_reduced:.4f}, RSS {rss[-1]:7.1f} MiB", flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n = frames[0].usable().sum()
    later = rss[1:] if len(rss) > 1 else rss
    slope = np.polyfit(np.arange(len(later)), later, 1)[0] if len(later) > 2 else float("nan")
    print(f"\nstep {args.step} ({frames[0].shape[1]} x {frames[0].shape[0]} px, {n} fitted), float32, load "
          f"{os.getloadavg()[0]:.1f}: peak RSS {peak:.0f} MiB; RSS after fit 2..{args.repeats}: "
          f"{min(later):.1f}..{max(later):.1f} MiB, trend {slope:+.2f} MiB/fit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
