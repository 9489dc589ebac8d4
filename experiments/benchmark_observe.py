"""Speed of ``brdfjax observe``'s prediction with a predictive band: 10^4 observations x 8 facets x 1,000 draws.

Synthetic relative rows (Sun altitude -12 to -30 deg, satellite altitude 15 to 85 deg, any azimuth difference,
heights 480-560 km), the V2 Mini's facets plus a second twist facet (8), every facet with three model families
fitted to its lab table (configs/v2mini: covariance draws from each result.json), the nominal prediction with
the solar disk (3 rings, 43 nodes) and the draws scaled by each (row, facet)'s disk/point ratio.  The first call
compiles; the second is timed.  ``--cache DIR`` turns on JAX's persistent compilation cache there (as the CLI does
in its default folder): a second process then loads the programs instead of compiling them.  Writes
experiments/results/benchmark_observe.json (with ``--cache``: the key ``cached_process_<n>`` per run).

    PYTHONPATH=$PWD python experiments/benchmark_observe.py [--n 10000] [--draws 1000] [--cache DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.io.observations import Observations  # noqa: E402
from brdfjax.lightcurve.config import build_models  # noqa: E402
from brdfjax.lightcurve.engine import SunDisk  # noqa: E402
from brdfjax.lightcurve.observe import FacetSpec, predict_set  # noqa: E402
from brdfjax.lightcurve.observe_config import load_observe_config  # noqa: E402
from brdfjax.lightcurve.skygeometry import sky_geometry  # noqa: E402
from brdfjax.runtime.compile_cache import enable_compilation_cache  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def synthetic(n: int, seed: int = 1) -> Observations:
    rng = np.random.default_rng(seed)
    return Observations(source="synthetic", kind="relative", line=np.arange(2, n + 2), mag=rng.normal(7, 1, n),
                        mag_err=np.full(n, 0.1), band=np.full(n, "AB", object), alt_deg=rng.uniform(15, 85, n),
                        sat_height_m=rng.uniform(480e3, 560e3, n), sun_alt_deg=rng.uniform(-30, -12, n),
                        az_diff_deg=rng.uniform(-180, 180, n))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--cache", default=None, metavar="DIR", help="a persistent compilation cache folder")
    a = ap.parse_args()
    if a.cache:
        enable_compilation_cache(a.cache)
    cfg = load_observe_config(ROOT / "configs" / "observe_v2mini_slingshot.toml")
    models = build_models(cfg, 550e-9)
    results = {k: cfg.resolve(m.fit_result) for k, m in cfg.models.items() if m.fit_result}
    facets = []
    for name, f in cfg.facets.items():
        facets.append(FacetSpec(name, f.area_m2, f.normal, [f.model, *f.alternatives], max_theta_i_deg=75.0, in_plane=True))
    facets.append(FacetSpec("twist_2", 0.6, (0.0, -0.5, -0.866), ["a700_binomial", "a700_abg", "a700_ggx"],
                            max_theta_i_deg=75.0, in_plane=True))
    facets[6] = FacetSpec("boom", 2.2, (0.0, 0.0, -1.0), ["boom_abg_authors"])
    many = synthetic(3 * a.n)
    keep = sky_geometry(many).keep  # sunlit and above the horizon
    obs = many.take(keep[: a.n])
    errors = {k: (v.inside_log_rms, v.outside_log_rms) for k, v in cfg.model_error.items()}
    kw = dict(normals="lumos", convention="lumos", disk=SunDisk.rings(3), draws=a.draws, result_paths=results,
              model_error=errors)
    t = time.perf_counter()
    predict_set("bench", obs, facets, models, **kw)
    t_first = time.perf_counter() - t
    t = time.perf_counter()
    pred = predict_set("bench", obs, facets, models, **kw)
    t_second = time.perf_counter() - t
    out = {"n_observations": len(pred.mag), "n_facets": len(facets), "draws": a.draws, "disk_nodes": SunDisk.rings(3).n_nodes,
           "first_call_s": t_first, "second_call_s": t_second, "cpu_count": os.cpu_count(),
           "median_band_68_width_mag": float(np.median(pred.band[:, 3] - pred.band[:, 1]))}
    print(f"{len(pred.mag)} observations x {len(facets)} facets x {a.draws} draws (disk {out['disk_nodes']} nodes): "
          f"first call {t_first:.1f} s (with compilation), second {t_second:.1f} s; {os.cpu_count()} CPUs")
    if a.n == 10_000 and a.draws == 1000:
        path = ROOT / "experiments" / "results" / "benchmark_observe.json"
        if a.cache:
            old = json.loads(path.read_text()) if path.exists() else {}
            k = sum(1 for key in old if key.startswith("cached_process_")) + 1
            old[f"cached_process_{k}"] = out
            out = old
        write_json_atomic(path, out)


if __name__ == "__main__":
    main()
