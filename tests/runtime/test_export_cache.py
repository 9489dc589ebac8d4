"""Issue 19: a fit's traced programs kept across processes (brdfjax.runtime.export_cache) give the plain fit's numbers
to every bit, on other data of the same shapes too, and a key that misses any static value cannot be built."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from brdfjax.runtime import export_cache
from brdfjax.runtime.export_cache import _canon, _key, _Uncacheable, exported_call

# tests/fit/test_fit_speed.py's table (a Beckmann lobe on a Lambertian floor), fitted in a fresh process: the step
# scales (Jacobian), the Levenberg-Marquardt solve and the final residuals and covariance; then a decimated
# solar-cell frame rendered (brdfjax.core.render's program)
FIT = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from brdfjax.runtime.compile_cache import enable_compilation_cache
    enable_compilation_cache()
    import brdfjax as bj
    from brdfjax.runtime import export_cache
    from brdfjax.fit import fit
    sys.path.insert(0, TESTS)
    from test_fit_speed import _peak_on_floor_table

    out = []
    for seed in map(int, sys.argv[1:]):
        model, tab = _peak_on_floor_table(25.0, 35.0, 41, seed)
        r = fit(model, tab, {"peak.m": 0.08, "peak.rho_s": 0.3, "floor.rho_d": 0.02}, first_stage=None)
        out.append({"chi2": r.chi2, "steps": r.n_iterations, "converged": r.converged,
                    "values": {k: [r.value(k), r.sigma(k)] for k in ("peak.m", "peak.rho_s", "floor.rho_d")}})
    det = bj.Detector.seed()
    img = np.asarray(bj.render(bj.solar_cell(), bj.Conditions.from_degrees(20.0), det, grid=det.grid(128)))
    print(json.dumps({"fits": out, "render": img.tobytes().hex(), "stats": export_cache.stats()}))
    """
).replace("TESTS", repr(str(Path(__file__).resolve().parents[1] / "fit")))


