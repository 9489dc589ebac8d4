"""The README's Python tour runs as written (docs that drift from code fail here)."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_tour_runs():
    text = README.read_text()
    block = re.search(r"## Tour of the Python API\n\n```python\n(.*?)```", text, re.S)
    assert block, "README has no Python tour block"
    ns: dict = {}
    exec(compile(block.group(1), str(README), "exec"), ns)
    assert ns["brdf"].shape == (2472, 3296)
    assert abs(float(ns["omega"]) - 2.864e-10) < 5e-14  # seed Table 3, centre pixel
    assert set(ns["parts"]) == {"center", "offset", "bars"}
    assert np.all(np.isfinite(np.asarray(ns["grads"].terms["center"].distribution.m)))
    np.testing.assert_allclose(np.asarray(ns["n_h"]), [0, 1648], atol=1e-6)


def test_readme_commands_match_ci():
    text = README.read_text()
    ci = (README.parent / ".ci" / "run").read_text()
    test_cmd = 'python3 -m pip install -e ".[test]" && python3 -m ruff check brdfjax tests experiments && python3 -m pytest -q'
    assert test_cmd in text
    for part in test_cmd.split(" && "):
        assert part.replace("python3 -m pip install", "python3 -m pip install -q") in ci or part in ci
    assert ci.index("ruff check") < ci.index("pytest -q")  # lint first, as the README says


def test_readme_instrument_example_runs(tmp_path, monkeypatch):
    from brdfjax.instrument.reduce import read_reduced_frame

    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    (block,) = [b for b in blocks if "SyntheticInstrument" in b]
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(block, str(README), "exec"), ns)
    frame = read_reduced_frame(ns["paths"][0])
    assert frame.brdf.shape == (48, 64) and (frame.extra["mask"] > 0).sum() > 100


def test_readme_fit_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    (block,) = [b for b in blocks if "from brdfjax.fit import" in b]
    ns: dict = {}
    exec(compile(block.replace("print(", "str("), str(README), "exec"), ns)
    r = ns["result"].to_json()
    r = r if isinstance(r, dict) else __import__("json").loads(r)
    assert r["converged"] is True
    m1 = r["parameters"]["m1"]
    assert abs(m1["value"] - 2e-4) < max(3 * m1["sigma"], 1e-6)
