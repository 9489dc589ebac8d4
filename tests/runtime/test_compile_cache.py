"""The CLI's persistent compilation cache: on by default in a user folder, off by env var or flag."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from brdfjax.runtime.compile_cache import cache_dir, enable_compilation_cache

ROOT = Path(__file__).resolve().parents[2]


def test_cache_dir_follows_env(monkeypatch, tmp_path):
    monkeypatch.delenv("BRDFJAX_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "brdfjax" / "jax"
    monkeypatch.setenv("BRDFJAX_CACHE_DIR", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine"


def test_env_var_turns_it_off(monkeypatch, tmp_path):
    monkeypatch.setenv("BRDFJAX_NO_CACHE", "1")
    assert enable_compilation_cache(tmp_path / "c") is None
    assert not (tmp_path / "c").exists()


def _simulate(tmp_path: Path, cache: Path, *flags: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "BRDFJAX_NO_CACHE"}
    env.update(BRDFJAX_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    out = tmp_path / f"out{len(list(tmp_path.iterdir()))}"
    proc = subprocess.run(
        [sys.executable, "-m", "brdfjax", *flags, "simulate", "--out", str(out), "--step", "256", "--no-figures"],
        capture_output=True, text=True, cwd=ROOT, env=env, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr


def test_cli_writes_compiled_programs_to_the_cache_and_no_cache_flag_skips_it(tmp_path):
    on, off = tmp_path / "on", tmp_path / "off"
    _simulate(tmp_path, on)
    assert on.is_dir() and len(list(on.rglob("*"))) > 0
    _simulate(tmp_path, off, "--no-cache")
    assert not off.exists()