def _run(tmp_path, *seeds: int, export: bool = True) -> dict:
    env = dict(os.environ, BRDFJAX_CACHE_DIR=str(tmp_path / ("cache" if export else "plain-cache")))
    env.pop("BRDFJAX_NO_CACHE", None)
    env.pop("BRDFJAX_NO_EXPORT", None)
    if not export:
        env["BRDFJAX_NO_EXPORT"] = "1"
    proc = subprocess.run([sys.executable, "-c", FIT, *map(str, seeds)], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_fit_through_exported_programs_equals_the_plain_fit_bit_for_bit(tmp_path):
    plain = _run(tmp_path, 0, 1, export=False)
    assert plain["stats"] == {"loaded": 0, "exported": 0, "reused": 0, "plain": 0}
    # traces and writes its three programs: the render, the solve (which returns the covariance's Jacobian) and
    # the residuals (also the step scales' differences); no Jacobian program
    first = _run(tmp_path, 0)
    assert first["stats"]["exported"] == 3 and first["stats"]["loaded"] == 0
    assert len(list((tmp_path / "cache" / "export").glob("*.jaxexport"))) == 3
    later = _run(tmp_path, 0, 1)  # a later process: reads them; then other data of the same shapes
    assert later["stats"]["loaded"] == 3 and later["stats"]["exported"] == 0 and later["stats"]["reused"] >= 3
    assert first["render"] == later["render"] == plain["render"]  # the frame: the same bytes
    for got in (first["fits"][0], later["fits"][0]):
        assert got == plain["fits"][0]  # chi^2, steps, values and sigmas: the same floats
    assert later["fits"][1] == plain["fits"][1]
    assert later["fits"][1]["chi2"] != later["fits"][0]["chi2"]  # the data did change
    assert all(f["converged"] for f in plain["fits"])


class _Toy(eqx.Module):
    x: jax.Array
    power: int = eqx.field(static=True)


def _toy(m: _Toy, offset):
    return (m.x**m.power + offset,)


_toy_plain = eqx.filter_jit(_toy)


class _Applied(eqx.Module):
    x: jax.Array
    fn: Any = eqx.field(static=True)


def _apply(m: _Applied):
    return (m.fn(m.x),)


_apply_plain = eqx.filter_jit(_apply)


@pytest.fixture
def export_dir(tmp_path):
    folder = export_cache.activate(tmp_path / "export")
    assert folder is not None
    export_cache.clear()
    yield folder
    export_cache.deactivate()


def test_static_values_make_the_key_and_array_values_do_not(export_dir):
    before = export_cache.stats()
    x = jnp.arange(4.0)
    (a,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 1.0))
    (b,) = exported_call("toy", _toy, _toy_plain, (_Toy(x + 1.0, 2), 1.0))  # new data: the same program
    (c,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 3), 1.0))  # a static field: another program
    (d,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 2.0))  # a Python scalar is static too
    np.testing.assert_array_equal(a, x**2 + 1.0)
    np.testing.assert_array_equal(b, (x + 1.0) ** 2 + 1.0)
    np.testing.assert_array_equal(c, x**3 + 1.0)
    np.testing.assert_array_equal(d, x**2 + 2.0)
    after = export_cache.stats()
    assert after["exported"] - before["exported"] == 3 and after["reused"] - before["reused"] == 1
    assert len(list(export_dir.glob("toy-*.jaxexport"))) == 3
    # another shape or dtype is another program
    k1, _ = _key("toy", *jax.tree_util.tree_flatten((_Toy(x, 2), 1.0)), ())
    k2, _ = _key("toy", *jax.tree_util.tree_flatten((_Toy(jnp.arange(5.0), 2), 1.0)), ())
    k3, _ = _key("toy", *jax.tree_util.tree_flatten((_Toy(x.astype(jnp.int32), 2), 1.0)), ())
    k4, _ = _key("toy", *jax.tree_util.tree_flatten((_Toy(x, 2), 1.0)), (("SWITCH", False),))
    assert len({k1, k2, k3, k4}) == 4


def test_a_damaged_file_is_made_again(export_dir):
    x = jnp.linspace(0.0, 1.0, 3)
    (a,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 0.5))
    (path,) = export_dir.glob("toy-*.jaxexport")
    path.write_bytes(b"not a serialised program")
    export_cache.clear()  # as a new process would: read the file
    before = export_cache.stats()
    (b,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 0.5))
    np.testing.assert_array_equal(a, b)
    assert export_cache.stats()["exported"] - before["exported"] == 1
    export_cache.clear()
    (c,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 0.5))  # the rewritten file reads back
    np.testing.assert_array_equal(a, c)
    assert export_cache.stats()["loaded"] - before["loaded"] == 1
    # a readable file that holds another program (other array shapes) under this name is made again too
    exported_call("toy", _toy, _toy_plain, (_Toy(jnp.ones(5), 2), 0.5))
    other = next(p for p in export_dir.glob("toy-*.jaxexport") if p != path)
    path.write_bytes(other.read_bytes())
    export_cache.clear()
    mid = export_cache.stats()
    (d,) = exported_call("toy", _toy, _toy_plain, (_Toy(x, 2), 0.5))
    np.testing.assert_array_equal(a, d)
    assert export_cache.stats()["exported"] - mid["exported"] == 1 and export_cache.stats()["loaded"] == mid["loaded"]


def test_values_that_cannot_be_written_out_go_the_plain_way(export_dir):
    k = 3.0
    for bad in (lambda v: v, (lambda: (lambda v: v * k))(), object()):
        with pytest.raises(_Uncacheable):
            _canon(bad, [])
    a, b = [], []
    _canon(np.array([1.0, 2.0, 3.0]), a)
    _canon(np.array([1.0, 2.0, 3.5]), b)
    assert a != b  # a static array by its content, not its (shortened) repr
    before = export_cache.stats()
    (y,) = exported_call("apply", _apply, _apply_plain, (_Applied(jnp.ones(2), lambda v: v * k),))
    np.testing.assert_array_equal(y, [3.0, 3.0])
    assert export_cache.stats()["plain"] - before["plain"] == 1
    assert not list(export_dir.glob("*.jaxexport"))


