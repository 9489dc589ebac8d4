"""Speed of light curves with posterior draws: 10^4 time steps x 10 facets x 1,000 draws, point Sun / adaptive / full disk.

The pass: the shipped config's two visible passes over Cerro Pachon
(configs/lightcurve_box_wing.toml), resampled to 10^4 steps (about 0.05 s
apart: real angular rates, including the diffraction glint of the second
pass).  Two satellites of 10 facets:

- ``shipped``: the shipped box-and-wing with the array split into two wings
  (6 bus faces Lambertian 0.3, 2 wing fronts of the seed's solar cell, 2
  wing backs Lambertian 0.1); the cell's posterior draws change the two wing
  fronts, the other eight are evaluated once.
- ``all_cell``: the same ten facets all of the cell plus a 0.02 Lambertian
  floor (so that every facet has a finite magnitude): every facet carries the
  posterior, and the bus faces glint too.

Draws: 1,000 of (m1, rho_s1, m2, rho_s2, rho_s3) scattered 5 % about the
seed's values.  For each satellite, in the same run and alternating
(medians of ``--repeats``): the point Sun and the adaptive disk (16 rings =
979 nodes where flagged) on all draws; the full 979-node disk on
``--full-draws`` draws (extrapolated to 1,000); the accuracy of the
adaptive disk and of the point Sun against the full disk on those draws
(max |dm| over all steps).  Results: experiments/results/benchmark_lightcurve.json.

    nice -n 19 python3 experiments/benchmark_lightcurve.py
    python3 experiments/benchmark_lightcurve.py --quick      # 2,000 steps, 50 draws
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.lightcurve.config import load_lightcurve_config  # noqa: E402
from brdfjax.lightcurve.engine import (  # noqa: E402
    AdaptiveDisk,
    Attitude,
    Facets,
    Geometry,
    Satellite,
    SunDisk,
    magnitude,
)
from brdfjax.lightcurve.ephemeris import parse_tle, pass_geometry, time_grid  # noqa: E402
from brdfjax.lightcurve.run import posterior_total_flux  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "configs" / "lightcurve_box_wing.toml"
NAMES = ("m1", "rho_s1", "m2", "rho_s2", "rho_s3")


def load() -> float:
    return float(os.getloadavg()[0])


def geometry(T: int) -> Geometry:
    """The shipped passes' visible spans, resampled to ``T`` steps in all."""
    cfg = load_lightcurve_config(SHIPPED)
    sat = parse_tle(*cfg.orbit.tle)
    ob = cfg.observer
    coarse = pass_geometry(sat, time_grid(cfg.time.start, cfg.time.stop, 1.0), ob.lat_deg, ob.lon_deg, ob.height_m)
    vis = (np.rad2deg(coarse.elevation()) >= ob.min_elevation_deg) & (np.rad2deg(coarse.sun_elevation()) <= ob.max_sun_elevation_deg)
    idx = np.flatnonzero(vis)
    spans = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    total = sum(len(s) for s in spans)
    times = []
    for s in spans:
        n = int(round(T * len(s) / total))
        t0, t1 = coarse.times[s[0]], coarse.times[s[-1]]
        times.append(t0 + ((t1 - t0).astype(np.int64) * np.arange(n) / max(n - 1, 1)).astype("timedelta64[us]"))
    times = np.concatenate(times)[:T]
    pg = pass_geometry(sat, times, ob.lat_deg, ob.lon_deg, ob.height_m)
    return Geometry.from_positions(pg.r_sat, pg.v_sat, pg.r_sun, pg.r_obs)


def satellite(kind: str) -> tuple[Satellite, int]:
    names = ["bus_nadir", "bus_zenith", "bus_ram", "bus_wake", "bus_port", "bus_starboard",
             "wing1_front", "wing2_front", "wing1_back", "wing2_back"]
    area = [3.9, 3.9, 0.84, 0.84, 1.7, 1.7, 11.35, 11.35, 11.35, 11.35]
    normal = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1], [0, 0, -1], [0, 0, 1], [0, 0, 1]]
    x_axis = [None] * 6 + [[0, 1.0, 0]] * 4
    tracking = [False] * 6 + [True] * 4
    phi_ref = [0.0] * 6 + [np.pi / 2] * 2 + [0.0] * 2
    fac = Facets.build(names, area, np.asarray(normal, float), x_axis, phi_ref, tracking)
    cell = bj.solar_cell()
    if kind == "shipped":
        models = (cell, bj.Model({"d": bj.Lambertian(0.3)}), bj.Model({"d": bj.Lambertian(0.1)}))
        return Satellite(fac, models, Attitude.nadir(), (1,) * 6 + (0, 0, 2, 2)), 0
    floor = bj.Model({**cell.terms, "floor": bj.Lambertian(0.02)}, cell.aliases)
    return Satellite(fac, (floor,), Attitude.nadir(), (0,) * 10), 0


def timed(f):
    t0 = time.perf_counter()
    out = np.asarray(f())
    return out, time.perf_counter() - t0


