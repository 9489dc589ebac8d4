"""Where the physically based fit of MERL aluminium loses to the binomial, and what structure closes the gap (issue 14).

Four parts, from the fits stored in
``experiments/results/real_data_fits_merl_aluminium.json`` (no fit is rerun):

1. Residuals ``r = ln(f_model / f_data)`` of the stored best physically based
   fit and of the binomial, per incident angle and per region of the
   offset from the mirror direction ``d = theta_s - theta_i`` (in-plane,
   signed, + on the specular side): the peak core ``|d| < 2 deg``, the near
   wings ``2-8 deg``, the wings ``8-25 deg``, the far floor ``>= 25 deg``
   forward and backward, and grazing ``|theta_s| > 75 deg``.  Each region's
   share of the total mean square (the square of the overall log-RMS is the
   sum of the shares of the disjoint regions) and its rms.

2. Floors: the lowest log-RMS that ANY function of the half-angle
   ``D(theta_h)`` times a fixed angular factor can reach on these data
   (least squares of ``ln f - ln A`` on a cubic B-spline basis in
   ``ln tan theta_h``, 40 knots), optionally with an arbitrary
   reciprocal per-direction factor ``g(theta_i) + g(theta_s)`` (a
   shadowing-like factor; 12 knots), an arbitrary factor of ``theta_d``, or the
   binomial's second variable ``V = sin theta_i sin theta_s``.  A model of
   the form ``D(theta_h) A(theta_i, theta_s)`` cannot go below its floor,
   whatever its distribution; the floors say which kind of angular
   structure the data need.  Angular factors: the seed's Eq 70 (``Q / (2
   (cos ti + cos ts)^2)``), Torrance-Sparrow with ``Q / 2`` or with the
   Fresnel reflectance at the microfacet angle ``F(theta_d)``, and none in the
   projected distance ``|beta - beta0|`` (ABg's and the binomial's variable).
   The index is scanned over a grid (n, k) for each factor, and a Smith
   GGX G2 of a free width (0, 0.2, 0.4, 0.7) multiplied in.

3. Two-component floors: ``exp(s1(theta_h)) A1 + exp(s2(theta_h)) A2 + rho_d / pi``
   with two free splines (25 knots each; nonlinear least squares) and
   ``A1`` the seed's Eq 70 factor (aluminium index): the lowest log-RMS of
   two lobes of ANY shapes whose angular factors differ (their own Smith
   G2, their own Fresnel factor, no factor at all).

4. The two-lobe floor with other structures (:func:`structure_floors`): a non-Lambertian reciprocal diffuse
   term, a Kirchhoff spike/halo split that changes with the directions, and (not a BRDF) a free weight per
   incident angle for each lobe: which structure, if any, reaches the binomial.

Prints the tables and writes ``experiments/results/merl_gap.json`` (atomically).

    python3 experiments/merl_gap.py
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.interpolate import BSpline  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

import brdfjax as bj  # noqa: E402
from brdfjax.core.fresnel import fresnel, q_factor  # noqa: E402
from brdfjax.core.shadowing import lambda_ggx  # noqa: E402
from brdfjax.io import write_json_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
import real_data_fits as R  # noqa: E402

REGIONS = ("core <2", "near 2-8", "wing 8-25", "far fwd >=25", "far back >=25", "grazing ts>75")


def regions(signed_deg: np.ndarray, ti_deg: np.ndarray) -> dict[str, np.ndarray]:
    off = signed_deg - ti_deg
    a = np.abs(off)
    return {
        "core <2": a < 2,
        "near 2-8": (a >= 2) & (a < 8),
        "wing 8-25": (a >= 8) & (a < 25),
        "far fwd >=25": (a >= 25) & (signed_deg > 0),
        "far back >=25": (a >= 25) & (signed_deg <= 0),
        "grazing ts>75": np.abs(signed_deg) > 75,  # overlaps the others
    }


def bspline(x: np.ndarray, knots: int, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    lo = float(x.min()) if lo is None else lo
    hi = float(x.max()) if hi is None else hi
    t = np.r_[[lo] * 3, np.linspace(lo, hi, knots), [hi] * 3]
    return BSpline.design_matrix(np.clip(x, lo, hi), t, 3).toarray()


def lsq_rms(y: np.ndarray, *blocks: np.ndarray) -> float:
    X = np.concatenate(blocks, 1)
    c, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(np.sqrt(np.mean(np.square(y - X @ c))))


def nonlinear_floor(resid, p0: np.ndarray, starts: int = 3) -> tuple[object, dict]:
    """The lowest log-RMS of a non-convex least-squares model from ``starts`` starts (``p0`` and ``p0`` moved by
    N(0, 0.7) per coefficient, seeded): a local optimum is an upper bound of the floor, so the spread over the
    starts and whether the best one converged are kept beside it."""
    rng = np.random.default_rng(0)
    sols = [least_squares(resid, p0 if k == 0 else p0 + rng.normal(0.0, 0.7, p0.shape), method="trf",
                          max_nfev=3000, x_scale="jac") for k in range(starts)]
    rms = [float(np.sqrt(np.mean(s.fun**2))) for s in sols]
    best = int(np.argmin(rms))
    return sols[best], {"floor": rms[best], "rms_over_starts": rms, "converged": bool(sols[best].status > 0)}


def structure_floors(y0, B, c1, A1, A2, ti, ts) -> dict:
    """Part 4: the two-lobe floor (free shapes, factors ``A1``, ``A2``) with three other structures in place of
    the Lambertian constant or the constant lobe weights, each the lowest log-RMS such a model can reach:

    - a non-Lambertian reciprocal diffuse term ``d(theta_i) d(theta_s)`` (a free 8-knot spline in each angle:
      covers Oren-Nayar-like and Fresnel-transmission ``(1 - F)(1 - F)`` diffuse shapes);
    - a Kirchhoff (Beckmann-Spizzichino) split of the weight between the spike and the halo that changes with
      the directions, ``exp(-g)`` and ``1 - exp(-g)``, ``g = (k sigma (cos ti + cos ts))^2``, ``k sigma`` free;
    - an arbitrary weight per incident angle for each lobe (7 + 7 free; not reciprocal, so not a BRDF model:
      the bound of what per-incidence weights can do).
    """
    nb = B.shape[1]
    Di = bspline(ti, 8, 0.0, np.pi / 2)
    Ds = bspline(ts, 8, 0.0, np.pi / 2)
    nd = Di.shape[1]
    angles = np.unique(np.round(ti, 4))
    W = (np.round(ti, 4)[:, None] == angles[None, :]).astype(float)
    nw = W.shape[1]
    kk = np.cos(ti) + np.cos(ts)
    lobes0 = np.r_[c1, c1 - 3.0 + np.log(np.mean(A1 / A2))]

    def separable(p):
        lobe = np.exp(B @ p[:nb]) * A1 + np.exp(B @ p[nb:2 * nb]) * A2
        return np.log(lobe + np.exp(Di @ p[2 * nb:] + Ds @ p[2 * nb:])) - y0

    def kirchhoff(p):
        g = np.minimum((np.exp(p[-2]) * kk) ** 2, 700.0)
        lobe = np.exp(B @ p[:nb] - g) * A1 + np.exp(B @ p[nb:2 * nb]) * (-np.expm1(-g)) * A2
        return np.log(lobe + np.exp(p[-1])) - y0

    def per_incidence(p):
        w1, w2 = p[2 * nb:2 * nb + nw], p[2 * nb + nw:2 * nb + 2 * nw]
        lobe = np.exp(B @ p[:nb] + W @ w1) * A1 + np.exp(B @ p[nb:2 * nb] + W @ w2) * A2
        return np.log(lobe + np.exp(p[-1])) - y0

    rows = {}
    print("\n4. two lobes of any shapes (seed Eq 70 and with Smith GGX G2 0.3) with other structures")
    for label, resid, p0 in (
        ("+ reciprocal diffuse d(ti) d(ts) (8-knot splines) instead of rho_d", separable, np.r_[lobes0, np.full(nd, np.log(1e-4) / 2)]),
        ("Kirchhoff spike/halo split exp(-g), g = (k sigma (cos ti + cos ts))^2, + rho_d", kirchhoff, np.r_[lobes0, np.log(1.0), np.log(1e-4)]),
        ("a free weight per incident angle for each lobe (not reciprocal), + rho_d", per_incidence, np.r_[lobes0, np.zeros(2 * nw), np.log(1e-4)]),
    ):
        sol, row = nonlinear_floor(resid, p0)
        if resid is kirchhoff:
            row["k_sigma"] = float(np.exp(sol.x[-2]))
        if resid is per_incidence:
            row["theta_i_deg"] = [float(a) for a in np.degrees(angles)]
            row["ln_weight_lobe1_rel_first"] = [float(v) for v in sol.x[2 * nb:2 * nb + nw] - sol.x[2 * nb]]
            row["ln_weight_lobe2_rel_first"] = [float(v) for v in sol.x[2 * nb + nw:2 * nb + 2 * nw] - sol.x[2 * nb + nw]]
        rows[label] = row
        extra = "".join(f", {k} {np.round(v, 3) if isinstance(v, list) else v if isinstance(v, bool) else round(v, 3)}"
                        for k, v in row.items() if k != "floor")
        print(f"   {label:84s} {row['floor']:.3f}{extra}", flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--results", type=Path, default=ROOT / "experiments" / "results" / "real_data_fits_merl_aluminium.json")
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "merl_gap.json")
    p.add_argument("--physical", default=None, help="stored physical model to compare (default: the stored best)")
    args = p.parse_args(argv)
    name = "merl_aluminium"
    stored = json.loads(args.results.read_text())
    fits = stored["fits"]
    physical = args.physical or stored["best_physical"]
    table = R.read(name)
    ti, pi, ts, ps = (np.asarray(getattr(table, f), float) for f in ("theta_i", "phi_i", "theta_s", "phi_s"))
    f = np.asarray(table.brdf, float)
    wl = np.asarray(table.wavelength)
    dirs = bj.Directions.from_angles(ti, pi, ts, ps)
    fwd = np.cos(ps - pi) < 0
    signed = np.degrees(np.where(fwd, ts, -ts))
    ti_deg = np.degrees(ti)
    angles = np.unique(np.round(ti_deg, 2))
    reg = regions(signed, ti_deg)
    out: dict = {"dataset": name, "physical": physical, "empirical": "binomial", "n_points": int(f.size)}

    # 1. residuals per region and angle
    res = {}
    for label in (physical, "binomial"):
        model = R._stored_model(label, name, fits)
        res[label] = np.log(np.asarray(model(dirs, wl)) / f)
    N = f.size
    print(f"1. residuals ln(model/data): {physical} vs binomial; log-RMS "
          f"{np.sqrt(np.mean(res[physical] ** 2)):.3f} vs {np.sqrt(np.mean(res['binomial'] ** 2)):.3f}")
    print(f"   {'region':14s} {'n':>5s}  share of mean square (phys, binom)  rms (phys, binom)  mean (phys, binom)")
    out["regions"] = {}
    for rn in REGIONS:
        sel = reg[rn]
        a, b = res[physical][sel], res["binomial"][sel]
        row = {"n": int(sel.sum()), "share_physical": float(np.sum(a**2) / N), "share_binomial": float(np.sum(b**2) / N),
               "rms_physical": float(np.sqrt(np.mean(a**2))), "rms_binomial": float(np.sqrt(np.mean(b**2))),
               "mean_physical": float(a.mean()), "mean_binomial": float(b.mean())}
        out["regions"][rn] = row
        print(f"   {rn:14s} {row['n']:5d}  {row['share_physical']:.4f} {row['share_binomial']:.4f}"
              f"                      {row['rms_physical']:.3f} {row['rms_binomial']:.3f}      "
              f"{row['mean_physical']:+.3f} {row['mean_binomial']:+.3f}")
    print("   rms per incident angle and region (phys/binom):")
    print("   theta_i  " + "  ".join(f"{rn:>13s}" for rn in REGIONS) + "        all")
    out["per_angle"] = {}
    for a in angles:
        s = np.round(ti_deg, 2) == a
        cells = {}
        for rn in REGIONS:
            q = s & reg[rn]
            cells[rn] = [float(np.sqrt(np.mean(res[m][q] ** 2))) if q.any() else None for m in (physical, "binomial")]
        cells["all"] = [float(np.sqrt(np.mean(res[m][s] ** 2))) for m in (physical, "binomial")]
        out["per_angle"][f"{a:g}"] = cells
        print(f"   {a:7.2f}  " + "  ".join(
            f"{'-':>13s}" if cells[rn][0] is None else f"{cells[rn][0]:6.2f}/{cells[rn][1]:<6.2f}" for rn in REGIONS)
            + f"  {cells['all'][0]:.2f}/{cells['all'][1]:.2f}")

    # 2. floors
    tx2, ty2, _ = (np.asarray(x) for x in dirs.half_slopes())
    th = np.arctan(np.sqrt(tx2 + ty2))
    wi = np.stack([np.asarray(c) for c in dirs.i], -1)
    ws = np.stack([np.asarray(c) for c in dirs.s], -1)
    h = (wi + ws) / np.linalg.norm(wi + ws, axis=1, keepdims=True)
    td = np.arccos(np.clip(np.sum(wi * h, 1), -1.0, 1.0))
    ci, cs = np.cos(ti), np.cos(ts)
    beta = np.abs(np.sin(np.where(fwd, ts, -ts)) - np.sin(ti))
    V = np.sin(ti) * np.sin(np.where(fwd, ts, -ts))
    xh = bspline(np.log(np.maximum(np.tan(th), 1e-5)), 40)
    xb = bspline(np.log(np.maximum(beta, 1e-5)), 40)
    xg = bspline(ti, 12, 0.0, np.pi / 2) + bspline(ts, 12, 0.0, np.pi / 2)
    xd = bspline(td, 12, 0.0, np.pi / 2)
    xv = bspline(V, 12)
    y0 = np.log(f)
    floors = {}
    # fixed index of the shipped configs first
    Q0 = np.asarray(q_factor(0.96, dirs, 6.69))
    for label, A, basis in (("seed Eq 70, D(theta_h), Al 0.96+6.69i", Q0 / (2 * (ci + cs) ** 2), xh),
                            ("Torrance-Sparrow Q/2, D(theta_h), Al 0.96+6.69i", Q0 / (8 * ci * cs), xh),
                            ("no factor, S(|beta - beta0|)", np.ones_like(ci), xb)):
        y = y0 - np.log(A)
        floors[label] = {"alone": lsq_rms(y, basis), "+ g(ti) + g(ts)": lsq_rms(y, basis, xg),
                         "+ e(theta_d)": lsq_rms(y, basis, xd), "+ e(theta_d) + g(ti) + g(ts)": lsq_rms(y, basis, xd, xg),
                         "+ V": lsq_rms(y, basis, xv)}
    # the index and a Smith GGX G2 scanned
    scan = {}
    for n in (0.3, 0.6, 1.0, 1.5, 2.0, 3.0, 5.0):
        for k in (0.0, 0.5, 1.0, 2.0, 4.0, 7.0):
            Q = np.asarray(q_factor(n, dirs, k))
            Fs, Fp = (np.asarray(x) for x in fresnel(n, td, k))
            F = 0.5 * (Fs + Fp)
            for a in (0.0, 0.2, 0.4, 0.7):
                G = 1.0 / (1.0 + np.asarray(lambda_ggx((a * np.tan(ti)) ** 2)) + np.asarray(lambda_ggx((a * np.tan(ts)) ** 2)))
                for label, A in (("seed Eq 70 (Q)", Q / (2 * (ci + cs) ** 2)), ("Torrance-Sparrow Q/2", Q / (8 * ci * cs)),
                                 ("Torrance-Sparrow F(theta_d)", F / (4 * ci * cs))):
                    r = lsq_rms(y0 - np.log(A * G), xh)
                    if label not in scan or r < scan[label]["floor"]:
                        scan[label] = {"floor": r, "n": n, "k": k, "smith_ggx_width": a}
    out["floors"] = floors
    out["floors_index_scanned"] = scan
    print("\n2. floors: the lowest log-RMS of ANY D(theta_h) (40-knot spline) times a fixed angular factor")
    for label, row in floors.items():
        print(f"   {label:48s} " + "  ".join(f"{k} {v:.3f}" for k, v in row.items()))
    print("   with the index (n, k) and a Smith GGX G2 width scanned, D(theta_h) alone:")
    for label, row in scan.items():
        print(f"   {label:30s} floor {row['floor']:.3f} at n = {row['n']}, k = {row['k']}, G2 width {row['smith_ggx_width']}")
    # 3. two components of any shapes, different angular factors
    def g2(a):
        return 1.0 / (1.0 + np.asarray(lambda_ggx((a * np.tan(ti)) ** 2)) + np.asarray(lambda_ggx((a * np.tan(ts)) ** 2)))

    Fs, Fp = (np.asarray(x) for x in fresnel(0.96, td, 6.69))
    A1 = Q0 / (2 * (ci + cs) ** 2)
    second = {"seed Eq 70 x Smith GGX G2 (width 0.3)": A1 * g2(0.3),
              "seed Eq 70 with F_s + F_p at theta_d": (Fs + Fp) / (2 * (ci + cs) ** 2),
              "Torrance-Sparrow Q/2 x Smith GGX G2 (width 0.4)": Q0 / (8 * ci * cs) * g2(0.4),
              "none (a function of theta_h alone)": np.ones_like(ci)}
    B = bspline(np.log(np.maximum(np.tan(th), 1e-5)), 25)
    nb = B.shape[1]
    c1, *_ = np.linalg.lstsq(B, y0 - np.log(A1), rcond=None)
    two, two_starts = {}, {}
    print("\n3. two-component floors: seed Eq 70 lobe of any shape + a second lobe of any shape with another factor + rho_d")
    for label, A2 in second.items():
        def resid(p, A2=A2):
            return np.log(np.exp(B @ p[:nb]) * A1 + np.exp(B @ p[nb:2 * nb]) * A2 + np.exp(p[-1])) - y0

        p0 = np.r_[c1, c1 - 3.0 + np.log(np.mean(A1 / A2)), np.log(1e-4)]
        _, row = nonlinear_floor(resid, p0)
        two[label] = row["floor"]
        two_starts[label] = row
        print(f"   + {label:50s} {row['floor']:.3f} (3 starts: {', '.join(f'{r:.4f}' for r in row['rms_over_starts'])}; "
              f"converged {row['converged']})", flush=True)
    out["two_component_floors"] = two
    out["two_component_floors_starts"] = two_starts
    out["structure_floors"] = structure_floors(y0, B, c1, A1, A1 * g2(0.3), ti, ts)
    path = write_json_atomic(args.out, out, allow_nan=False)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
