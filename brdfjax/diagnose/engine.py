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
5. HOW FAR: the search of :mod:`brdfjax.diagnose.search` on :class:`FrameProblem`: at each step every
   applicable candidate is refitted added to the current set (the signature orders the work, it excludes
   nothing); the ``pair_top`` best admissible ones are also refitted in pairs; an effect whose own terms end
   dead, undetermined or on a bound never enters; a generic effect (a floor, a response curve) does not
   enter where a specific one explains its residual on their joint refit; the best single or pair enters
   when it gains more than ``bic_threshold`` (a pair only when it beats its better member by that much); after
   every step each effect of the set is taken out in turn (the model refitted) and one whose removal costs
   less than ``bic_threshold`` is taken out.  The search stops when nothing passes the threshold, the reduced
   chi^2 is within one standard deviation of the noise's (``1 + sqrt(2/dof)``, data with sigma), or after
   ``max_steps``
   (``Diagnosis.stop_reason`` says which).  A step after which the held-out gap grows is flagged.  Every
   step records the global gap (``chi2_reduced``, ``rms_log10``), the per-zone reduced chi^2 on the base's
   zones, and, when ``heldout_blocks`` are given, the prediction gap on them (the fitted model evaluated,
   nothing refitted, at the held-out frames' nominal conditions).  Every trial (failed ones included) is in
   ``settings.trials``; failed refits are counted in ``settings.failed_refits``.

The engine never sees a generator's truth: only the blocks and the library.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from ..core.terms import Model
from ..fit import FitInputError, FrameData, TableData
from ..runtime import export_cache
from ..runtime.choices import check_choices
from ..runtime.compile_cache import maps_near_limit, release_compiled, resident_mb
from ..runtime.errors import InputError
from .admission import _WEAK, effect_flags
from .context import build_context, gap_measures, residual_maps
from .effects import EFFECT_LIBRARY
from .model_config import (  # noqa: F401 - the model-to-TOML writer, importable from here as before
    final_model_config,
    model_terms_config,
    toml_text,
)
from .refits import (  # noqa: F401 - truth_gap and the refit budget, importable from here as before
    FAR_FACTOR,
    RETRY_STEPS,
    STOP_SIGMAS,
    _by_gain,
    _check_effect,
    _fit_state,
    _fresh_refit,
    _heldout_gap,
    _noise_level,
    _params_report,
    _rank,
    _refit_effect,
    _refit_fresh,
    _score,
    _start_context,
    _State,
    _with_context,
    _without,
    _zone_stats,
    model_weighted_blocks,
    refine_data_side,
    refit_on,
    truth_gap,
)
from .report import heldout_grew
from .results import Candidate, Diagnosis, Step, finite_or_none
from .search import SearchMove, Trial, search
from .zones import find_regions, zone_masks

__all__ = ["DiagnoseInputError", "diagnose", "final_model_config", "model_terms_config", "toml_text", "truth_gap"]


#: With the persistent compilation cache on, the compiled programs of earlier refits are dropped from memory
#: once the process holds more than this many MB (:func:`brdfjax.runtime.compile_cache.release_compiled`): each
#: candidate model compiles about 100 MB of programs of its own, and a set refitted again reads them back
#: from disk (measured on the shipped withheld-diffraction example: 2.04 GB peak without, 0.74 GB with a drop
#: after every refit).
RELEASE_ABOVE_MB = 450.0

#: Refits side by side (:class:`_ReleaseGate`) pause to drop compiled programs once the process holds more than
#: this many MB: each drop waits for the refits in flight, so it is set above :data:`RELEASE_ABOVE_MB`, where one
#: refit after another drops them.
PARALLEL_RELEASE_ABOVE_MB = 650.0

#: The most refits run at once by default (:meth:`FrameProblem.refit_many`): each refit in flight holds its own
#: model's programs (about 100 MB each on the shipped example).
MAX_WORKERS = 4


def default_workers() -> int:
    """Half the cores this process may use (at least 1, at most :data:`MAX_WORKERS`).

    One refit already keeps about 1.3 cores busy (XLA compiles on threads of its own: 126 s of CPU in 101 s
    wall on the shipped example, one refit after another); on 2 cores two refits side by side took 89 s against
    101 s but peaked at 0.79 GB against 0.62 GB (``experiments/benchmark_diagnose.py --workers 1,2``,
    ``experiments/results/benchmark_diagnose_workers.json``), so a 2-core machine refits one after another
    unless asked."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(n // 2, MAX_WORKERS))


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


@dataclass
class _Fitted:
    """What a :class:`~brdfjax.diagnose.search.Trial` of the frame/table problem carries: the fit state (None
    when the refit failed) and, for a trial that added one effect, its :class:`Candidate` (signature, note)."""

    state: _State | None
    cand: Candidate | None = None
    polish_note: str = ""
    polish_failed: bool = False


class _ReleaseGate:
    """Refits in flight side by side, and the release of their compiled programs between them.

    Each refit holds its own model's programs (about 100 MB on the shipped example), and
    :func:`~brdfjax.runtime.compile_cache.release_compiled` may only run where no other thread is tracing or
    compiling.  Once a refit ends with the process above :data:`PARALLEL_RELEASE_ABOVE_MB`, no new refit starts until
    those in flight end; the last of them releases the programs, and the refits go on.  (Holding every
    program until the step's last refit measured 1,467 MB peak on the shipped example, against 778 MB one
    refit after another.)"""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._in = 0
        self._drain = False

    def enter(self) -> None:
        with self._cond:
            while self._drain:
                self._cond.wait()
            self._in += 1

    def leave(self) -> None:
        with self._cond:
            self._in -= 1
            if not self._drain:
                mb = resident_mb()
                self._drain = maps_near_limit() or (mb is not None and mb > PARALLEL_RELEASE_ABOVE_MB)
            if self._drain and self._in == 0:
                release_compiled(above_mb=RELEASE_ABOVE_MB)
                self._drain = False
                self._cond.notify_all()


class FrameProblem:
    """The frame/table diagnosis as a :class:`~brdfjax.diagnose.search.SearchProblem`.

    A refit adds each missing effect by its ``Effect.extend`` on the context of the fit it extends (warm start
    at its optimum; a failed refit is retried from a second start, :func:`~brdfjax.diagnose.refits._refit_effect`)
    and takes an extra effect out by :func:`~brdfjax.diagnose.refits._without` (refitted).  Where the fit it
    extends moved far from its fresh starts (``fresh``), a single effect is also refitted from the fresh start
    and the better refit kept.  Flags: :func:`~brdfjax.diagnose.admission.effect_flags`.
    """

    def __init__(self, base: _State, names: list[str], library: Mapping[str, Any], params0: Mapping[str, Any],
                 zones: Any, has_tables: bool, *, fresh: bool, presence: bool, noise: float | None,
                 bic_threshold: float, say: Any, workers: int = 1):
        self._base, self._names, self._lib, self._params0 = base, list(names), library, params0
        self._zones, self._tables, self._fresh, self._presence = zones, has_tables, fresh, presence
        self._noise, self._T, self._say, self._workers = noise, bic_threshold, say, max(int(workers), 1)
        self._checks: dict[tuple[frozenset, str], Candidate] = {}
        self._starts: dict[frozenset, Any] = {}
        self._known: dict[frozenset, Trial] = {}
        self.base_trial = self._trial(base, None, None, ())

    # --- the protocol ---
    def candidates(self) -> list[str]:
        return list(self._names)

    def generic(self, effect: str) -> bool:
        return bool(getattr(self._lib[effect], "generic", False))

    def base(self) -> Trial:
        return self.base_trial

    def applicable(self, current: tuple[str, ...], effect: str) -> str | None:
        st = self._state(current)
        if st is None:
            return "the set's fit is not available"
        if current and self._lib[effect].present_in(st.model):
            return "already in the model"
        c = self.check(current, effect)
        return None if c.status == "ranked" else f"{c.status}: {c.note}"

    def within_noise(self, trial: Trial) -> bool | None:
        """Whether ``trial``'s reduced chi^2 is within the search's stop level; None: the data carry no sigma."""
        return None if self._noise is None else bool(trial.ok and trial.chi2_reduced <= self._noise)

    def order(self, current: Trial, effects: list[str]) -> list[str]:
        return sorted(effects, key=lambda e: -_score(self.check(current.effects, e)))

    def polish(self, trial: Trial) -> Trial:
        """The committed set refitted jointly from fresh starts as well (the lower chi^2 kept), then its data-side
        parameters (the footprint's width) rescanned on that fit and refitted (:func:`refine_data_side`)."""
        return self.refine(self._polish_fresh(trial))

    def refine(self, trial: Trial) -> Trial:
        """``trial`` with its data-side parameters (the footprint's width) rescanned on its own fit and refitted
        (:func:`refine_data_side`); the trial itself where none of its effects has one, or nothing moved."""
        if not trial.ok or trial.state is None or not any(hasattr(self._lib[e], "refine") for e in trial.effects):
            return trial
        st = self._ctx(trial.state.state)
        new, note = refine_data_side(st, self._base.blocks, self._lib)
        release_compiled(above_mb=RELEASE_ABOVE_MB)
        if not note:
            return trial
        t = self._trial(new, trial.state.cand, None, trial.effects)
        t.flags = trial.flags | {e: effect_flags(new, e, None) for e in trial.effects}
        t.state.polish_note = "; ".join(x for x in (trial.state.polish_note, note) if x)
        t.state.polish_failed = trial.state.polish_failed
        return t

    def _polish_fresh(self, trial: Trial) -> Trial:
        f = trial.state
        if f.cand is not None and f.cand.refit_start == "fresh":
            f.polish_note = "refitted from the fresh starts already (the fit had moved far from them); no second joint refit"
            return trial
        st = _with_context(f.state) if f.state.ctx is None else f.state
        fresh = _fresh_refit(st, self._params0)
        release_compiled(above_mb=RELEASE_ABOVE_MB)
        if fresh is None:
            f.polish_note, f.polish_failed = "the joint refit from fresh starts failed; the warm refit is kept", True
            return trial
        warm_chi2, fresh_chi2 = float(st.result.chi2), float(fresh.result.chi2)
        if fresh_chi2 < warm_chi2 * (1 - 1e-6):
            new = self._trial(_with_context(fresh), f.cand, None, trial.effects)
            new.flags = trial.flags | {e: effect_flags(new.state.state, e, None) for e in trial.effects}
            new.state.polish_note = (f"the joint refit from fresh starts reached chi2 {fresh_chi2:.6g} below the warm "
                                     f"refit's {warm_chi2:.6g} and is kept")
            return new
        f.polish_note = f"joint refit from fresh starts: chi2 {fresh_chi2:.6g} (warm {warm_chi2:.6g}, kept)"
        return trial

    def refit(self, effects: tuple[str, ...], warm: Trial | None) -> Trial:
        try:
            return self._refit(effects, warm)
        finally:
            # each set of effects is a differently shaped model with programs of its own; with the persistent
            # compilation cache on they are dropped from memory here (read back from disk if a later refit of
            # the same set needs them) once they pass RELEASE_ABOVE_MB, so the memory stays that of a few refits,
            # not of every refit so far
            release_compiled(above_mb=RELEASE_ABOVE_MB)

    def refit_many(self, requests: Sequence[tuple[tuple[str, ...], Trial | None]],
                   labels: Sequence[str] | None = None) -> list[Trial]:
        """The refits of ``requests`` (effects, warm start), in threads (``workers`` at a time), in their order.

        Each refit is independent of the others (its own model, its own fit from its own warm start), so they
        run side by side: much of a refit's time is XLA's compilation of the new model's programs, which runs
        outside Python's lock.  What the refits share is prepared first, in this thread (the warm fits'
        contexts, the fresh starts, the signature checks); compiled programs are released only while no refit
        is in flight (:class:`_ReleaseGate`).  The numbers are those of the refits one after another
        (``tests/diagnose/test_diagnose_engine.py`` compares them)."""
        labels = list(labels) if labels is not None else [None] * len(requests)
        if self._workers <= 1 or len(requests) <= 1:
            out = []
            for (effects, warm), label in zip(requests, labels):
                if label:
                    self._say(label)
                out.append(self.refit(effects, warm))
            return out
        for effects, warm in requests:
            st, add, drop = self._start_of(effects, warm)
            if len(add) == 1 and not drop:
                known = self._known.get(_key(st.effects))
                if known is not None and known.state is not None and known.state.state is st:
                    self.check(st.effects, add[0])
                if self._fresh:
                    self._start(st)
        gate = _ReleaseGate()

        def one(i: int) -> Trial:
            gate.enter()
            try:
                if labels[i]:
                    self._say(labels[i])
                effects, warm = requests[i]
                return self._refit(effects, warm)
            finally:
                gate.leave()

        known = set(self._known)
        with ThreadPoolExecutor(max_workers=min(self._workers, len(requests)), thread_name_prefix="brdfjax-refit") as pool:
            out = list(pool.map(one, range(len(requests))))
        release_compiled(above_mb=RELEASE_ABOVE_MB)
        # a set first fitted here is known by its first fit in the requests' order (not the first to finish),
        # as one refit after another would leave it
        for t in out:
            k = _key(t.effects)
            if t.ok and k not in known:
                self._known[k] = t
                known.add(k)
        return out

    def _start_of(self, effects: tuple[str, ...], warm: Trial | None) -> tuple[_State, list[str], list[str]]:
        """Where the refit of ``effects`` from ``warm`` starts (the base where ``warm`` failed): the warm fit's
        state (its context built), the effects to add and those to take out."""
        warm = warm if warm is not None and warm.ok else self.base_trial
        add = [e for e in effects if e not in warm.effects]
        drop = [e for e in warm.effects if e not in effects]
        return self._ctx(warm.state.state), add, drop

    def _refit(self, effects: tuple[str, ...], warm: Trial | None) -> Trial:
        st, add, drop = self._start_of(effects, warm)
        try:
            for e in drop:
                st = _without(st, e, self._base, self._lib)
        except Exception as ex:  # noqa: BLE001 - reported as a failed trial
            return self._failed(effects, f"taking out {', '.join(drop)} failed: {type(ex).__name__}: {ex}")
        cand = None
        before = st
        for i, e in enumerate(add):
            known = self._known.get(_key(st.effects))
            if known is not None and known.state is not None and known.state.state is st:
                c = copy.copy(self.check(st.effects, e))  # the signature on this fit, computed once
            else:
                c = _check_effect(e, self._lib[e], st.ctx, st, self._tables)
            c.flags = []
            if c.status != "ranked":
                return self._failed(effects, f"{e} cannot be added to {' + '.join(st.effects) or 'the base'}: {c.note}")
            gap0 = gap_measures(st.result)

            def own_flags(s: _State, e: str = e, st: _State = st) -> list[str]:
                """The admission flags of ``e``'s own terms in a refit ``s`` of ``st`` plus ``e``."""
                return effect_flags(s, e, st, None)

            _refit_effect(c, self._lib[e], st.ctx, st, self._zones, gap0, own_flags)
            if c.status == "ranked" and self._fresh and len(add) == 1:
                started = self._start(st)
                if started is not None:
                    fctx, moved = started
                    self._say(f"refitting with {e} from the fresh start as well (the fit moved far from its starts)")
                    _refit_fresh(c, self._lib[e], fctx, moved, st, self._zones, gap0, self._T, own_flags)
            if c.status != "ranked" and self._fresh and len(add) == 1:
                # the warm refit failed twice (warm start, second start): a third start, from the fresh starts,
                # where the fit it extends moved far from them
                started = self._start(st)
                if started is not None:
                    fctx, moved = started
                    self._say(f"the refit with {e} failed; refitting from the fresh start")
                    alt = Candidate(e, c.title, "ranked", signature=c.signature)
                    _refit_effect(alt, self._lib[e], fctx, st, self._zones, gap0, own_flags)
                    if alt.status == "ranked":
                        alt.refit_start, alt.retried = "fresh", True
                        alt.note = (f"the warm refit failed ({c.note[:240]}); refitted from the fresh start (the fit "
                                    f"had moved far: {', '.join(moved[:3])}): {alt.note}")
                        c = alt
                    else:
                        c.note += f"; from the fresh start: {alt.note[:240]}"
            if c.status != "ranked":
                return self._failed(effects, c.note, c)
            before = st
            st = c.state if i == len(add) - 1 else self._ctx(c.state)
            cand = c
        t = self._trial(st, cand if len(add) == 1 else None, before if add else None, effects)
        if cand is not None and len(add) == 1:
            cand.flags = list(t.flags.get(add[0], []))
        return t

    # --- helpers ---
    def check(self, current: tuple[str, ...], effect: str) -> Candidate:
        """Applicability, identifiability and signature of ``effect`` on the fit of ``current`` (cached)."""
        k = (_key(current), effect)
        if k not in self._checks:
            st = self._state(current)
            self._checks[k] = _check_effect(effect, self._lib[effect], st.ctx, st, self._tables)
        return self._checks[k]

    def _ctx(self, st: _State) -> _State:
        return _with_context(st) if st.ctx is None else st

    def _state(self, current: tuple[str, ...]) -> _State | None:
        t = self._known.get(_key(current))
        if t is None or t.state is None or t.state.state is None:
            return None
        t.state.state = self._ctx(t.state.state)
        return t.state.state

    def _start(self, st: _State):
        k = _key(st.effects)
        if k not in self._starts:
            self._starts[k] = _start_context(st, self._params0, self._base.result)
        return self._starts[k]

    def _trial(self, st: _State, cand: Candidate | None, before: _State | None, effects: tuple[str, ...]) -> Trial:
        g = gap_measures(st.result)
        new = [e for e in st.effects if before is None or e not in before.effects]
        flags = {}
        for e in st.effects:
            weak = None
            if self._presence and cand is not None and e == cand.effect:
                score, pres = cand.signature.get("score"), getattr(self._lib[e], "presence", 3.0)
                if score is not None and score < pres:
                    weak = f"its signature score {score:.3g} is below its {_WEAK} {pres:g}"
            flags[e] = effect_flags(st, e, before if e in new else None, weak)
        t = Trial(tuple(st.effects), True, None, g["bic"], g["chi2_reduced"], g["n_free"], None, flags, _Fitted(st, cand))
        self._known.setdefault(_key(st.effects), t)
        return t

    def remember(self, t: Trial) -> None:
        """The search moved to ``t``: later applicability checks of its set use this fit."""
        self._known[_key(t.effects)] = t

    def _failed(self, effects: tuple[str, ...], why: str, cand: Candidate | None = None) -> Trial:
        return Trial(tuple(effects), False, why, math.nan, math.nan, 0, None, {}, _Fitted(None, cand))


def _confirm_with_model_weights(problem: FrameProblem, result: Any, library: Mapping[str, Any], T: float,
                                notes: list[str], say: Any) -> Any:
    """Rule 7: every term the final set added stays only if it also pays for itself with noise weights evaluated
    at the final model.

    The search weighs every fit by the readings' own noise (one weighting for every candidate).  A reading's
    relative noise falls as the reading rises, so the upward fluctuations of the faint pixels weigh more (and
    a detection cut keeps only those): a floor or a wide lobe then gains BIC from the weighting, not from the
    surface (measured on the reference generator, diffraction withheld, every 4th pixel: a floor entered
    jointly with diffraction at 13.8; with the weights at the diffraction fit it gains 4.4 in chi^2, below
    the BIC's own penalty).  Each effect that added terms is taken out of the final fit refitted on the
    frames weighted at that fit's model; the cheapest whose removal costs less than ``T`` there is removed
    (the path's row is the set refitted with the readings' weights, as every other row) and the test repeats.
    Effects that changed the model otherwise (a footprint, a response, a swap) are not retested.
    """
    cur = result.final
    moves = list(result.moves)
    step = moves[-1].step if moves else 1
    while cur.ok and cur.effects:
        F = problem._ctx(cur.state.state)
        terms = [e for e in cur.effects if F.added_terms.get(e)]
        if not terms:
            break
        rw = model_weighted_blocks(F)
        if rw is None:
            break
        say("confirming the final set with noise weights evaluated at its model")
        try:
            Fm = refit_on(F, rw)
        except Exception as ex:  # noqa: BLE001 - reported; the search's set stands
            notes.append(f"the final set could not be refitted with noise weights at its model ({type(ex).__name__}: {ex}); "
                         "it stands as the search left it")
            break
        bic_m = gap_measures(Fm.result)["bic"]
        costs = []
        for e in terms:
            try:
                Sm = _without(Fm, e, None, library)  # dropped, never replayed: the base was fitted on other weights
            except Exception as ex:  # noqa: BLE001 - reported; the effect stays
                notes.append(f"with noise weights at the final model, taking out {e} could not be refitted "
                             f"({type(ex).__name__}: {ex}); it stays")
                continue
            costs.append((gap_measures(Sm.result)["bic"] - bic_m, e))
        text = ", ".join(f"{e} {c:+.4g}" for c, e in costs)
        below = sorted(c for c in costs if c[0] < T)
        if not below:
            notes.append(f"confirmed with noise weights evaluated at the final model: taking out each term-adding "
                         f"effect costs (BIC) {text} (each >= {T:g})")
            break
        cost, e = below[0]
        rest = tuple(x for x in cur.effects if x != e)
        t = problem.refit(rest, cur)
        if not t.ok:
            notes.append(f"with noise weights at the final model taking out {e} costs {cost:.4g} < {T:g}, but the set "
                         f"without it could not be refitted ({t.failure}); it stays")
            break
        problem.remember(t)
        note = (f"taken out with noise weights evaluated at the final model: there its removal costs {cost:+.4g} "
                f"(< {T:g}; removals there: {text}), against {t.bic - cur.bic:+.4g} with the readings' own weights, "
                "which favour the upward fluctuations of faint pixels (rule 7)")
        say(f"removed {e} with the noise weights at the final model (BIC {cost:+.1f} < {T:g})")
        moves.append(SearchMove("remove", (e,), t, cur.bic - t.bic, step, [note]))
        cur = t
    if cur is result.final:
        return result
    return dataclasses.replace(result, final=cur, moves=moves)


def _key(effects: Sequence[str]) -> frozenset:
    return frozenset(effects)


def _candidates_of(trials: list[Trial], before: Trial, best_of: Mapping[frozenset, Trial] | None = None,
                   zones: Any = None) -> list[Candidate]:
    """The single-effect trials of one step as :class:`Candidate` (gains relative to ``before``).

    A candidate is ranked by the best fit of its set that the search found (``best_of``, by set of effects):
    a refit warm-started from the model it extends can sit in a poorer optimum than the same model reached
    from a larger fit with another effect taken out (rules 3 and 5).  On the shipped example diffraction alone
    refitted from the base reached a BIC gain of 1.92e7 (reduced chi^2 5044), behind a uniform floor's 2.20e7;
    taken out of its joint refit with the floor it reaches 1.028, the final model: the floor ranked first for
    a gap it does not explain.  The candidate's figures (gain, parameters, zones) are then those of the better
    fit, and its note says so."""
    out = []
    for t in trials:
        c = t.state.cand if t.state is not None else None
        e = t.effects[-1] if t.effects else "?"
        if c is None:
            c = Candidate(e, e, "failed" if not t.ok else "ranked", note=t.failure or "")
        if not t.ok:
            c.status = "failed"
            c.note = t.failure or c.note
        else:
            best = (best_of or {}).get(_key(t.effects))
            if best is not None and best is not t and best.ok and best.bic < t.bic and best.state is not None \
                    and best.state.state is not None and c.status == "ranked":
                st = best.state.state
                c = copy.copy(c)
                g = gap_measures(st.result)
                c.note = (f"ranked by its best fit, which the search reached from another start (a larger fit with "
                          f"an effect taken out, or a smaller one fitted forward): delta BIC {before.bic - best.bic:.6g}"
                          f" (refitted from {' + '.join(before.effects) or 'the base'}: {before.bic - t.bic:.6g}); "
                          f"{c.note}")
                c.delta_chi2 = c.delta_chi2 + (c.gap_after.get("chi2", g["chi2"]) - g["chi2"])
                c.gap_after = g
                c.parameters = {k: p.natural() for k, p in st.result.parameters.items()
                                if k.split("[", 1)[0] in {x.split("[", 1)[0] for x in c.parameters}}
                if zones is not None:
                    c.zones_after = _zone_stats(residual_maps(st.result, st.blocks), zones)
                t = best
            c.flags = list(t.flags.get(c.effect, []))
            c.delta_bic = before.bic - t.bic
        out.append(c)
    return out


def _explanation_first(ranked: list[Candidate], explanation: set[str] | frozenset[str]) -> list[Candidate]:
    """The ranking with the candidates the search's final explanation holds before those it does without.

    The ranking answers "which effect"; the search's answer is its final explanation.  A candidate that gains
    most alone but that the final set does without was bettered by that set: alone it stood in for the final
    set's effects (measured on the withheld-effect benchmark, seeds 9608-9655: the first-ranked effect was not in
    the final model in 27 of 227 trials, 8 of them with diffraction withheld, and the report's headline, read
    from the final model, then named another effect than its own ranking).  Each group keeps its order by gain; gains
    stay those of the single refits; a moved candidate's note names those it was moved before.  Candidates
    ranked by a detection stay first."""
    lead = [c for c in ranked if c.ranked_by == "detection"]
    rest = [c for c in ranked if c.ranked_by != "detection"]
    held = [c for c in rest if c.effect in explanation]
    others = [c for c in rest if c.effect not in explanation]
    if not held or rest[:len(held)] == held:
        return ranked
    for c in held:
        above = [o.effect for o in rest[:rest.index(c)] if o.effect not in explanation]
        if above:
            c.ranked_by = "explanation"
            c.note = (f"ranked before {', '.join(above)} (not in the final model, larger gains alone): the search's "
                      f"final explanation holds {c.effect} and does without them" + (f"; {c.note}" if c.note else ""))
    return lead + held + others


def _specific_first(ranked: list[Candidate], before: Trial, best_of: Mapping[frozenset, Trial],
                    generic: Callable[[str], bool], T: float,
                    explanation: set[str] | frozenset[str] | None = None) -> list[Candidate]:
    """The ranking with the specific effect that the data require beside a leading generic one moved before it.

    A generic effect G (a floor, a second lobe, a distribution swap) ranked first takes, alone, what it absorbs
    of every signature on top of its own.  A specific candidate S (admissible, gaining more than ``T`` alone)
    that still gains more than ``T`` beside G on their joint refit (the best fit of ``before + {G, S}`` the
    search found, S's own terms sound there) is required by the data whatever G takes, and names the cause:
    the S whose joint fit with G is lowest (the one that best completes G) is ranked before G.  Only that one:
    where G alone is far from the data every specific effect gains more than ``T`` beside it (measured on the
    NumPy reference, diffraction and a floor withheld, seed 9641: stray light and a misalignment, 7.6e6 and
    2.0e5 alone, gained beside a second lobe too), and their order then says nothing their gains do not.
    Measured on the withheld-effect benchmark, seeds 9608-9640: with diffraction and a floor withheld a second
    lobe or a distribution swap ranked first in 4 of the 8 trials.  Gains stay those of the single refits; only
    the order moves, and the moved candidate's note says why.  Candidates ranked by a detection stay first.
    Where G is in the search's final ``explanation``, S is sought among the explanation's effects only (the
    ranking's first entry stays one the final model holds).
    """
    lead = [c for c in ranked if c.ranked_by == "detection"]
    rest = [c for c in ranked if c.ranked_by != "detection"]
    if not rest or not generic(rest[0].effect) or not rest[0].delta_bic > T:
        return ranked
    g = rest[0]
    g_fit = best_of.get(_key(before.effects + (g.effect,)))
    if g_fit is None or not g_fit.ok:
        return ranked
    need: list[tuple[float, Candidate]] = []  # (the joint fit's BIC, S)
    within = explanation if explanation and g.effect in explanation else None
    for c in rest[1:]:
        if generic(c.effect) or c.flags or not c.delta_bic > T or (within is not None and c.effect not in within):
            continue
        pair = best_of.get(_key(before.effects + (g.effect, c.effect)))
        if pair is not None and pair.ok and not pair.own_flags([c.effect]) and g_fit.bic - pair.bic > T:
            need.append((pair.bic, c))
    if not need:
        return ranked
    pair_bic, s = min(need, key=lambda x: x[0])
    s.ranked_by = "specific"
    s.note = (f"ranked before {g.effect} (generic, delta BIC {g.delta_bic:.4g}): on their joint refit "
              f"{s.effect} still gains {g_fit.bic - pair_bic:.4g} > {T:g} beside it, so the data require it whatever "
              f"{g.effect} absorbs" + (f"; {s.note}" if s.note else ""))
    return lead + [s] + [c for c in rest if c is not s]


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
    pair_top: int = 3,
    fresh_top: int = 3,
    threshold: float = 4.0,
    smooth: int = 3,
    presence: bool = False,
    noise_stop: bool = True,
    library: Mapping[str, Any] | None = None,
    progress: Any = None,
    workers: int | None = None,
    fast_compile: bool = True,
    path_pool: int | None = None,
    refit_top: int | None = None,
) -> Diagnosis:
    """Diagnose the gap between ``base_model`` and the data (see the module docstring).

    ``params``: the base fit's parameter spec (as :func:`brdfjax.fit.fit`); ``effects``: candidate names
    (default: the whole library; an unknown name, or a name whose effect the base already contains, is an
    error); ``heldout_blocks``: frames/tables predicted, never fitted; ``fit_kwargs``: passed to every fit;
    ``bic_threshold``: the BIC gain an effect needs to enter, and the BIC cost of its removal it needs to stay;
    ``max_steps``: the most steps of the search; ``pair_top``: the best admissible singles refitted in pairs at
    each step (:func:`brdfjax.diagnose.search.search`); ``fresh_top``: 0 turns off the refits from the fresh
    starts (any other value: where the fit a candidate extends moved far from its starts, a free parameter
    beyond ``FAR_FACTOR`` = 2 of its start, the candidate is refitted from the fresh start as well and the
    better refit kept); ``threshold``/``smooth``: the region detection (smoothed ``|z|`` and box size);
    ``presence``: also keep off a candidate whose signature score is below its effect's presence threshold
    (default False: the signature orders the refits and is reported, it never excludes); ``noise_stop``: stop
    once the reduced chi^2 after a move is within one standard deviation of the noise's (``1 + sqrt(2/dof)``,
    :data:`~brdfjax.diagnose.refits.STOP_SIGMAS`; data with sigma only; the base is always taken through step 1); ``library``: the
    effect library; ``progress``: a callable taking a message string; ``workers``: how many of a step's
    independent refits (its singles, its pairs) run at once, in threads (default :func:`default_workers`: half
    the cores this process may use, at most :data:`MAX_WORKERS`; 1: one after another; the numbers are the same);
    ``fast_compile``: on the CPU, compile the fits' exported programs with
    :data:`~brdfjax.runtime.export_cache.FAST_COMPILE_CPU` (every candidate model is a program of its own, compiled
    for a few solves: compiling dominates a diagnosis; False: XLA's defaults; the numbers agree to about 1e-13
    relative).  ``path_pool`` and ``refit_top`` belonged
    to the earlier greedy path and are refused (every candidate is refitted at every step now).
    """
    if not isinstance(fast_compile, bool):
        raise DiagnoseInputError(f"fast_compile must be true or false, got {fast_compile!r}")
    options = export_cache.FAST_COMPILE_CPU if fast_compile and jax.default_backend() == "cpu" else None
    with export_cache.compiler_options(options):
        return _diagnose(base_model, blocks, params, effects=effects, heldout_blocks=heldout_blocks,
                         fit_kwargs=fit_kwargs, bic_threshold=bic_threshold, max_steps=max_steps, pair_top=pair_top,
                         fresh_top=fresh_top, threshold=threshold, smooth=smooth, presence=presence,
                         noise_stop=noise_stop, library=library, progress=progress, workers=workers,
                         path_pool=path_pool, refit_top=refit_top)


def _diagnose(base_model, blocks, params, *, effects, heldout_blocks, fit_kwargs, bic_threshold, max_steps, pair_top,
              fresh_top, threshold, smooth, presence, noise_stop, library, progress, workers, path_pool,
              refit_top) -> Diagnosis:
    """:func:`diagnose`'s body, under the compiler options it chose."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: None)
    if refit_top is not None or path_pool is not None:
        raise DiagnoseInputError(
            f"{'refit_top' if refit_top is not None else 'path_pool'} is no longer an option of diagnose(): the search "
            "refits every applicable candidate at every step (signatures only order the work); remove it")
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
    if not (isinstance(pair_top, int) and pair_top >= 1):
        raise DiagnoseInputError(f"pair_top must be a positive integer, got {pair_top!r}")
    if workers is None:
        workers = default_workers()
    if not (isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1):
        raise DiagnoseInputError(f"workers must be a positive integer, got {workers!r}")
    has_tables = any(isinstance(b, TableData) for b in blocks)
    notes: list[str] = []

    say("fitting the base model")
    base = _fit_state(base_model, blocks, dict(params), fit_kwargs, ())
    if not base.result.converged:
        notes.append(f"the base fit did not converge: {base.result.message}")
    t_base = time.perf_counter()
    ctx = build_context(base_model, params, base.result, blocks, fit_kwargs)
    base.model, base.params, base.ctx = ctx.model, dict(ctx.params), ctx
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
    release_compiled()  # the base fit's programs: read back from the persistent cache when needed again
    if has_tables:
        notes.append("goniometer tables: zones are angle intervals relative to the specular direction; effects that need a 2-D frame are skipped")

    noise = _noise_level(base_gap, blocks, STOP_SIGMAS) if noise_stop else None
    consistent = _noise_level(base_gap, blocks)  # what pure noise stays below (3 sigma): the final fit's verdict
    problem = FrameProblem(base, names, library, params, zones, has_tables, fresh=fresh_top > 0, presence=presence,
                           noise=noise, bic_threshold=bic_threshold, say=say, workers=workers)
    base_trial = problem.base()
    # the search's moves update which fit a set's applicability is judged on
    real_polish = problem.polish

    def polish(t: Trial) -> Trial:
        out = real_polish(t)
        problem.remember(out)
        return out

    problem.polish = polish  # type: ignore[method-assign]
    result = search(problem, bic_threshold=bic_threshold, max_steps=max_steps, pair_top=pair_top, progress=say)
    result = _confirm_with_model_weights(problem, result, library, bic_threshold, notes, say)

    # --- the search's record as the Diagnosis (ranking, path, rankings per step) ---
    rankings: list[list[Candidate]] = []
    start_of: dict[int, Trial] = {1: base_trial}
    for mv in result.moves:
        start_of[mv.step + 1] = mv.trial  # the set at the start of the next step: the last move's
    first_ranked: list[Candidate] = []
    best_of: dict[frozenset, Trial] = {}  # each set's best fit in the whole search (a candidate is ranked by it)
    for t in result.trials:
        if t.ok and math.isfinite(t.bic) and (_key(t.effects) not in best_of or t.bic < best_of[_key(t.effects)].bic):
            best_of[_key(t.effects)] = t
    singles = list(result.singles)
    extra_trials: list[Trial] = []
    if not singles:
        # nothing refitted (max_steps = 0, or the base fit failed): step 1's candidates are still ranked
        extra_trials = [problem.refit((n,), base_trial) for n in names if problem.applicable((), n) is None]
        singles = [extra_trials]
    for k, trials_k in enumerate(singles, start=1):
        start = start_of.get(k, base_trial)
        ranked, rest = _rank(_candidates_of(trials_k, start, best_of, zones))
        # the effects the final explanation adds to this step's set come first (the search's answer), then the
        # specific effect the data require beside a leading generic one
        explanation = frozenset(result.final.effects) - frozenset(start.effects) if result.final.ok else frozenset()
        ranked = _explanation_first(ranked, explanation)
        ranked = _specific_first(ranked, start, best_of, problem.generic, bic_threshold, explanation)
        rankings.append(ranked)
        if k == 1:
            first_ranked = ranked
            skipped += rest
    for n in names:
        if not any(c.effect == n for c in skipped + first_ranked):
            c = problem.check((), n)
            if c.status != "ranked":
                skipped.append(c)
    all_trials = list(result.trials) + extra_trials
    failed_names = [f"{' + '.join(t.effects)}: {(t.failure or '')[:300]}" for t in all_trials if not t.ok]
    n_failed = len(failed_names)

    path = [Step("base", base_gap, _zone_stats(ctx.residuals, zones), base_heldout, math.nan, _params_report(base.result),
                 action="base")]
    fresh_failed = 0
    fresh_taken = False
    for mv in result.moves:
        step_singles = rankings[mv.step - 1] if mv.step - 1 < len(rankings) else []
        if mv.action == "add":
            first = mv.effects[0]
            alts = [{"effect": c.effect, "delta_bic": c.delta_bic, "margin": mv.gain - c.delta_bic, "flags": c.flags}
                    for c in _by_gain(step_singles) if c.effect not in mv.effects and c.delta_bic > 0][:3]
            gain = mv.gain
            if len(mv.effects) == 2:
                single = next((t for t in result.singles[mv.step - 1] if t.ok and t.effects[-1] == first), None)
                if single is not None:
                    st = problem._ctx(single.state.state)
                    g1 = path[-1].gap["bic"] - single.bic
                    path.append(_step(first, "add", library[first], st, zones, heldout, blocks, g1, path,
                                      [f"entered jointly with {mv.effects[1]} (this row: {first} alone)"], alts))
                    gain = mv.gain - g1
            f = mv.trial.state
            st = problem._ctx(f.state)
            fresh_taken = fresh_taken or (f.cand is not None and f.cand.refit_start == "fresh")
            notes_ = list(mv.notes) + ([f.polish_note] if f.polish_note else [])
            eff = mv.effects[-1]
            path.append(_step(eff, "add", library[eff], st, zones, heldout, blocks, gain, path, notes_,
                              alts if len(mv.effects) == 1 else []))
            if path[-1].heldout is not None:
                mv.trial.heldout = finite_or_none(path[-1].heldout.get("rms_log10"))
            if f.polish_failed:
                fresh_failed += 1
                path[-1].flags.append("the joint refit from fresh starts failed (counted in settings.failed_refits); "
                                      "the warm refit is kept")
        else:
            (e,) = mv.effects
            st = problem._ctx(mv.trial.state.state)
            path.append(_step(e, "remove", library[e], st, zones, heldout, blocks, mv.gain, path, list(mv.notes), []))
            if path[-1].heldout is not None:
                mv.trial.heldout = finite_or_none(path[-1].heldout.get("rms_log10"))
    final = result.final.state.state
    final = problem._ctx(final)
    for s_ in path:
        for f in s_.flags:
            notes.append(f"path step {s_.action} {s_.effect}: {f}")
    for r in rankings:
        for c in r:
            c.state = None  # drop the refits' data (memory); the path keeps what it needs
    n_retried = sum(1 for r in rankings for c in r if c.retried) + sum(1 for c in skipped if c.retried)
    stop_reason = result.stop_reason
    if max_steps == 0:
        stop_reason = "max_steps = 0: the candidates are ranked, none added"
    elif "within the noise" in stop_reason:
        stop_reason += f" (<= {noise:.4g}, 1 + {'' if STOP_SIGMAS == 1 else f'{STOP_SIGMAS:g} '}sqrt(2/dof))"
    t_end = time.perf_counter()
    return Diagnosis(
        gap=gap,
        regions=regions,
        block_names=[b.name for b in base.result.blocks],
        ranking=first_ranked,
        skipped=skipped,
        path=path,
        significant=len(final.effects) > 0,
        bic_threshold=float(bic_threshold),
        notes=notes + [f"{c.effect}: {c.status}: {c.note}" for c in skipped],
        timings={"base_fit_s": t_base - t_start, "where_s": t_where - t_base, "which_and_path_s": t_end - t_where,
                 "total_s": t_end - t_start},
        settings={
            "effects": list(names),
            "max_steps": max_steps,
            "search": "every applicable candidate refitted at every step; the best admissible ones also in pairs; "
                      "backward elimination with the same threshold",
            "pair_top": pair_top,
            "fresh_top": fresh_top,
            "workers": workers,
            "compiler_options": dict(export_cache.current_compiler_options() or {}),
            "presence_threshold": presence,
            "noise_stop": noise_stop,
            "bic_threshold": bic_threshold,
            "threshold_sigma": threshold,
            "smooth": smooth,
            "n_blocks": len(blocks),
            "n_heldout": 0 if heldout is None else len(heldout),
            "fresh_refit_on_path": fresh_taken,
            "n_trials": len(result.trials),
            "trials": [{"effects": list(t.effects), "ok": t.ok, "failure": t.failure,
                        "bic": t.bic if math.isfinite(t.bic) else None, "chi2_reduced": t.chi2_reduced,
                        "n_params": t.n_params, "heldout_rms_log10": t.heldout, "flags": {k: v for k, v in t.flags.items() if v}} for t in result.trials],
            "failed_refits": {
                "candidates": n_failed,
                "which": failed_names,
                "retried": n_retried,
                "fresh_start_on_path": fresh_failed,
            },
            "within_noise": bool(consistent is not None and gap_measures(final.result)["chi2_reduced"] <= consistent),
        },
        context=ctx,
        final_context=final.ctx,
        path_rankings=rankings,
        base_result=base.result,
        final_result=final.result,
        stop_reason=stop_reason,
        final_params=dict(final.params),
        final_effects=[(e, getattr(library[e], "side", "material")) for e in final.effects],
    )
