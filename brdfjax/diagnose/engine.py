"""The diagnosis engine: WHERE the base model misses the data, WHICH effect explains it, HOW FAR it shrinks.

``diagnose(base_model, blocks, params)`` runs, on measured frames
(:class:`~brdfjax.fit.FrameData`) and/or goniometer tables
(:class:`~brdfjax.fit.TableData`):

1. the base fit (:func:`brdfjax.fit.fit`);
2. the :class:`~brdfjax.diagnose.context.Context` of the fit (:func:`~brdfjax.diagnose.context.build_context`): per block the
   normalised residual ``r = (ln d - ln f) / sigma_ln`` on the block's grid
   (NaN where unused), the fitted model's values and the scatter geometry with
   the specular-relative coordinates ``sx, sy`` (degrees,
   :func:`~brdfjax.diagnose.zones.specular_coordinates`);
3. WHERE: significant residual regions and their zones
   (:mod:`brdfjax.diagnose.zones`);
4. WHICH: every candidate effect of :data:`~brdfjax.diagnose.effects.EFFECT_LIBRARY`
   (or the named ones) is checked (applicable? identifiable?), its
   refit-independent signature computed, and the model refitted with the
   effect added (``Effect.extend``: warm start at the base's optimum).
   ``delta_chi2 = chi2_base - chi2_with`` and ``delta_bic = BIC_base -
   BIC_with`` (``BIC = chi2 + k ln N``, ``k`` free parameters, ``N`` points)
   are *decreases*: positive means the effect explains part of the gap.  The
   ranking is by ``delta_bic``;
5. HOW FAR: forward selection with backward elimination: the best
   *admissible* effect is added when its BIC gain exceeds ``bic_threshold``
   (a candidate whose refit failed or ended above the model it extends is
   ``failed`` and never ranked; one whose new parameter ends on a bound, that
   drives a term of the model to zero, or whose signature is below its
   presence threshold is ranked but flagged and not added); a generic best
   (a floor, a response curve) is compared with the best specific runner-up
   on their joint refit, and the one the joint model needs more enters first;
   the chosen model is refitted jointly from fresh starts as well (the lower
   chi^2 is kept); then every earlier effect on the path is tried out again
   and removed when the BIC without it is within ``bic_threshold``.  The
   previous step's runners-up and the candidates with the strongest
   signatures in the new residual (``path_pool`` of each) are re-tried on the
   extended model, and so on until the gain is not significant, the reduced
   chi^2 is within the noise (``1 + 3 sqrt(2/dof)``, data with sigma), or
   ``max_steps`` (``Diagnosis.stop_reason`` says which).  A step after which
   the held-out gap grows is flagged.  Every step records the global gap (``chi2_reduced``,
   ``rms_log10``), the per-zone reduced chi^2 on the base's zones, and, when
   ``heldout_blocks`` are given, the prediction gap on them (the fitted model
   evaluated, nothing refitted, at the held-out frames' nominal conditions).

The engine never sees a generator's truth: only the blocks and the library.
"""
from __future__ import annotations

import copy
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..core.terms import Model
from ..fit import FitInputError, FrameData, TableData
from ..runtime.choices import check_choices
from ..runtime.errors import InputError
from .admission import (  # noqa: F401 - the path search's rules, importable from here as before
    _DEAD,
    _UNDETERMINED,
    _WEAK,
    DEAD_FRACTION,
    DOMINANCE,
    WIDTH_FIELDS,
    _admission_flags,
    _admit_dominant,
    _natural,
    _own_terms_flags,
    _sampling_rad,
    _weak_only,
)
from .context import build_context, gap_measures
from .effects import EFFECT_LIBRARY
from .model_config import (  # noqa: F401 - the model-to-TOML writer, importable from here as before
    final_model_config,
    model_terms_config,
    toml_text,
)
from .refits import (  # noqa: F401 - the refits, importable from here as before
    FAR_FACTOR,
    RETRY_STEPS,
    _by_gain,
    _candidate_copy,
    _check_effect,
    _extend_state,
    _fit_state,
    _fresh_refit,
    _fresh_spec,
    _heldout_gap,
    _moved_far,
    _nested,
    _noise_level,
    _params_report,
    _rank,
    _refit_effect,
    _refit_failure,
    _refit_fresh,
    _restore_candidate,
    _score,
    _second_start,
    _start_context,
    _start_values,
    _State,
    _with_context,
    _without,
    _zone_stats,
    truth_gap,
)
from .report import heldout_grew
from .results import Candidate, Diagnosis, Step
from .zones import find_regions, zone_masks

__all__ = ["DiagnoseInputError", "diagnose", "final_model_config", "model_terms_config", "toml_text", "truth_gap"]


