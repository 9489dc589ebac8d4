"""Diagnosis of the real goniometer tables (tests/data/real) with a plain one-lobe + Lambertian base: the first
effect is a physical one (second lobe, shadowing, distribution shape or angular sampling), never an instrument
response, and the report says that sigma was estimated.

Each dataset's diagnosis refits the base with every candidate (minutes on a loaded 2-core box): the tables are
decimated (every ``STEP``-th row) and the runs gated by --slow; the fitting-tables guide's numbers are from these runs.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import brdfjax as bj
from brdfjax.diagnose import diagnose
from brdfjax.fit import prepare, read_cornell_brdf, read_merl_inplane

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
PHYSICAL = {"second_lobe", "shadowing", "distribution_shape", "angular_sampling"}
EFFECTS = ["second_lobe", "shadowing", "distribution_shape", "angular_sampling", "pixel_nonlinearity", "flux_scale"]
STEP = 2

CASES = [
    ("merl_aluminium_inplane.txt", dict(n=0.96, k=6.69)),
    ("cornell_krylon_blue.brdf", dict(n=1.5)),
    ("cornell_cayman_metallic.brdf", dict(n=1.5)),
]


@pytest.mark.slow  # a diagnosis of a real table
@pytest.mark.parametrize("file, index", CASES, ids=[c[0].split(".")[0] for c in CASES])
def test_real_table_diagnosis_names_a_physical_effect_first(file, index):
    table = read_merl_inplane(REAL / file) if file.startswith("merl") else read_cornell_brdf(REAL / file)
    table = table.select(slice(None, None, STEP))
    model = bj.Model(terms={"spec": bj.Specular(bj.GGX(0.1), rho_s=0.5, **index, **bj.SEED_FORM), "diffuse": bj.Lambertian(0.05)})
    params = {"spec.alpha": "auto", "spec.rho_s": "auto", "diffuse.rho_d": "auto"}
    d = diagnose(prepare(model, table, params, resolution_check=False), effects=EFFECTS, max_steps=1)
    print(f"\n{file}:\n{d.summary()}")
    for c in d.ranking:
        print(f"  ranked {c.effect}: delta BIC {c.delta_bic:.1f}, signature {c.signature.get('score')}, {c.note}")
    assert d.ranking and d.ranking[0].effect in PHYSICAL, [c.effect for c in d.ranking]
    skipped = {c.effect: c.note for c in d.skipped}
    for inst in ("pixel_nonlinearity", "flux_scale"):
        assert "ranked only on detector frames" in skipped[inst], skipped
    doc = d.to_dict()
    assert doc["sigma_estimated"] is True and doc["gap"]["sigma_ln"] > 0
    assert "sigma ESTIMATED" in doc["noise"] and "sigma ESTIMATED" in d.summary()
