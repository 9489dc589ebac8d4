"""brdfjax.core.fft.fast_len: one FFT-length helper, equal to brute force and to scipy's choice."""

from __future__ import annotations

from pathlib import Path

import pytest

from brdfjax.core.fft import fast_len


def _brute(n: int) -> int:
    m = max(n, 1)
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def test_equals_brute_force_and_scipy():
    fft = pytest.importorskip("scipy.fft")
    for n in [*range(0, 3000), 3296 + 40, 2472 + 40, 4097, 65537, 1_000_003]:
        assert fast_len(n) == _brute(n), n
        if n >= 1:
            assert fast_len(n) == fft.next_fast_len(n, real=True), n


def test_known_values():
    assert [fast_len(n) for n in (0, 1, 7, 11, 13, 17, 97, 4097)] == [1, 1, 8, 12, 15, 18, 100, 4320]


def test_one_definition_in_the_package():
    root = Path(__file__).resolve().parents[2] / "brdfjax"
    assert sorted(str(p.relative_to(root)) for p in root.rglob("*.py") if "def _fast_len" in p.read_text()
                  or "def fast_len" in p.read_text()) == ["core/fft.py"]
