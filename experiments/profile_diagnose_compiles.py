"""Where a cold ``brdfjax diagnose`` spends its time: compilations counted and timed, in one process.

Runs the diagnose command in this process with ``BRDFJAX_CACHE_DIR`` set to a fresh temporary folder (cold) and
records, through ``jax.monitoring``, every backend compilation (new or read back from the persistent cache),
trace and lowering, with their summed durations, the exported programs by name (``brdfjax.runtime.export_cache``:
one per program and model shape) with the summed wall time of each one's first call (trace, export and
compilation), the process's CPU seconds and its peak resident memory.  The counts and the
CPU seconds do not depend on the machine's load, unlike the wall time (``experiments/benchmark_diagnose.py``
measures that, in a child process).

    python3 experiments/profile_diagnose_compiles.py [--config configs/diagnose_withheld_diffraction.toml]
        [--out experiments/results/diagnose_compiles.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "diagnose_withheld_diffraction.toml"))
    p.add_argument("--out", default=str(ROOT / "experiments" / "results" / "diagnose_compiles.json"))
    args = p.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="diagnose_compiles")
    os.environ["BRDFJAX_CACHE_DIR"] = str(Path(tmp) / "cache")
    import jax
    import jax.monitoring as mon

    dur: dict[str, float] = collections.defaultdict(float)
    cnt: collections.Counter = collections.Counter()
    events: collections.Counter = collections.Counter()
    mon.register_event_duration_secs_listener(lambda name, secs, **kw: (dur.__setitem__(name, dur[name] + secs),
                                                                          cnt.update([name])))
    mon.register_event_listener(lambda name, **kw: events.update([name]))

    import brdfjax.runtime.export_cache as ec
    from brdfjax.cli import main as cli_main
    from brdfjax.runtime.atomic import write_json_atomic

    programs: dict[str, str] = {}
    key = ec._key

    def named_key(name, leaves, treedef, switches):
        k, dyn = key(name, leaves, treedef, switches)
        programs.setdefault(k, name)
        return k, dyn

    ec._key = named_key
    # each exported program's first call (its trace, export and compilation) timed, by name
    first_call: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    call = ec.exported_call

    def timed_call(name, raw, plain, args, switches=()):
        n0 = len(programs)
        t = time.perf_counter()
        out = jax.block_until_ready(call(name, raw, plain, args, switches))
        if len(programs) > n0:  # a key not seen before: this call built the program
            first_call[name][0] += 1
            first_call[name][1] += time.perf_counter() - t
        return out

    ec.exported_call = timed_call
    out = Path(tmp) / "diag"
    load0 = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    rc = cli_main(["diagnose", args.config, "--out", str(out), "--no-figures"])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rec = {
        "config": args.config, "exit": rc, "cpu_s": cpu, "wall_s": wall,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "load_before": load0, "load_after": os.getloadavg(), "cpus": os.cpu_count(),
        "durations_s": {k.rsplit("/", 1)[-1]: round(v, 2) for k, v in dur.items()},
        "counts": {k.rsplit("/", 1)[-1]: v for k, v in cnt.items()},
        "events": {k.rsplit("/", 1)[-1]: v for k, v in events.items()},
        "exported_programs": dict(collections.Counter(programs.values())),
        "first_calls_s": {k: {"programs": v[0], "seconds": round(v[1], 2)} for k, v in first_call.items()},
        "export_stats": ec.stats(),
    }
    if rc == 0:
        d = json.loads((out / "diagnosis.json").read_text())
        rec.update({"path": [(s["action"], s["effect"], s["chi2_reduced"], s["heldout_rms_log10"]) for s in d["path"]],
                    "explained_by": d["explained_by"], "n_trials": d["settings"]["n_trials"],
                    "timings_s": d.get("timings_s")})
    write_json_atomic(args.out, rec)
    comp = rec["durations_s"].get("backend_compile_duration", 0.0)
    print(f"CPU {cpu:.1f} s, wall {wall:.1f} s at load {load0[0]:.1f}, peak RSS {rec['peak_rss_mb']:.0f} MB; "
          f"{rec['counts'].get('backend_compile_duration', 0)} backend compilations ({rec['events'].get('cache_misses', 0)} "
          f"new, {rec['events'].get('cache_hits', 0)} read back), {comp:.1f} s compiling; exported programs "
          f"{rec['exported_programs']}; first calls {rec['first_calls_s']}")
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
