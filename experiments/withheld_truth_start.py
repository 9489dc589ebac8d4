"""Can the withheld effects' own model reach the truth's chi^2 at all?  A check of a withheld-effect trial.

For one library trial of ``experiments/withheld_effects.py`` (the same seed
rule, scenario and fitted frames), the withheld effects are added to the base
fit in the given order with the search's own candidate refit
(:func:`brdfjax.diagnose.refits._refit_effect`), then that model is refitted
from the truth's values of every parameter the scenario names in its truth
(``center.*``, ``bars.*``, ``offset.*``, ...; an instrument effect's own
parameters, which the truth does not name that way, start where the search's
refit left them), once with everything free and once with only the parameters
the truth does not give free.  Where even that fit stays far above the truth's
reduced chi^2, the trial measures the model family against the generator, not
the search.  Printed and written (``--out``, JSON): the reduced chi^2 of each
fit beside the truth's, and per frame the pixels of largest residual relative
to the model's brightest pixel.

    python3 experiments/withheld_truth_start.py --seed 9620 --trial two:stray_light+diffraction:1 \\
        --effects stray_light,diffraction --out experiments/results/withheld_truth_start_seed9620_stray_light_diffraction.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

import withheld_effects as W  # noqa: E402

from brdfjax.diagnose import effects as fx  # noqa: E402
from brdfjax.diagnose.context import gap_measures  # noqa: E402
from brdfjax.diagnose.refits import _fit_state, _refit_effect, _with_context  # noqa: E402
from brdfjax.diagnose.results import Candidate  # noqa: E402
from brdfjax.fit.internal import as_param  # noqa: E402
from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402


def _free_values(st) -> dict[str, float]:
    return {k: float(np.asarray(v.value)) for k, v in st.result.parameters.items() if v.free and "[" not in k}


def _worst_pixels(st, n: int = 6) -> list[dict]:
    out = []
    for k in st.ctx.frames():
        r = np.asarray(st.ctx.residuals[k], float)
        f = np.asarray(st.ctx.model_values[k], float)
        pr, pc = np.unravel_index(int(np.nanargmax(f)), f.shape)
        ok = np.isfinite(r)
        order = np.argsort(np.where(ok, -np.abs(r), 0.0).ravel())[:n]
        out.append({"frame": int(k), "shape": list(r.shape), "peak": [int(pr), int(pc)],
                    "chi2": float(np.nansum(r**2)), "n": int(ok.sum()),
                    "worst": [{"offset_from_peak": [int(a - pr), int(b - pc)], "pixel": [int(a), int(b)],
                               "residual": float(r[a, b]), "model": float(f[a, b])}
                              for a, b in (np.unravel_index(i, r.shape) for i in order)]})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, required=True, help="the benchmark seed (withheld_effects.py --seed)")
    ap.add_argument("--trial", required=True, help="the trial id, e.g. two:stray_light+diffraction:1")
    ap.add_argument("--effects", required=True, help="the withheld effects, in the order to add them (the trial "
                    "injects them in the order of its id)")
    ap.add_argument("--step", type=int, default=16)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    effects = a.effects.split(",")
    injected = a.trial.split(":")[1].split("+")  # as withheld_effects.run_trial: the id's order
    if sorted(injected) != sorted(effects):
        raise SystemExit(f"--effects {a.effects!r} are not the effects of the trial {a.trial!r} ({injected})")
    sc, seed, fitted, _, params, rows = W.trial_case({"id": a.trial, "effects": injected},
                                                     argparse.Namespace(seed=a.seed, frames=a.frames, step=a.step,
                                                                        path="render"))
    if rows is not None:
        raise SystemExit(f"{a.trial!r} is a goniometer-table trial; this check takes frame trials")
    true = W._true_gap(sc, seed, fitted)
    lib = fx.EFFECT_LIBRARY
    st = _with_context(_fit_state(sc.base_model, fitted, dict(params), {}, ()))
    rows = [{"fit": "base", "chi2_reduced": float(st.result.chi2_reduced), "free": _free_values(st)}]
    for e in effects:
        c = Candidate(e, lib[e].title, "ranked")
        _refit_effect(c, lib[e], st.ctx, st, {}, gap_measures(st.result))
        if c.state is None:
            raise SystemExit(f"the refit adding {e} failed: {c.note}")
        st = _with_context(c.state)
        rows.append({"fit": f"+ {e} (the search's refit)", "chi2_reduced": float(st.result.chi2_reduced),
                     "free": _free_values(st), "note": c.note})
    spec = dict(st.params)
    given = [k for k, v in sc.truth.items() if k in spec and isinstance(v, float)]
    for k in given:
        spec[k] = dataclasses.replace(as_param(k, spec[k]), value=float(sc.truth[k]))
    for label, s in (("from the truth's values, all free", spec),
                     ("the truth's values held, the rest free",
                      {k: (dataclasses.replace(as_param(k, v), free=False) if k in given else v) for k, v in spec.items()})):
        fs = _with_context(_fit_state(st.model, st.blocks, s, st.fit_kwargs, st.effects, st.starts, st.added_terms))
        rows.append({"fit": label, "chi2_reduced": float(fs.result.chi2_reduced), "free": _free_values(fs),
                     "worst_pixels": _worst_pixels(fs)})
    for r in rows:
        print(f"{r['fit']:45s} reduced chi2 {r['chi2_reduced']:.4g}")
    print(f"{'the truth (noiseless frames)':45s} reduced chi2 {true['chi2_reduced']:.4g}")
    rec = {"settings": {"seed": a.seed, "trial": a.trial, "effects": effects, "step": a.step, "frames": a.frames,
                        "trial_seed": seed, "truth_parameters_given": given},
           "truth": {k: (v if isinstance(v, int | float | str) else str(v)) for k, v in sc.truth.items()},
           "chi2_reduced_true": true["chi2_reduced"], "fits": rows}
    if a.out is not None:
        write_json_atomic(a.out, W._clean(rec))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