class DiagnoseInputError(InputError):
    """Bad diagnosis input (no usable pixels, unknown effect, effect already in the base); says what to change."""


# --- the engine ----------------------------------------------------------------------------



def _check_blocks(blocks: Sequence[Any], what: str) -> list[Any]:
    blocks = [blocks] if isinstance(blocks, FrameData | TableData) else list(blocks)
    if not blocks:
        raise DiagnoseInputError(f"{what}: no data blocks given; give at least one FrameData or TableData")
    for i, b in enumerate(blocks):
        if not isinstance(b, FrameData | TableData):
            raise DiagnoseInputError(f"{what}[{i}] is a {type(b).__name__}; expected FrameData or TableData")
        try:
            b.check_usable()
        except FitInputError as e:
            raise DiagnoseInputError(f"{what}: {e}") from None
    return blocks


def _select_effects(library: Mapping[str, Any], names: Sequence[str] | None, base_model: Model) -> tuple[list[str], list[Candidate]]:
    explicit = names is not None
    names = list(library) if names is None else list(names)
    check_choices("effect", names, library, error=DiagnoseInputError)
    chosen, skipped = [], []
    for n in names:
        eff = library[n]
        if eff.present_in(base_model):
            if explicit:
                raise DiagnoseInputError(
                    f"the base model already contains the effect '{n}' ({eff.title}); remove it from the base model "
                    "or from the candidate effects"
                )
            skipped.append(Candidate(n, eff.title, "skipped", "already in the base model"))
            continue
        chosen.append(n)
    return chosen, skipped


def _specific_first(best: Candidate, admissible: list[Candidate], state: _State, library: Mapping[str, Any],
                    bic_threshold: float, notes: list[str], say: Any, n_specific: int = 3) -> Candidate:
    """A generic best (a floor, a response curve) against the best specific runners-up, on their joint refits.

    For each of the ``n_specific`` specific runners-up S (by BIC gain) the
    joint model J = S's refit extended by the generic effect G is refitted.
    The rule (stated in the report): a generic effect does not enter before a
    specific one that explains its signature, that is when taking G out of J
    costs less than ``bic_threshold`` (G would not pass the entry test on top
    of S); failing that, S enters first when J needs it more than G (taking G
    out of J costs less BIC than taking S out).  G is re-tried on S at the
    next step.  (Measured: far-field diffraction fringes look like a uniform
    floor to a score test; once the floor was in, the bars' refit started from
    a contaminated model and the path ended at reduced chi^2 7695 against the
    truth's 1.02.)
    """
    spec = sorted((c for c in admissible if c is not best and not getattr(library[c.effect], "generic", False)
                   and c.delta_bic > bic_threshold and c.state is not None), key=lambda c: -c.delta_bic)[:n_specific]
    if not spec:
        return best
    choice = None
    for s_c in spec:
        say(f"comparing {best.effect} with {s_c.effect} on their joint refit")
        try:
            joint = _extend_state(_with_context(s_c.state), best.effect, library)
        except Exception as e:  # noqa: BLE001 - reported; the ranking stands
            notes.append(f"joint refit of {s_c.effect} + {best.effect} failed ({type(e).__name__}: {e}); not compared")
            continue
        b_j = gap_measures(joint.result)["bic"]
        cost_g = gap_measures(s_c.state.result)["bic"] - b_j
        cost_s = gap_measures(best.state.result)["bic"] - b_j
        notes.append(f"{best.effect} (generic, delta BIC {best.delta_bic:.4g}) vs {s_c.effect} (delta BIC {s_c.delta_bic:.4g}) "
                     f"on their joint refit: BIC cost of taking out {best.effect} {cost_g:.4g}, {s_c.effect} {cost_s:.4g}")
        if cost_g < bic_threshold:
            notes.append(f"{s_c.effect} enters first: on the joint refit it explains {best.effect}'s signature "
                         f"(taking {best.effect} out costs {cost_g:.4g} < {bic_threshold:g})"
                         + (f" (although {'; '.join(s_c.flags)})" if s_c.flags else ""))
            return s_c
        if choice is None and cost_g < cost_s:
            choice = s_c
    if choice is not None:
        notes.append(f"{choice.effect} enters first: the joint refit needs it more than {best.effect}"
                     + (f" (although {'; '.join(choice.flags)})" if choice.flags else ""))
        return choice
    return best


