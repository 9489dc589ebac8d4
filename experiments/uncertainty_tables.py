"""Reproduce the seed's Chapter IV uncertainty numbers and print them beside the seed's.

Everything here goes through :func:`brdfjax.instrument.uncertainty.brdf_uncertainty`
/ :func:`~brdfjax.instrument.uncertainty.geometry_uncertainty` (autodiff
sensitivities of the core pixel mapping and of Eq 45) and
:func:`~brdfjax.instrument.uncertainty.optical_density_uncertainty` (Eq 97).
Values are printed in percent, as the seed prints them.

Sections:

1. §4.4 maxima over the array of Eq 99-101 (theta_s terms, tan-scaled) and
   Eq 102-104 (phi_s terms, divided by phi_s) at theta_c = 20, 40, 60 deg;
   the §4.4 misalignment examples.
2. §4.5 solid-angle terms (dR at the centre pixel, dd, misalignment).
3. Eq 97 ND-filter term for the seed's filter stacks.
4. Table 5 (array statistics, theta_i = 0 and 60 deg).
5. Table 6 (single centre-row pixels, theta_i = 20 and 40 deg).

What the seed does not give, and how it is handled:

- The per-pixel scatter non-linearity map (§4.2) is not published, only its
  mean 2.18 %, std 0.50 %, max 16.32 % and min 1.05 %.  Table 5's scatter-
  flux row is therefore echoed, and its total rows are bracketed: the max and
  min totals lie between the NL extreme combined with the smallest and the
  largest of the other terms; the average is estimated with
  E[dNL^2] = mean^2 + std^2; the standard deviation is not estimated.
- Table 6 totals are per pixel, so they also need that map.  The table's
  offsets land on the same centre-row pixels at 20 and 40 deg, so one
  non-linearity per pixel must explain four printed numbers; the script
  finds the interval of values that does (each printed number +- half its
  last digit) and prints the totals recomputed with it.
- The ND stack for Table 5's right half (OD_m = 3.5) is not given; its
  59.7 % ND term is used as printed.  With it the bracket for the maximum
  total is 61.99-62.0 % against the seed's 61.9 %; an ND term of 59.65 %
  (which also prints as 59.7, e.g. 3.0 +-0.15 with 0.5 +-0.03) gives 61.9.  The 1.0 OD filter's tolerance (+-0.06)
  is inferred from the seed's 14.2 % and 14.0 % results; the 3.0 OD filter's
  (+-"0.15") from its 59.3 % result assuming OD_m = 3.3 = 3.0 + 0.3 (§6), and
  is used only in that line.

Usage::

    python experiments/uncertainty_tables.py [--step 1] [--precision float64]

``--step 1`` (the default) evaluates the full 3296 x 2472 frame for the
Table 5 statistics (about two minutes on a CPU in float64); the §4.4 maxima use
the full frame too unless ``--step`` is larger.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

# Printed values, kept as the seed prints them.
SEED_THETA_MAX = {20: ("0.018", "8.34e-4", "0.35"), 40: ("0.039", "0.0018", "0.77"), 60: ("0.080", "0.038", "1.61")}
SEED_PHI_MAX = {20: ("0.036", "0.0017", "0.056"), 40: ("0.017", "8.13e-4", "0.012"), 60: ("0.012", "5.81e-4", "0.0042")}
SEED_MISALIGNMENT = {
    (20, 3, 5): ("0.0034", "0.012"),
    (40, -1, -1): ("0.0049", "0.0036"),
    (60, 72, -3): ("0.23", "0.0045"),
}
SEED_TABLE5 = {  # row -> (left: avg, std, max, min), (right: ...)
    "total": ((3.93, 0.300, 16.6, 3.41), (59.8, 0.0211, 61.9, 59.8)),
    "scatter_flux": ((2.18, 0.502, 16.3, 1.05), (2.18, 0.502, 16.3, 1.05)),
    "incident_flux": ((1.01, 0, 1.01, 1.01), (59.7, 0, 59.7, 59.7)),
    "scatter_angle": ((0.0122, 0.00703, 0.0244, 0), (1.53, 0.0569, 1.63, 1.43)),
    "solid_angle": ((3.08, 0.00122, 3.08, 3.07), (3.08, 0.00122, 3.08, 3.07)),
    "total (ND = 0)": ((3.93, 0.300, 16.6, 3.41), (4.22, 0.282, 16.7, 3.72)),
}
SEED_TABLE6 = {  # theta_s - theta_i (deg) -> 20 deg with ND 2.30 %, 20 deg ND 0, 40 deg with ND 14.2 %, 40 deg ND 0
    0.011: (5.05, 4.50, 14.9, 4.54),
    0.022: (4.45, 3.81, 14.7, 3.86),
    0.05: (4.36, 3.70, 14.7, 3.76),
    0.1: (4.38, 3.73, 14.7, 3.79),
    0.5: (4.24, 3.57, 14.7, 3.63),
    1.0: (4.83, 4.24, 14.8, 4.30),
}
NL_MEAN, NL_STD, NL_MAX, NL_MIN = 2.18, 0.502, 16.32, 1.05  # %, seed §4.2 / Table 5


def pct(x):
    return 100.0 * np.asarray(x, dtype=np.float64)


def line(label: str, ours, seed, width: int = 44) -> str:
    fmt = lambda v: v if isinstance(v, str) else f"{v:.4g}"  # noqa: E731
    return f"  {label:<{width}} ours {fmt(ours):>12}   seed {fmt(seed):>10}"


def edge_grid(det, step: int):
    from brdfjax.core.detector import PixelGrid

    h0, h1, v0, v1 = det.index_range
    return PixelGrid(np.unique(np.r_[np.arange(h0, h1 + 1, step), 0, h1]), np.unique(np.r_[np.arange(v0, v1 + 1, step), 0, v1]))


def section_44(det, grid, precision):
    from brdfjax.instrument.uncertainty import geometry_uncertainty

    print("§4.4  maximum relative uncertainty over the array, %  (theta_s: Eq 99-101 x tan; phi_s: Eq 102-104 / phi_s)")
    hh, vv = np.meshgrid(grid.n_h, grid.n_v)
    for tc in (20, 40, 60):
        res = geometry_uncertainty(det, np.deg2rad(tc), grid, precision=precision)
        phi_s = np.asarray(det.angles(hh, vv, np.deg2rad(tc))[1], dtype=np.float64)
        for k, name, seed in zip(("R", "d", "c"), ("dR", "dd", "dtheta_c"), SEED_THETA_MAX[tc]):
            note = "  (seed misprint? Eq 100 gives 0.0038)" if (tc, k) == (60, "d") else ""
            print(line(f"theta_c={tc}  theta_s term, {name}", pct(res[f"theta_{k}"].max()), seed) + note)
        for k, name, seed in zip(("R", "d", "c"), ("dR", "dd", "dtheta_c"), SEED_PHI_MAX[tc]):
            print(line(f"theta_c={tc}  phi_s term, {name}", pct((res[f"dphi_s_{k}"] / phi_s).max()), seed))
    print("§4.4  misalignment (roll 0.11, yaw 0.062, pitch 0.025 deg; peak offsets m_h, m_v), max %")
    from brdfjax.core.detector import Detector

    for (tc, mh, mv), (s_th, s_ph) in SEED_MISALIGNMENT.items():
        res = geometry_uncertainty(
            det, np.deg2rad(tc), grid, misaligned=Detector.seed_misaligned_example(mh, mv), precision=precision
        )
        phi_s = np.asarray(det.angles(hh, vv, np.deg2rad(tc))[1], dtype=np.float64)
        print(line(f"theta_c={tc} m=({mh},{mv})  theta_s", pct(res["theta_misalignment"].max()), s_th))
        print(line(f"theta_c={tc} m=({mh},{mv})  phi_s", pct((res["dphi_s_misalignment"] / phi_s).max()), s_ph))


def section_45(det, grid, precision):
    from brdfjax.core.detector import Detector
    from brdfjax.instrument.uncertainty import geometry_uncertainty

    print("§4.5  solid angle, %")
    res = geometry_uncertainty(
        det, 0.0, grid, misaligned=Detector.seed_misaligned_example(-1, -1), precision=precision
    )
    centre = (np.searchsorted(grid.n_v, 0), np.searchsorted(grid.n_h, 0))
    print(line("dR term at the centre pixel (Eq 107)", pct(res["solid_angle_R"][centre]), "3.08"))
    print(line("dR term, max over the array", pct(res["solid_angle_R"].max()), "3.08"))
    print(line("dd term, max (centre) (Eq 108)", pct(res["solid_angle_d"].max()), "0.15"))
    print(line("misalignment, beam offsets (-1,-1), max (Eq 109)", pct(res["solid_angle_misalignment"].max()), "0.012"))


def section_nd():
    from brdfjax.instrument.nd import SEED_ND_TOLERANCES
    from brdfjax.instrument.uncertainty import optical_density_uncertainty

    print("Eq 97  ND-filter term, %  (tolerances: 0.1/0.2/0.3 +-0.01, 4.0 +-0.2 printed; 1.0 +-0.06 inferred)")
    cases = [
        ("mirror: 4.0+1.0+0.2 vs 4.0+1.0 (§4.6)", "4.0+1.0+0.2", "4.0+1.0", None, "2.30"),
        ("polished Al: vs 4.0+0.1 (§4.6)", "4.0+1.0+0.2", "4.0+0.1", None, "14.2"),
        ("solar cell 60 deg: vs 4.0 (§6)", "4.0+1.0+0.2", "4.0", None, "14.0"),
        ("solar cell 20 deg: vs 3.0+0.3, 3.0 +-0.15 inferred (§6)", "4.0+1.0+0.2", "3.0+0.3",
         {**SEED_ND_TOLERANCES, 3.0: 0.15}, "59.3"),
    ]
    for label, beam, sample, tol, seed in cases:
        print(line(label, pct(optical_density_uncertainty(beam, sample, tol)), seed, width=56))
    print(line("Kapton: vs OD_m = 3.5 (stack not given)", "n/a", "59.7", width=56))


def _stats(a):
    a = pct(a)
    return (a.mean(), a.std(), a.max(), a.min())


def section_table5(det, step, precision):
    from brdfjax.core.detector import Detector
    from brdfjax.instrument.uncertainty import brdf_uncertainty, incident_flux_uncertainty

    grid = det.grid(step)
    print(f"Table 5  array statistics, %  (grid {grid.shape[0]} x {grid.shape[1]} pixels)  avg / std / max / min")
    beam = Detector.seed_misaligned_example(-1, -1)
    halves = {
        "theta_i = 0 (OD_m = OD_b)": dict(theta_i=0.0, nd=0.0, misaligned=beam),
        "theta_i = 60 (ND 59.7 %)": dict(
            theta_i=np.deg2rad(60), nd=0.597, misaligned=Detector.seed_misaligned_example(72, -3)
        ),
    }
    for side, (label, kw) in enumerate(halves.items()):
        t0 = time.perf_counter()
        theta_i = kw.pop("theta_i")
        res = brdf_uncertainty(
            det, theta_i, grid, scatter_nonlinearity=0.0, misaligned_solid_angle=beam, precision=precision, **kw
        )
        dt = time.perf_counter() - t0
        print(f"  {label}   ({dt:.1f} s)")
        show = lambda vals: " / ".join(f"{v:.3g}" for v in vals)  # noqa: E731
        incident = float(pct(res["incident_flux"]))
        rows = {
            "incident_flux": (incident, 0.0, incident, incident),
            "scatter_angle": _stats(res["scatter_angle"]),
            "solid_angle": _stats(res["solid_angle"]),
        }
        for name, vals in rows.items():
            print(f"    {name:<16} ours {show(vals):<36} seed {show(SEED_TABLE5[name][side])}")
        unpublished = "(the seed's NL map: not published)"
        print(f"    {'scatter_flux':<16} ours {unpublished:<36} seed {show(SEED_TABLE5['scatter_flux'][side])}")
        geometric2 = pct(res["scatter_angle"]) ** 2 + pct(res["solid_angle"]) ** 2
        for name, inc in (("total", incident), ("total (ND = 0)", float(pct(incident_flux_uncertainty(0.0))))):
            rest2 = inc**2 + geometric2
            avg = np.sqrt(NL_MEAN**2 + NL_STD**2 + rest2).mean()
            mx = (np.sqrt(NL_MAX**2 + rest2.min()), np.sqrt(NL_MAX**2 + rest2.max()))
            mn = (np.sqrt(NL_MIN**2 + rest2.min()), np.sqrt(NL_MIN**2 + rest2.max()))
            est = f"~{avg:.3g} / ? / {mx[0]:.4g}-{mx[1]:.4g} / {mn[0]:.3g}-{mn[1]:.3g}"
            print(f"    {name:<16} ours {est:<36} seed {show(SEED_TABLE5[name][side])}")
    print("    (totals: avg with E[dNL^2] = 2.18^2 + 0.502^2; max/min bracketed by the other terms' range)")


def section_table6(det, precision):
    from brdfjax.core.detector import Detector, PixelGrid
    from brdfjax.instrument.uncertainty import brdf_uncertainty

    print("Table 6  totals at centre-row pixels, %  (20 deg: mirror, m=(3,5); 40 deg: polished Al, m=(-1,-1))")
    cases = [(20.0, "4.0+1.0", (3, 5)), (40.0, "4.0+0.1", (-1, -1))]
    rest2, pixels = [], None
    for theta_deg, sample, m in cases:
        tc = np.deg2rad(theta_deg)
        n_h = np.arange(0, det.index_range[1] + 1)
        off = np.rad2deg(np.asarray(det.angles(n_h, np.zeros_like(n_h), tc)[0]) - tc)
        pixels = np.array([n_h[np.argmin(np.abs(off - o))] for o in SEED_TABLE6])
        kw = dict(
            misaligned=Detector.seed_misaligned_example(*m),
            misaligned_solid_angle=Detector.seed_misaligned_example(-1, -1),
            precision=precision,
        )
        grid = PixelGrid(pixels, np.array([0]))
        with_nd = brdf_uncertainty(det, tc, grid, scatter_nonlinearity=0.0, nd_beam="4.0+1.0+0.2", nd_sample=sample, **kw)
        without = brdf_uncertainty(det, tc, grid, scatter_nonlinearity=0.0, nd=0.0, **kw)
        rest2 += [pct(with_nd["total"][0]) ** 2, pct(without["total"][0]) ** 2]
    printed = np.array(list(SEED_TABLE6.values()))
    lo, hi = np.full(len(SEED_TABLE6), -np.inf), np.full(len(SEED_TABLE6), np.inf)
    for col, r2 in enumerate(rest2):
        half = 0.05 if printed[0, col] >= 10 else 0.005
        lo = np.maximum(lo, (printed[:, col] - half) ** 2 - r2)
        hi = np.minimum(hi, (printed[:, col] + half) ** 2 - r2)
    print("  offset  n_h   dNL_s fitting all four (%)   ours: 20 ND / 20 / 40 ND / 40    seed")
    for i, off in enumerate(SEED_TABLE6):
        if lo[i] > hi[i]:
            print(f"  {off:<6} {pixels[i]:>5}   none (lo {lo[i]:.4g} > hi {hi[i]:.4g})")
            continue
        nl2 = 0.5 * (lo[i] + hi[i])
        ours = [np.sqrt(nl2 + r2[i]) for r2 in rest2]
        nl_rng = f"{np.sqrt(max(lo[i], 0)):.3f}-{np.sqrt(hi[i]):.3f}"
        print(
            f"  {off:<6} {pixels[i]:>5}   {nl_rng:<26} "
            + " / ".join(f"{v:.1f}" if v >= 10 else f"{v:.2f}" for v in ours)
            + "    "
            + " / ".join(f"{v:.1f}" if v >= 10 else f"{v:.2f}" for v in printed[i])
        )
    print("  (dNL_s: the range of pixel non-linearities consistent with all four printed totals; ours: recomputed with its midpoint)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--step", type=int, default=1, help="pixel decimation for Table 5 and the maxima (1: full frame)")
    ap.add_argument("--precision", choices=["float32", "float64"], default="float64")
    args = ap.parse_args(argv)

    import jax

    if args.precision == "float64":
        jax.config.update("jax_enable_x64", True)  # this script's own process; brdfjax never flips it
    from brdfjax.core.detector import Detector

    det = Detector.seed()
    grid = edge_grid(det, args.step) if args.step > 1 else det.grid()
    t0 = time.perf_counter()
    section_44(det, grid, args.precision)
    section_45(det, grid, args.precision)
    section_nd()
    section_table5(det, args.step, args.precision)
    section_table6(det, args.precision)
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
