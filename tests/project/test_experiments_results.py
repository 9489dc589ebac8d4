"""experiments/results: every file is listed in its index with the script that writes it; names carry no history."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results"
INDEX = RESULTS / "README.md"
HISTORY = re.compile(r"issue\d*|final|round|_new|_old|_v\d+(?![a-z])|one_trace|shared_trace|_before|_after|_fix", re.I)


def _rows() -> dict[str, str]:
    rows = {}
    for line in INDEX.read_text().splitlines():
        m = re.match(r"\| `([^`]+)` \| (.+?) \| (.+) \|$", line)
        if m:
            rows[m.group(1)] = m.group(2)
    return rows


def test_every_result_file_is_indexed_and_every_indexed_file_exists():
    files = {p.name for p in RESULTS.iterdir() if p.is_file() and p.name != "README.md"}
    rows = _rows()
    assert sorted(files - set(rows)) == []  # unlisted files
    # the CPU device check may not have been run in this checkout; every other listed file exists
    assert sorted(set(rows) - files - {"device_check_cpu.json"}) == []


def test_each_file_names_the_script_that_writes_it():
    scripts = {p.name for p in (ROOT / "experiments").glob("*.py")}
    last = None
    for name, writer in _rows().items():
        named = re.findall(r"experiments/([a-z_0-9]+\.py)", writer)
        if named:
            assert set(named) <= scripts, (name, named)
            last = writer
        else:  # "the same ..." continues the row above; otherwise a brdfjax command
            assert writer.startswith("the same") and last is not None or "brdfjax " in writer, (name, writer)


def test_names_say_what_not_when():
    assert [n for n in _rows() if HISTORY.search(n)] == []
    assert [p.name for p in RESULTS.iterdir() if HISTORY.search(p.name)] == []


def test_the_readme_cites_only_files_that_exist():
    cited = set(re.findall(r"experiments/results/([A-Za-z0-9_.]+\.jsonl?)", (ROOT / "README.md").read_text()))
    assert sorted(c for c in cited if not (RESULTS / c).exists() and c != "device_check_cpu.json") == []
