"""release_compiled: compiled programs dropped from memory only where the persistent cache can give them back."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from brdfjax.runtime import compile_cache
from brdfjax.runtime.compile_cache import release_compiled, resident_mb


def _compiled_once():
    @jax.jit
    def f(x):
        return jnp.sin(x) * 2.0

    f(jnp.arange(3.0))
    assert f._cache_size() == 1
    return f


def test_nothing_is_dropped_without_the_persistent_cache(monkeypatch):
    monkeypatch.setattr(compile_cache, "persistent_cache_on", lambda: False)
    f = _compiled_once()
    assert release_compiled() is False
    assert f._cache_size() == 1


def test_programs_are_dropped_when_forced_and_the_numbers_stay():
    f = _compiled_once()
    before = f(jnp.arange(3.0))
    assert release_compiled(force=True) is True
    assert f._cache_size() == 0
    assert jnp.array_equal(f(jnp.arange(3.0)), before)


def test_a_memory_threshold_above_the_resident_memory_drops_nothing(monkeypatch):
    monkeypatch.setattr(compile_cache, "persistent_cache_on", lambda: True)
    now = resident_mb()
    assert now is not None and now > 10.0  # Linux: /proc/self/statm
    f = _compiled_once()
    assert release_compiled(above_mb=now + 10_000.0) is False
    assert f._cache_size() == 1
    assert release_compiled(above_mb=1.0) is True
    assert f._cache_size() == 0

