"""The chain store: one HDF5 file per chain, shared by the emcee and the NUTS samplers.

What both samplers' chain files have in common lives here, once:

- the open policy: a fresh run refuses an existing file, ``--resume`` refuses a missing one, and nothing is
  written before the checks pass (an existing chain is never overwritten);
- the problem's record, group ``brdfjax`` (attribute ``meta``, JSON): the parameter names, the problem's
  fingerprint (:mod:`brdfjax.io.fingerprint`) and whatever else the sampler records (units, seed, settings);
  a resumed chain must sample the same names, with the same number of walkers or chains, and match the
  fingerprint, each difference named;
- unreadable files (corrupted, truncated, not HDF5): an error naming the file, which is left untouched;
- appending per-step rows (resizable datasets, leading step axis) with the step counter ``iteration``
  written after the rows, so that a run killed at any moment resumes from its last complete step.

The step data itself: emcee's chain in emcee's own :class:`~emcee.backends.HDFBackend` (group ``mcmc``), the
NUTS chain through :meth:`ChainStore.append` (group ``nuts``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..io.fingerprint import check_resume
from ._priors import SampleError

__all__ = ["META", "ChainStore"]

#: The group holding the problem's record (attribute ``meta``, JSON).
META = "brdfjax"


@dataclass(frozen=True)
class ChainStore:
    """A chain file at ``path``; ``group`` holds the sampler's step data; ``kind`` names it in messages."""

    path: Path
    group: str
    kind: str  # "emcee" or "NUTS"
    not_mine_hint: str = ""  # said when the file holds no such group (e.g. another sampler's chain)

    # -- errors ---------------------------------------------------------------------------------
    def corrupt(self, why: str) -> SampleError:
        return SampleError(
            f"{self.path}: the {'' if self.kind == 'emcee' else self.kind + ' '}chain file cannot be read ({why}); it may be corrupted or truncated. It was "
            "left untouched: move or delete it to start a new chain, or choose another --out"
        )

    # -- opening --------------------------------------------------------------------------------
    @staticmethod
    def check_open(path: str | os.PathLike | None, *, resume: bool) -> bool:
        """Whether ``path`` holds a chain to continue (``True``) or a new one is to be made (``False``).

        Refuses an existing file without ``resume``, a missing one with it, and ``resume`` without a file.
        """
        if path is None:
            if resume:
                raise SampleError("resume needs a chain file")
            return False
        path = Path(path)
        if path.exists():
            if not resume:
                raise SampleError(
                    f"{path} already holds a chain; continue it with --resume (resume=True), or move it away / choose "
                    "another --out to start a new one (an existing chain is never overwritten)"
                )
            return True
        if resume:
            raise SampleError(f"--resume: there is no chain to resume at {path}; run without --resume to start one")
        return False

    def read_meta(self) -> dict[str, Any]:
        """The problem's record (``{}`` for a file without one); raises :meth:`corrupt` for an unreadable file."""
        try:
            with h5py.File(self.path, "r") as f:
                if self.group not in f:
                    raise SampleError(
                        f"{self.path}: not a{'n' if self.kind[0] in 'aeiou' else ''} {self.kind} chain (no '{self.group}' group"
                        f"{self.not_mine_hint}); it was left untouched: move it or choose another --out"
                    )
                return json.loads(f[META].attrs["meta"]) if META in f and "meta" in f[META].attrs else {}
        except SampleError:
            raise
        except (OSError, KeyError, ValueError, RuntimeError) as e:
            raise self.corrupt(f"{type(e).__name__}: {e}") from None

    def check_same_problem(
        self, stored: dict[str, Any], names: Sequence[str], sizes: Sequence[tuple[str, int, int]], setting: str,
        fingerprint: dict[str, Any] | None,
    ) -> None:
        """A resumed chain must sample ``names``, have the same ``sizes`` (``(noun, in the file, asked)``, e.g.
        ``("walkers", 8, 10)``; ``setting`` is the option to keep) and match ``fingerprint`` (when given); each
        difference is an error naming the file."""
        have = tuple(stored.get("names", ()))
        if have and have != tuple(names):
            raise SampleError(
                f"{self.path}: the chain samples {', '.join(have)}, but this problem's free parameters are "
                f"{', '.join(names)}; it cannot be resumed with this config"
            )
        if any(a != b for _, a, b in sizes):
            raise SampleError(
                f"{self.path}: the chain has {' x '.join(f'{a} {noun}' for noun, a, _ in sizes)}, but this run asks for "
                f"{' x '.join(str(b) for _, _, b in sizes)}; resume with the same {setting}"
            )
        if fingerprint is not None:
            check_resume(
                self.path, stored.get("fingerprint"), fingerprint,
                "Resume with the problem that started the chain, or start a new chain in another --out "
                "(the chain is left untouched).",
            )

    def write_meta(self, names: Sequence[str], meta: dict[str, Any] | None = None,
                   fingerprint: dict[str, Any] | None = None) -> None:
        """Record the problem (names, fingerprint, ``meta``) in a new chain file."""
        record = dict(meta or {}, names=list(names), **({"fingerprint": fingerprint} if fingerprint else {}))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(self.path, "a") as f:
            f.require_group(META).attrs["meta"] = json.dumps(record)

    # -- step data ------------------------------------------------------------------------------
    def append(self, rows: dict[str, np.ndarray], iteration: int) -> int:
        """Append ``rows`` (arrays with a leading step axis) after step ``iteration``; returns the new count.

        The counter (attribute ``iteration`` of the group) is written after the rows are flushed.
        """
        n_new = next(iter(rows.values())).shape[0]
        with h5py.File(self.path, "a") as f:
            g = f.require_group(self.group)
            for k, v in rows.items():
                if k not in g:
                    g.create_dataset(k, shape=(0, *v.shape[1:]), maxshape=(None, *v.shape[1:]), dtype=v.dtype, chunks=True)
                d = g[k]
                d.resize(iteration + n_new, axis=0)
                d[iteration:] = v
            f.flush()
            g.attrs["iteration"] = iteration + n_new  # last: the rows above are complete
        return iteration + n_new
