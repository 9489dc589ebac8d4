"""Whole programs kept across processes with ``jax.export``: a later process skips tracing them.

JAX's persistent compilation cache (:mod:`brdfjax.runtime.compile_cache`) keeps the
compiled executables, but its key is the lowered program, so every process
still traces and lowers each program before it can look it up.  On the
synthetic solar-cell fit that is most of a second process's first fit: the
Levenberg-Marquardt program and the structured Jacobian take about 3 s to
trace and lower against 0.7 s to run.  JAX has no cache of traces;
``jax.export`` serialises a traced program (StableHLO), so this module keeps
one file per program and structure and calls the deserialised program in
later processes, whose compile then comes from the persistent cache.

The key is everything that decides what is traced, written out without
tracing:

- the program's name, the versions of JAX, jaxlib, equinox, optimistix,
  lineax, NumPy, SciPy, opt_einsum and ml_dtypes, a hash of brdfjax's own source files, the backend and the JAX
  options that change tracing (64-bit mode, matmul precision, promotion
  rules, debug checks), and any module switches the caller names;
- the arguments' tree structure with every static value (equinox static
  fields, Python scalars, strings, tuples, NumPy arrays by content hash,
  enums, module-level functions by name) and each array's shape and dtype.

A value it cannot write out faithfully (a closure, a lambda, an object of an
unknown class) makes the call uncacheable: it runs as a plain ``jit`` call,
as without this module.  The data (every array) are arguments of the
exported program, so one file serves every data set of the same shapes.
Only single-device calls are exported (sharded arrays go the plain way).

On when the persistent compilation cache is on (the CLI's default; files in
``<cache>/export``); off with the cache, or alone with ``BRDFJAX_NO_EXPORT=1``.
A file that cannot be read is replaced.  A dependency edited in place without a new version number is not
seen: delete ``<cache>/export`` (or set ``BRDFJAX_NO_EXPORT=1``) after such an edit.  Exported calls give the numbers of
the plain call (``tests/runtime/test_export_cache.py`` checks a fit to every bit).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import hashlib
import importlib.metadata
import os
import re
import types
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax import export

from .atomic import atomic_output

try:  # jax.export's serialisation needs flatbuffers (a dependency of brdfjax; without it: no files)
    from jax._src.export import serialization as _serialization  # noqa: F401
except ImportError:
    _SERIALISABLE = False
else:
    _SERIALISABLE = True

__all__ = ["activate", "deactivate", "exportable", "exported_call", "stats", "clear", "compiler_options",
           "current_compiler_options", "FAST_COMPILE_CPU"]

_FOLDER: Path | None = None
_MEM: dict[str, Callable[..., Any]] = {}
_STATS = {"loaded": 0, "exported": 0, "reused": 0, "plain": 0}
#: XLA options the exported programs are compiled with (None: XLA's defaults); set by :func:`compiler_options`.
_COMPILER: dict[str, Any] | None = None

#: XLA's CPU options for programs that are compiled once and run briefly (:func:`compiler_options`): XLA's
#: older elemental emitters instead of its fusion emitters.  Measured on the 2-core CPU
#: (``experiments/benchmark_fast_compile.py``, ``experiments/results/fast_compile_cpu.json``): the shipped
#: diagnosis's solve programs compile in 0.69 of the time, the whole cold diagnosis takes 0.83 of the wall time
#: (101 s against 121 s, the same final chi^2), while a full-frame render runs 1.34 times slower: worth it where
#: every model is compiled for a few solves, not where one program runs many times (sampling, rendering).
FAST_COMPILE_CPU: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}
_OPTIONS = (
    "jax_enable_x64",
    "jax_default_matmul_precision",
    "jax_numpy_rank_promotion",
    "jax_numpy_dtype_promotion",
    "jax_enable_checks",
    "jax_debug_nans",
    "jax_debug_infs",
    "jax_disable_jit",
)


class _Uncacheable(Exception):
    """A static value that cannot be written out faithfully: the call goes the plain way."""


def activate(folder: str | os.PathLike) -> Path | None:
    """Keep exported programs in ``folder`` (made if missing); None when ``BRDFJAX_NO_EXPORT`` says no or the
    folder cannot be made or serialisation is not available (``flatbuffers`` missing)."""
    global _FOLDER
    if os.environ.get("BRDFJAX_NO_EXPORT", "").strip() not in ("", "0") or not _SERIALISABLE:
        return None
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    _FOLDER = path
    return path


def deactivate() -> None:
    """Stop exporting (and forget the programs held in this process)."""
    global _FOLDER
    _FOLDER = None
    clear()


def clear() -> None:
    """Forget the deserialised programs held in this process (the files stay)."""
    _MEM.clear()


@contextlib.contextmanager
def compiler_options(options: Mapping[str, Any] | None) -> Iterator[None]:
    """Compile the exported programs first called inside with these XLA ``options`` (``jax.jit``'s
    ``compiler_options``; None: XLA's defaults); the previous options come back on exit.

    Process-wide, not per thread (a diagnosis's refits run in threads of their own): two calls side by side in
    different threads would see each other's options.  A program compiled with other options is another
    program (its own entry here and in JAX's persistent cache, whose key holds the options); the numbers can
    differ in the last bits, so a run is reproducible under the same options.  Without a folder
    (:func:`activate`) the programs are exported in memory only, for this process; calls that cannot be exported
    (an argument that cannot be written out, several devices) go the plain way with XLA's defaults."""
    global _COMPILER
    before = _COMPILER
    _COMPILER = None if options is None else dict(options)
    try:
        yield
    finally:
        _COMPILER = before


def current_compiler_options() -> dict[str, Any] | None:
    """The XLA options exported programs are compiled with now (:func:`compiler_options`; None: XLA's defaults)."""
    return None if _COMPILER is None else dict(_COMPILER)


def stats() -> dict[str, int]:
    """Calls so far: ``loaded`` (a program read from its file), ``exported`` (traced and written),
    ``reused`` (held in this process), ``plain`` (not exportable: a plain call)."""
    return dict(_STATS)


def _canon(x: Any, out: list[str]) -> None:
    """Append a faithful text form of the static value ``x`` (raises :class:`_Uncacheable`)."""
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        out.append(f"{type(x).__name__}:{x!r}")  # repr of a float round-trips exactly
    elif isinstance(x, (tuple, list)):
        out.append(f"{type(x).__name__}[{len(x)}")
        for y in x:
            _canon(y, out)
        out.append("]")
    elif isinstance(x, dict):
        out.append(f"dict[{len(x)}")
        for k in sorted(x, key=repr):
            _canon(k, out)
            _canon(x[k], out)
        out.append("]")
    elif isinstance(x, (set, frozenset)):
        parts = []
        for y in x:
            o: list[str] = []
            _canon(y, o)
            parts.append("\x1e".join(o))
        out.append(f"set[{chr(0x1d).join(sorted(parts))}]")
    elif isinstance(x, np.ndarray):
        if x.dtype.hasobject:
            raise _Uncacheable("an object array")
        data = hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()
        out.append(f"ndarray:{x.dtype.str}:{x.shape}:{data}")
    elif isinstance(x, np.dtype):
        out.append(f"dtype:{x.str}")
    elif isinstance(x, np.generic):
        out.append(f"{x.dtype.str}:{x.item()!r}")
    elif isinstance(x, enum.Enum):
        out.append(f"enum:{type(x).__module__}.{type(x).__qualname__}.{x.name}")
    elif isinstance(x, type):
        out.append(f"type:{x.__module__}.{x.__qualname__}")
    elif isinstance(x, types.FunctionType):
        # a module-level function is its name (its code is in the source hash or a versioned package);
        # a closure or a function defined in a function carries values the name does not
        if x.__closure__ or "<" in x.__qualname__:
            raise _Uncacheable(f"function {x.__qualname__}")
        out.append(f"function:{x.__module__}.{x.__qualname__}")
    elif isinstance(x, (types.BuiltinFunctionType, np.ufunc)):
        out.append(f"builtin:{getattr(x, '__module__', None)}.{x.__name__}")
    elif isinstance(x, functools.partial):
        out.append("partial(")
        _canon(x.func, out)
        _canon(x.args, out)
        _canon(x.keywords, out)
        out.append(")")
    elif dataclasses.is_dataclass(x):
        out.append(f"dataclass:{type(x).__module__}.{type(x).__qualname__}(")
        for f in dataclasses.fields(x):
            out.append(f.name)
            _canon(getattr(x, f.name), out)
        out.append(")")
    elif type(x).__module__.startswith("equinox") and type(x).__qualname__ in ("_Missing", "Missing"):
        out.append("equinox:Missing")  # equinox's marker of a dynamic field in a module's static data
    else:
        raise _Uncacheable(f"a {type(x).__module__}.{type(x).__qualname__}")


def _canon_tree(treedef: Any, out: list[str]) -> None:
    node = treedef.node_data()
    if node is None:
        out.append("*")
        return
    kind, aux = node
    out.append(f"node:{kind.__module__}.{kind.__qualname__}(")
    _canon(aux, out)
    for child in treedef.children():
        _canon_tree(child, out)
    out.append(")")


@functools.lru_cache(maxsize=1)
def _environment() -> str:
    versions = []
    # the libraries whose code runs while a fit or a render is traced (numpy and scipy on static values,
    # opt_einsum's contraction order)
    for dist in ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "scipy", "opt_einsum", "ml_dtypes"):
        try:
            versions.append(f"{dist}={importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{dist}=?")
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    dev = jax.devices()[0]
    return "|".join(versions + [f"brdfjax-source={h.hexdigest()}", f"device={dev.platform}:{dev.device_kind}"])


def _single_device(x: Any) -> bool:
    # a tracer: called while another program is traced, which is the one to keep
    if isinstance(x, jax.core.Tracer):
        return False
    return not isinstance(x, jax.Array) or isinstance(x.sharding, jax.sharding.SingleDeviceSharding)


def _key(name: str, leaves: Sequence[Any], treedef: Any, switches: tuple) -> tuple[str, list[int]]:
    out = [name, _environment(), f"devices={jax.device_count()}"]
    out += [f"{k}={getattr(jax.config, k, None)!r}" for k in _OPTIONS]
    _canon(switches, out)
    _canon_tree(treedef, out)
    dyn = []
    for i, x in enumerate(leaves):
        if eqx.is_array(x):
            weak = bool(getattr(x, "weak_type", False))
            out.append(f"array:{np.dtype(x.dtype).str}:{tuple(x.shape)}:{weak}")
            dyn.append(i)
        else:
            _canon(x, out)  # equinox's filter_jit makes every non-array leaf static
    return hashlib.sha256("\x1f".join(out).encode()).hexdigest()[:40], dyn


def _export(raw: Callable[..., Any], leaves: list[Any], treedef: Any, dyn: list[int]) -> Any:
    def flat(*arrays):
        full = list(leaves)
        for i, a in zip(dyn, arrays):
            full[i] = a
        return raw(*jax.tree_util.tree_unflatten(treedef, full))

    specs = [jax.ShapeDtypeStruct(leaves[i].shape, leaves[i].dtype, weak_type=bool(getattr(leaves[i], "weak_type", False)))
             for i in dyn]
    allowed: set[str] = set()
    # LAPACK's custom calls (the solver's QR) have no cross-version guarantee; the key holds jaxlib's version,
    # so a file is only ever read by the jaxlib that wrote it
    while True:
        checks = [export.DisabledSafetyCheck.custom_call(n) for n in sorted(allowed)]
        try:
            return export.export(jax.jit(flat), disabled_checks=checks)(*specs)
        except ValueError as e:
            names = set(re.findall(r"custom_call @(\w+)\(", str(e))) - allowed
            if "no compatibility guarantees" not in str(e) or not names:
                raise
            allowed |= names


def exported_call(name: str, raw: Callable[..., Any], plain: Callable[..., Any], args: tuple, switches: tuple = ()) -> Any:
    """``raw(*args)`` through its exported program when the cache is on or compiler options are set
    (:func:`compiler_options`), else ``plain(*args)``.

    ``raw``: the unjitted function (it must return arrays in tuples, lists or dicts: the exported program's
    output); ``plain``: its jitted form, used when nothing is exported; ``switches``: module-level values
    that ``raw`` reads while it is traced (part of the key).
    """
    opts = _COMPILER
    if _FOLDER is None and opts is None:
        return plain(*args)
    leaves, treedef = jax.tree_util.tree_flatten(args)
    if jax.device_count() != 1 or not all(_single_device(x) for x in leaves):
        _STATS["plain"] += 1
        return plain(*args)
    try:
        key, dyn = _key(name, leaves, treedef, switches)
    except _Uncacheable:
        _STATS["plain"] += 1
        return plain(*args)
    mem_key = key if opts is None else f"{key}|{sorted(opts.items())!r}"
    call = _MEM.get(mem_key)
    if call is None:
        # without a folder (compiler options set, no cache) the program is exported in memory only: jax.jit takes
        # compiler options, equinox's filter_jit (the plain way) does not
        path = None if _FOLDER is None else _FOLDER / f"{name}-{key}.jaxexport"
        exp = None
        if path is not None and path.is_file():
            try:
                exp = export.deserialize(bytearray(path.read_bytes()))
                # (JAX's canonical dtypes: float64 data are float32 arrays without 64-bit mode)
                want = [(tuple(leaves[i].shape), jax.dtypes.canonicalize_dtype(leaves[i].dtype)) for i in dyn]
                if [(tuple(a.shape), np.dtype(a.dtype)) for a in exp.in_avals] != want:
                    raise ValueError("the file's program takes other arrays")
                _STATS["loaded"] += 1
            except Exception:
                exp = None  # damaged, or not this program's: made again below
        if exp is None:
            exp = _export(raw, leaves, treedef, dyn)
            try:
                if path is not None:
                    with atomic_output(path) as tmp:
                        tmp.write_bytes(exp.serialize())
            except OSError:
                pass  # a read-only cache: this process still uses the program
            _STATS["exported"] += 1
        call = jax.jit(exp.call, compiler_options=opts)
        _MEM[mem_key] = call
    else:
        _STATS["reused"] += 1
    return call(*(leaves[i] for i in dyn))


def exportable(name: str, plain: Callable[..., Any], switches: Callable[[], tuple] = tuple) -> Callable[..., Any]:
    """``plain`` (an ``eqx.filter_jit`` function) called through :func:`exported_call` under ``name``;
    ``switches()`` gives the module switches its trace reads, at each call."""
    raw = plain.__wrapped__

    @functools.wraps(raw)
    def call(*args: Any) -> Any:
        return exported_call(name, raw, plain, args, switches())

    return call
