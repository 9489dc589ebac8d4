"""Light curves with the seed's solar cell (issue 17): glints over the shipped passes, the glint map, the glint height.

1. The shipped config (configs/lightcurve_box_wing.toml: a box-and-wing
   satellite at 550 km, one night over Cerro Pachon): number and total
   duration of glints brighter than the config's threshold for the seed
   model, the model without diffraction and the Lambertian baseline of the
   same albedo; and the same with the cells' bars turned 90 deg
   (phi_ref = 0).  Figure: experiments/figures/lightcurve_box_wing.png.
2. Glint map of the solar-array facet: observer directions where the
   disk-averaged seed model is brighter than the same-albedo Lambertian by
   more than 1 mag, at several Sun incidence angles; the solid angle with and
   without diffraction and their ratio.  Figure:
   experiments/figures/lightcurve_glint_map.png.
3. Solar-disk integration: a mirror-like facet's glint height, disk-averaged
   vs analytic vs point Sun.
(Speed, 10^4 steps x 10 facets x 1,000 draws with the point Sun, the adaptive and the full disk:
experiments/benchmark_lightcurve.py.)

    python3 experiments/lightcurve_glints.py --out experiments/results/lightcurve_glints.json
    python3 experiments/lightcurve_glints.py --quick --out /tmp/lc_quick.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.lightcurve.config import load_lightcurve_config  # noqa: E402
from brdfjax.lightcurve.engine import Attitude, Facets, Geometry, Satellite, SunDisk, facet_flux  # noqa: E402
from brdfjax.lightcurve.ephemeris import AU_M  # noqa: E402
from brdfjax.lightcurve.glintmap import glint_map  # noqa: E402
from brdfjax.lightcurve.models import directional_albedo  # noqa: E402
from brdfjax.lightcurve.run import run_lightcurve  # noqa: E402
from brdfjax.plotting import save_figure_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "configs" / "lightcurve_box_wing.toml"
FIGS = ROOT / "experiments" / "figures"


def load() -> str:
    return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"


def shipped(quick: bool) -> dict:
    out: dict = {}
    for label, edit in (("bars_across_axis", {}), ("bars_along_axis", {"phi_ref_deg = 90.0": "phi_ref_deg = 0.0 "})):
        text = SHIPPED.read_text()
        if quick:
            text = text.replace("disk_rings = 16 ", "disk_rings = 8  ")
        for a, b in edit.items():
            text = text.replace(a, b)
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / SHIPPED.name
            p.write_text(text)
            cfg = load_lightcurve_config(p)
            t0 = time.perf_counter()
            s = run_lightcurve(cfg, Path(d) / "out")
            wall = time.perf_counter() - t0
            if label == "bars_across_axis" and not quick:
                shutil.copy(Path(d) / "out" / "lightcurve.png", FIGS / "lightcurve_box_wing.png")
        out[label] = {
            "threshold_mag": s["glint_threshold_mag"],
            "glints": {k: {"count": v["count"], "total_duration_s": v["total_duration_s"],
                           "peaks": [(r["peak_s"], r["peak_mag"]) for r in v["runs"]]} for k, v in s["glints"].items()},
            "brightest_mag": s["brightest_mag"],
            "comparisons": {k: {kk: vv for kk, vv in c.items() if kk != "intervals_beyond_tol"} for k, c in s["comparisons"].items()},
            "n_visible_steps": s["n_visible_steps"],
            "wall_s": wall,
        }
        print(f"[shipped, {label}] {s['n_visible_steps']} visible 1-s steps, {s['sun_disk_nodes']} disk nodes, {wall:.0f} s ({load()})")
        for k, v in s["glints"].items():
            print(f"  {k:>15s}: {v['count']} glint(s) brighter than {s['glint_threshold_mag']} mag, "
                  f"{v['total_duration_s']:.0f} s in total; brightest {s['brightest_mag'][k]:.2f} mag")
        for k, c in s["comparisons"].items():
            print(f"  {k:>15s} vs seed model: max |dm| {c['max_abs_diff_mag']:.2f} mag at t = {c['at_s']:.0f} s; "
                  f"{100 * c['fraction_beyond_tol']:.1f} % of steps beyond 0.1 mag")
    return out


def glint_maps(quick: bool) -> dict:
    cell = bj.solar_cell()
    nodiff = bj.Model({k: v for k, v in cell.terms.items() if k != "bars"})
    albedo = directional_albedo(cell, 0.0, 550e-9)
    base = bj.Model({"d": bj.Lambertian(albedo)})
    angles = (30.0,) if quick else (10.0, 30.0, 50.0, 70.0)
    kw = {"du": 8e-5, "dv": 1.6e-4} if quick else {}
    rows, shown = [], None
    for th in angles:
        t0 = time.perf_counter()
        g1 = glint_map(cell, base, np.deg2rad(th), **kw)
        g2 = glint_map(nodiff, base, np.deg2rad(th), **kw)
        rows.append({"theta_i_deg": th, "solid_angle_sr_seed": g1.solid_angle_sr, "solid_angle_sr_no_diffraction": g2.solid_angle_sr,
                     "ratio": g1.solid_angle_sr / g2.solid_angle_sr, "edge_ratio_seed": g1.edge_excess,
                     "wall_s": time.perf_counter() - t0})
        print(f"[glint map] theta_i {th:g} deg: > 1 mag above the Lambertian (albedo {albedo:.4f}) over "
              f"{g1.solid_angle_sr:.3e} sr with diffraction, {g2.solid_angle_sr:.3e} sr without: x{rows[-1]['ratio']:.1f} "
              f"(border ratio {g1.edge_excess:.2f} < 2.51)")
        if th == 30.0:
            shown = (g1, g2)
    tot1 = sum(r["solid_angle_sr_seed"] for r in rows)
    tot2 = sum(r["solid_angle_sr_no_diffraction"] for r in rows)
    print(f"[glint map] over {len(rows)} Sun angles: the diffraction term multiplies the glinting solid angle by {tot1 / tot2:.1f}")
    if shown is not None and not quick:
        fig = Figure(figsize=(8.5, 4.2), constrained_layout=True)
        axes = fig.subplots(1, 2, sharey=True)
        for ax, g, name in zip(axes, shown, ("seed model (with diffraction)", "without diffraction")):
            r = np.log10(np.maximum(g.model, 1e-12) / g.baseline) * 2.5
            step = (max(1, r.shape[0] // 800), max(1, r.shape[1] // 400))
            im = ax.imshow(r[:: step[0], :: step[1]], origin="lower", aspect="auto", cmap="magma", vmin=-5, vmax=10,
                           extent=[np.rad2deg(g.u[0] - g.u.mean()), np.rad2deg(g.u[-1] - g.u.mean()),
                                   np.rad2deg(g.v[0]), np.rad2deg(g.v[-1])])
            ax.contour(np.rad2deg(g.u - g.u.mean()), np.rad2deg(g.v), g.glint.astype(float), levels=[0.5], colors="cyan",
                       linewidths=0.6)
            ax.set_title(f"{name}: {g.solid_angle_sr:.2e} sr", fontsize=9)
            ax.set_xlabel("in-plane offset from the mirror direction (deg)", fontsize=8)
        axes[0].set_ylabel("out of plane (deg)")
        fig.colorbar(im, ax=axes, label="brighter than the Lambertian baseline (mag)")
        fig.suptitle("Solar-array facet, Sun at 30 deg, disk-averaged: cyan = brighter by > 1 mag", fontsize=9)
        save_figure_atomic(fig, FIGS / "lightcurve_glint_map.png", dpi=110)
    return {"albedo": albedo, "threshold_mag": 1.0, "angles": rows, "ratio_total": tot1 / tot2}


def glint_height() -> dict:
    m, n, theta = 2e-4, 1.5, np.deg2rad(30.0)
    model = bj.Model({"s": bj.Specular(bj.Beckmann(m), rho_s=1.0, n=n, **bj.SEED_FORM)})
    r = np.array([[0.0, 0.0, 7e6]])
    s, o = np.array([np.sin(theta), 0, np.cos(theta)]), np.array([-np.sin(theta), 0, np.cos(theta)])
    g = Geometry.from_positions(r, np.array([[7e3, 0, 0]]), r + s * AU_M, r + o * 1e6)
    sat = Satellite(Facets.build(["mirror"], [1.0], [[0, 0, 1.0]]), (model,), Attitude.inertial(), (0,))
    out = {}
    Fs, Fp = bj.fresnel(n, theta)
    for rings in (0, 8, 12, 16, 24):
        disk = SunDisk.rings(rings)
        out[f"rings_{rings}"] = {"nodes": disk.n_nodes, "flux": float(facet_flux(sat, g, disk)["flux"][0, 0])}
    omega = 2 * np.pi * (1 - np.cos(SunDisk.rings(1).radius))
    out["analytic_disk"] = np.cos(theta) * float(Fs + Fp) / (2 * omega) / 1e12
    for k, v in out.items():
        if k.startswith("rings"):
            print(f"[glint height] {k}: {v['nodes']} nodes: flux / analytic disk average = {v['flux'] / out['analytic_disk']:.5f}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", default="shipped,map,height")
    args = ap.parse_args()
    parts = args.only.split(",")
    # parts run separately (--only) are merged into the same results file
    res: dict = json.loads(args.out.read_text()) if args.out.exists() else {}
    res["quick"] = args.quick
    if "height" in parts:
        res["glint_height"] = glint_height()
    if "shipped" in parts:
        res["shipped"] = shipped(args.quick)
    if "map" in parts:
        res["glint_map"] = glint_maps(args.quick)
    write_json_atomic(args.out, res, allow_nan=False)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