def _close_alternatives(best: Candidate, ranked: list[Candidate], bic_threshold: float) -> list[str]:
    """The admissible runners-up of ``best`` whose BIC gain came within 10 % of its own (a near-tie at that step).

    A near-tie on one step's refits is decided by what joins later: measured on a reference floor trial
    (diffraction withheld, a true floor) ``distribution_shape``, ``lambertian`` and ``second_lobe`` tied at
    step 1 (delta BIC 1.375e7 / 1.374e7 / 1.374e7); the heavy tail took the floor, and once diffraction was
    in, the path ended at reduced chi^2 2.29 against the truth's 1.022.
    """
    margin = max(10.0, 0.1 * abs(best.delta_bic))
    return [c.effect for c in _by_gain(ranked) if c is not best and not c.flags and c.delta_bic > bic_threshold
            and best.delta_bic - c.delta_bic < margin]


def _try_swaps(state: _State, base: _State, close: Mapping[str, list[str]], tried: set, removed: list[str],
               library: Mapping[str, Any], bic_threshold: float, say: Any,
               notes: list[str], params0: Mapping[str, Any] | None = None) -> tuple[_State, _State, str, str, float] | None:
    """The best swap of an earlier path effect for one of its close alternatives, on the joint refit.

    For each earlier effect ``e`` with close alternatives ``g`` (:func:`_close_alternatives`), the path
    without ``e`` (:func:`_without`) is extended by ``g`` and refitted; the swap with the lowest BIC is
    returned as ``(without e, with g, e, g, BIC change)`` when it lowers the BIC by more than
    ``bic_threshold``, or at all when the path with ``g`` has fewer free parameters (the threshold guards
    against adding what the noise alone pays for; a simpler model that the data like as well or better
    needs no margin), else None.  Each pair is tried once; each try (and a failed refit) is noted in ``notes``.
    With ``params0`` (the base's parameter spec) the swapped path is also refitted from the fresh starts and
    the lower chi^2 kept: the path without ``e`` starts where the path with it ended, and there the other
    terms may have taken ``e``'s role (measured on reference frames, diffraction withheld, a true floor: the
    centre lobe had widened to m = 0.69 rad, a floor, and the second lobe had become the centre peak, so the
    floor in the second lobe's place, refitted warm, was 1.2e7 worse in BIC).
    """
    best = None
    b_now = gap_measures(state.result)["bic"]
    n_now = len(state.result.free_names)
    for e in state.effects[:-1]:
        for g in close.get(e, []):
            if (e, g) in tried or g in state.effects or g in removed:
                continue
            tried.add((e, g))
            say(f"trying {g} in place of {e} (they tied when {e} entered)")
            try:
                w = _with_context(_without(state, e, base, library))
                sw = _extend_state(w, g, library)
            except Exception as ex:  # noqa: BLE001 - reported; a failed swap leaves the path as it is
                notes.append(f"{g} in place of {e}: the refit failed ({type(ex).__name__}: {ex})")
                continue
            fresh = _fresh_refit(sw, params0) if params0 is not None else None
            start = ""
            if fresh is not None and float(fresh.result.chi2) < float(sw.result.chi2) * (1 - 1e-6):
                sw, start = fresh, " (refitted from the fresh starts: lower chi^2 than warm)"
            change = gap_measures(sw.result)["bic"] - b_now
            n_sw = len(sw.result.free_names)
            simpler = n_sw < n_now
            notes.append(f"{g} in place of {e}: BIC {'+' if change >= 0 else ''}{change:.4g}{start}"
                         + (f" ({n_sw} free parameters against {n_now}: a simpler model is taken on any BIC decrease)"
                            if simpler else ""))
            if change < (0.0 if simpler else -bic_threshold) and (best is None or change < best[4]):
                best = (w, sw, e, g, change)
    return best


def _final_check(state: _State, base: _State, library: Mapping[str, Any], bic_threshold: float, path: list[Step],
                 removed: list[str], zones: Any, heldout: Any, blocks: Sequence[Any], say: Any) -> _State:
    """Every effect of the final model passes the test it passed to enter: taking it out (model refitted) must
    cost at least ``bic_threshold`` in BIC.  The cheapest effect below the threshold is taken out, and the check
    repeats on what is left, until every remaining effect stays on its own evidence.

    (The backward elimination after each addition tries the earlier effects only; the last one entered, and an
    effect whose role a later one took over, are judged here.)
    """
    for _ in range(len(state.effects)):
        if not state.effects:
            break
        costs = []
        for e in state.effects:
            say(f"final check: the model without {e}")
            try:
                w = _without(state, e, base, library)
            except Exception as ex:  # noqa: BLE001 - reported; the effect stays
                path[-1].notes.append(f"final check: removing {e} failed ({type(ex).__name__}: {ex}); it stays")
                continue
            cost = gap_measures(w.result)["bic"] - gap_measures(state.result)["bic"]
            costs.append((cost, e, w))
            path[-1].notes.append(f"final check: without {e}: BIC {'+' if cost >= 0 else ''}{cost:.4g}"
                                  + (" (stays)" if cost >= bic_threshold else ""))
        below = sorted((c for c in costs if c[0] < bic_threshold), key=lambda c: c[0])
        if not below:
            break
        cost, e, w = below[0]
        state = w if w.ctx is not None else _with_context(w)
        removed.append(e)
        say(f"final check: removed {e} (BIC without it {cost:+.1f} < {bic_threshold:g})")
        path.append(_step(e, "remove", library[e], state, zones, heldout, blocks, -cost, path,
                          [f"taken out by the final check: without it the BIC changes by {cost:+.4g}, less than the "
                           f"{bic_threshold:g} it needed to enter"], []))
    return state


