"""``brdfjax batch STUDY.toml --out DIR``: many fit / sample / diagnose / synthesize jobs, on Ray or a process pool.

A study is a TOML file::

    [batch]
    backend = "auto"      # auto (Ray if installed, else a local pool of job processes), ray, process, serial
    address = ""          # Ray: "" starts a local instance; "auto" or "ray://host:10001" joins a cluster
    workers = 2           # concurrent jobs (the local Ray instance's CPUs, or the pool's processes)

    [[jobs]]
    name = "fit_20deg"    # unique; the job's outputs go to DIR/fit_20deg/
    command = "fit"       # fit, sample, diagnose or synthesize (any brdfjax subcommand that takes --out)
    config = "fit_20.toml"  # relative to the study file
    args = ["--no-figures"]  # more command-line arguments (optional)

Each job runs ``python -m brdfjax COMMAND CONFIG --out DIR/NAME ARGS`` in a
fresh process (a process-wide switch such as 64-bit JAX cannot leak from one
job to the next; JAX's persistent compilation cache makes the repeated
start-up cheap).  When a job ends, the driver writes ``DIR/jobs/NAME.json``
atomically: the job, its exit code, wall time and the tail of its output.  A
study that is run again (after a kill, a crash, a failed job) skips every job
whose result file says it succeeded with the same job description; the rest
run again.  Each result file also records the job's problem fingerprint
(:mod:`brdfjax.io.fingerprint`: the command line and the SHA-256 of its
config file): a job that succeeded under another config is not silently
counted as done, the rerun is refused naming the job and what differs.
Progress is shown as a bar on stderr.

Ray is an optional extra (``pip install brdfjax[cluster]``): on a cluster the
study folder and the configs must be on a filesystem every node sees.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator
from tqdm import tqdm

from .config import ConfigError, StrictModel, check_choice, read_toml, validate
from .io import write_json_atomic
from .io.fingerprint import check_resume, file_digest, value_digest
from .runtime.errors import InputError

__all__ = ["StudyError", "Job", "Study", "load_study", "run_study", "add_arguments", "run", "BACKENDS"]

BACKENDS = ("auto", "ray", "process", "serial")
COMMANDS = ("fit", "sample", "diagnose", "synthesize", "simulate", "reduce")


class StudyError(InputError):
    """A study file that cannot be run (the message names the file and the key)."""


class Job(StrictModel):
    name: str = Field(description="unique job name: its outputs go to DIR/NAME/, its result to DIR/jobs/NAME.json")
    command: str = Field(description="the brdfjax subcommand: " + ", ".join(COMMANDS))
    config: str | None = Field(None, description="the command's config file, relative to the study file")
    args: list[str] = Field(default_factory=list, description="more command-line arguments")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v or any(c in v for c in "/\\") or v.startswith(".") or v == "jobs":
            raise ValueError("a non-empty file name (no '/', not starting with '.', not 'jobs')")
        return v

    @field_validator("command")
    @classmethod
    def _command(cls, v: str) -> str:
        return check_choice("command", v, COMMANDS)


class BatchSection(StrictModel):
    backend: str = Field("auto", description="auto, ray, process or serial")
    address: str = Field("", description="Ray address ('' = a local instance)")
    workers: int = Field(2, ge=1, description="concurrent jobs")

    @field_validator("backend")
    @classmethod
    def _backend(cls, v: str) -> str:
        return check_choice("backend", v, BACKENDS)


class Study(StrictModel):
    batch: BatchSection = Field(default_factory=BatchSection, description="the [batch] table: where and how many jobs run")
    jobs: list[Job] = Field(description="one [[jobs]] table per job")


def load_study(path: str | os.PathLike) -> tuple[Study, Path]:
    """Read and validate a study file; relative config paths are resolved against its folder."""
    p = Path(path)
    try:  # the project's TOML reader and validation-error describer (file, dotted key, what was expected)
        study = validate(Study, read_toml(p, "study file"), str(p))
    except ConfigError as e:
        raise StudyError(str(e)) from None
    names = [j.name for j in study.jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise StudyError(f"{p}: jobs: names must be unique; repeated: {', '.join(dup)}")
    for i, j in enumerate(study.jobs):
        if j.config is not None and not (p.parent / j.config).is_file():
            raise StudyError(f"{p}: jobs[{i}].config: no such file: {p.parent / j.config}")
    return study, p.parent


def _describe(job: Job, base: Path, out: Path) -> dict[str, Any]:
    """The job as it runs (absolute paths): what a result file must match to be skipped."""
    argv = [job.command]
    if job.config is not None:
        argv.append(str((base / job.config).resolve()))
    argv += ["--out", str((out / job.name).resolve()), *job.args]
    fingerprint = {"argv": value_digest(argv)}
    if job.config is not None:
        fingerprint["config_file"] = file_digest(base / job.config)
    return {"name": job.name, "argv": argv, "fingerprint": fingerprint}


def run_job(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one job in a fresh ``python -m brdfjax`` process; returns its record (picklable, for any backend)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "brdfjax", *spec["argv"]], capture_output=True, text=True)
    return {
        **spec,
        "exit_code": proc.returncode,
        "ok": proc.returncode == 0,
        "wall_s": time.perf_counter() - t0,
        "host": os.uname().nodename,
        "output_tail": (proc.stdout + proc.stderr)[-4000:],
    }


def _done(path: Path, spec: dict[str, Any]) -> bool:
    """Whether the job's result file says it succeeded with this description; a success under another
    config (its fingerprint differs) is refused, naming the difference."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    if not (bool(old.get("ok")) and old.get("argv") == spec["argv"]):
        return False
    check_resume(
        path, old.get("fingerprint"), spec["fingerprint"],
        f"Job '{spec['name']}' finished under another problem: remove {path} to run it again with this one, "
        "or run the study into another --out.",
    )
    return True


