"""Shared test cases and builders: the distributions, terms, models and configs that tests parametrise over.

Import as ``from helpers import ...`` (pytest puts ``tests/`` on the path; it holds no tests itself).
"""

from __future__ import annotations

import textwrap
import tomllib
from pathlib import Path

import brdfjax as bj
from brdfjax.config import ModelConfig
from brdfjax.core import distributions as D, presets

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"

#: A narrow (near-specular) and a wide instance of every registered distribution, plus the edge shapes
#: (GTR at gamma -> 1, a cosine lobe of power 0, Beard-Maxwell at and past s = 1).
DISTRIBUTION_CASES = [
    D.Beckmann(2e-4), D.Beckmann(0.3),
    D.BeckmannAniso(2e-4, 5e-4), D.BeckmannAniso(0.3, 0.1),
    D.GGX(2e-4), D.GGX(0.3),
    D.GGXAniso(2e-4, 6e-4), D.GGXAniso(0.3, 0.15),
    D.GTR(2e-4, 2.0), D.GTR(0.3, 1.0), D.GTR(0.3, 1.5), D.GTR(2e-3, 3.0), D.GTR(0.3, 1.0 + 1e-8),
    D.HyperCauchy(2e-4, 3.0), D.HyperCauchy(0.3, 1.5),
    D.Ribardiere(1 / 0.3**2, 2.5), D.Ribardiere(1 / (2e-4) ** 2, 4.0),
    D.StudentT(2e-4, 1.5), D.StudentT(0.3, 10.0),
    D.StudentTAniso(2e-4, 4e-4, 2.5), D.StudentTAniso(0.3, 0.2, 1.8),
    D.CosineLobe(5e7), D.CosineLobe(0.0), D.CosineLobe(20.0),
    D.AshikhminShirley(5e7, 1e8), D.AshikhminShirley(10.0, 40.0),
    D.BeardMaxwell(2e-4), D.BeardMaxwell(0.3), D.BeardMaxwell(0.999), D.BeardMaxwell(1.0), D.BeardMaxwell(2.0),
]

#: Single terms that must be reciprocal (Helmholtz): isotropic and anisotropic lobes, a conductor, a
#: diffuse floor and an offset-normal wrapper.
TERM_CASES = [
    bj.Specular(D.Beckmann(0.2), rho_s=0.5, n=1.5),
    bj.Specular(D.GGXAniso(0.1, 0.3), rho_s=0.5, n=1.2, k=3.0),
    bj.Specular(D.StudentT(0.25, 3.0), rho_s=1.0, n=3.6),
    bj.Specular(D.AshikhminShirley(30.0, 5.0), rho_s=1.0, n=2.0),
    bj.Lambertian(0.3),
    bj.OffsetNormal(bj.Specular(D.Beckmann(0.2), rho_s=0.7, n=1.4), dtheta=0.1, dphi0=0.7),
]

#: The shipped models: the seed's solar cell and the material presets, by name.
MODEL_CASES = {
    "solar_cell": bj.solar_cell,
    "mirror": presets.mirror,
    "polished_aluminium": presets.polished_aluminium,
    "kapton": presets.kapton,
}

#: The shipped configs by what reads them (file names under configs/).
CONFIG_CASES = {
    "fit": sorted(p.name for p in CONFIGS.glob("fit_*.toml")),
    "sample": sorted(p.name for p in CONFIGS.glob("sample_*.toml")),
    "simulate": sorted(p.name for p in CONFIGS.glob("seed_*.toml")) + ["default.toml"],
    "capture": ["capture_simulated.toml"],
    "diagnose": sorted(p.name for p in CONFIGS.glob("diagnose_*.toml")),
    "instrument": ["instrument_seed.toml"],
    "lightcurve": sorted(p.name for p in CONFIGS.glob("lightcurve_*.toml")),
    "observe": sorted(p.name for p in CONFIGS.glob("observe_*.toml")),
    "skygap": sorted(p.name for p in CONFIGS.glob("skygap_*.toml")),
    "batch": sorted(p.name for p in CONFIGS.glob("batch_*.toml")),
}


def write_config(folder: Path, text: str, name: str = "fit.toml", **fmt: object) -> Path:
    """Write ``text`` (dedented; ``str.format(**fmt)`` when given) to ``folder/name``; returns the path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    body = textwrap.dedent(text)
    p = folder / name
    p.write_text(body.format(**fmt) if fmt else body)
    return p


def model_config(text: str) -> ModelConfig:
    """The ``[model]`` table of a TOML snippet (dedented), validated."""
    return ModelConfig.model_validate(tomllib.loads(textwrap.dedent(text))["model"])


def withheld_module():
    """``experiments/withheld_effects.py`` as a module (the benchmark script is not a package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "experiments" / "withheld_effects.py"
    spec = importlib.util.spec_from_file_location("withheld", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
