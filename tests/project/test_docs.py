"""The README and the documentation site: their examples run, their reference pages are complete.

- Every fenced ``python`` block of ``README.md`` and ``docs/**/*.md`` runs
  verbatim in a fresh interpreter, without this suite's 64-bit switch
  (``tests/conftest.py`` turns it on for the whole suite, which once hid an
  example that failed when pasted into a new interpreter): the blocks that do
  not turn 64-bit JAX on run one after another in one process, each in a fresh
  namespace; each block that turns it on runs in a process of its own.  After
  each block a probe reads a few of its results, checked below.  A block
  preceded by ``<!-- docs-test: slow -->`` is compiled always and run only
  with ``--slow`` (a diagnosis: minutes).
- The CLI and config-key reference pages are generated (``docs/gen/``); a flag
  or key without a description fails here.
- The README is one screen (<= 200 lines) and, like the hand-written pages,
  free of history; its install and test commands are the ones CI runs.
- ``mkdocs build --strict`` itself runs in ``.ci/run`` (and here only with
  ``--slow``, reusing the tutorials an earlier build executed), to keep the suite fast.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS / "gen"))

import cli_reference  # noqa: E402
import config_reference  # noqa: E402
import equations  # noqa: E402
import validation  # noqa: E402

#: Hand-written Markdown: the README and every page under docs/ (generated pages and tutorials are not files there).
PAGES = [ROOT / "README.md"] + sorted(p for p in DOCS.rglob("*.md") if "gen" not in p.relative_to(DOCS).parts
                                      and "tutorials" not in p.relative_to(DOCS).parts)
_FENCE = re.compile(r"(?:<!--\s*docs-test:\s*(\w+)\s*-->\s*\n)?```python\n(.*?)```", re.S)


def _blocks() -> list[tuple[str, str, str]]:
    """``(id, marker, source)`` of every python block, id ``<page>:<n>``."""
    out = []
    for page in PAGES:
        for n, m in enumerate(_FENCE.finditer(page.read_text(encoding="utf-8"))):
            out.append((f"{page.relative_to(ROOT)}:{n}", m.group(1) or "", m.group(2)))
    return out


BLOCKS = _blocks()

#: What is read back from a block's namespace, by a string the block contains (a Python expression -> JSON).
PROBES = {
    "grads = eqx.filter_grad(loss)(model)": "dict(shape=list(brdf.shape), omega=float(omega), parts=sorted(parts), "
    "n_h=[float(x) for x in n_h], grads_finite=bool(__import__('numpy').all(__import__('numpy').isfinite("
    "__import__('numpy').asarray(grads.terms['center'].distribution.m)))))",
    "SyntheticInstrument": "(lambda f: dict(shape=list(f.brdf.shape), usable=int((f.extra['mask'] > 0).sum())))("
    "__import__('brdfjax.instrument.reduce', fromlist=['x']).read_reduced_frame(paths[0]))",
    "result = fit(": "dict(result=__import__('json').loads(result.to_json()) if isinstance(result.to_json(), str) "
    "else result.to_json(), brdf_shape=list(brdf.shape) if 'brdf' in dir() else None)",
    "spike_halo": "dict(lam=float(lam), seed=float(seed_form.rho_s))",
}

RUNNER = r"""
import json, sys, traceback
import jax
todo = json.loads(sys.stdin.read())
for key, src, probe in todo:
    assert not jax.config.jax_enable_x64, "64-bit JAX is on before block %s" % key
    ns = {"__name__": "__main__"}
    try:
        exec(compile(src, key, "exec"), ns)
        got = eval(probe, ns) if probe else None
    except BaseException:
        traceback.print_exc()
        print("FAILED python block %s" % key, file=sys.stderr)
        sys.exit(1)
    print("RESULT " + json.dumps([key, got], default=str))
