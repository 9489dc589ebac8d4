"""Floor-placeholder screening of goniometer tables: false positives on noise floors, detection of written-in floors.

The row screening (``brdfjax.fit.Screen``, ``floor_repeats``) drops a value
that occurs in >= 3 rows, is the lowest of every slice it is in, and is
written two or more decimal places more coarsely than the table's next larger
values.  This script measures, on tables it did not tune on:

- false positives: tables made by the NumPy reference (``brdfjax/reference.py``:
  Beckmann specular, Eq 70, plus a Lambertian) with 5 % log-normal noise and an
  additive instrument floor (|N(floor, 0.15 floor)|, the floor log-uniform in
  1e-6 .. 1e-3 sr^-1), four incident angles (5, 30, 50, 70 deg), signed
  in-plane scans every 1 deg, written in five styles: 2, 3 and 4 significant
  digits, 5 and 6 fixed decimals, and 12 significant digits.  Rows counted as
  ``placeholder_floor`` there are false positives;
- detection: the same tables with 3-8 isolated rows at |theta_s| >= 55 deg
  replaced by a round floor, the power of ten just below the table's lowest
  positive value (as a provider writes ``0.0001`` for "below the detection
  limit"); a table counts as detected when exactly those rows are dropped.

It also reports the shipped real tables (MERL, Cornell at every wavelength, the
V2 Mini lab tables): rows dropped as floor placeholders (expected 0).

    python experiments/table_floor_screening.py [--n 200] [--json experiments/results/table_floor_screening.json]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from brdfjax import reference as ref
from brdfjax.fit import FitInputError, read_cornell_brdf, read_merl_inplane
from brdfjax.runtime.atomic import write_json_atomic

ROOT = Path(__file__).resolve().parents[1]
STYLES = {"sig2": "{:.2g}", "sig3": "{:.3g}", "sig4": "{:.4g}", "fixed5": "{:.5f}", "fixed6": "{:.6f}", "sig12": "{:.12g}"}
THETA_I = (5.0, 30.0, 50.0, 70.0)


def _table(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rows (theta_i, theta_s signed) in degrees and the BRDF (a reference model + noise + an instrument floor)."""
    m = math.exp(rng.uniform(math.log(0.02), math.log(0.3)))
    rho_s, rho_d = rng.uniform(0.2, 1.0), math.exp(rng.uniform(math.log(1e-5), math.log(1e-2)))
    floor = math.exp(rng.uniform(math.log(1e-6), math.log(1e-3)))
    rows, vals = [], []
    for ti in THETA_I:
        ts = np.arange(-89.0, 90.0, 1.0)
        t_i = np.full(ts.shape, math.radians(ti))
        t_s, p_s = np.radians(np.abs(ts)), np.where(ts >= 0, math.pi, 0.0)
        f = ref.specular(t_i, np.zeros_like(t_i), t_s, p_s, lambda th, ph: ref.beckmann(th, m), rho_s, 1.5) + rho_d / math.pi
        f = f * np.exp(0.05 * rng.standard_normal(f.size)) + np.abs(floor * (1 + 0.15 * rng.standard_normal(f.size)))
        rows += [(ti, t) for t in ts]
        vals.append(f)
    return np.array(rows), np.concatenate(vals)


def _write(path: Path, rows: np.ndarray, text: list[str]) -> None:
    body = "".join(f"{ti:g} -180 {ts:g} 0 {v}\n" for (ti, ts), v in zip(rows, text))
    path.write_text("phi_i theta_i phi_o theta_o brdf\n" + body)


def _floor_rows(path: Path) -> tuple[int, list[int]]:
    try:
        t = read_merl_inplane(path)
    except FitInputError as e:  # e.g. a slice made only of one value: not this check's concern
        return -1, [str(e)[:80]]
    d = t.screening["dropped"].get("placeholder_floor")
    return (0, []) if d is None else (d["count"], d["lines"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200, help="tables per style")
    ap.add_argument("--seed", type=int, default=20261204)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    t0 = time.time()
    rng = np.random.default_rng(args.seed)
    out: dict = {"n_tables_per_style": args.n, "seed": args.seed, "styles": {}}
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "t.txt"
        stats = {s: {"false_positive_tables": 0, "false_positive_rows": 0, "detected": 0, "missed": 0,
                     "over_dropped": 0, "errors": 0} for s in STYLES}
        for _ in range(args.n):
            rows, b = _table(rng)
            k = int(rng.integers(3, 9))
            grazing = np.flatnonzero(np.abs(rows[:, 1]) >= 55)
            chosen = np.sort(rng.choice(grazing[::2], size=k, replace=False))  # every other row: never adjacent
            for style, fmt in STYLES.items():
                text = [fmt.format(v) for v in b]
                _write(f, rows, text)
                n_fp, _ = _floor_rows(f)
                st = stats[style]
                if n_fp < 0:
                    st["errors"] += 1
                    continue
                st["false_positive_tables"] += n_fp > 0
                st["false_positive_rows"] += n_fp
                low = min(float(x) for x in text if float(x) > 0)
                ph = 10.0 ** math.floor(math.log10(low * (1 - 1e-9)))
                placed = list(text)
                for i in chosen:
                    placed[i] = f"{ph:g}"
                _write(f, rows, placed)
                n, lines = _floor_rows(f)
                want = (chosen + 2).tolist()
                if n < 0:
                    st["errors"] += 1
                elif lines == want:
                    st["detected"] += 1
                elif set(want) <= set(lines):
                    st["over_dropped"] += 1
                else:
                    st["missed"] += 1
        out["styles"] = stats
    real: dict = {}
    real["merl_aluminium_inplane"] = _floor_rows(ROOT / "tests/data/real/merl_aluminium_inplane.txt")[0]
    for name in ("cornell_cayman_metallic", "cornell_krylon_blue"):
        n = 0
        for wl in ["mean", *np.arange(400.0, 701.0, 10.0)]:
            d = read_cornell_brdf(ROOT / f"tests/data/real/{name}.brdf", wl).screening["dropped"]
            n += d.get("placeholder_floor", {}).get("count", 0)
        real[f"{name} (mean and 31 wavelengths)"] = n
    for p in sorted((ROOT / "tests/data/satellites/starlink_v2mini_lab").glob("*.csv")):
        real[f"v2mini/{p.stem}"] = _floor_rows(p)[0]
    out["real_tables_floor_rows"] = real
    out["wall_s"] = time.time() - t0
    print(f"{args.n} tables per style (reference model + 5 % noise + an instrument floor of 1e-6 .. 1e-3 sr^-1):")
    print(f"{'style':8s} {'FP tables':>10s} {'FP rows':>8s} {'detected':>9s} {'missed':>7s} {'over':>5s} {'errors':>6s}")
    for s, st in out["styles"].items():
        print(f"{s:8s} {st['false_positive_tables']:10d} {st['false_positive_rows']:8d} {st['detected']:9d} "
              f"{st['missed']:7d} {st['over_dropped']:5d} {st['errors']:6d}")
    print("real tables, rows dropped as floor placeholders:", real)
    print(f"wall {out['wall_s']:.1f} s")
    if args.json:
        write_json_atomic(args.json, out)


if __name__ == "__main__":
    main()
