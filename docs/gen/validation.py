"""Validation pages, generated from the measurement records in ``experiments/results/*.json``.

One page per area (seed reproduction, recovery, posterior calibration, the
withheld-effect benchmark, real data, performance).  Each record is listed
with the script that wrote it, the command that reproduces it (the one the
record stores, else the script's documented invocations), the commit it was
last measured on (``git log`` of the file), its figures where the script
writes any, and its headline numbers (top-level scalars and its ``summary``).
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "experiments" / "figures"

#: page slug -> (title, introduction, record-name prefixes)
PAGES: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "recovery": ("Recovery and diagnosis of shipped examples",
                 "Fits and diagnoses whose truth is known: the shipped synthetic examples and the NUTS/emcee check.",
                 ("diagnose_shipped_example", "shipped_sample_emcee_check", "benchmark_nuts")),
    "calibration": ("Posterior calibration",
                    "Coverage of the posterior intervals over independent noise realisations of the synthetic instrument.",
                    ("posterior_calibration",)),
    "withheld": ("Withheld-effect benchmark",
                 "The diagnosis given a base model without one effect of the truth: is the withheld effect found?",
                 ("withheld_",)),
    "real-data": ("Real data",
                  "Every model fitted to measured tables (Cornell, MERL), per incident angle, the MERL gap analysis, "
                  "and the row screening's floor placeholders on reference and real tables.",
                  ("real_data_fits", "merl_gap", "real_table_paths", "ftol_real_data", "table_floor_screening")),
    "performance": ("Performance",
                    "Timings and memory of frames, fits, sampling, light curves and studies. Wall times depend on the "
                    "machine and its load; each record keeps the load and CPU count it was measured at.",
                    ("benchmark_", "fit_memory", "batch_study", "lightcurve_glints", "device_check", "tour")),
    "sky": ("Satellites and the sky",
            "Predictions of real satellite observations from lab BRDFs, their bands, and the gap on the sky.",
            ("sky_", "observe_")),
    "other": ("Other measurements",
              "Every other record of `experiments/results/`: studies of one question each.",
              ()),
}

#: record-name prefix -> the script that writes it (longest prefix wins)
SCRIPTS = {
    "withheld_": "withheld_effects.py",
    "diagnose_shipped_example": "withheld_effects.py",
    "shipped_sample_emcee_check": "check_shipped_sample.py",
    "benchmark_lobe": "benchmark_frame.py",
    "benchmark_fit_ftol": "benchmark_fit.py",
    "real_data_fits": "real_data_fits.py",
}


def _script_for(stem: str) -> str | None:
    scripts = {p.name for p in (ROOT / "experiments").glob("*.py")}
    for prefix in sorted(SCRIPTS, key=len, reverse=True):
        if stem.startswith(prefix):
            return SCRIPTS[prefix]
    best = [s for s in scripts if stem.startswith(s[:-3])]
    return max(best, key=len) if best else None


def _documented_invocations(script: str) -> list[str]:
    path = ROOT / "experiments" / script
    try:
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    except (OSError, SyntaxError):
        return []
    return [" ".join(m.split()) for m in re.findall(rf"python3? experiments/{re.escape(script)}[^\n`]*", doc)]


def _commit(path: Path) -> str:
    try:
        out = subprocess.run(["git", "log", "-1", "--format=%h %cs", "--", str(path.relative_to(ROOT))],
                             cwd=ROOT, capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        out = ""
    return out or "(not committed)"


def _fmt(v: object) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, int):
        return str(v)
    s = str(v)
    return s if len(s) <= 80 else s[:77] + "..."


def _scalars(d: object, prefix: str = "", depth: int = 0) -> list[tuple[str, str]]:
    """Scalar leaves (and short lists of numbers) of a record, two levels deep."""
    out: list[tuple[str, str]] = []
    if isinstance(d, dict):
        for k, v in d.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if isinstance(v, (int, float, str, bool)) or v is None:
                out.append((key, _fmt(v)))
            elif isinstance(v, list) and v and len(v) <= 6 and all(isinstance(x, (int, float)) for x in v):
                out.append((key, "[" + ", ".join(_fmt(x) for x in v) + "]"))
            elif isinstance(v, dict) and depth < 1:
                out += _scalars(v, key, depth + 1)
    return out


def _is_scalar(v: object) -> bool:
    return isinstance(v, (int, float, str, bool)) or v is None


def _tables(data: dict, max_rows: int = 30, max_cols: int = 8) -> list[str]:
    """A table per top-level list of records or mapping of records (``rows``, ``fits``, ``trials``, ...)."""
    out: list[str] = []
    for key, value in data.items():
        if isinstance(value, list) and value and all(isinstance(r, dict) for r in value):
            rows = [(str(i), r) for i, r in enumerate(value)]
        elif isinstance(value, dict) and value and all(isinstance(r, dict) for r in value.values()):
            rows = [(str(k), r) for k, r in value.items()]
        else:
            continue
        cols: list[str] = []
        for _, r in rows:
            cols += [c for c, v in r.items() if _is_scalar(v) and c not in cols]
        cols = cols[:max_cols]
        if not cols:
            continue
        out += ["", f"`{key}`:", "", "| | " + " | ".join(f"`{c}`" for c in cols) + " |",
                "| --- " * (len(cols) + 1) + "|"]
        for name, r in rows[:max_rows]:
            cells = [_fmt(r.get(c, "")).replace("|", "/").replace("\n", " ") for c in cols]
            out.append(f"| `{name}` | " + " | ".join(cells) + " |")
        if len(rows) > max_rows:
            out.append(f"| ... | {len(rows) - max_rows} more rows in the record |" + " |" * (len(cols) - 1))
    return out


def _figures(stem: str) -> list[Path]:
    names = {
        "real_data_fits_": lambda s: [f"real_data_{s.removeprefix('real_data_fits_')}.png",
                                      f"fit_{s.removeprefix('real_data_fits_')}.png"],
        "lightcurve_glints": lambda s: ["lightcurve_box_wing.png", "lightcurve_glint_map.png"],
        "benchmark_nuts": lambda s: ["posterior_degeneracy_rho_s1_n1.png", "posterior_degeneracy_rho_s1_n1_two_angles.png"],
    }
    for prefix, f in names.items():
        if stem.startswith(prefix):
            return [FIGURES / n for n in f(stem) if (FIGURES / n).exists()]
    return []


def records(slug: str) -> list[Path]:
    """The records a page shows: those whose names start with its prefixes; ``other`` shows the rest."""
    every = sorted(RESULTS.glob("*.json"))
    if PAGES[slug][2]:
        return [p for p in every if p.stem.startswith(PAGES[slug][2])]
    claimed = tuple(x for v in PAGES.values() for x in v[2])
    return [p for p in every if not p.stem.startswith(claimed)]


def figures() -> list[Path]:
    """Every figure of ``experiments/figures`` (the hook copies them into the site's ``figures/``)."""
    return sorted(FIGURES.glob("*.png"))


def page(slug: str, max_rows: int = 30) -> str:
    title, intro, _ = PAGES[slug]
    lines = [f"# {title}", "", intro, "",
             "Generated from `experiments/results/` by `docs/gen/validation.py`. These are measurement records: "
             "each names the commit it was last measured on, so the code may have moved on since.", ""]
    for path in records(slug):
        data = json.loads(path.read_text())
        script = _script_for(path.stem)
        lines += [f"## {path.stem}", "", f"- record: `experiments/results/{path.name}`",
                  f"- measured at commit: `{_commit(path)}`"]
        stored = data.get("command") or data.get("argv") if isinstance(data, dict) else None
        if stored:
            cmd = stored if isinstance(stored, str) else " ".join(map(str, stored))
            lines += ["- command (stored in the record):", "", "    ```bash", f"    {cmd}", "    ```", ""]
        elif script:
            inv = _documented_invocations(script) or [f"python3 experiments/{script}"]
            lines += [f"- written by `experiments/{script}`; its documented invocations (this record's exact options "
                      "are those in its `settings`/`note` where it keeps them):", "", "    ```bash"]
            lines += [f"    {c}" for c in inv[:4]] + ["    ```", ""]
        for fig in _figures(path.stem):
            lines += ["", f"![{fig.stem}](../figures/{fig.name})", ""]
        rows = []
        if isinstance(data, dict):
            rows = _scalars({k: v for k, v in data.items() if k not in ("command", "argv")})
        if rows:
            lines += ["", "| quantity | value |", "| --- | --- |"]
            lines += [f"| `{k}` | {v.replace('|', '/')} |" for k, v in rows[:max_rows]]
            if len(rows) > max_rows:
                lines.append(f"| ... | {len(rows) - max_rows} more in the record |")
        if isinstance(data, dict):
            lines += _tables(data)
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(page(sys.argv[1] if len(sys.argv) > 1 else "real-data"))
