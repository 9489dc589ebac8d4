"""Where a cold fit's time goes: the synthetic solar-cell fit, the process's first fit profiled (cProfile).

Run it twice with one cache folder (the first run fills JAX's persistent compilation cache, the second starts
with it, as a user's second process would)::

    BRDFJAX_CACHE_DIR=/tmp/brdfjax-cache python3 experiments/profile_cold_fit.py --data /tmp/brdfjax-sc
    BRDFJAX_CACHE_DIR=/tmp/brdfjax-cache python3 experiments/profile_cold_fit.py --data /tmp/brdfjax-sc

It prints the imports, the frames' loading, the first fit (with ``FitResult.timings``) and the same fit again
(warm), then the profile's totals for tracing (``trace_to_jaxpr``), loading executables from the cache
(``get_executable_and_time``) and lowering (``jaxpr_subcomp``), and the brdfjax functions by cumulative time.
The fit is the benchmark's (``experiments/benchmark_fit.py``: the config without its nuisance parameters).
"""

from __future__ import annotations

import time

T0 = time.perf_counter()

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
from pathlib import Path  # noqa: E402

from brdfjax.runtime.compile_cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from brdfjax.fit import fit  # noqa: E402
from brdfjax.fit.config import load_fit_config  # noqa: E402
from brdfjax.fit.job import build_fit_job  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "fit_synthetic_solar_cell.toml"
PARTS = {"tracing": "trace_to_jaxpr", "cache loads": "get_executable_and_time", "lowering": "jaxpr_subcomp"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="folder for the synthetic frames (made on the first run)")
    p.add_argument("--top", type=int, default=25, help="brdfjax functions listed")
    args = p.parse_args(argv)
    t_imp = time.perf_counter()
    job = build_fit_job(load_fit_config(CONFIG), work_dir=Path(args.data))
    t_job = time.perf_counter()
    kw = dict(job.fit_kwargs)
    kw["nuisance"] = None
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    first = fit(job.model, job.blocks, job.params, **kw)
    prof.disable()
    t1 = time.perf_counter()
    warm = fit(job.model, job.blocks, job.params, **kw)
    t2 = time.perf_counter()
    print(f"imports {t_imp - T0:.2f} s, frames {t_job - t_imp:.2f} s, first fit {t1 - t0:.2f} s "
          f"({', '.join(f'{k} {v:.2f}' for k, v in first.timings.items())}), warm fit {t2 - t1:.2f} s; "
          f"steps {first.n_iterations} / {warm.n_iterations}, chi2 {first.chi2:.6f} / {warm.chi2:.6f}")
    stats = pstats.Stats(prof)
    for label, fn in PARTS.items():
        # the outermost call of each: its cumulative time (nested calls are inside it)
        cum = max((v[3] for k, v in stats.stats.items() if k[2] == fn), default=0.0)
        n = sum(v[1] for k, v in stats.stats.items() if k[2] == fn)
        print(f"  {label:12s} {cum:6.2f} s cumulative (outermost call; {n} primitive calls)")
    stats.sort_stats("cumulative").print_stats("brdfjax", args.top)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