def _step(effect: str, action: str, eff: Any, state: _State, zones: Mapping[str, list[np.ndarray]], heldout: Any,
          blocks: Sequence[Any], delta_bic: float, path: list[Step], notes: list[str], alts: list[dict],
          compare: Step | None | bool = True) -> Step:
    """One path step; its held-out gap is compared with ``path[-1]``'s (``compare``: another step, or False: none)."""
    h = _heldout_gap(state, heldout, blocks)
    st = Step(effect, gap_measures(state.result), _zone_stats(state.ctx.residuals, zones), h, delta_bic,
              _params_report(state.result), action=action, side=getattr(eff, "side", "material"), notes=list(notes),
              alternatives=alts)
    ref = (path[-1] if path else None) if compare is True else (compare or None)
    prev = ref.heldout if ref is not None else None
    if heldout_grew(prev, h):
        st.flags.append(f"the held-out rms log10 rose from {prev['rms_log10']:.4g} to {h['rms_log10']:.4g}: this step is "
                        "questioned (it may fit what the fitted frames alone show, or start a dead end)")
    if alts and alts[0]["margin"] < max(10.0, 0.1 * abs(delta_bic)):  # within 10 % of the gain: a close call
        st.notes.append(f"close alternative: {alts[0]['effect']} (delta BIC {alts[0]['delta_bic']:.4g}, "
                        f"{alts[0]['margin']:.4g} behind)")
    return st


