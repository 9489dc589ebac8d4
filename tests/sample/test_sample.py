"""Posteriors with emcee (brdfjax.sample): likelihood = the fit's, priors, resume, diagnostics, errors, outputs.

Data: the seed's solar cell rendered around the centre peak (every 6th pixel of
a 121 x 121 pixel region, 3 % log-normal noise), three free parameters (m1,
rho_s1, rho_s3); one fit serves the module.  Chains are short (tens of steps):
the numbers checked are exact identities (chi^2, bit-identical resumed chains)
or properties that hold for any chain length.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

import brdfjax as bj
from brdfjax.fit import fit, get_solver, render_noisy_frames
from brdfjax.fit.internal import prepare_problem
from brdfjax.sample import Prior, SampleError, build_log_posterior, sample
from brdfjax.sample._chain import diagnose, run_chain
from brdfjax.sample._posterior import start_ball

ROOT = Path(__file__).resolve().parents[2]
MODEL = bj.solar_cell()
SPEC = {"m1": 2.1e-4, "rho_s1": 0.016, "rho_s3": 280.0}
NAMES = ("m1", "rho_s1", "rho_s3")


@pytest.fixture(scope="module")
def frames():
    return render_noisy_frames(MODEL, [20.0], roi=(-60, 60, -60, 60), step=6, seed=3)


@pytest.fixture(scope="module")
def fitted(frames):
    res = fit(MODEL, frames, SPEC)
    assert res.converged, res.message
    return res


@pytest.fixture(scope="module")
def prepared(frames):
    return prepare_problem(MODEL, frames, SPEC, solver=get_solver("levenberg_marquardt"))


@pytest.fixture(scope="module")
def short_run(tmp_path_factory, frames, fitted):
    out = tmp_path_factory.mktemp("post")
    res = sample(MODEL, frames, SPEC, start=fitted, n_steps=40, n_walkers=8, out_dir=out, seed=5, predictive_draws=16)
    return out, res


def test_vectorised_log_prob_equals_per_walker_and_the_fit_chi2(prepared, fitted):
    post = build_log_posterior(prepared, {"rho_s3": Prior.normal(300.0, 20.0)})
    assert post.names == NAMES
    x_opt = np.array([fitted.value(n) for n in NAMES])
    # -2 log L at the least-squares optimum is the fit's chi^2
    assert -2.0 * post.log_likelihood(x_opt[None, :])[0] == pytest.approx(fitted.chi2, rel=1e-10)
    rng = np.random.default_rng(0)
    sig = np.array([fitted.sigma(n) for n in NAMES])
    X = x_opt + 3 * sig * rng.standard_normal((8, 3))  # emcee's first batch shape: compiled once
    X[3, 0] = -1e-5  # outside the physical bound m1 >= 0
    vec = post(X)
    one = np.array([post.log_prob_one(x) for x in X])
    assert vec.shape == (8,) and vec.dtype == np.float64
    np.testing.assert_allclose(vec[np.isfinite(vec)], one[np.isfinite(one)], rtol=1e-12)
    assert vec[3] == -np.inf and one[3] == -np.inf
    # log-posterior = log-likelihood + log-prior (normal on rho_s3, flat elsewhere)
    ll = post.log_likelihood(X[:3])
    lp = -0.5 * ((X[:3, 2] - 300.0) / 20.0) ** 2 - math.log(20.0 * math.sqrt(2 * math.pi))
    np.testing.assert_allclose(vec[:3], ll + lp, rtol=1e-12)


def test_priors_against_closed_forms(prepared):
    stats = pytest.importorskip("scipy.stats")
    priors = {
        "m1": Prior.log_uniform(1e-4, 4e-4),
        "rho_s1": Prior.truncated_normal(0.015, 0.002, lower=0.012),
        "rho_s3": Prior.uniform(200.0, 400.0),
    }
    post = build_log_posterior(prepared, priors)
    x = np.array([[2e-4, 0.016, 310.0], [3e-4, 0.013, 250.0]])
    want = (
        stats.loguniform(1e-4, 4e-4).logpdf(x[:, 0])
        + stats.truncnorm((0.012 - 0.015) / 0.002, np.inf, loc=0.015, scale=0.002).logpdf(x[:, 1])
        + stats.uniform(200.0, 200.0).logpdf(x[:, 2])
    )
    np.testing.assert_allclose(post.log_prior(x), want, rtol=1e-9)
    # a normal prior on a positive parameter is truncated at the physical bound 0
    post2 = build_log_posterior(prepared, {"rho_s1": Prior.normal(0.001, 0.002)})
    z = stats.norm(0.001, 0.002).sf(0.0)
    assert post2.log_prior(np.array([[2e-4, 0.001, 300.0]]))[0] == pytest.approx(
        stats.norm(0.001, 0.002).logpdf(0.001) - math.log(z), rel=1e-9
    )
    # outside any support: -inf, also through the JAX path
    out = np.array([[5e-4, 0.016, 310.0], [2e-4, 0.011, 310.0], [2e-4, 0.016, 401.0], [2e-4, -0.1, 310.0]])
    assert np.all(post.log_prior(out) == -np.inf)
    assert np.all(post(out) == -np.inf)
    assert post.describe_priors()["rho_s3"] == "uniform[200, 400] sr^-1"


@pytest.mark.parametrize(
    "priors, n_walkers, match",
    [
        ({"rho_s3": Prior.uniform(100.0, 200.0)}, 8, r"prior excludes the starting point: 'rho_s3' = \d+\.\d+ sr\^-1"),
        ({"m2": Prior.uniform(1e-4, 3e-4)}, 8, r"prior on 'm2', which is held fixed"),
        ({"bogus": Prior.uniform(0.0, 1.0)}, 8, r"prior on unknown parameter 'bogus'.*free parameters are m1, rho_s1, rho_s3"),
        ({"m1": Prior.log_uniform(0.0, 1.0)}, 8, r"prior on 'm1': a log_uniform prior needs lower > 0"),
        ({"m1": Prior.normal(2e-4, -1.0)}, 8, r"prior on 'm1': sigma must be a positive number"),
        ({"m1": Prior("gamma", 1.0, 2.0)}, 8, r"prior on 'm1': unknown kind 'gamma'; known: uniform, log_uniform"),
        ({}, 5, r"n_walkers = 5 is fewer than twice the 3 free parameters"),
    ],
)
def test_bad_input_is_a_clear_error(frames, fitted, tmp_path, priors, n_walkers, match):
    with pytest.raises(SampleError, match=match):
        sample(MODEL, frames, SPEC, priors=priors, start=fitted, n_steps=5, n_walkers=n_walkers, out_dir=tmp_path)
    assert not (tmp_path / "posterior.json").exists()


def test_corrupted_or_foreign_chain_files_are_errors_and_left_untouched(frames, fitted, tmp_path):
    chain = tmp_path / "chain.h5"
    chain.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)) * 8)
    before = chain.read_bytes()
    with pytest.raises(SampleError, match=r"chain\.h5: the chain file cannot be read .*left untouched"):
        sample(MODEL, frames, SPEC, start=fitted, n_steps=5, n_walkers=8, out_dir=tmp_path, resume=True)
    with pytest.raises(SampleError, match=r"chain\.h5 already holds a chain; continue it with --resume"):
        sample(MODEL, frames, SPEC, start=fitted, n_steps=5, n_walkers=8, out_dir=tmp_path)
    assert chain.read_bytes() == before
    with pytest.raises(SampleError, match=r"no chain to resume"):
        sample(MODEL, frames, SPEC, start=fitted, n_steps=5, n_walkers=8, out_dir=tmp_path / "new", resume=True)


def test_output_contract(short_run, fitted, frames):
    out, res = short_run
    s = json.loads((out / "posterior.json").read_text())
    for key in ("n_steps", "n_walkers", "acceptance_fraction_mean", "converged", "sampling", "map", "warnings"):
        assert key in s
    assert s["n_steps"] == 40 and s["n_walkers"] == 8 and isinstance(s["converged"], bool)
    assert len(s["acceptance_fraction"]) == 8 and 0 < s["acceptance_fraction_mean"] < 1
    for name in NAMES:
        p = s["parameters"][name]
        for key in ("median", "q16", "q84", "q025", "q975", "tau", "ess", "map", "unit"):
            assert key in p, (name, key)
        assert p["q025"] <= p["q16"] <= p["median"] <= p["q84"] <= p["q975"]
        assert p["ess"] == pytest.approx(8 * (40 - s["burn"]) / p["tau"], rel=1e-9)
    # a 40-step chain is shorter than 50 tau: warned, not converged
    assert not s["converged"] and s["chain_shorter_than_50_tau"]
    assert any("shorter than 50 autocorrelation times" in w for w in s["warnings"])
    assert s["least_squares"]["chi2"] == pytest.approx(fitted.chi2, rel=1e-10)
    assert s["sampling"]["blocks"][0]["grid_step_px"] == 6 and s["sampling"]["blocks"][0]["grid_shape"] == [21, 21]
    for f in ("chain.h5", "corner.png", "trace.png", "predictive_ti20.png"):
        assert (out / f).stat().st_size > 1000, f
    # the chain in the file is the one summarised; MAP is the best sample
    assert res.chain.shape == (40, 8, 3)
    assert s["map"]["log_posterior"] == pytest.approx(float(res.log_prob.max()))
    # the predictive bands' model is the likelihood's: at the optimum, the fitted model at the usable pixels
    from brdfjax.sample._outputs import model_at_points

    x_opt = np.array([fitted.value(n) for n in NAMES])
    f = model_at_points(res.posterior, np.tile(x_opt, (16, 1)))[0][0]  # 16 draws: the shape compiled above
    data = frames[0]
    rows, cols = np.nonzero(data.usable())
    want = bj.evaluate_pixels(fitted.models[0], fitted.frames[0], data.arm_detector(), data.grid.n_h[cols], data.grid.n_v[rows])
    np.testing.assert_allclose(f, np.asarray(want), rtol=1e-8)


def test_resume_continues_the_same_chain_bit_identically(frames, fitted, tmp_path):
    kw = dict(start=fitted, n_walkers=8, seed=11, figures=False)
    full = sample(MODEL, frames, SPEC, n_steps=30, out_dir=tmp_path / "full", **kw)
    part = sample(MODEL, frames, SPEC, n_steps=12, out_dir=tmp_path / "part", **kw)
    first_k = part.chain.copy()
    resumed = sample(MODEL, frames, SPEC, n_steps=30, out_dir=tmp_path / "part", resume=True, **kw)
    assert resumed.chain.shape == (30, 8, 3)
    assert np.array_equal(resumed.chain[:12], first_k)  # the interrupted steps, untouched
    assert np.array_equal(resumed.chain, full.chain)  # and the same chain as an uninterrupted run
    assert np.array_equal(resumed.log_prob, full.log_prob)
    assert resumed.summary["new_steps"] == 18
    # a resumed run must keep the walkers
    with pytest.raises(SampleError, match=r"8 walkers x 3 parameters, but this run asks for 10 x 3"):
        sample(MODEL, frames, SPEC, n_steps=40, out_dir=tmp_path / "part", resume=True, **{**kw, "n_walkers": 10})


def test_run_chain_stops_when_converged_and_diagnoses_a_gaussian():
    """Pure NumPy: a 2-d Gaussian, the stop rule (chain > 50 tau, tau stable to 1 %) and ESS = walkers * steps / tau."""
    import emcee

    cov = np.array([[1.0, 0.8], [0.8, 1.0]])
    icov = np.linalg.inv(cov)

    def logp(X):
        return -0.5 * np.einsum("ni,ij,nj->n", X, icov, X)

    backend = emcee.backends.Backend()
    p0 = 0.1 * np.random.default_rng(1).standard_normal((16, 2))
    out = run_chain(logp, backend, p0, 20000, seed=3, progress=False, stop_when_converged=True, check_every=100)
    assert out.stopped_converged and out.iterations < 20000 and out.iterations % 100 == 0
    tau = np.array(out.tau_history[-1][1])
    assert np.all(50 * tau < out.iterations)
    d = diagnose(backend, ["x", "y"], burn=0, check_every=100)
    np.testing.assert_allclose(d.ess, 16 * out.iterations / d.tau)
    flat = backend.get_chain(flat=True)
    assert np.corrcoef(flat.T)[0, 1] == pytest.approx(0.8, abs=0.05)
    assert 0.2 < d.acceptance_fraction_mean < 0.9


def test_start_ball_stays_inside_the_prior(prepared, fitted):
    post = build_log_posterior(prepared, {"rho_s1": Prior.uniform(0.0, fitted.value("rho_s1") + 1e-9)})
    x0 = np.array([fitted.value(n) for n in NAMES])
    sig = np.array([fitted.sigma(n) for n in NAMES])
    X = start_ball(post, x0, sig, 8, 1.0, np.random.default_rng(0))
    assert X.shape == (8, 3) and np.all(np.isfinite(post(X)))
    assert np.all(X[:, 1] <= fitted.value("rho_s1") + 1e-9)


def test_decimated_sampling_grid_is_recorded(frames):
    from brdfjax.sample import decimate_frame
    from brdfjax.sample._api import sampling_record

    small = [decimate_frame(f, 2, (-30, 30, -30, 30)) for f in frames]
    rec = sampling_record(small, 2, (-30, 30, -30, 30))
    assert rec["step"] == 2 and rec["roi"] == [-30, 30, -30, 30]
    assert rec["blocks"][0]["grid_step_px"] == 12 and rec["blocks"][0]["grid_shape"] == [6, 6]
    assert rec["blocks"][0]["extent"] == [-30, 30, -30, 30]
    np.testing.assert_array_equal(small[0].brdf, np.asarray(frames[0].brdf)[5:16:2, 5:16:2])
    prep = prepare_problem(MODEL, small, SPEC, solver=get_solver("levenberg_marquardt"))
    assert sum(prep.problem.counts) == rec["n_points"] == int(small[0].usable().sum())
    with pytest.raises(SampleError, match=r"roi \(500, 600, 0, 10\) contains no pixel of its grid"):
        decimate_frame(frames[0], 1, (500, 600, 0, 10))


# --- brdfjax sample CONFIG --out DIR -------------------------------------------------------------

import textwrap  # noqa: E402

from brdfjax.cli import main  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "data"
slow = pytest.mark.slow

TINY = """
precision = "float64"
[data]
frames = ["{frame}"]
footprint_w_px = 0.0
sigma = "noise"
sigma_floor = 0.0068
max_sigma_rel = 0.1
[model]
preset = "solar_cell"
[params]
m1 = {{ value = 2.0e-4, lower = 1e-5, upper = 1e-3 }}
rho_s1 = 0.015
[output]
figures = {figures}
[nuisance]
enabled = false
[sample]
n_walkers = 8
n_steps = 20
seed = 4
fit_result = "start.json"
predictive_draws = 0
[sample.priors]
rho_s1 = {{ kind = "uniform", lower = 0.0, upper = 0.1 }}
{priors}
"""

#: A least-squares result in the JSON form of brdfjax fit (natural units): the walkers' start.
START = {"parameters": {"m1": {"value": 2.0e-4, "sigma": 2e-7, "unit": "1", "free": True},
                        "rho_s1": {"value": 0.015, "sigma": 5e-5, "unit": "1", "free": True}}}


@pytest.fixture(scope="module")
def example_frame(tmp_path_factory):
    from brdfjax.instrument.reduce import reduce_measurement_set

    (path,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", tmp_path_factory.mktemp("reduced"),
                                     correct_nonlinearity=True)
    return path


def _tiny(tmp_path, frame, priors="", figures="true") -> Path:
    (tmp_path / "start.json").write_text(json.dumps(START))
    return write_config(tmp_path, TINY, "tiny.toml", frame=Path(frame).as_posix(), priors=textwrap.dedent(priors),
                        figures=figures)


def test_a_fit_result_reweighted_at_its_model_is_sampled_with_the_same_weights(tmp_path, example_frame, capsys):
    """A fit result whose noise weights were evaluated at its model (brdfjax fit's default): the posterior uses
    the same weights, not the readings' (the fit is repeated from its values), and its record says so."""
    cfg = _tiny(tmp_path, example_frame, figures="false")
    start = dict(START, noise={"estimated": False, "reweighted": "noise weights evaluated at the model of a first fit"})
    (tmp_path / "start.json").write_text(json.dumps(start))
    out = tmp_path / "out"
    assert main(["sample", str(cfg), "--out", str(out), "--no-progress", "--steps", "4"]) == 0
    assert "its noise weights were evaluated at its model" in capsys.readouterr().err
    doc = json.loads((out / "posterior.json").read_text())
    assert doc["sampling"]["noise_weights"].startswith("noise weights at the model of the fit result")
    refit = json.loads((out / "fit_result.json").read_text())
    assert "reweighted" in refit["noise"]
    # without the mark, the readings' weights are the fit result's: no refit, nothing recorded
    (tmp_path / "start.json").write_text(json.dumps(START))
    out2 = tmp_path / "out2"
    assert main(["sample", str(cfg), "--out", str(out2), "--no-progress", "--steps", "4"]) == 0
    assert "noise_weights" not in json.loads((out2 / "posterior.json").read_text())["sampling"]
    assert not (out2 / "fit_result.json").exists()


def test_cli_runs_resumes_and_writes_the_contract(tmp_path, example_frame, capsys):
    cfg = _tiny(tmp_path, example_frame)
    out = tmp_path / "out"
    assert main(["sample", str(cfg), "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "posterior.json").read_text())
    assert doc["n_steps"] == 20 and doc["n_walkers"] == 8 and set(doc["parameters"]) == {"m1", "rho_s1"}
    for k in ("median", "q16", "q84", "q025", "q975", "tau", "ess", "map"):
        assert k in doc["parameters"]["m1"]
    assert doc["parameters"]["rho_s1"]["prior"] == "uniform[0, 0.1] 1"
    assert doc["sampling"]["config"].endswith("tiny.toml") and doc["sampling"]["fit_result"].endswith("start.json")
    assert doc["sampling"]["blocks"][0]["name"] == "solar_cell_20deg"
    for f in ("chain.h5", "corner.png", "trace.png"):
        assert (out / f).is_file(), f
    err = capsys.readouterr().err
    assert "acceptance fraction: mean" in err and "shorter than 50 autocorrelation times" in err
    from brdfjax.sample import read_chain

    first = read_chain(out / "chain.h5").get_chain()
    # a second run without --resume refuses to touch the chain; --resume --steps 28 continues it
    assert main(["sample", str(cfg), "--out", str(out), "--no-progress"]) == 2
    assert "already holds a chain; continue it with --resume" in capsys.readouterr().err
    assert main(["sample", str(cfg), "--out", str(out), "--resume", "--steps", "28", "--no-figures", "--no-progress"]) == 0
    chain = read_chain(out / "chain.h5").get_chain()
    assert chain.shape == (28, 8, 2) and np.array_equal(chain[:20], first)
    assert json.loads((out / "posterior.json").read_text())["n_steps"] == 28


def test_cli_bad_input_names_the_key_or_file(tmp_path, example_frame, capsys):
    cfg = _tiny(tmp_path, example_frame, priors='bogus_deg = { kind = "normal", mu = 0.0, sigma = 1.0 }', figures="false")
    assert main(["sample", str(cfg), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "tiny.toml: sample.priors.bogus_deg: prior on unknown parameter" in err
    cfg = _tiny(tmp_path, example_frame, priors='m1 = { kind = "uniform", lower = 5e-4, upper = 8e-4 }', figures="false")
    assert main(["sample", str(cfg), "--out", str(tmp_path / "o2")]) == 2
    assert "prior excludes the starting point: 'm1' = 0.0002" in capsys.readouterr().err
    cfg = _tiny(tmp_path, example_frame, figures="false")
    assert main(["sample", str(cfg), "--out", str(tmp_path / "o3"), "--walkers", "3"]) == 2
    assert "n_walkers = 3 is fewer than twice the 2 free parameters" in capsys.readouterr().err
    (tmp_path / "o4").mkdir()
    (tmp_path / "o4" / "chain.h5").write_bytes(b"garbage" * 100)
    assert main(["sample", str(cfg), "--out", str(tmp_path / "o4"), "--resume"]) == 2
    assert "chain.h5: the chain file cannot be read" in capsys.readouterr().err
    assert (tmp_path / "o4" / "chain.h5").read_bytes() == b"garbage" * 100


@pytest.mark.parametrize("_", [pytest.param(0, marks=slow)])
def test_cli_interrupted_by_a_signal_resumes(tmp_path, example_frame, _):
    """A subprocess stopped by SIGINT (Ctrl-C) mid-run keeps its steps and exits 130; --resume completes the chain."""
    cfg = _tiny(tmp_path, example_frame, figures="false")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "brdfjax", "sample", str(cfg), "--out", str(out), "--steps", "100000", "--no-progress"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    from brdfjax.sample._chain import read_chain_info

    deadline = time.time() + 300
    while time.time() < deadline:
        time.sleep(1.0)
        try:
            if read_chain_info(out / "chain.h5").iteration >= 30:
                break
        except (SampleError, FileNotFoundError, OSError):
            continue
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err.decode()[-2000:]
    k = read_chain_info(out / "chain.h5").iteration
    assert k >= 30
    from brdfjax.sample import read_chain

    before = read_chain(out / "chain.h5").get_chain()
    assert main(["sample", str(cfg), "--out", str(out), "--resume", "--steps", str(k + 10), "--no-progress"]) == 0
    after = read_chain(out / "chain.h5").get_chain()
    assert after.shape[0] == k + 10 and np.array_equal(after[:k], before)


@pytest.mark.parametrize("_", [pytest.param(0, marks=slow)])
def test_shipped_config_runs(tmp_path, _):
    """configs/sample_synthetic_solar_cell.toml end to end (synthetic instrument, reduction, fit, 60 steps)."""
    out = tmp_path / "run"
    cfg = ROOT / "configs" / "sample_synthetic_solar_cell.toml"
    assert main(["sample", str(cfg), "--out", str(out), "--steps", "60", "--no-progress"]) == 0
    doc = json.loads((out / "posterior.json").read_text())
    assert doc["n_steps"] == 60 and doc["n_walkers"] == 20
    truth = dict(bj.SOLAR_CELL_SEED)
    p = doc["parameters"]["m1"]
    assert p["median"] == pytest.approx(truth["m1"], rel=0.05)
    for k in ("rho_s1", "rho_s3"):  # sampled as log rho, their ND budget 0.37 wide in it: a short chain spreads
        p = doc["parameters"][k]
        assert abs(math.log(p["median"] / truth[k])) < 0.5 and p["q025"] < truth[k] < p["q975"]
    assert doc["sampled_as_log"] == ["rho_s1", "rho_s3"] and "footprint" in doc["nuisance"]["parameters"]
    assert (out / "fit_result.json").is_file() and (out / "predictive_ti20.png").is_file()


def test_config_priors_convert_units_and_name_unknown_keys():
    from brdfjax.config import ConfigError
    from brdfjax.sample.config import SampleSection, priors_from_config

    sec = SampleSection.model_validate({"priors": {
        "dtheta_deg": {"kind": "normal", "mu": 0.5, "sigma": 0.1},
        "a_m": {"kind": "log_uniform", "lower": 1e-4, "upper": 1e-3},
        "phi_ref_deg[ti20]": {"kind": "truncated_normal", "mu": 0.0, "sigma": 0.05, "lower": -1.0},
    }})
    pri = priors_from_config("x.toml", sec, MODEL)
    assert pri["dtheta"] == Prior.normal(math.radians(0.5), math.radians(0.1))
    assert pri["a"] == Prior.log_uniform(1e-4, 1e-3)
    assert pri["phi_ref[ti20]"] == Prior.truncated_normal(0.0, math.radians(0.05), lower=math.radians(-1.0))
    bad = SampleSection.model_validate({"priors": {"dtheta": {"kind": "uniform", "lower": 0.0, "upper": 1.0},
                                                   "m1": {"kind": "uniform", "lower": 1.0, "upper": 0.5}}})
    with pytest.raises(ConfigError) as e:
        priors_from_config("x.toml", bad, MODEL)
    msg = str(e.value)
    assert "x.toml: sample.priors.dtheta: prior on unknown parameter" in msg and "did you mean 'dtheta_deg'" in msg
    assert "x.toml: sample.priors.m1: prior on 'm1': lower 1.0 must be < upper 0.5" in msg
