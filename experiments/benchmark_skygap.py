"""Wall time and peak memory of one sky gap diagnosis of the full Slingshot V2 Mini set (``brdfjax skygap``).

Runs ``python -m brdfjax skygap`` in a child process on ``configs/skygap_v2mini_slingshot.toml`` with every row
kept (``every = 1``: 1,583 observations; the shipped config keeps every 4th) and an empty compile cache, and
prints the wall time of the whole command (setup, diagnosis, held-out figures, predictive bands, the rerun of the
written model in observe), the diagnosis's own seconds, the child's peak resident memory
(``getrusage(RUSAGE_CHILDREN).ru_maxrss``) and the load average before and after (the box may be shared: the
figures are comparable only at a similar load).  Target: one diagnosis of a 1,500-observation set in under
10 minutes on the 2-core CPU.

    python3 experiments/benchmark_skygap.py [--every 1] [--out experiments/results/benchmark_skygap.json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

CONFIG = ROOT / "configs" / "skygap_v2mini_slingshot.toml"
TARGET_S = 600.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--every", type=int, default=1, help="keep every n-th row (1: the full set)")
    p.add_argument("--out", default=str(ROOT / "experiments" / "results" / "benchmark_skygap.json"))
    args = p.parse_args(argv)
    text = CONFIG.read_text()
    text = re.sub(r'(?m)^observe = "([^"]+)"', lambda m: f'observe = "{(CONFIG.parent / m.group(1)).resolve()}"', text)
    text = re.sub(r"(?m)^every = \d+", f"every = {args.every}", text)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "skygap_full.toml"
        cfg.write_text(text)
        env = dict(os.environ)
        env["BRDFJAX_CACHE_DIR"] = str(Path(tmp) / "cache")
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        out = Path(tmp) / "out"
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "brdfjax", "skygap", str(cfg), "--out", str(out), "--no-figures"],
                              env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()
        rss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0  # kB on Linux
        rec = {"config": str(CONFIG.relative_to(ROOT)), "every": args.every, "exit": proc.returncode, "wall_s": wall,
               "target_s": TARGET_S, "under_target": bool(proc.returncode == 0 and wall < TARGET_S),
               "peak_rss_mb": rss_mb, "load_before": load0, "load_after": load1, "cpus": os.cpu_count()}
        if proc.returncode == 0:
            s = json.loads((out / "skygap.json").read_text())
            rec.update({"rows": s["rows"], "diagnosis_s": s["seconds"], "refits": s["refits"],
                        "failed_refits": s["failed_refits"], "named_first": s["named_first"],
                        "path": [p["effect"] for p in s["path"]], "effects": s["effects_named"],
                        "stopped": s["stopped"], "heldout": s.get("heldout"),
                        "rerun_max_abs_diff_mag": s["rerun_check"]["max_abs_diff_mag"]})
        else:
            rec["stderr_tail"] = proc.stderr[-3000:]
    write_json_atomic(Path(args.out), rec)
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        print(f"brdfjax skygap failed (exit {proc.returncode}) after {wall:.1f} s")
        return 1
    print(f"brdfjax skygap on {rec['rows']} rows: {wall:.1f} s wall (diagnosis {rec['diagnosis_s']:.1f} s, "
          f"{rec['refits']} refits, {rec['failed_refits']} failed), peak RSS {rss_mb:.0f} MB; load "
          f"{load0[0]:.2f} -> {load1[0]:.2f}; target < {TARGET_S:.0f} s: {'met' if rec['under_target'] else 'missed'}")
    print(f"path {rec['path']}; held-out {rec['heldout']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
