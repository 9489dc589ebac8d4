"""release_compiled: compiled programs dropped from memory only where the persistent cache can give them back.

Whether a program was dropped is seen by its trace: a jitted function traced again on its next call (a Python
counter in its body) was dropped; one that is not traced again was kept.  (The jit's in-memory fast-path cache
size is not used: other tests in the same process can change configuration that bypasses that cache.)
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp

from brdfjax.runtime import compile_cache
from brdfjax.runtime.compile_cache import release_compiled, resident_mb


def _compiled_once():
    traces = []

    @jax.jit
    def f(x):
        traces.append(1)
        return jnp.sin(x) * 2.0

    f(jnp.arange(3.0))
    f(jnp.arange(3.0))
    assert len(traces) == 1
    return f, traces


def test_nothing_is_dropped_without_the_persistent_cache(monkeypatch):
    monkeypatch.setattr(compile_cache, "persistent_cache_on", lambda: False)
    f, traces = _compiled_once()
    assert release_compiled() is False
    f(jnp.arange(3.0))
    assert len(traces) == 1


def test_programs_are_dropped_when_forced_and_the_numbers_stay():
    f, traces = _compiled_once()
    before = f(jnp.arange(3.0))
    assert release_compiled(force=True) is True
    after = f(jnp.arange(3.0))
    assert len(traces) == 2 and jnp.array_equal(after, before)


def test_a_memory_threshold_above_the_resident_memory_drops_nothing(monkeypatch):
    monkeypatch.setattr(compile_cache, "persistent_cache_on", lambda: True)
    now = resident_mb()
    assert now is not None and now > 10.0  # Linux: /proc/self/statm
    f, traces = _compiled_once()
    assert release_compiled(above_mb=now + 10_000.0) is False
    f(jnp.arange(3.0))
    assert len(traces) == 1
    assert release_compiled(above_mb=1.0) is True
    f(jnp.arange(3.0))
    assert len(traces) == 2


def test_programs_dropped_near_the_mapping_limit_without_the_persistent_cache(monkeypatch):
    """Without the persistent cache nothing is dropped, unless the process's memory mappings near the kernel's
    limit: a long diagnosis through the Python API died with LLVM "Cannot allocate memory" near 65,000
    mappings."""
    import brdfjax.runtime.compile_cache as cc

    n = cc.map_count()
    assert n is None or n > 0
    monkeypatch.setattr(cc, "persistent_cache_on", lambda: False)
    monkeypatch.setattr(cc, "maps_near_limit", lambda fraction=cc.MAPS_FRACTION: False)
    assert cc.release_compiled(above_mb=0.0) is False
    monkeypatch.setattr(cc, "maps_near_limit", lambda fraction=cc.MAPS_FRACTION: True)
    assert cc.release_compiled(above_mb=1e9) is True  # near the limit the memory threshold does not hold it back
    monkeypatch.undo()
    if cc.map_count() is None or not Path("/proc/sys/vm/max_map_count").is_file():
        return  # no Linux /proc: the limit is unknown and nothing is dropped for it
    monkeypatch.setattr(cc, "map_count", lambda: 10**9)
    assert cc.maps_near_limit() is True
    monkeypatch.setattr(cc, "map_count", lambda: 1)
    assert cc.maps_near_limit() is False
