"""Seams and errors of the HDR merges: the seed's replacement scheme (§3.6) vs the inverse-variance merge.

Target: a synthetic "ramp" BRDF frame, constant down each column and rising
by 5.5 decades across the columns, measured through 3.0 OD by the seed
instrument on a coarse camera (8 x 8 binned pixels, :meth:`InstrumentConfig.coarse`),
four exposures 1-1000 ms.  Every flux level of the stitched range is then
sampled by many pixels, so the merges can be compared level by level.

Merges (:mod:`brdfjax.instrument.reduce`):

* ``replacement`` -- the seed's scheme (§3.6);
* ``weighted`` -- the default inverse-variance merge: each reading weighted by
  the inverse of its full variance, noise plus the square of its
  non-linearity error from the calibration curve (here the synthetic
  instrument's documented curve, ``SYNTHETIC_NONLINEARITY_CURVE``, which is
  what the camera does);
* ``weighted, noise only`` -- the same with noise variances only (no curve);
* ``weighted + taper`` -- ``weighted`` with the hand-over taper from 0.5 of
  full scale;
* ``weighted, corrected`` -- the readings corrected by the curve first, weights
  from noise plus the curve's residual uncertainty.

Printed:

* RMS relative error of the stitched flux against the expected light, by
  flux band: once with every effect of the instrument, once without the
  non-linearity (noise only: what a merge can act on; the weights then use
  no curve, as for a camera calibrated to be linear), pooled over
  ``--seeds`` noise seeds;
* the seams: the jump of the mean relative error across each exposure
  switch (pixels at 85-97 % vs 103-120 % of the flux where the longer
  exposure saturates), on a noise-free stack with only the non-linearity,
  also as a fraction of the replacement scheme's;
* a summary line per merge: overall RMS and the largest seam.

Written: ``merge_seams.png`` (:func:`brdfjax.instrument.reduce.plot_merge_comparison`
on the full-instrument stack: one row's flux, and the relative error averaged
down the columns, where the seams stand out of the noise).

Usage::

    python experiments/merge_seams.py --out runs/merge_seams
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import brdfjax as bj
from brdfjax.instrument.reduce import (
    SYNTHETIC_NONLINEARITY_CURVE,
    plot_merge_comparison,
    stitch_replacement,
    stitch_weighted,
)
from brdfjax.instrument.synthetic import InstrumentConfig, SyntheticInstrument

BANDS = ((5e2, 5e3), (5e3, 1.6e4), (1.6e4, 1.6e5), (1.6e5, 1.6e6), (1.6e6, 1.6e7), (5e2, 1.6e7))


def merges(curve):
    """Name -> merge(stack, background) with the camera's calibration ``curve`` (None: calibrated linear)."""
    out = {
        "replacement": lambda st, bg: stitch_replacement(st, bg),
        "weighted": lambda st, bg: stitch_weighted(st, bg, nonlinearity_curve=curve),
        "weighted, noise only": lambda st, bg: stitch_weighted(st, bg, nonlinearity_curve=None),
        "weighted + taper": lambda st, bg: stitch_weighted(st, bg, nonlinearity_curve=curve, taper_start=0.5),
    }
    if curve is not None:
        out["weighted, corrected"] = lambda st, bg: stitch_weighted(
            st, bg, nonlinearity_curve=curve, correct_nonlinearity=True)
    return out


def ramp_measurement(config: InstrumentConfig, seed: int, shape=(48, 256), decades=(-1.0, 4.5)):
    """A ramp target measured by the instrument: (stack, background, expected light in sDC)."""
    det = bj.Detector.seed(shape=shape, pixel_pitch=44e-6, pixel_pitch_v=44e-6)
    ins = SyntheticInstrument(det, config, seed=seed)
    frame = bj.Conditions.from_degrees(20.0)
    ramp = np.broadcast_to(10 ** np.linspace(*decades, shape[1]), shape).astype(np.float32)
    st = ins.measure_sample(ramp, frame, "3.0")
    bg = ins.measure_background(st.attrs)
    light = ins.sample_flux(ramp, frame, "3.0")
    if ins.camera.ambient is not None:
        light = light - ins.camera.ambient
    return st, bg, light * float(st.exposure_times[-1])


