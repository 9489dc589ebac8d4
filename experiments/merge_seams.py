"""Seams and errors of the HDR merges: the seed's replacement scheme (§3.6) vs the inverse-variance merge.

Target: a synthetic "ramp" BRDF frame, constant down each column and rising
by 5.5 decades across the columns, measured through 3.0 OD by the seed
instrument on a coarse camera (8 x 8 binned pixels, :meth:`InstrumentConfig.coarse`),
four exposures 1-1000 ms.  Every flux level of the stitched range is then
sampled by many pixels, so the merges can be compared level by level.

Printed:

* RMS relative error of the stitched flux against the expected light, by
  flux band, for the replacement scheme, the inverse-variance merge and the
  inverse-variance merge with the hand-over taper (``taper_start=0.5``):
  once with every effect of the instrument, once without the non-linearity
  (noise only: what a merge can act on), pooled over ``--seeds`` noise seeds;
* the seams: the jump of the mean relative error across each exposure
  switch (pixels at 85-97 % vs 103-120 % of the flux where the longer
  exposure saturates), on a noise-free stack with only the non-linearity.

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
from brdfjax.instrument.reduce import plot_merge_comparison, stitch_replacement, stitch_weighted
from brdfjax.instrument.synthetic import InstrumentConfig, SyntheticInstrument

BANDS = ((5e2, 5e3), (5e3, 1.6e4), (1.6e4, 1.6e5), (1.6e5, 1.6e6), (1.6e6, 1.6e7), (5e2, 1.6e7))
MERGES = {
    "replacement": lambda st, bg: stitch_replacement(st, bg),
    "weighted": lambda st, bg: stitch_weighted(st, bg),
    "weighted+taper": lambda st, bg: stitch_weighted(st, bg, taper_start=0.5),
}


def ramp_measurement(config: InstrumentConfig, seed: int, shape=(48, 256), decades=(-1.0, 4.5)):
    """A ramp target measured by the instrument: (stack, background, expected light in sDC)."""
    det = bj.Detector.seed(shape=shape, pixel_pitch=44e-6, pixel_pitch_v=44e-6)
    ins = SyntheticInstrument(det, config, seed=seed)
    frame = bj.Frame.from_degrees(20.0)
    ramp = np.broadcast_to(10 ** np.linspace(*decades, shape[1]), shape).astype(np.float32)
    st = ins.measure_sample(ramp, frame, "3.0")
    bg = ins.measure_background(st.attrs)
    light = ins.sample_flux(ramp, frame, "3.0")
    if ins.camera.ambient is not None:
        light = light - ins.camera.ambient
    return st, bg, light * float(st.exposure_times[-1])


def band_errors(config: InstrumentConfig, seeds) -> dict:
    sq: dict = {}
    for seed in seeds:
        st, bg, light = ramp_measurement(config, seed)
        for name, merge in MERGES.items():
            m = merge(st, bg)
            for band in BANDS:
                sel = (light > band[0]) & (light < band[1]) & ~m.saturated
                sq.setdefault((name, band), []).append(np.mean((m.flux[sel] / light[sel] - 1) ** 2))
    return {k: float(np.sqrt(np.mean(v))) for k, v in sq.items()}


def seams(config: InstrumentConfig) -> dict:
    st, bg, light = ramp_measurement(config, 0)
    t, fs = st.exposure_times, st.attrs.full_scale
    out = {}
    for name, merge in MERGES.items():
        m = merge(st, bg)
        jumps = []
        for k in range(len(t) - 1):
            level = 0.98 * fs * t[-1] / t[k + 1]  # sDC at which exposure k+1 saturates
            below = (light > 0.85 * level) & (light < 0.97 * level)
            above = (light > 1.03 * level) & (light < 1.20 * level)
            jumps.append(float(np.mean(m.flux[above] / light[above]) - np.mean(m.flux[below] / light[below])))
        out[name] = jumps
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("runs/merge_seams"))
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args(argv)
    base = InstrumentConfig().coarse(8)
    seeds = range(args.seeds)
    full = band_errors(base, seeds)
    noise_only = band_errors(base.without("nonlinearity"), seeds)
    seam = seams(base.ideal().with_effects(nonlinearity=True, black_level=True, quantisation=True, saturation=True))
    names = list(MERGES)
    print(f"RMS relative error of the stitched flux vs the expected light ({args.seeds} seeds, 48 x 256 px each)")
    print(f"| {'band (sDC)':<17} | " + " | ".join(f"{n + ' (all)':>20}" for n in names) + " | "
          + " | ".join(f"{n + ' (noise)':>22}" for n in names) + " |")
    for band in BANDS:
        label = f"{band[0]:.1e}-{band[1]:.1e}"
        print(f"| {label:<17} | " + " | ".join(f"{full[(n, band)]:>20.4%}" for n in names) + " | "
              + " | ".join(f"{noise_only[(n, band)]:>22.4%}" for n in names) + " |")
    print("\nSeams: jump of the mean relative error across each exposure switch (non-linearity only, no noise)")
    for n in names:
        print(f"  {n:<15} " + "  ".join(f"{1e3 * t:g} ms: {j:+.3%}" for t, j in zip((0.01, 0.1, 1.0), seam[n])))
    args.out.mkdir(parents=True, exist_ok=True)
    st, bg, light = ramp_measurement(base, 0)
    png = plot_merge_comparison(st, bg, args.out / "merge_seams.png", row=24, truth=light, average_rows=True)
    print(f"\nwrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
