"""The SCORE set split by observing mode (MMT-9 CMOS magnitudes against visual estimates) and by the satellite's
height (on an operational shell or below it) (writes experiments/results/sky_score_modes.json).

SCORE mixes ~2,350 MMT-9 five-second averages (CMOS, +-0.1 mag) and ~430 naked-eye estimates (VISUAL, +-0.2-0.5
mag); both are compared as V.  It also holds satellites below every operational V2 Mini shell (raising or
lowering their orbits, in another attitude): the shipped config's ``[attitude] min_height_km`` flags them.  The
authors' model and brdfjax's shipped config on each split.

    PYTHONPATH=$PWD python experiments/sky_score_modes.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "lightcurve"))

from test_observe import _authors_facets, _authors_models  # noqa: E402

from brdfjax.io import write_json_atomic  # noqa: E402
from brdfjax.io.observations import read_observations  # noqa: E402
from brdfjax.lightcurve.observe import metrics, predict_set  # noqa: E402
from brdfjax.lightcurve.observe_config import load_observe_config, predict_all  # noqa: E402


def main() -> None:
    path = ROOT / "tests/data/satellites/observations/score_v2mini.csv"
    obs = read_observations(path, "score")
    mode = {"CMOS": obs.extra["instrument"] == "MMT9"}
    mode["VISUAL"] = ~mode["CMOS"]
    out: dict = {}
    facets = _authors_facets()
    cfg = load_observe_config(ROOT / "configs" / "observe_v2mini_score.toml")
    h = cfg.attitude.min_height_km
    preds = {
        "authors_with_offset": predict_set("score", obs, facets, _authors_models(), normals="lumos", band_map={"CLEAR": "V"},
                                           min_height_km=h),
        "authors_lab_only": predict_set("score", obs, facets[:-1], _authors_models(), normals="lumos",
                                        band_map={"CLEAR": "V"}, min_height_km=h),
        "brdfjax_shipped_config": predict_all(cfg)[0],
    }
    for label, p in preds.items():
        keep = p.geometry.keep
        out[label] = {}
        splits = {m: sel[keep] for m, sel in mode.items()}
        splits.update(operational=~p.off_shell, off_shell=p.off_shell)
        splits.update({f"operational_{m}": ~p.off_shell & sel[keep] for m, sel in mode.items()})
        for m, s in splits.items():
            out[label][m] = metrics(p.observed[s], p.mag[s], None if p.band is None else p.band[s])
            print(f"{label:24s} {m:18s}: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                                       for k, v in out[label][m].items()), flush=True)
    out["n_rows"] = {m: int(np.sum(s)) for m, s in mode.items()}
    out["min_height_km"] = h
    write_json_atomic(ROOT / "experiments" / "results" / "sky_score_modes.json", out)


if __name__ == "__main__":
    main()
