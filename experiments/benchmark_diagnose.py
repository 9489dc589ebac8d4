"""Wall time and peak memory of ``brdfjax diagnose`` on the shipped example, cold (empty caches).

Runs ``python -m brdfjax diagnose CONFIG --out <tmp>`` in a child process with ``BRDFJAX_CACHE_DIR`` set to a
fresh temporary folder (no compiled or exported program from an earlier run) and prints the wall time, the
child's CPU seconds (user + system: comparable across loads), its peak resident memory (``getrusage(RUSAGE_CHILDREN).ru_maxrss``), the load average before and after
(the box may be shared: the figures are only comparable at a similar load), and the diagnosis's own outcome
(path, final explanation, held-out figures against the truth's).  Targets: <= 120 s wall and <= 1 GB
peak RSS on an idle 2-core box.

``--workers 1,2``: one cold run per value of ``[diagnose] workers`` (the refits run side by side), one after
the other, each in its own child (its own figures, from ``os.wait4``), with each run's ratios to the first.

    python3 experiments/benchmark_diagnose.py [--config configs/diagnose_withheld_diffraction.toml]
        [--out experiments/results/benchmark_diagnose.json] [--cache-dir DIR] [--diagnosis-out FILE]
        [--workers 1,2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402


def _config_with(config: str, key: str, value: str, folder: Path, tag: str) -> str:
    """A copy of ``config`` with ``[diagnose] key = value`` set (any line of the key replaced; the shipped example
    names no file by a relative path)."""
    lines = Path(config).read_text(encoding="utf-8").splitlines()
    out = [ln for ln in lines if not ln.strip().startswith(key)]
    at = next((i for i, ln in enumerate(out) if ln.strip() == "[diagnose]"), None)
    if at is None:
        out += ["", "[diagnose]", f"{key} = {value}"]
    else:
        out.insert(at + 1, f"{key} = {value}")
    path = folder / f"{tag}_{Path(config).name}"
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return str(path)


def _run(config: str, cache_dir: str | None, tmp: Path, tag: str) -> tuple[dict, Path]:
    """One ``brdfjax diagnose`` in its own child process: its wall time, CPU seconds and peak RSS."""
    env = dict(os.environ)
    env["BRDFJAX_CACHE_DIR"] = cache_dir or str(tmp / f"cache_{tag}")
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    out = tmp / f"diag_{tag}"
    log = tmp / f"log_{tag}.txt"
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "brdfjax", "diagnose", config, "--out", str(out), "--no-figures"],
                                env=env, stdout=fh, stderr=subprocess.STDOUT)
        _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    code = os.waitstatus_to_exitcode(status)
    rec = {"config": config, "cold": cache_dir is None, "exit": code, "wall_s": wall,
           "cpu_s": ru.ru_utime + ru.ru_stime,  # the child's CPU seconds: comparable across loads, unlike the wall
           "peak_rss_mb": ru.ru_maxrss / 1024.0,  # kB on Linux
           "load_before": load0, "load_after": load1, "cpus": os.cpu_count()}
    if code == 0:
        d = json.loads((out / "diagnosis.json").read_text())
        rec.update({
            "workers": d["settings"].get("workers"),
            "path": [(s["action"], s["effect"], s["chi2_reduced"], s["heldout_rms_log10"]) for s in d["path"]],
            "explained_by": d["explained_by"], "truth": d.get("truth"),
            "failed_refits": d["settings"].get("failed_refits"),
            "final_model_toml": (out / "final_model.toml").is_file(),
            "ranking": [(c["effect"], c["delta_bic"], c["ranked_by"]) for c in d["ranking"][:3]],
            "timings_s": d.get("timings_s"),
        })
    else:
        rec["stderr_tail"] = log.read_text(errors="replace")[-3000:]
    return rec, out


def _print(rec: dict) -> None:
    print(f"wall {rec['wall_s']:.1f} s, CPU {rec['cpu_s']:.1f} s, peak RSS {rec['peak_rss_mb']:.0f} MB, exit {rec['exit']}, "
          f"workers {rec.get('workers')}, load {rec['load_before'][0]:.1f} -> {rec['load_after'][0]:.1f} on "
          f"{os.cpu_count()} cores (targets: <= 120 s, <= 1024 MB on an idle 2-core box)")
    if rec["exit"] == 0:
        print("path:", " -> ".join(f"{'-' if a == 'remove' else ('+' if a == 'add' else '')}{e} ({c:.4g}; held-out "
                                    f"{'-' if h is None else format(h, '.3g')})" for a, e, c, h in rec["path"]))
        print("explained by:", rec["explained_by"], " failed refits:", rec["failed_refits"])
        print("ranked first:", ", ".join(f"{e} (delta BIC {g:.4g})" for e, g, _ in rec["ranking"]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "diagnose_withheld_diffraction.toml"))
    p.add_argument("--out", default=str(ROOT / "experiments" / "results" / "benchmark_diagnose.json"))
    p.add_argument("--cache-dir", default=None, help="reuse this cache folder (a warm run) instead of a fresh one")
    p.add_argument("--diagnosis-out", default=None,
                   help="also keep the run's diagnosis.json here (experiments/results/diagnose_shipped_example.json)")
    p.add_argument("--workers", default=None,
                   help="comma-separated [diagnose] workers values, one cold run each (default: the config's own)")
    args = p.parse_args(argv)
    try:
        workers = None if args.workers is None else [int(w) for w in args.workers.split(",") if w.strip()]
    except ValueError:
        p.error(f"--workers: comma-separated positive integers expected, got {args.workers!r}")
    if workers is not None and (not workers or min(workers) < 1):
        p.error(f"--workers: comma-separated positive integers expected, got {args.workers!r}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if workers is None:
            rec, out = _run(args.config, args.cache_dir, tmp, "config")
            runs = [rec]
        else:
            runs, out = [], None
            for w in workers:
                rec, o = _run(_config_with(args.config, "workers", str(w), tmp, f"workers{w}"), args.cache_dir, tmp, f"w{w}")
                runs.append(rec)
                out = out or o
        if args.diagnosis_out and runs[0]["exit"] == 0:
            write_json_atomic(args.diagnosis_out, json.loads((out / "diagnosis.json").read_text()))
    for rec in runs:
        _print(rec)
    if len(runs) > 1:
        base = runs[0]
        for rec in runs[1:]:
            rec["ratio_to_first"] = {k: rec[k] / base[k] for k in ("wall_s", "cpu_s", "peak_rss_mb")}
            print(f"workers {rec.get('workers')} / workers {base.get('workers')}: wall x{rec['ratio_to_first']['wall_s']:.3f}, "
                  f"CPU x{rec['ratio_to_first']['cpu_s']:.3f}, peak RSS x{rec['ratio_to_first']['peak_rss_mb']:.3f}")
    write_json_atomic(args.out, runs[0] if len(runs) == 1 else {"runs": runs})
    return max(r["exit"] for r in runs)


if __name__ == "__main__":
    raise SystemExit(main())
