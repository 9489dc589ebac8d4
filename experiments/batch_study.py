"""A study of 20 fits through ``brdfjax batch``: Ray on the local machine, a real kill and a resume, against the serial loop.

Issue 19: "A study of 20 fits through Ray on the local machine: all results
correct, a killed study resumes without redoing finished jobs, and the wall
time against the serial loop reported."

The data are made here by the NumPy reference (``brdfjax/reference.py``), not
by brdfjax's own model: 20 in-plane goniometer tables (theta_i = 20, 40,
60 deg, theta_s every 0.5 deg near the mirror and every 2 deg elsewhere) of
a Beckmann specular lobe (Eq 70, n = 1.5) plus a Lambertian floor, with
known truths drawn per table (m in [0.03, 0.1], rho_s in [0.2, 1],
rho_d in [0.02, 0.2]) and 3 % log-normal noise stated in a ``sigma_rel``
column.  Each job fits m, rho_s and rho_d from a common start with
``brdfjax fit``.

"Correct" is checked per job and pooled: the fit converged, chi^2_red is
within the 99.9 % band of its chi^2 distribution, and the pulls
``(fit - truth) / sigma`` of the 60 fitted values have mean ~ 0 and standard
deviation ~ 1 (no job more than 4.5 sigma off).

Runs, each into its own folder with its own fresh compilation cache (so each
includes the same one-off compile):

1. ``serial``: the 20 jobs one after another (``backend = "serial"``);
2. ``ray``: a local Ray instance of ``--workers`` CPUs;
3. ``ray`` killed: the ``brdfjax batch`` process is started, SIGKILLed (its
   whole process group: driver, Ray and running jobs) once ``--kill-after``
   job records exist, and the same command is run again: every job whose
   record existed before the kill must be skipped, the rest run, and the 20
   results must be correct.

Prints the wall times and the speed-up; ``--json`` writes them.

    python3 experiments/batch_study.py                     # ~3-5 min on the 2-core box
    python3 experiments/batch_study.py --json experiments/results/batch_study.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax import reference as ref  # noqa: E402

N_JOBS = 20
NOISE = 0.03
N_INDEX = 1.5

CONFIG = """precision = "float64"

[[data.tables]]
path = "{table}"
format = "table"
columns = {{ theta_i = "theta_i", theta_s = "theta_s", phi_s = "phi_s", brdf = "brdf", sigma_rel = "sigma_rel" }}
angle_unit = "deg"

[model.terms.spec]
kind = "specular"
distribution = "beckmann"
shadowing = "none"           # the seed's Eq 70 form, which the reference tables are made with
normalisation = "seed"
fresnel = "q_factor"
params = {{ m = 0.08, rho_s = 0.5, n = {n} }}

[model.terms.diffuse]
kind = "lambertian"
params = {{ rho_d = 0.08 }}

[params]
"spec.m" = {{ lower = 1e-3, upper = 0.5 }}
"spec.rho_s" = "free"
"diffuse.rho_d" = "free"

[fit]
first_stage = "none"

