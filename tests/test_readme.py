"""The README's commands match CI.  Its Python blocks run, and their results are checked, in
``tests/test_readme_blocks.py`` (fresh processes, without this suite's 64-bit switch)."""

from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_commands_match_ci():
    text = README.read_text()
    ci = (README.parent / ".ci" / "run").read_text()
    test_cmd = 'python3 -m pip install -e ".[test,cluster]" && python3 -m pip install --no-deps "lumos-sat>=1.0.9,<2" && python3 -m ruff check brdfjax tests experiments && python3 -m pytest -q -n 2 --dist worksteal'
    assert test_cmd in text
    for part in test_cmd.split(" && "):
        assert part.replace("python3 -m pip install", "python3 -m pip install -q") in ci or part in ci, part
    assert ci.index("ruff check") < ci.index("pytest -q")  # lint first, as the README says
