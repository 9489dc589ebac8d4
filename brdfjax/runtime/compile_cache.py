"""JAX's persistent compilation cache for the command line: compile once per machine, not once per process.

Every ``brdfjax`` process used to trace and compile its programs again (a
cold synthetic fit spent about a third of its time there).  The CLI turns on
JAX's persistent compilation cache (``jax_compilation_cache_dir``) before it
runs a command, so the second process on the same machine loads the compiled
executables from disk.  Shapes are kept stable across frames (stacked frames
are padded to a multiple of :data:`brdfjax.fit._problem.PAD_MULTIPLE`,
renders use fixed-size row chunks), so one executable serves many data sets.

The traced programs of a fit are kept beside the executables (``export/``, :mod:`brdfjax.runtime.export_cache`),
so a later process skips their tracing as well.

Where: ``$BRDFJAX_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/brdfjax/jax``
(``~/.cache/brdfjax/jax``).  Off: ``BRDFJAX_NO_CACHE=1`` or ``brdfjax
--no-cache``.  The library never turns it on by itself (the switch is
process-wide); call :func:`enable_compilation_cache` to opt in.
"""

from __future__ import annotations

import ctypes
import gc
import os
import sys
from pathlib import Path

import jax

from . import export_cache
from .export_cache import activate as activate_export

__all__ = ["cache_dir", "cache_disabled", "enable_compilation_cache", "map_count", "maps_near_limit", "persistent_cache_on",
           "release_compiled", "resident_mb"]


def cache_dir() -> Path:
    """The cache folder (see the module docstring).

    The XDG rule is written out rather than taken from ``platformdirs``: it is
    three lines, and the cache must land where JAX users look on Linux.
    """
    explicit = os.environ.get("BRDFJAX_CACHE_DIR")
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "brdfjax" / "jax"


def cache_disabled() -> bool:
    """True when ``BRDFJAX_NO_CACHE`` is set to anything but ``""``/``0``."""
    return os.environ.get("BRDFJAX_NO_CACHE", "").strip() not in ("", "0")


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`cache_dir`).

    Returns the folder, or None when ``BRDFJAX_NO_CACHE`` says no or the
    folder cannot be created (the run then simply compiles, as without a cache).
    """
    if cache_disabled():
        return None
    folder = Path(path) if path is not None else cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # Cache every program: the fit's small ones add up, and loading is cheaper than any compile here.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # and the traced programs of a fit, so that a later process skips tracing them too (off alone with
    # BRDFJAX_NO_EXPORT=1): brdfjax.runtime.export_cache
    activate_export(folder / "export")
    return folder


def persistent_cache_on() -> bool:
    """Whether JAX's persistent compilation cache is on in this process (a folder is set and the cache enabled)."""
    return bool(jax.config.jax_compilation_cache_dir) and bool(jax.config.jax_enable_compilation_cache)


def _malloc_trim() -> None:
    """Hand the heap's free pages back to the system (glibc only; elsewhere nothing happens)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def resident_mb() -> float | None:
    """The process's resident memory now, in MB (Linux ``/proc/self/statm``; None elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


#: Programs are dropped, with or without the persistent cache, once the process's memory mappings pass this
#: fraction of the kernel's limit (``vm.max_map_count``): every compiled CPU program maps memory of its own,
#: and a long diagnosis without the persistent cache (the Python API's default) died with LLVM "Cannot allocate
#: memory" near 65,000 mappings at about 2.3 GB resident (a two-effect trial of the withheld-effect benchmark;
#: the mappings grew by about 170 a second).
MAPS_FRACTION = 0.5


def map_count() -> int | None:
    """The number of this process's memory mappings (Linux ``/proc/self/maps``; None where there is none)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def maps_near_limit(fraction: float = MAPS_FRACTION) -> bool:
    """Whether the process's memory mappings passed ``fraction`` of ``vm.max_map_count`` (False where unknown)."""
    n = map_count()
    if n is None:
        return False
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return False
    return n > fraction * limit


def release_compiled(force: bool = False, above_mb: float | None = None) -> bool:
    """Drop the compiled programs, traces and exported programs this process holds, when they can be read back.

    A program's executable and its trace are kept in memory after their first call; a diagnosis that refits
    many differently shaped models collects one set per model (measured on the shipped withheld-diffraction
    example: about 100 MB per model, 2 GB peak over its 17 models).  With the persistent compilation cache on,
    every program is on disk as soon as it is compiled (:func:`enable_compilation_cache` caches every program;
    the exported traces are in ``export/``), so a program needed again is read back, not compiled: this drops
    them (``jax.clear_caches``, :func:`brdfjax.runtime.export_cache.clear`), collects the garbage and gives the
    freed heap back to the system.  Without the persistent cache nothing is dropped (a program needed again
    would be compiled again) unless ``force``.  ``above_mb``: only when the resident memory is above this many
    MB (each drop costs the small programs' reloads: about 0.6 s on the shipped example).  Returns whether
    anything was dropped.  Process-wide: call it where no other thread is tracing or compiling.  Whatever the
    cache, programs are dropped when the process's memory mappings near the kernel's limit
    (:func:`maps_near_limit`): a program compiled again is slower than one kept, a process out of mappings dies.
    """
    near = maps_near_limit()
    if not (force or near or persistent_cache_on()):
        return False
    if above_mb is not None and not near:
        now = resident_mb()
        if now is not None and now <= above_mb:
            return False
    export_cache.clear()
    jax.clear_caches()
    gc.collect()
    _malloc_trim()
    return True