"""


def _probe(src: str) -> str | None:
    return next((p for k, p in PROBES.items() if k in src), None)


@pytest.fixture(scope="module")
def results(tmp_path_factory, run_slow):
    tmp = tmp_path_factory.mktemp("docs_blocks")
    chosen = [(k, src, _probe(src)) for k, marker, src in BLOCKS if marker != "slow" or run_slow]
    x64 = [c for c in chosen if "jax_enable_x64" in c[1]]
    groups = [[c for c in chosen if c not in x64]] + [[c] for c in x64]
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_ENABLE_X64")}
    env.update(PYTHONPATH=str(ROOT), MPLBACKEND="Agg", JAX_PLATFORMS="cpu")
    out: dict[str, object] = {}
    for group in groups:
        proc = subprocess.run([sys.executable, "-c", RUNNER], input=json.dumps(group), capture_output=True, text=True,
                              cwd=tmp, env=env, timeout=900)
        assert proc.returncode == 0, proc.stderr[-4000:]
        for line in proc.stdout.splitlines():
            if line.startswith("RESULT "):
                key, got = json.loads(line[7:])
                out[key] = got
    assert sorted(out) == sorted(c[0] for c in chosen)
    return out


def _key(contains: str, page: str | None = None) -> str:
    (key,) = [k for k, _, src in BLOCKS if contains in src and (page is None or k.startswith(page))]
    return key


def test_every_block_compiles_and_few_are_skipped():
    assert len(BLOCKS) >= 6
    for key, _, src in BLOCKS:
        compile(src, key, "exec")
    slow = [k for k, marker, _ in BLOCKS if marker]
    assert all(m in ("", "slow") for _, m, _ in BLOCKS)
    assert len(slow) <= len(BLOCKS) // 3, slow  # most blocks run in the suite


def test_readme_example(results):
    r = results[_key("render_noisy_frames(", "README.md")]
    assert r["brdf_shape"] == [309, 412]  # every 8th pixel of 2472 x 3296
    fit = r["result"]
    assert fit["converged"] is True
    m1 = fit["parameters"]["m1"]
    assert abs(m1["value"] - 2e-4) < max(3 * m1["sigma"], 1e-6)


def test_tour_block(results):
    r = results[_key("grads = eqx.filter_grad(loss)(model)")]
    assert r["shape"] == [2472, 3296]
    assert abs(r["omega"] - 2.864e-10) < 5e-14  # seed Table 3, centre pixel
    assert set(r["parts"]) == {"center", "offset", "bars"} and r["grads_finite"]
    # pasted as is, the inverse map runs before the block turns 64-bit JAX on: float32, 2e-3 px measured
    np.testing.assert_allclose(r["n_h"], [0, 1648], atol=5e-3)


def test_instrument_block(results):
    r = results[_key("SyntheticInstrument")]
    assert r["shape"] == [48, 64] and r["usable"] > 100


def test_fit_guide_block(results):
    fit = results[_key("result = fit(", "docs/guides/fitting-frames.md")]["result"]
    assert fit["converged"] is True
    m1 = fit["parameters"]["m1"]
    assert abs(m1["value"] - 2e-4) < max(3 * m1["sigma"], 1e-6)


def test_shadowing_block(results):
    r = results[_key("spike_halo")]
    assert 0 < r["lam"] < 10 and r["seed"] == 0.5


# --- the README -----------------------------------------------------------------------------------

#: Words of a lab notebook, not a manual (allowed in CHANGELOG.md and the generated validation records).
HISTORY = re.compile(r"\bissue\s*#?\d+|\bthis round\b|\bload average\b|\bload ~?\d|\bidle box\b|\bwas \d[\d.]* ?s\b"
                     r"|\bbefore this (?:change|round)\b|\bnot met\b|\btoday'?s?\b", re.I)


def test_readme_is_one_screen_and_keeps_its_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert "python3 -m pip install -e . && brdfjax simulate --out runs/default" in text
    ci = (ROOT / ".ci" / "run").read_text()
    test_cmd = ('python3 -m pip install -e ".[test,cluster]" && python3 -m pip install --no-deps "lumos-sat>=1.0.9,<2" '
                "&& python3 -m ruff check brdfjax tests experiments && python3 -m pytest -q -n 2 --dist worksteal")
    assert test_cmd in text
    for part in test_cmd.split(" && "):
        assert part.replace("python3 -m pip install", "python3 -m pip install -q") in ci or part in ci, part
    assert ci.index("ruff check") < ci.index("pytest -q")  # lint first, as the README says
    assert "mkdocs build --strict" in ci
    for command in cli_reference._subparsers():  # every command is listed
        assert f"`brdfjax {command} " in text, command


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_no_history_in_readme_or_docs(page):
    hits = [m.group(0) for m in HISTORY.finditer(page.read_text(encoding="utf-8"))]
    assert not hits, f"{page.relative_to(ROOT)}: {hits}"


def test_no_history_in_the_package():
    """Comments and docstrings say what the code does and why, not when or in which round it changed."""
    hits = []
    for path in sorted((ROOT / "brdfjax").rglob("*.py")):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            hits += [f"{path.relative_to(ROOT)}:{n}: {m.group(0)}" for m in HISTORY.finditer(line)]
    assert not hits, hits


def test_history_pattern_catches_history():
    for s in ("as issue 18 asked", "at load average 12", "(871 s before this round's savings)", "target not met"):
        assert HISTORY.search(s), s
    assert not HISTORY.search("the load is balanced by work stealing")


def test_citation_names_the_dissertation():
    cff = (ROOT / "CITATION.cff").read_text()
    refs = (DOCS / "references.md").read_text()
    title = "Improved Out-of-Plane Measurement and Modeling for Bidirectional Reflectance Distribution Functions"
    for text in (cff, refs):
        assert title in text and "Air Force Institute of Technology" in text and "Small" in text and "2021" in text
    for source in ("Walter", "Heitz", "Harvey", "Greynolds", "Foreman-Mackey", "Hoffman", "Optimistix", "JAX"):
        assert source in refs, source


# --- generated reference pages --------------------------------------------------------------------


def test_every_cli_flag_has_a_description_and_a_row():
    assert cli_reference.undocumented() == []
    page = cli_reference.page()
    for name, parser in cli_reference._subparsers().items():
        assert f"## `brdfjax {name}`" in page
        for action in parser._actions:
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert flag in page, (name, flag)


def test_cli_reference_flags_a_missing_description():
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("--documented", help="yes")
    p.add_argument("--bare")
    rows = cli_reference._rows(p)
    assert [r[0] for r in rows if not r[3]] == ["`--bare`"]


def test_every_config_key_has_a_description_unit_and_default():
    missing = config_reference.undocumented()
    assert missing == [], f"{len(missing)} config keys without a description: {missing[:20]}"
    page = config_reference.page()
    from brdfjax.config import DetectorConfig, FrameConfig

    for name in FrameConfig.model_fields:
        assert f"`frames[].{name}`" in page
    for name in DetectorConfig.model_fields:
        assert f"`detector.{name}`" in page
    assert "| `frames[].theta_i_deg` | `float` | deg | required |" in page
    assert "| `detector.distance_m` | `float or None` | m |" in page


def test_config_reference_flags_a_missing_description():
    from pydantic import Field

    from brdfjax.config import StrictModel

    class Inner(StrictModel):
        width_px: float = Field(1.0, description="a width")
        bare: int = 0

    rows = {key: (unit, desc) for key, _, unit, _, desc in config_reference.rows("t", Inner)}
    assert rows["t.width_px"] == ("px", "a width") and rows["t.bare"] == ("-", "")


def test_equation_table_lists_every_term_and_distribution():
    from brdfjax.core.registry import DISTRIBUTIONS, TERMS

    page = equations.page()
    for name in (*TERMS, *DISTRIBUTIONS):
        assert f"`{name}`" in page, name
    for cls in set(DISTRIBUTIONS.values()):
        assert cls.equation.startswith("Eq "), cls  # every distribution is the seed's
    for kind, cls in TERMS.items():
        assert cls.equation, kind  # every term names the equation or source it implements
    assert "| `lambertian` | `Lambertian` | Eq 50, 70 |" in page
    assert "| `beckmann` | `Beckmann` | Eq 64 |" in page


def test_validation_pages_cover_every_record():
    records = {p.stem for p in (ROOT / "experiments" / "results").glob("*.json")}
    shown = {p.stem for slug in validation.PAGES for p in validation.records(slug)}
    assert records <= shown, sorted(records - shown)
    page = validation.page("real-data")
    assert "## real_data_fits_merl_aluminium" in page and "measured at commit: `" in page
    assert "experiments/real_data_fits.py" in page


def test_nav_lists_every_page():
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in PAGES[1:]:
        rel = page.relative_to(DOCS).as_posix()
        if not rel.startswith("guides/"):  # guides/ pages are added to the nav by the hook
            assert f" {rel}" in nav, rel
    for uri in ("reference/cli.md", "reference/config.md", "physics/equations.md", "changelog.md"):
        assert f" {uri}" in nav


@pytest.mark.slow  # the strict site build runs in .ci/run; here only with --slow
def test_mkdocs_build_strict(tmp_path):
    pytest.importorskip("mkdocs")
    env = dict(os.environ, PYTHONPATH=str(ROOT), BRDFJAX_DOCS_EXECUTE="keep")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert (tmp_path / "site" / "reference" / "config" / "index.html").exists()
