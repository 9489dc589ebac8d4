"""Write the example measurement set ``tests/data/example_set/`` with the synthetic instrument.

The set is a complete, valid instance of the raw format of
:mod:`brdfjax.io.raw`: a beam signature and its background, the seed's
solar-cell model at theta_i = 20 deg and its background, and a
``manifest.toml``.  To stay small enough for git it uses a coarse camera: 64 x
48 pixels of 44 um (the seed's 5.5 um pixels binned 8 x 8, 0.43 x 0.32 deg
at R = 0.325 m) with the seed instrument scaled to it
(:meth:`InstrumentConfig.coarse`: same per-pixel counts, so the 1 ms beam
peak is near 1e4 counts and the noise-equivalent BRDF is the seed's), four
exposures (1, 10, 100, 1000 ms) of 32 averaged frames, 14 bits, ZIP.

The sample is measured through a 3.0 OD filter (the beam through 4.0 + 1.0 +
0.2), so no filter is shared and the reduction needs the 3.0 filter's
tolerance: ``[calibration.nd_tolerances] "3.0" = 0.15`` (the value that
reproduces the seed's 59.3 % for its 3.3 OD solar-cell measurement, §6.2).

Run from the repository root::

    python tests/data/make_example_set.py            # (re)writes tests/data/example_set/
    brdfjax reduce tests/data/example_set/manifest.toml --out runs/example

The same seeds give the same files; the tests import :func:`example_instrument`
and :data:`SAMPLES` to rebuild the truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import brdfjax as bj
from brdfjax.instrument.synthetic import InstrumentConfig, StrayLight, SyntheticInstrument
from brdfjax.io.raw import Calibration

#: Binning factor of the coarse example camera relative to the seed's pixels.
BIN = 8
#: Array shape (n_v rows, n_h columns).
SHAPE = (48, 64)
#: Stray-light sub-peaks placed inside the small array: (dh_px, dv_px, log10 peak ratio).
STRAY_PEAKS = ((20, -9, -4.85), (-26, 6, -5.05), (9, 17, -5.3))
#: Sample name -> (theta_i in degrees, ND filter stack).
SAMPLES = {"solar_cell_20deg": (20.0, "3.0")}
CALIBRATION = Calibration(nd_tolerances={3.0: 0.15})
CAMERA_SEED = 3
NOISE_SEED = 20240


def example_detector(**kw) -> bj.Detector:
    """The coarse example camera (64 x 48 pixels of 44 um at R = 0.325 m); ``kw`` adds misalignment."""
    return bj.Detector.seed(shape=SHAPE, pixel_pitch=5.5e-6 * BIN, pixel_pitch_v=5.5e-6 * BIN, **kw)


def example_config(**updates) -> InstrumentConfig:
    """The seed instrument scaled to the example camera (every effect at its seed default)."""
    cfg = InstrumentConfig(camera_seed=CAMERA_SEED).coarse(BIN)
    cfg = cfg.model_copy(update={"stray_light": StrayLight(peaks=STRAY_PEAKS)})
    return cfg.model_copy(update=updates) if updates else cfg


def example_instrument(seed: int = NOISE_SEED, detector: bj.Detector | None = None, config=None) -> SyntheticInstrument:
    return SyntheticInstrument(
        example_detector() if detector is None else detector,
        example_config() if config is None else config,
        seed=seed,
    )


def write_example_set(folder: Path, seed: int = NOISE_SEED) -> Path:
    ins = example_instrument(seed)
    model = bj.solar_cell()
    samples = {
        name: (model, bj.Frame.from_degrees(theta_i), nd) for name, (theta_i, nd) in SAMPLES.items()
    }
    return ins.write_set(folder, samples, calibration=CALIBRATION)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "example_set")
    args = ap.parse_args(argv)
    manifest = write_example_set(args.out)
    files = sorted(args.out.iterdir())
    total = sum(p.stat().st_size for p in files)
    print(f"wrote {manifest} and {len(files) - 1} raw files, {total / 1024:.0f} KiB in all")
    for p in files:
        print(f"  {p.name:40s} {p.stat().st_size / 1024:7.1f} KiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