def band_errors(config: InstrumentConfig, seeds, curve) -> dict:
    sq: dict = {}
    for seed in seeds:
        st, bg, light = ramp_measurement(config, seed)
        for name, merge in merges(curve).items():
            m = merge(st, bg)
            for band in BANDS:
                sel = (light > band[0]) & (light < band[1]) & ~m.saturated
                sq.setdefault((name, band), []).append(np.mean((m.flux[sel] / light[sel] - 1) ** 2))
    return {k: float(np.sqrt(np.mean(v))) for k, v in sq.items()}


def seams(config: InstrumentConfig, curve) -> dict:
    st, bg, light = ramp_measurement(config, 0)
    t, fs = st.exposure_times, st.attrs.full_scale
    out = {}
    for name, merge in merges(curve).items():
        m = merge(st, bg)
        jumps = []
        for k in range(len(t) - 1):
            level = 0.98 * fs * t[-1] / t[k + 1]  # sDC at which exposure k+1 saturates
            below = (light > 0.85 * level) & (light < 0.97 * level)
            above = (light > 1.03 * level) & (light < 1.20 * level)
            jumps.append(float(np.mean(m.flux[above] / light[above]) - np.mean(m.flux[below] / light[below])))
        out[name] = jumps
    return out


def _table(title: str, rms: dict, names) -> None:
    print(title)
    print(f"| {'merge':<21} | " + " | ".join(f"{f'{a:.1e}-{b:.1e}':>17}" for a, b in BANDS[:-1])
          + f" | {'all, 5e2-1.6e7':>14} |")
    for n in names:
        print(f"| {n:<21} | " + " | ".join(f"{rms[(n, band)]:>17.4%}" for band in BANDS[:-1])
              + f" | {rms[(n, BANDS[-1])]:>14.4%} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("runs/merge_seams"))
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args(argv)
    base = InstrumentConfig().coarse(8)
    curve = SYNTHETIC_NONLINEARITY_CURVE  # the synthetic camera's documented curve (NonLinearity.common_max)
    assert curve.points == ((0.0, -base.nonlinearity.common_max), (1.0, base.nonlinearity.common_max))
    seeds = range(args.seeds)
    full = band_errors(base, seeds, curve)
    noise_only = band_errors(base.without("nonlinearity"), seeds, None)
    seam = seams(base.ideal().with_effects(nonlinearity=True, black_level=True, quantisation=True, saturation=True),
                 curve)
    names = list(merges(curve))
    print(f"RMS relative error of the stitched flux vs the expected light ({args.seeds} seeds, 48 x 256 px each)\n")
    _table("every effect of the instrument:", full, names)
    print()
    _table("noise only (no non-linearity; weights without a curve):", noise_only,
           [n for n in names if n in merges(None) and n != "weighted, noise only"])
    print("\nSeams: jump of the mean relative error across each exposure switch (non-linearity only, no noise)")
    ref = max(abs(j) for j in seam["replacement"])
    for n in names:
        print(f"  {n:<21} " + "  ".join(f"{1e3 * t:g} ms: {j:+.3%}" for t, j in zip((0.01, 0.1, 1.0), seam[n]))
              + f"   (largest {max(abs(j) for j in seam[n]) / ref:.0%} of replacement's)")
    print("\nSummary (overall RMS with every effect; largest seam):")
    r0 = full[("replacement", BANDS[-1])]
    for n in names:
        r = full[(n, BANDS[-1])]
        verdict = "reference" if n == "replacement" else f"{'lower' if r < r0 else 'HIGHER'} than replacement"
        print(f"  {n:<21} RMS {r:.4%} ({verdict}), largest seam {max(abs(j) for j in seam[n]):.3%}")
    args.out.mkdir(parents=True, exist_ok=True)
    st, bg, light = ramp_measurement(base, 0)
    png = plot_merge_comparison(st, bg, args.out / "merge_seams.png", row=24, truth=light, average_rows=True,
                                nonlinearity_curve=curve, corrected=True)
    print(f"\nwrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