def diagnose(
    base_model: Model,
    blocks: FrameData | TableData | Sequence[FrameData | TableData],
    params: Mapping[str, Any],
    *,
    effects: Sequence[str] | None = None,
    heldout_blocks: Sequence[FrameData | TableData] | None = None,
    fit_kwargs: Mapping[str, Any] | None = None,
    bic_threshold: float = 10.0,
    max_steps: int = 4,
    path_pool: int = 4,
    refit_top: int | None = None,
    fresh_top: int = 3,
    threshold: float = 4.0,
    smooth: int = 3,
    presence: bool = True,
    noise_stop: bool = True,
    library: Mapping[str, Any] | None = None,
    progress: Any = None,
) -> Diagnosis:
    """Diagnose the gap between ``base_model`` and the data (see the module docstring).

    ``params``: the base fit's parameter spec (as :func:`brdfjax.fit.fit`);
    ``effects``: candidate names (default: the whole library; an unknown name,
    or a name whose effect the base already contains, is an error);
    ``heldout_blocks``: frames/tables predicted, never fitted; ``fit_kwargs``:
    passed to every fit; ``bic_threshold``: the BIC gain an effect needs to
    enter the path; ``max_steps``: the most effects added; ``path_pool``: at
    each later step, the previous step's ``path_pool`` best candidates and the
    ``path_pool`` best signatures of the new residual are refitted, with the simpler effects those reduce to
    (``Effect.nests``);
    ``refit_top``: refit only the candidates with the ``refit_top``
    highest signature scores, and at later steps also the previous step's
    runners-up (default: all; the others are reported as not refitted; a
    speed-up with a measured risk: the signature scores of
    different effects are not on one scale, and in the withheld-effect
    benchmark ``refit_top=3`` left the withheld effect unrefitted in 2 of 3
    trials); ``fresh_top``: where a fit moved far from its starts (a free parameter beyond ``FAR_FACTOR``
    = 2 of its start: the base bent to soak up what it lacks), the ``fresh_top`` candidates with the largest
    warm BIC gains are also refitted from the fresh start (initialised on the residual of the model at its
    starts), the better refit kept (0: warm refits only); ``threshold``/``smooth``: the region detection (smoothed ``|z|`` and
    box size); ``library``: the effect library (default
    :data:`brdfjax.diagnose.effects.EFFECT_LIBRARY`); ``presence``: keep a
    candidate whose signature score is below its effect's presence threshold
    (``Effect.presence``, 3) off the path (reported with the reason; False:
    rank by the refit alone); ``noise_stop``: stop once the reduced chi^2 is
    within the noise (``1 + 3 sqrt(2/dof)``; data with sigma only); ``progress``: a callable taking a message string.

    The path is greedy.  Where it took a refit from the fresh starts (``fresh_top``) and still ends above the
    noise, the path without fresh-start refits (``fresh_top = 0``) is run as well and the final model with the
    lower BIC is kept (the same data and likelihood, so the two BICs compare); the report says which and what
    the other path reached.  Measured: on the shipped example (starts far from the truth) the bars refitted
    from the fresh starts entered first and the path stalled at 21x the truth's reduced chi^2, while the warm
    path reached it (1.028 against 1.045); on a reference frame the warm path stalled instead (840 against
    1.112) and the fresh one reached the noise (so no second path is run there).
    """
    kw = dict(effects=effects, heldout_blocks=heldout_blocks, fit_kwargs=fit_kwargs, bic_threshold=bic_threshold,
              max_steps=max_steps, path_pool=path_pool, refit_top=refit_top, threshold=threshold, smooth=smooth,
              presence=presence, noise_stop=noise_stop, library=library, progress=progress)
    # the second path starts as the first did: the base fit and the first step's warm refits are the same
    # computation, so the first path's are reused
    reuse: dict[Any, Any] = {}
    first = _diagnose_once(base_model, blocks, params, fresh_top=fresh_top, reuse=reuse, **kw)
    if fresh_top == 0 or not first.settings["fresh_refit_on_path"] or first.settings["within_noise"]:
        return first
    say = progress or (lambda msg: None)
    say("the path took a fresh-start refit and ends above the noise: trying the path without fresh-start refits")
    second = _diagnose_once(base_model, blocks, params, fresh_top=0, reuse=reuse, **kw)
    bics = [gap_measures(d.final_result)["bic"] for d in (first, second)]
    keep, other = (second, first) if bics[1] < bics[0] else (first, second)

    def describe(d: Diagnosis) -> str:
        steps = " -> ".join(("- " if s_.action == "remove" else "") + s_.effect for s_ in d.path)
        return (f"{steps} (fresh_top = {d.settings['fresh_top']}), final reduced chi^2 "
                f"{d.path[-1].gap['chi2_reduced']:.4g}, BIC {gap_measures(d.final_result)['bic']:.6g}")

    keep.notes.insert(0, f"two paths compared (the first took a fresh-start refit and ended above the noise): kept "
                         f"{describe(keep)}; the other {describe(other)}")
    keep.settings["paths_compared"] = [
        {"fresh_top": d.settings["fresh_top"], "path": [[s_.action, s_.effect] for s_ in d.path],
         "chi2_reduced": d.path[-1].gap["chi2_reduced"], "bic": gap_measures(d.final_result)["bic"],
         "stop_reason": d.stop_reason, "kept": d is keep} for d in (first, second)]
    keep.settings["fresh_top"] = fresh_top
    keep.timings = {k: first.timings.get(k, 0.0) + second.timings.get(k, 0.0) for k in first.timings}
    return keep


