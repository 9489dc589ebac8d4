"""Reproduce the seed's solar-cell frames (Figs 33-35) and print their headline numbers.

Renders ``configs/seed_fig33.toml``, ``seed_fig34.toml`` and ``seed_fig35.toml``
through the same library calls as ``brdfjax simulate`` (not by shelling out),
writes each config's EXR/PNG/summary.json to ``<out>/<config stem>/``, and
prints the headline numbers beside the seed's (physics.md, "Reference numbers"):

- Fig 33: the centre-peak maximum (the maximum of the full frame within a few
  pixels of (0, 0)), the offset-peak maximum (of the offset term alone), the
  diffraction term at the centre, and the number of diffraction maxima between
  the centre and the top edge along the centre column ``n_h = 0`` (local maxima
  of the diffraction term alone, with and without the seed's 2 cos(theta_i)
  grating factor);
- Figs 34 and 35: where the offset peak lands (theta_s, phi_s, pixel) as the
  sample turns with phi_ref.

Usage::

    python experiments/reproduce_seed.py [--out runs/reproduce_seed] [--step 1] [--no-figures]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np

import brdfjax as bj
from brdfjax.config import load_simulate_config
from brdfjax.simulate import FrameResult, run_simulate

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {name: ROOT / "configs" / f"seed_{name}.toml" for name in ("fig33", "fig34", "fig35")}

#: The seed's Fig 33 numbers (physics.md), by theta_i in degrees.
SEED_FIG33 = {
    20: {"centre_max": 1.11e4, "offset_max": 4.44e4, "bars_centre": 300.0, "n_maxima": 26, "n_maxima_no_gf": 14},
    60: {"centre_max": 3.91e4, "offset_max": 4.19e5, "bars_centre": 300.0, "n_maxima": 26, "n_maxima_no_gf": 26},
}
CENTRE_HALF_WIDTH = 3  # pixels: "near the centre peak"


def count_local_maxima(values: np.ndarray) -> int:
    """Interior local maxima of a 1-D profile (a plateau counts once)."""
    v = np.asarray(values, dtype=np.float64)
    rising = v[1:-1] > v[:-2]
    not_falling_after = v[1:-1] >= v[2:]
    return int(np.sum(rising & not_falling_after))


def diffraction_maxima(model: bj.Model, frame: bj.Conditions, detector: bj.Detector, precision: str) -> tuple[int, int]:
    """Maxima of the diffraction term on ``n_h = 0`` from the centre to the top edge, with/without 2 cos(theta_i)."""
    _, _, v_min, _ = detector.index_range
    roi = (0, 0, v_min, 0)  # centre column, top edge .. centre (the endpoints are not maxima)
    bars = model.terms["bars"]
    no_gf = eqx.tree_at(lambda m: m.terms["bars"], model, dataclasses.replace(bars, grating_factor=False))
    counts = []
    for m in (model, no_gf):
        col = np.asarray(bj.render(m, frame, detector, roi=roi, precision=precision, per_term=True)["bars"])[:, 0]
        counts.append(count_local_maxima(col))
    return counts[0], counts[1]


def headline(res: FrameResult, model: bj.Model, detector: bj.Detector, precision: str) -> dict:
    n_h, n_v = res.grid.n_h, res.grid.n_v
    near = (np.abs(n_v)[:, None] <= CENTRE_HALF_WIDTH) & (np.abs(n_h)[None, :] <= CENTRE_HALF_WIDTH)
    if not near.any():
        raise ValueError("the grid misses the centre pixel (0, 0); use a step that divides the offsets")
    centre = np.where(near, res.brdf, -np.inf)
    offset = res.terms["offset"]
    oh, ov = res.argmax(offset)
    out = {
        "name": res.stem,
        "theta_i_deg": float(np.rad2deg(res.frame.theta_i)),
        "phi_ref_deg": float(np.rad2deg(res.frame.phi_ref)),
        "centre_max": float(centre.max()),
        "centre_pixel": list(res.argmax(centre)),
        "offset_max": float(offset.max()),
        "offset_pixel": [oh, ov],
        "offset_theta_s_deg": float(np.rad2deg(res.at(res.geometry["theta_s"], oh, ov))),
        "offset_phi_s_deg": float(np.rad2deg(res.at(res.geometry["phi_s"], oh, ov))),
        "bars_centre": res.at(res.terms["bars"], 0, 0) if (0 in n_h and 0 in n_v) else float("nan"),
        "render_s": res.render_s,
        "write_s": res.write_s,
    }
    out["n_maxima"], out["n_maxima_no_gf"] = diffraction_maxima(model, res.frame, detector, precision)
    return out


def _fmt(x: float) -> str:
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def print_tables(rows: dict[str, list[dict]], file=sys.stdout) -> None:
    p = lambda *a: print(*a, file=file)  # noqa: E731
    p("\nFig 33 (phi_ref = 0): brdfjax vs seed")
    p(f"{'quantity':<44}{'theta_i':>8}{'brdfjax':>12}{'seed':>10}{'ratio':>8}")
    labels = {
        "centre_max": "centre-peak max, |n_h|,|n_v| <= 3 (sr^-1)",
        "offset_max": "offset-peak max (offset term, sr^-1)",
        "bars_centre": "diffraction term at (0, 0) (sr^-1)",
        "n_maxima": "diffraction maxima, centre..top edge",
        "n_maxima_no_gf": "  same without 2 cos(theta_i)",
    }
    for key, label in labels.items():
        for r in rows["fig33"]:
            ti = round(r["theta_i_deg"])
            seed = SEED_FIG33[ti][key]
            ratio = r[key] / seed
            p(f"{label:<44}{ti:>8}{_fmt(r[key]):>12}{_fmt(seed):>10}{ratio:>8.3f}")
    p("\nFigs 34/35: where the offset peak lands as the sample turns (phi_ref)")
    p(
        f"{'frame':<16}{'theta_i':>8}{'phi_ref':>8}{'offset max':>12}{'theta_s':>9}{'phi_s':>9}"
        f"{'pixel (n_h, n_v)':>19}{'dir in array':>14}"
    )
    for fig in ("fig33", "fig34", "fig35"):
        for r in rows[fig]:
            oh, ov = r["offset_pixel"]
            direction = np.rad2deg(np.arctan2(ov, oh))  # angle of the offset peak from +n_h toward +n_v
            p(
                f"{fig + ' ' + r['name']:<16}{r['theta_i_deg']:>8.4g}{r['phi_ref_deg']:>8.4g}{r['offset_max']:>12.4g}"
                f"{r['offset_theta_s_deg']:>9.3f}{r['offset_phi_s_deg']:>9.3f}{f'({oh}, {ov})':>19}{direction:>13.1f}°"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/reproduce_seed", help="output folder (default runs/reproduce_seed)")
    ap.add_argument("--step", type=int, default=None, help="override grid.step (default: the configs' full resolution)")
    ap.add_argument("--no-figures", action="store_true", dest="no_plot", help="skip the PNG figures")
    ap.add_argument("--no-plot", action="store_true", dest="no_plot", help=argparse.SUPPRESS)  # the old spelling
    args = ap.parse_args(argv)

    from rich.console import Console

    console = Console(stderr=True, highlight=False, soft_wrap=True)
    out = Path(args.out)
    rows: dict[str, list[dict]] = {}
    t0 = time.perf_counter()
    for fig, path in CONFIGS.items():
        cfg = load_simulate_config(path)
        if args.step is not None:
            cfg = cfg.with_overrides(step=args.step)
        model, detector = cfg.build_model(), cfg.build_detector()
        rows[fig] = []
        console.print(f"{fig}: {path.relative_to(ROOT)} -> {out / fig}", markup=False)
        run_simulate(
            cfg,
            out / fig,
            plot=not args.no_plot,
            console=console,
            on_frame=lambda res, rows=rows[fig], m=model, d=detector, p=cfg.precision: rows.append(headline(res, m, d, p)),
        )
    wall = time.perf_counter() - t0
    print_tables(rows)
    print(f"\n6 frames in {wall:.1f} s; outputs in {out}/")
    (out / "headline.json").write_text(json.dumps({"wall_s": wall, "frames": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
