"""The coverage statistics of experiments/posterior_calibration_instrument.py: the standard error and the Wilson
interval count realisations (parameters that move together are one draw), against scipy's binomial Wilson interval."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

_spec = importlib.util.spec_from_file_location(
    "posterior_calibration_instrument",
    Path(__file__).resolve().parents[2] / "experiments" / "posterior_calibration_instrument.py")
calib = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(calib)


def _scipy_wilson(k, n):
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return [ci.low, ci.high]


def test_one_parameter_is_the_binomial():
    st = calib.coverage_stats([[True]] * 45 + [[False]] * 14)
    p = 45 / 59
    assert st["cover"] == pytest.approx(p)
    assert st["se"] == pytest.approx(math.sqrt(p * (1 - p) / 59), rel=1e-12)
    assert st["n_eff"] == pytest.approx(59)
    np.testing.assert_allclose(st["wilson"], _scipy_wilson(45, 59), rtol=1e-9)


def test_parameters_that_move_together_count_once():
    together = calib.coverage_stats([[True, True]] * 45 + [[False, False]] * 14)
    single = calib.coverage_stats([[True]] * 45 + [[False]] * 14)
    assert together["n"] == 118 and together["n_realisations"] == 59
    assert together["n_eff"] == pytest.approx(59)
    assert together["se"] == pytest.approx(single["se"], rel=1e-12)
    np.testing.assert_allclose(together["wilson"], single["wilson"], rtol=1e-12)


def test_independent_parameters_count_twice():
    # 9 realisations of two parameters whose hits are uncorrelated (P(both) = p^2 = 4/9): 18 effective draws
    rows = [[True, True]] * 4 + [[True, False]] * 2 + [[False, True]] * 2 + [[False, False]]
    st = calib.coverage_stats(rows)
    assert st["cover"] == pytest.approx(2 / 3)
    assert st["n_eff"] == pytest.approx(18)
    np.testing.assert_allclose(st["wilson"], _scipy_wilson(12, 18), rtol=1e-9)


def test_all_covered_and_empty():
    st = calib.coverage_stats([[True, True]] * 10)
    assert st["cover"] == 1.0 and st["se"] == 0.0 and st["n_eff"] == 10
    np.testing.assert_allclose(st["wilson"], _scipy_wilson(10, 10), rtol=1e-9)
    assert calib.coverage_stats([])["cover"] is None


def test_coverage_groups_skip_a_missing_sigma():
    truth = {"m1": 2e-4, "rho_s1": 0.015, "rho_s3": 300.0, "c": 4e-5}
    # m1 0.5 sigma off, rho_s1 and rho_s3 1.5 sigma off (inside 95 %, outside 68 %), c without a sigma
    params = {"m1": {"value": 2e-4 + 0.5e-7, "sigma": 1e-7}, "rho_s1": {"value": 0.015 * 1.15, "sigma": 0.015 * 0.1},
              "rho_s3": {"value": 300 * 1.15, "sigma": 300 * 0.1}, "c": {"value": 4e-5, "sigma": None}}
    res = calib.coverage([{"truth": truth, "fit": {"params": params}}] * 3, "fit")
    assert res["shape"]["n"] == 3 and res["shape"]["cover68"] == 1.0
    assert res["weights"]["n"] == 6 and res["weights"]["cover68"] == 0.0 and res["weights"]["cover95"] == 1.0
    assert res["overall"]["n"] == 9 and res["overall"]["cover68"] == pytest.approx(1 / 3)
    assert res["c"]["n"] == 0 and res["c"]["cover68"] is None