[output]
figures = false
"""


def make_tables(folder: Path, seed: int = 19) -> list[dict]:
    """20 reference tables with known truths; returns the truths."""
    rng = np.random.default_rng(seed)
    truths = []
    for j in range(N_JOBS):
        t = {"spec.m": float(rng.uniform(0.03, 0.10)), "spec.rho_s": float(rng.uniform(0.2, 1.0)),
             "diffuse.rho_d": float(rng.uniform(0.02, 0.2))}
        rows = []
        for ti in (20.0, 40.0, 60.0):
            near = np.arange(ti - 15.0, ti + 15.01, 0.5)
            far = np.arange(-80.0, 80.01, 2.0)
            ts_signed = np.unique(np.round(np.concatenate([near, far]), 6))
            ts_signed = ts_signed[np.abs(ts_signed) <= 80.0]
            # signed in-plane angle: positive = forward (mirror side, azimuth 180 deg), negative = source side
            ts = np.abs(ts_signed)
            ps = np.where(ts_signed >= 0, 180.0, 0.0)
            args = (np.deg2rad(ti), 0.0, np.deg2rad(ts), np.deg2rad(ps))
            f = ref.specular(*args, lambda th, ph, m=t["spec.m"]: ref.beckmann(th, m), t["spec.rho_s"], N_INDEX)
            f = f + ref.lambertian(t["diffuse.rho_d"])
            d = f * np.exp(NOISE * rng.standard_normal(f.shape))
            rows += [(ti, a, p, v, NOISE) for a, p, v in zip(ts, ps, d)]
        path = folder / f"table_{j:02d}.csv"
        with open(path, "w") as fh:
            fh.write("theta_i,theta_s,phi_s,brdf,sigma_rel\n")
            fh.writelines(f"{a:.6f},{b:.6f},{c:.1f},{v:.10e},{s}\n" for a, b, c, v, s in rows)
        (folder / f"fit_{j:02d}.toml").write_text(CONFIG.format(table=path.name, n=N_INDEX))
        truths.append(t)
    return truths


def write_study(folder: Path, backend: str, workers: int) -> Path:
    jobs = [f'[[jobs]]\nname = "fit_{j:02d}"\ncommand = "fit"\nconfig = "fit_{j:02d}.toml"\nargs = ["--no-figures", "--quiet"]\n'
            for j in range(N_JOBS)]
    path = folder / f"study_{backend}.toml"
    path.write_text(f'[batch]\nbackend = "{backend}"\nworkers = {workers}\n\n' + "\n".join(jobs))
    return path


def _env(cache: Path) -> dict:
    env = dict(os.environ)
    env.pop("BRDFJAX_NO_CACHE", None)
    env["BRDFJAX_CACHE_DIR"] = str(cache)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def run_batch(study: Path, out: Path, cache: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "brdfjax", "batch", str(study), "--out", str(out), "--quiet"],
                       env=_env(cache), capture_output=True, text=True)
    if p.returncode != 0:
        print(p.stdout[-2000:], p.stderr[-2000:], file=sys.stderr)
    return time.perf_counter() - t0, p.returncode


def records(out: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((out / "jobs").glob("*.json"))}


def check(out: Path, truths: list[dict]) -> dict:
    """Every job converged, chi^2_red plausible, pulls ~ N(0, 1)."""
    from scipy import stats

    pulls, bad = [], []
    for j, t in enumerate(truths):
        res = json.loads((out / f"fit_{j:02d}" / "result.json").read_text())
        dof = res["dof"]
        lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], dof) / dof
        if not res["converged"] or not (lo <= res["chi2_reduced"] <= hi):
            bad.append(f"fit_{j:02d}: converged={res['converged']} chi2_red={res['chi2_reduced']:.3f} (band {lo:.2f}-{hi:.2f})")
        for name, truth in t.items():
            p = res["parameters"][name]
            pulls.append((p["value"] - truth) / p["sigma"])
    pulls = np.asarray(pulls)
    ok = not bad and abs(pulls.mean()) < 0.5 and 0.6 < pulls.std() < 1.5 and np.abs(pulls).max() < 4.5
    return {"ok": bool(ok), "bad_jobs": bad, "pull_mean": float(pulls.mean()), "pull_std": float(pulls.std()),
            "pull_max_abs": float(np.abs(pulls).max()), "n_pulls": int(pulls.size)}


def killed_run(study: Path, out: Path, cache: Path, kill_after: int) -> dict:
    """Start the study, SIGKILL its process group once ``kill_after`` records exist, then run it again."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "brdfjax", "batch", str(study), "--out", str(out), "--quiet"],
                         env=_env(cache), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    while time.perf_counter() - t0 < 1800:
        if len(list((out / "jobs").glob("*.json"))) >= kill_after or p.poll() is not None:
            break
        time.sleep(0.2)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    t_kill = time.perf_counter() - t0
    time.sleep(1.0)  # let the killed processes' files settle
    before = {n for n, r in records(out).items() if r.get("ok")}
    mtimes = {n: (out / n / "result.json").stat().st_mtime_ns for n in before}
    t_resume, rc = run_batch(study, out, cache)
    summary = json.loads((out / "study.json").read_text())
    redone = sorted(n for n in before if (out / n / "result.json").stat().st_mtime_ns != mtimes[n])
    return {"killed_after_s": t_kill, "finished_before_kill": sorted(before), "resume_s": t_resume, "resume_exit": rc,
            "resume_skipped": summary["skipped"], "resume_ran": summary["ran"], "redone": redone,
            "resume_ok": rc == 0 and sorted(summary["skipped"]) == sorted(before) and not redone
            and len(summary["ran"]) == N_JOBS - len(before)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--kill-after", type=int, default=8, help="job records to wait for before the kill")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--keep", type=Path, help="work in this folder (kept) instead of a temporary one")
    args = ap.parse_args(argv)
    try:
        import ray  # noqa: F401
    except ImportError:
        print("Ray is not installed (pip install 'brdfjax[cluster]'): this experiment needs it", file=sys.stderr)
        return 2
    work = args.keep or Path(tempfile.mkdtemp(prefix="brdfjax_batch_"))
    work.mkdir(parents=True, exist_ok=True)
    truths = make_tables(work)
    load = os.getloadavg()
    out = {"n_jobs": N_JOBS, "workers": args.workers, "cpus": os.cpu_count(), "load_before": load}

    serial = write_study(work, "serial", 1)
    t_serial, rc = run_batch(serial, work / "out_serial", work / "cache_serial")
    out["serial"] = {"wall_s": t_serial, "exit": rc, **check(work / "out_serial", truths)}
    print(f"serial loop   : {t_serial:7.1f} s  exit {rc}  results correct: {out['serial']['ok']}")

    ray_study = write_study(work, "ray", args.workers)
    t_ray, rc = run_batch(ray_study, work / "out_ray", work / "cache_ray")
    out["ray"] = {"wall_s": t_ray, "exit": rc, **check(work / "out_ray", truths)}
    print(f"ray ({args.workers} CPUs)  : {t_ray:7.1f} s  exit {rc}  results correct: {out['ray']['ok']}  "
          f"speed-up over serial {t_serial / t_ray:.2f}x")

    k = killed_run(ray_study, work / "out_killed", work / "cache_killed", args.kill_after)
    k.update(check(work / "out_killed", truths))
    out["ray_killed"] = k
    print(f"ray, killed   : SIGKILL after {k['killed_after_s']:.1f} s with {len(k['finished_before_kill'])} jobs done; "
          f"resume {k['resume_s']:.1f} s skipped {len(k['resume_skipped'])}, ran {len(k['resume_ran'])}, "
          f"redone {len(k['redone'])}; resume correct: {k['resume_ok']}; results correct: {k['ok']}")
    out["pulls"] = {m: {key: out[m][key] for key in ("pull_mean", "pull_std", "pull_max_abs")} for m in ("serial", "ray")}
    out["load_after"] = os.getloadavg()
    print(f"pulls (serial): mean {out['serial']['pull_mean']:+.3f}, std {out['serial']['pull_std']:.3f}, "
          f"max |pull| {out['serial']['pull_max_abs']:.2f} over {out['serial']['n_pulls']} fitted values")
    print(f"load average before {load[0]:.1f}, after {out['load_after'][0]:.1f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)
    good = out["serial"]["ok"] and out["ray"]["ok"] and k["ok"] and k["resume_ok"]
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
