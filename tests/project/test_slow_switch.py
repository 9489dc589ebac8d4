"""The one slow switch: ``@pytest.mark.slow`` tests run with ``pytest --slow`` or ``BRDFJAX_SLOW=1``, else skip."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

HERE = Path(__file__).resolve().parents[1]  # tests/
CASE = """
import pytest

@pytest.mark.slow
def test_long():
    pass

def test_quick(run_slow):
    assert isinstance(run_slow, bool)
"""


def test_slow_marker_skips_by_default(pytester, monkeypatch):
    # the real conftest in a scratch project: the marked test is skipped, with the reason naming the switch
    pytester.makeconftest((HERE / "conftest.py").read_text())
    pytester.makepyfile(test_case=CASE)
    monkeypatch.delenv("BRDFJAX_SLOW", raising=False)
    res = pytester.runpytest_inprocess("-p", "no:cacheprovider", "-rs")
    res.assert_outcomes(passed=1, skipped=1)
    res.stdout.fnmatch_lines(["*slow: run with --slow (or BRDFJAX_SLOW=1)*"])


class _Config:
    def __init__(self, slow: bool):
        self.slow = slow

    def getoption(self, name):
        assert name == "--slow"
        return self.slow


class _Item:
    def __init__(self, slow: bool):
        self.slow, self.added = slow, []

    def get_closest_marker(self, name):
        return object() if (name == "slow" and self.slow) else None

    def add_marker(self, m):
        self.added.append(m)


@pytest.mark.parametrize("option, env, runs", [(False, None, False), (True, None, True), (False, "1", True),
                                               (False, "0", False), (False, "", False), (True, "0", True)])
def test_option_or_environment_turns_it_on(monkeypatch, option, env, runs):
    conftest = pytest.importorskip("conftest")
    if env is None:
        monkeypatch.delenv("BRDFJAX_SLOW", raising=False)
    else:
        monkeypatch.setenv("BRDFJAX_SLOW", env)
    assert conftest.slow_enabled(_Config(option)) is runs
    items = [_Item(True), _Item(False)]
    conftest.pytest_collection_modifyitems(_Config(option), items)
    assert [len(i.added) for i in items] == ([0, 0] if runs else [1, 0])


def test_one_spelling_across_the_tests():
    # no test file reads the environment variable itself or gates on skipif: the marker is the only switch
    others = [p.name for p in HERE.rglob("test_*.py") if p.name != Path(__file__).name
              and re.search(r"BRDFJAX_SLOW[\"']|skipif\([^)]*SLOW", p.read_text())]
    assert others == []