def bench(kind: str, geo: Geometry, draws: np.ndarray, full_draws: int, repeats: int, chunk: int) -> dict:
    sat, mi = satellite(kind)
    point, full = SunDisk.point(), SunDisk.rings(16)
    adaptive = AdaptiveDisk(full)
    sub = sat.subset([j for j in range(10) if sat.model_of[j] == mi])
    planned = adaptive.plan(sub, geo, chunk=chunk)
    n_post = len(sub.facets.names)

    def run(disk, d):
        return posterior_total_flux(sat, geo, disk, 550e-9, mi, NAMES, d, chunk=chunk)

    # compile (and warm) every path with the shapes that are timed
    first = {}
    for label, disk, d in (("point", point, draws), ("adaptive", planned, draws), ("full", full, draws[:full_draws])):
        first[label] = timed(lambda disk=disk, d=d: run(disk, d))[1]
    times: dict[str, list[float]] = {"point": [], "adaptive": []}
    loads = []
    for _ in range(repeats):  # alternating
        for label, disk in (("point", point), ("adaptive", planned)):
            loads.append(load())
            fl, dt = timed(lambda disk=disk: run(disk, draws))
            times[label].append(dt)
            if label == "adaptive":
                fl_adaptive = fl
            else:
                fl_point = fl
    # the full disk on a few draws, and the accuracy there
    loads.append(load())
    fl_full, dt_full = timed(lambda: run(full, draws[:full_draws]))
    with np.errstate(divide="ignore", invalid="ignore"):
        m_full = np.asarray(magnitude(fl_full))
        m_ad = np.asarray(magnitude(fl_adaptive[:full_draws]))
        m_pt = np.asarray(magnitude(fl_point[:full_draws]))
    ok = np.isfinite(m_full)
    flagged = np.asarray(_flag_total(planned, sub, geo, chunk))
    res = {
        "satellite": kind, "T": len(geo), "facets": 10, "facets_carrying_posterior": n_post, "draws": len(draws),
        "disk_nodes_full": full.n_nodes, "capacity": list(planned.capacity), "flagged_pairs_base_model": flagged.tolist(),
        "flagged_fraction": float(flagged.sum() / (len(geo) * n_post)),
        "point_s": float(np.median(times["point"])), "adaptive_s": float(np.median(times["adaptive"])),
        "point_s_all": times["point"], "adaptive_s_all": times["adaptive"],
        "adaptive_over_point": float(np.median(np.asarray(times["adaptive"]) / np.asarray(times["point"]))),
        "first_call_s": first, "full_draws": full_draws, "full_s": dt_full, "full_s_extrapolated": dt_full * len(draws) / full_draws,
        "max_abs_dm_adaptive_vs_full": float(np.max(np.abs(m_ad - m_full)[ok])),
        "max_abs_dm_point_vs_full": float(np.max(np.abs(m_pt - m_full)[ok])),
        "brightest_full_mag": float(np.min(m_full[ok])), "steps_compared": int(ok.sum()),
        "load_average": loads, "cpus": os.cpu_count(),
    }
    print(f"[{kind}] {len(geo)} steps x 10 facets ({n_post} carry the posterior) x {len(draws)} draws: "
          f"point Sun {res['point_s']:.1f} s, adaptive disk {res['adaptive_s']:.1f} s (x{res['adaptive_over_point']:.2f}); "
          f"full 979-node disk {dt_full:.1f} s for {full_draws} draws -> {res['full_s_extrapolated']:.0f} s for {len(draws)}")
    print(f"[{kind}] flagged (step, facet, term) pairs of the base model: {flagged.tolist()} "
          f"({100 * res['flagged_fraction']:.2f} % of the step-facet pairs per term); capacity {list(planned.capacity)}")
    print(f"[{kind}] vs the full disk over {full_draws} draws x {ok.sum() // full_draws} steps: adaptive max |dm| "
          f"{res['max_abs_dm_adaptive_vs_full']:.2e} mag, point Sun {res['max_abs_dm_point_vs_full']:.2f} mag "
          f"(brightest {res['brightest_full_mag']:.2f} mag); load average {min(loads):.1f}-{max(loads):.1f} on {os.cpu_count()} cores")
    return res


def _flag_total(disk: AdaptiveDisk, sub: Satellite, geo: Geometry, chunk: int):
    from brdfjax.lightcurve.engine import _flag_counts

    return _flag_counts(sub, geo, disk, chunk, 6378137.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "benchmark_lightcurve.json")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--draws", type=int, default=None)
    ap.add_argument("--full-draws", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--chunk", type=int, default=1000)
    ap.add_argument("--only", default="shipped,all_cell")
    args = ap.parse_args()
    T = args.steps or (2000 if args.quick else 10_000)
    S = args.draws or (50 if args.quick else 1000)
    geo = geometry(T)
    rng = np.random.default_rng(0)
    draws = np.array([2e-4, 0.015, 2e-4, 0.7, 300.0]) * (1 + 0.05 * rng.normal(size=(S, 5)))
    res = {"quick": args.quick, "jax": jax.__version__, "backend": jax.default_backend()}
    for kind in args.only.split(","):
        res[kind] = bench(kind, geo, draws, args.full_draws, args.repeats, args.chunk)
    if not args.quick or args.out != ap.get_default("out"):
        write_json_atomic(args.out, res, allow_nan=False)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