def test_compiler_options_reach_xla_and_make_another_program(export_dir):
    """brdfjax.runtime.export_cache.compiler_options: programs first called inside are compiled with the options
    (an unknown option is XLA's error), held apart from those compiled with XLA's defaults, with the same numbers
    here; the previous options come back on exit."""
    x = jnp.linspace(0.1, 2.0, 7)
    args = (_Toy(x, 3), 0.25)
    assert export_cache.current_compiler_options() is None
    (a,) = exported_call("toy", _toy, _toy_plain, args)
    with export_cache.compiler_options(export_cache.FAST_COMPILE_CPU):
        assert export_cache.current_compiler_options() == {"xla_cpu_use_fusion_emitters": False}
        before = export_cache.stats()
        (b,) = exported_call("toy", _toy, _toy_plain, args)
        assert export_cache.stats()["reused"] == before["reused"]  # not the program compiled with the defaults
        with export_cache.compiler_options({"xla_no_such_option_here": True}):
            with pytest.raises(Exception, match="xla_no_such_option_here"):
                exported_call("toy", _toy, _toy_plain, args)
        assert export_cache.current_compiler_options() == {"xla_cpu_use_fusion_emitters": False}
    assert export_cache.current_compiler_options() is None
    np.testing.assert_allclose(b, a, rtol=1e-15)
    keys = list(export_cache._MEM)  # one program, held three times: XLA's defaults, the fast options, the bad one
    assert len(keys) == 3 and len({k.split("|")[0] for k in keys}) == 1
    assert sum("xla_cpu_use_fusion_emitters" in k for k in keys) == 1


def _strip_timings(doc):
    if isinstance(doc, dict):
        return {k: _strip_timings(v) for k, v in doc.items() if not k.endswith("_s") and k not in ("versions", "config")}
    if isinstance(doc, list):
        return [_strip_timings(v) for v in doc]
    return doc


def test_a_real_table_fit_through_exported_programs_equals_the_plain_fit(tmp_path):
    """On data brdfjax did not make (Cornell's Krylon blue, the shipped config; noise estimated from the
    residuals, so the solve and the residuals run again for the profile likelihood): the CLI's result.json
    is the same, number for number, plain, exporting, and read back in a later process."""
    root = Path(__file__).resolve().parents[2]
    docs = {}
    for run, export in (("plain", False), ("exporting", True), ("later", True)):
        env = dict(os.environ, BRDFJAX_CACHE_DIR=str(tmp_path / ("cache" if export else "plain-cache")))
        env.pop("BRDFJAX_NO_CACHE", None)
        env.pop("BRDFJAX_NO_EXPORT", None)
        if not export:
            env["BRDFJAX_NO_EXPORT"] = "1"
        out = tmp_path / run
        cmd = [sys.executable, "-m", "brdfjax", "fit", str(root / "configs" / "fit_cornell_krylon_blue.toml"),
               "--out", str(out), "--no-figures", "--quiet"]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=root)
        assert proc.returncode == 0, proc.stderr[-3000:]
        docs[run] = json.loads((out / "result.json").read_text())
        if run == "exporting":
            files = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "cache" / "export").glob("*.jaxexport")}
    assert docs["plain"]["noise"]["estimated"] is True
    # the later process read the programs: none was written again
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "cache" / "export").glob("*.jaxexport")} == files
    assert len(files) >= 3
    assert _strip_timings(docs["exporting"]) == _strip_timings(docs["plain"])
    assert _strip_timings(docs["later"]) == _strip_timings(docs["plain"])
