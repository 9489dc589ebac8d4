"""Wall time and peak memory of ``brdfjax diagnose`` on the shipped example, cold (empty caches).

Runs ``python -m brdfjax diagnose CONFIG --out <tmp>`` in a child process with ``BRDFJAX_CACHE_DIR`` set to a
fresh temporary folder (no compiled or exported program from an earlier run) and prints the wall time, the
child's CPU seconds (user + system: comparable across loads), its peak resident memory (``getrusage(RUSAGE_CHILDREN).ru_maxrss``), the load average before and after
(the box may be shared: the figures are only comparable at a similar load), and the diagnosis's own outcome
(path, final explanation, held-out figures against the truth's).  Targets: <= 120 s wall and <= 1 GB
peak RSS on an idle 2-core box.

    python3 experiments/benchmark_diagnose.py [--config configs/diagnose_withheld_diffraction.toml]
        [--out experiments/results/benchmark_diagnose.json] [--cache-dir DIR] [--diagnosis-out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "diagnose_withheld_diffraction.toml"))
    p.add_argument("--out", default=str(ROOT / "experiments" / "results" / "benchmark_diagnose.json"))
    p.add_argument("--cache-dir", default=None, help="reuse this cache folder (a warm run) instead of a fresh one")
    p.add_argument("--diagnosis-out", default=None,
                   help="also keep the run's diagnosis.json here (experiments/results/diagnose_shipped_example.json)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ)
        env["BRDFJAX_CACHE_DIR"] = args.cache_dir or str(Path(tmp) / "cache")
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        out = Path(tmp) / "diag"
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "brdfjax", "diagnose", args.config, "--out", str(out), "--no-figures"],
                              env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        rss_mb = ru.ru_maxrss / 1024.0  # kB on Linux
        cpu = ru.ru_utime + ru.ru_stime  # the child's CPU seconds: comparable across loads, unlike the wall time
        rec = {"config": args.config, "cold": args.cache_dir is None, "exit": proc.returncode, "wall_s": wall,
               "cpu_s": cpu, "peak_rss_mb": rss_mb, "load_before": load0, "load_after": load1, "cpus": os.cpu_count()}
        if proc.returncode == 0:
            d = json.loads((out / "diagnosis.json").read_text())
            if args.diagnosis_out:
                write_json_atomic(args.diagnosis_out, d)
            rec.update({
                "path": [(s["action"], s["effect"], s["chi2_reduced"], s["heldout_rms_log10"]) for s in d["path"]],
                "explained_by": d["explained_by"], "truth": d.get("truth"),
                "failed_refits": d["settings"].get("failed_refits"),
                "final_model_toml": (out / "final_model.toml").is_file(),
                "ranking": [(c["effect"], c["delta_bic"], c["ranked_by"]) for c in d["ranking"][:3]],
                "timings_s": d.get("timings_s"),
            })
        else:
            rec["stderr_tail"] = proc.stderr[-3000:]
    write_json_atomic(args.out, rec)
    print(f"wall {wall:.1f} s, CPU {cpu:.1f} s, peak RSS {rss_mb:.0f} MB, exit {proc.returncode}, load {load0[0]:.1f} -> {load1[0]:.1f} "
          f"on {os.cpu_count()} cores (targets: <= 120 s, <= 1024 MB on an idle 2-core box)")
    if proc.returncode == 0:
        print("path:", " -> ".join(f"{'-' if a == 'remove' else ('+' if a == 'add' else '')}{e} ({c:.4g}; held-out "
                                    f"{'-' if h is None else format(h, '.3g')})" for a, e, c, h in rec["path"]))
        print("explained by:", rec["explained_by"], " failed refits:", rec["failed_refits"])
        print("ranked first:", ", ".join(f"{e} (delta BIC {g:.4g})" for e, g, _ in rec["ranking"]))
    return proc.returncode


if __name__ == "__main__":
    raise SystemExit(main())