def _diagnose_once(
    base_model: Model, blocks: Any, params: Mapping[str, Any], *, effects, heldout_blocks, fit_kwargs, bic_threshold,
    max_steps, path_pool, refit_top, fresh_top, threshold, smooth, presence, noise_stop, library, progress,
    reuse: dict | None = None,
) -> Diagnosis:
    """One greedy path; :func:`diagnose` (whose signature holds the defaults) runs it once or twice.

    ``reuse``: a dict shared by the two paths of one diagnosis.  The first call stores its base fit and its first
    step's warm refits there (copies, taken before anything later changes them); a second call with the same data
    and settings but another ``fresh_top`` starts from them instead of repeating those fits: until the first
    fresh-start refit, the two paths are the same computation.
    """
    t_start = time.perf_counter()
    say = progress or (lambda msg: None)
    if not isinstance(base_model, Model):
        raise DiagnoseInputError(f"base_model must be a brdfjax Model, got {type(base_model).__name__}")
    if library is None:
        library = EFFECT_LIBRARY
    blocks = _check_blocks(blocks, "data")
    heldout = _check_blocks(heldout_blocks, "heldout_blocks") if heldout_blocks else None
    names, skipped = _select_effects(library, effects, base_model)
    fit_kwargs = dict(fit_kwargs or {})
    if not (isinstance(max_steps, int) and max_steps >= 0):
        raise DiagnoseInputError(f"max_steps must be a non-negative integer, got {max_steps!r}")
    if not (isinstance(fresh_top, int) and fresh_top >= 0):
        raise DiagnoseInputError(f"fresh_top must be a non-negative integer, got {fresh_top!r}")
    has_tables = any(isinstance(b, TableData) for b in blocks)
    notes: list[str] = []

    if reuse is not None and "base" in reuse:
        say("the base fit: the first path's, reused")
        base = copy.copy(reuse["base"])
    else:
        say("fitting the base model")
        base = _fit_state(base_model, blocks, dict(params), fit_kwargs, ())
        if reuse is not None:
            reuse["base"] = copy.copy(base)
    if not base.result.converged:
        notes.append(f"the base fit did not converge: {base.result.message}")
    t_base = time.perf_counter()
    ctx = build_context(base_model, params, base.result, blocks, fit_kwargs)
    base.model, base.params = ctx.model, dict(ctx.params)
    groups = [None if isinstance(b, FrameData) else np.round(np.asarray(b.theta_i, float), 6) for b in blocks]
    groups = [None if g is None else np.unique(g, return_inverse=True)[1] for g in groups]
    data_values = [np.where(b.usable(), np.asarray(b.brdf, float), np.nan) for b in blocks]
    regions = find_regions(ctx.residuals, ctx.geometry, data_values, groups=groups, threshold=threshold, smooth=smooth)
    zones = zone_masks(regions, ctx.residuals)
    base_gap = gap_measures(base.result)
    base_heldout = _heldout_gap(base, heldout, blocks)
    gap = dict(base_gap)
    gap["heldout_rms_log10"] = None if base_heldout is None else base_heldout["rms_log10"]
    gap["heldout_chi2_reduced"] = None if base_heldout is None else base_heldout["chi2_reduced"]
    gap["regions_share"] = float(sum(r.share for r in regions))
    t_where = time.perf_counter()
    if has_tables:
        notes.append("goniometer tables: zones are angle intervals relative to the specular direction; effects that need a 2-D frame are skipped")

    base.ctx = ctx
    path = [Step("base", base_gap, _zone_stats(ctx.residuals, zones), base_heldout, math.nan, _params_report(base.result), action="base")]
    state = base
    rankings: list[list[Candidate]] = []
    pool, retry = list(names), []
    removed: list[str] = []
    close: dict[str, list[str]] = {}
    tried_swaps: set = set()
    first_ranked: list[Candidate] = []
    noise = _noise_level(base_gap, blocks) if noise_stop else None
    stop_reason = f"max_steps = {max_steps} reached"
    fresh_taken = False
    fresh_failed = 0
    n_failed, n_retried, failed_names = 0, 0, []
    if noise is not None and base_gap["chi2_reduced"] <= noise:
        stop_reason = f"the base's reduced chi^2 {base_gap['chi2_reduced']:.4g} is within the noise (<= {noise:.4g})"
    for step in range(max(max_steps, 1)):
        current_ctx = state.ctx
        cands = []
        for n in pool:
            eff = library[n]
            if step > 0 and eff.present_in(state.model):
                continue
            cands.append(_check_effect(n, eff, current_ctx, state, has_tables))
        live = sorted((c for c in cands if c.status == "ranked"), key=lambda c: -_score(c))
        if step > 0:
            # re-tried: the previous step's runners-up and the best signatures of the new residual (an
            # effect masked by a larger one at step 1 shows in the residual only once that one is added)
            keep = set(retry) | {c.effect for c in live[:path_pool]}
            keep |= _nested(keep, library)
            for c in live:
                if c.effect not in keep:
                    c.status = "not retried"
                    c.note = f"neither among the previous step's {path_pool} best nor the {path_pool} best signatures"
            live = [c for c in live if c.effect in keep]
        if refit_top is not None:
            # the previous step's runners-up are kept whatever their new signature: they already explained part
            # of the gap (measured: the shipped config's diffraction, second at step 1 with delta BIC 1.2e7, was
            # cut at step 2 by four larger signatures and never entered the path)
            top = {c.effect for c in live[:refit_top]} | set(retry)
            top |= _nested(top, library)
            for c in live:
                if c.effect not in top:
                    c.status = "not refitted"
                    c.note = f"signature score {_score(c):.3g} below the {refit_top} best (refit_top = {refit_top})"
            live = [c for c in live if c.effect in top]
        state_gap = gap_measures(state.result)
        for i, c in enumerate(live):  # "(i/n)": the CLI's progress line counts these for its time estimate
            key = ("warm", c.effect)
            if reuse is not None and step == 0 and key in reuse:
                say(f"step 1: {c.effect}: the first path's warm refit, reused ({i + 1}/{len(live)})")
                _restore_candidate(c, reuse[key])
                continue
            say(f"step {step + 1}: refitting with {c.effect} ({i + 1}/{len(live)}, signature {_score(c):.3g})")
            _refit_effect(c, library[c.effect], current_ctx, state, zones, state_gap)
            if reuse is not None and step == 0:
                reuse[key] = _candidate_copy(c)
        # fresh starts: where the fit moved far from its starts (it bent the model to soak up what it lacks), the
        # fresh_top best candidates are refitted from the fresh start as well, the better refit kept
        top_fresh = _by_gain([c for c in cands if c.status == "ranked" and math.isfinite(c.delta_bic)])[:fresh_top]
        started = _start_context(state, params, base.result) if top_fresh else None
        if started is not None:
            fctx, moved = started
            notes.append(f"step {step + 1}: the fit moved far from its fresh starts ({', '.join(moved)}); the "
                         f"{len(top_fresh)} best candidates were refitted from the fresh starts as well")
            for i, c in enumerate(top_fresh):
                say(f"step {step + 1}: refitting with {c.effect} from the fresh start ({i + 1}/{len(top_fresh)})")
                _refit_fresh(c, library[c.effect], fctx, moved, state, zones, state_gap, bic_threshold)
        ranked, rest = _rank(cands)
        for c in ranked:
            c.flags = _admission_flags(c, library[c.effect], state, presence)
        _admit_dominant(ranked)
        rankings.append(ranked)
        n_failed += sum(1 for c in rest if c.status == "failed")
        n_retried += sum(1 for c in cands if c.retried)
        failed_names += [f"step {step + 1}: {c.effect}" for c in rest if c.status == "failed"]
        if step == 0:
            first_ranked = ranked
            skipped += rest
        if max_steps == 0:
            stop_reason = "max_steps = 0: the candidates are ranked, none added"
            break
        if noise is not None and state_gap["chi2_reduced"] <= noise:
            break
        admissible = _by_gain([c for c in ranked if not c.flags])
        if not admissible or not (admissible[0].delta_bic > bic_threshold):
            held = [c for c in ranked if c.flags and c.delta_bic > bic_threshold]
            stop_reason = ("the gain is not significant: " + (
                f"the best admissible effect, {admissible[0].effect}, gains delta BIC {admissible[0].delta_bic:.4g} "
                f"<= {bic_threshold:g}" if admissible else "no admissible candidate is left"))
            if held:
                stop_reason += "; not added although their BIC gain is larger: " + "; ".join(
                    f"{c.effect} (delta BIC {c.delta_bic:.4g}: {', '.join(c.flags)})" for c in held)
            break
        best = admissible[0]
        step_notes: list[str] = []
        if getattr(library[best.effect], "generic", False):
            # specific runners-up whose only flag is a weak signature are compared too: next to a floor that
            # soaks up their residual the signature is the weaker evidence (measured on reference frames with the
            # far field masked: the bars' periodogram gave 2.0 while a floor took delta BIC 1e7)
            weak = [c for c in ranked if _weak_only(c)]
            best = _specific_first(best, admissible + weak, state, library, bic_threshold, step_notes, say)
        new_state = _with_context(best.state)
        # a candidate refitted from the fresh start already is the joint refit from fresh starts (the same spec)
        fresh_taken = fresh_taken or best.refit_start == "fresh"
        fresh = None if best.refit_start == "fresh" else _fresh_refit(new_state, params)
        if best.refit_start == "fresh":
            step_notes.append("refitted from the fresh starts already (the fit had moved far from them); no second joint refit")
        elif fresh is not None:
            warm_chi2, fresh_chi2 = float(new_state.result.chi2), float(fresh.result.chi2)
            if fresh_chi2 < warm_chi2 * (1 - 1e-6):
                new_state = _with_context(fresh)
                step_notes.append(f"the joint refit from fresh starts reached chi2 {fresh_chi2:.6g} below the warm refit's "
                                  f"{warm_chi2:.6g} and is kept")
            else:
                step_notes.append(f"joint refit from fresh starts: chi2 {fresh_chi2:.6g} (warm {warm_chi2:.6g}, kept)")
        else:
            step_notes.append("the joint refit from fresh starts failed; the warm refit is kept")
            fresh_failed += 1
        state = new_state
        say(f"step {step + 1}: added {best.effect} (delta BIC {best.delta_bic:.1f})")
        alts = [{"effect": c.effect, "delta_bic": c.delta_bic, "margin": best.delta_bic - c.delta_bic, "flags": c.flags}
                for c in _by_gain(ranked) if c is not best and c.delta_bic > 0][:3]
        path.append(_step(best.effect, "add", library[best.effect], state, zones, heldout, blocks, best.delta_bic, path,
                          step_notes, alts))
        if "the joint refit from fresh starts failed; the warm refit is kept" in step_notes:
            path[-1].flags.append("the joint refit from fresh starts failed (counted in settings.failed_refits); "
                                  "the warm refit is kept")
        # backward elimination: an effect on the path that the others now explain is taken out again
        # (measured: a floor taken first for far-field fringes stayed in once the bars were added)
        if len(state.effects) >= 2:
            for e in state.effects[:-1]:
                say(f"step {step + 1}: trying the path without {e}")
                try:
                    w = _without(state, e, base, library)
                except Exception as ex:  # noqa: BLE001 - reported; the effect stays
                    path[-1].notes.append(f"removing {e} failed: {type(ex).__name__}: {ex}")
                    continue
                cost = gap_measures(w.result)["bic"] - gap_measures(state.result)["bic"]
                path[-1].notes.append(f"without {e}: BIC {'+' if cost >= 0 else ''}{cost:.4g}")
                if cost < bic_threshold:
                    state = w
                    removed.append(e)
                    say(f"step {step + 1}: removed {e} (BIC without it {cost:+.1f})")
                    path.append(_step(e, "remove", library[e], state, zones, heldout, blocks, -cost, path,
                                      [f"taken out again: the other effects explain it (BIC change without it {cost:+.4g} "
                                       f"< {bic_threshold:g})"], []))
                    break
        close[best.effect] = _close_alternatives(best, ranked, bic_threshold)
        # swaps: an earlier effect that tied with an alternative when it entered is tried against that
        # alternative now that more of the model is in (the tie is decided on the joint refit)
        swap = _try_swaps(state, base, close, tried_swaps, removed, library, bic_threshold, say, path[-1].notes, params)
        if swap is not None:
            w, sw, e, g, change = swap
            removed.append(e)
            say(f"step {step + 1}: swapped {e} for {g} (BIC {change:+.1f})")
            cost_w = gap_measures(w.result)["bic"] - gap_measures(state.result)["bic"]
            before_swap = path[-1]
            path.append(_step(e, "remove", library[e], w, zones, heldout, blocks, -cost_w, path,
                              [f"taken out for {g}, its close alternative when it entered: the path with {g} in its "
                               f"place has BIC {change:+.4g} (the middle of a swap: its held-out gap is not "
                               "questioned; the next step's is compared with the step before the swap)"], [],
                              compare=False))
            state = _with_context(sw)
            path.append(_step(g, "add", library[g], state, zones, heldout, blocks, gap_measures(w.result)["bic"]
                              - gap_measures(state.result)["bic"], path,
                              [f"swapped in for {e} (BIC {change:+.4g} against the path with {e})"], [],
                              compare=before_swap))
        retry = [c.effect for c in _by_gain(ranked) if c is not best and c.delta_bic > 0][:path_pool]
        pool = [n for n in names if n not in state.effects and n not in removed]
        g_now = gap_measures(state.result)
        if noise is not None and g_now["chi2_reduced"] <= noise:
            stop_reason = f"the reduced chi^2 {g_now['chi2_reduced']:.4g} is within the noise (<= {noise:.4g}, 1 + 3 sqrt(2/dof))"
            break
    state = _final_check(state, base, library, bic_threshold, path, removed, zones, heldout, blocks, say)
    current_ctx = state.ctx
    for s_ in path:
        for f in s_.flags:
            notes.append(f"path step {s_.action} {s_.effect}: {f}")
    for r in rankings:
        for c in r:
            c.state = None  # drop the refits' data (memory); the path keeps what it needs
    t_end = time.perf_counter()
    return Diagnosis(
        gap=gap,
        regions=regions,
        block_names=[b.name for b in base.result.blocks],
        ranking=first_ranked,
        skipped=skipped,
        path=path,
        significant=len(state.effects) > 0,
        bic_threshold=float(bic_threshold),
        notes=notes + [f"{c.effect}: {c.status}: {c.note}" for c in skipped],
        timings={"base_fit_s": t_base - t_start, "where_s": t_where - t_base, "which_and_path_s": t_end - t_where, "total_s": t_end - t_start},
        settings={
            "effects": list(names),
            "max_steps": max_steps,
            "path_pool": path_pool,
            "refit_top": refit_top,
            "fresh_top": fresh_top,
            "presence_threshold": presence,
            "noise_stop": noise_stop,
            "bic_threshold": bic_threshold,
            "threshold_sigma": threshold,
            "smooth": smooth,
            "n_blocks": len(blocks),
            "n_heldout": 0 if heldout is None else len(heldout),
            "fresh_refit_on_path": fresh_taken,
            "failed_refits": {
                "candidates": n_failed,
                "which": failed_names,
                "retried": n_retried,
                "fresh_start_on_path": fresh_failed,
            },
            "within_noise": bool(noise is not None and gap_measures(state.result)["chi2_reduced"] <= noise),
        },
        context=ctx,
        final_context=current_ctx,
        path_rankings=rankings,
        base_result=base.result,
        final_result=state.result,
        stop_reason=stop_reason,
        final_params=dict(state.params),
        final_effects=[(e, getattr(library[e], "side", "material")) for e in state.effects],
    )

