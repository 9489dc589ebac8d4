"""brdfjax.sample._store.ChainStore: the one chain store behind the emcee and the NUTS chain files."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from brdfjax.sample import SampleError
from brdfjax.sample._chain import open_chain, read_chain_info
from brdfjax.sample._nuts import _read, open_nuts
from brdfjax.sample._store import META
from brdfjax.sample.internal import ChainStore

FP = {"model": "abc", "data": [1, 2]}


def _nuts(path, resume=False, names=("a", "b"), n_chains=2, fp=FP):
    return open_nuts(path, list(names), n_chains, resume=resume, center=np.zeros(2), scale=np.eye(2), seed=3,
                     n_warmup=10, fingerprint=fp)


def test_both_samplers_record_the_problem_in_the_same_place(tmp_path):
    open_chain(tmp_path / "e.h5", ["a", "b"], 6, resume=False, meta={"seed": 1}, fingerprint=FP)
    _nuts(tmp_path / "n.h5")
    for name, group in (("e.h5", "mcmc"), ("n.h5", "nuts")):
        meta = ChainStore(tmp_path / name, group, "x").read_meta()
        assert meta["names"] == ["a", "b"] and meta["fingerprint"] == FP
        with h5py.File(tmp_path / name) as f:
            assert set(f) == {META, group}
    assert read_chain_info(tmp_path / "e.h5").meta["seed"] == 1


def test_append_resumes_from_the_last_complete_step(tmp_path):
    chain = _nuts(tmp_path / "n.h5")
    z = np.arange(2 * 2 * 2, dtype=np.float64).reshape(2, 2, 2)
    chain.save_warmup(np.ones(2), np.ones((2, 2)), z[0], np.zeros(2), z[0])
    rows = {k: z for k in ("z", "grad", "x")} | {k: np.zeros((2, 2)) for k in ("logdensity", "log_prob", "accept")}
    rows |= {"diverging": np.zeros((2, 2), np.int8), "n_leapfrog": np.ones((2, 2), np.int32)}
    chain.append(rows)
    chain.append({k: v[:1] for k, v in rows.items()})
    back = _nuts(tmp_path / "n.h5", resume=True)
    assert back.iteration == 3 and np.array_equal(back.rows["z"], np.concatenate([z, z[:1]]))
    assert back.names == ("a", "b") and back.fingerprint == FP
    # a row written without its counter (a kill between the two) is not read
    with h5py.File(tmp_path / "n.h5", "a") as f:
        f["nuts"]["z"].resize(5, axis=0)
    assert _read(Path(tmp_path / "n.h5")).iteration == 3


def test_the_same_refusals_for_both(tmp_path):
    open_chain(tmp_path / "e.h5", ["a", "b"], 6, resume=False, fingerprint=FP)
    _nuts(tmp_path / "n.h5")
    for opener in (lambda p, **k: open_chain(p, ["a", "b"], 6, **k), _nuts):
        with pytest.raises(SampleError, match=r"already holds a chain; continue it with --resume"):
            opener(tmp_path / ("e.h5" if opener is not _nuts else "n.h5"), resume=False)
        with pytest.raises(SampleError, match=r"no chain to resume"):
            opener(tmp_path / "missing.h5", resume=True)
    with pytest.raises(SampleError, match=r"the chain samples a, b, but this problem's free parameters are a, c"):
        _nuts(tmp_path / "n.h5", resume=True, names=("a", "c"))
    with pytest.raises(SampleError, match=r"n\.h5: the chain has 2 chains, but this run asks for 3; resume with the same n_chains"):
        _nuts(tmp_path / "n.h5", resume=True, n_chains=3)
    with pytest.raises(SampleError, match=r"e\.h5: the chain has 6 walkers x 2 parameters, but this run asks for 8 x 2"):
        open_chain(tmp_path / "e.h5", ["a", "b"], 8, resume=True)
    with pytest.raises(SampleError, match=r"e\.h5: not a NUTS chain \(no 'nuts' group; an emcee chain\?"):
        _nuts(tmp_path / "e.h5", resume=True)
    with pytest.raises(SampleError, match=r"not an emcee chain \(no 'mcmc' group\)"):
        open_chain(tmp_path / "n.h5", ["a", "b"], 6, resume=True)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(SampleError, match=r"bad\.h5: the NUTS chain file cannot be read .*left untouched"):
        _nuts(tmp_path / "bad.h5", resume=True)
    assert (tmp_path / "bad.h5").read_bytes() == b"not hdf5"


def test_one_store_in_the_package():
    root = Path(__file__).resolve().parents[2] / "brdfjax"
    has = lambda s: sorted(str(p.relative_to(root)) for p in root.rglob("*.py") if s in p.read_text())  # noqa: E731
    assert has("already holds a chain") == ["sample/_store.py"]
    assert has("maxshape=(None") == ["sample/_store.py"]


def test_a_nuts_file_from_before_the_shared_store_still_resumes(tmp_path):
    _nuts(tmp_path / "n.h5")
    with h5py.File(tmp_path / "n.h5", "a") as f:  # the earlier layout: names and fingerprint on the nuts group
        del f[META]
        f["nuts"].attrs["names"] = '["a", "b"]'
        f["nuts"].attrs["fingerprint"] = '{"model": "abc", "data": [1, 2]}'
    back = _nuts(tmp_path / "n.h5", resume=True)
    assert back.names == ("a", "b") and back.fingerprint == FP