def _ray():
    try:
        import ray  # noqa: PLC0415 -- optional extra [cluster]: imported only when the Ray backend is used
    except ImportError:
        return None
    return ray


def _run_ray(specs, workers: int, address: str) -> Iterable[dict[str, Any]]:
    ray = _ray()
    if ray is None:
        raise StudyError("backend 'ray' needs Ray: pip install 'brdfjax[cluster]'")
    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(run_job)
        pending = [task.remote(s) for s in specs]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            yield ray.get(ready[0])
    finally:
        if started:
            ray.shutdown()


def _run_pool(specs, workers: int) -> Iterable[dict[str, Any]]:
    # Every job already is its own process (run_job starts it), so a pool of threads that wait on them is
    # the process pool: no fork of this (multithreaded, JAX-importing) process, no pickling.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for fut in as_completed([pool.submit(run_job, s) for s in specs]):
            yield fut.result()


@dataclass
class StudyReport:
    backend: str
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    wall_s: float = 0.0


def run_study(
    study_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    backend: str | None = None,
    address: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    on_result: Callable[[dict[str, Any]], None] | None = None,
) -> StudyReport:
    """Run the jobs of a study not yet done in ``out_dir``; one result file per job (see the module docstring)."""
    t0 = time.perf_counter()
    study, base = load_study(study_path)
    b = study.batch
    backend = backend or b.backend
    if backend not in BACKENDS:
        raise StudyError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    address = b.address if address is None else address
    workers = workers or b.workers
    if backend == "auto":
        backend = "ray" if _ray() is not None else "process"
    out = Path(out_dir)
    results = out / "jobs"
    results.mkdir(parents=True, exist_ok=True)
    report = StudyReport(backend)
    specs = []
    for job in study.jobs:
        spec = _describe(job, base, out)
        if _done(results / f"{job.name}.json", spec):
            report.skipped.append(job.name)
        else:
            specs.append(spec)
    if backend == "ray":
        stream = _run_ray(specs, workers, address)
    elif backend == "process":
        stream = _run_pool(specs, workers)
    else:
        stream = (run_job(s) for s in specs)
    bar = tqdm(total=len(study.jobs), initial=len(report.skipped), desc=f"study ({backend})", unit="job",
               disable=not progress, file=sys.stderr)
    with bar:
        for rec in stream:
            write_json_atomic(results / f"{rec['name']}.json", rec)
            (report.ran if rec["ok"] else report.failed).append(rec["name"])
            if on_result is not None:
                on_result(rec)
            bar.update(1)
            if not rec["ok"]:
                bar.write(f"job {rec['name']} failed (exit {rec['exit_code']}): {rec['output_tail'][-300:]}")
    report.wall_s = time.perf_counter() - t0
    write_json_atomic(out / "study.json", {
        "study": str(Path(study_path).resolve()), "backend": backend, "jobs": [j.name for j in study.jobs],
        "ran": report.ran, "skipped": report.skipped, "failed": report.failed, "wall_s": report.wall_s,
    })
    return report


# --- CLI --------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("study", metavar="STUDY", help="a study file (TOML: [batch] and [[jobs]])")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: DIR/NAME/ per job, DIR/jobs/NAME.json")
    p.add_argument("--backend", choices=BACKENDS, default=None, help="override [batch].backend")
    p.add_argument("--address", default=None, help="Ray cluster address (override [batch].address)")
    p.add_argument("--workers", type=int, default=None, help="concurrent jobs (override [batch].workers)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Exit 0 when every job succeeded, 1 when some failed, 2 for a bad study file."""
    try:
        report = run_study(args.study, args.out, backend=args.backend, address=args.address, workers=args.workers,
                           progress=not args.no_progress)
    except StudyError as e:
        print(f"brdfjax batch: error: {e}", file=sys.stderr)
        return 2
    print(
        f"brdfjax batch: {len(report.ran)} ran, {len(report.skipped)} skipped (done before), {len(report.failed)} failed "
        f"on {report.backend} in {report.wall_s:.1f} s; results in {Path(args.out) / 'jobs'}",
        file=sys.stderr,
    )
    return 1 if report.failed else 0
