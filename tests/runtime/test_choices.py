"""Every name a user picks is checked by one function with did-you-mean: configs, the CLI and the Python API."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.cli import main
from brdfjax.config import check_choice as config_check_choice
from brdfjax.core.registry import lookup
from brdfjax.fit import FitInputError, TableData, fit
from brdfjax.runtime.choices import check_choice, check_choices, closest

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_the_checker():
    assert check_choice("solver", "lm", ["lm", "bfgs"]) == "lm"
    with pytest.raises(ValueError, match=r"^unknown solver 'bgfs' \(did you mean 'bfgs'\?\); known: lm, bfgs$"):
        check_choice("solver", "bgfs", ["lm", "bfgs"])
    with pytest.raises(KeyError, match=r"x: unknown a 'zzz'; known: b, c\W*$"):  # nothing close: no suggestion
        check_choice("a", "zzz", ["c", "b"], error=KeyError, sort=True, prefix="x: ")
    with pytest.raises(ValueError, match=r"unknown effect\(s\) \['difraction'\] \(did you mean 'diffraction'\?\)"):
        check_choices("effect", ["difraction"], ["diffraction", "lambertian"])
    with pytest.raises(ValueError, match=r"\(did you mean 'diffraction' for 'difraction', 'lambertian' for 'lambertan'\?\)"):
        check_choices("effect", ["difraction", "lambertan", "qqq"], ["diffraction", "lambertian"])
    assert closest("ggxx", ["ggx", "beckmann"]) == "ggx" and closest("qqq", ["ggx"]) is None


def test_config_registry_and_terms_suggest():
    with pytest.raises(ValueError, match=r"unknown sampler 'nut' \(did you mean 'nuts'\?\); expected 'emcee' or 'nuts'"):
        config_check_choice("sampler", "nut", ["emcee", "nuts"])
    with pytest.raises(KeyError, match=r"unknown distribution 'ggxx' \(did you mean 'ggx'\?\); known: ashikhmin_shirley"):
        lookup("distribution", "ggxx")
    with pytest.raises(ValueError, match=r"specular: unknown shadowing 'smiht' \(did you mean 'smith'\?\)"):
        bj.Specular(bj.GGX(0.1), 1.0, 1.5, shadowing="smiht")
    with pytest.raises(KeyError, match=r"unknown parameter 'rho_s4' \(did you mean 'rho_s3'\?\)"):
        bj.solar_cell().with_params({"rho_s4": 1.0})
    with pytest.raises(KeyError, match=r"mirror: unknown parameter\(s\) \['rho'\] \(did you mean 'rho_s'\?\)"):
        bj.core.presets.mirror(rho=0.5)


def test_fit_config_solver_suggests():
    from brdfjax.fit.config import FitSection

    with pytest.raises(ValueError, match=r"unknown solver 'levenberg_marquard' \(did you mean 'levenberg_marquardt'\?\)"):
        FitSection(solver="levenberg_marquard")


def test_api_fit_with_a_wrong_parameter_name_suggests():
    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.2), rho_s=0.5, n=1.5), "d": bj.Lambertian(0.05)})
    ti = np.radians(np.full(5, 30.0))
    table = TableData(ti, np.zeros(5), np.radians(np.linspace(20.0, 40.0, 5)), np.full(5, np.pi), np.ones(5))
    with pytest.raises(FitInputError, match=r"unknown parameter 's.alpah' \(did you mean 's.alpha'\?\)"):
        fit(model, table, {"s.alpah": "free"})


def test_cli_effects_typo_suggests(tmp_path, capsys):
    code = main(["diagnose", str(CONFIGS / "diagnose_withheld_diffraction.toml"), "--out", str(tmp_path / "d"),
                 "--effects", "difraction"])
    assert code == 2
    err = capsys.readouterr().err
    assert "unknown effect(s) ['difraction'] (did you mean 'diffraction'?)" in err, err
    assert "Traceback" not in err
