"""Evaluate models over detector frames: vmapped over pixels, jit-compiled, chunked.

The measurement conditions (:class:`~brdfjax.core.conditions.Conditions`: incidence,
the sample's rotation, wavelength) come from :mod:`brdfjax.core.conditions`.
:func:`render` is the one entry: it evaluates a model on
every pixel of a :class:`~brdfjax.core.detector.PixelGrid` (the full array, every
k-th pixel, or a region of interest) and returns BRDF in sr^-1 shaped
``(n_v rows, n_h columns)``.  Rows are processed in chunks with
``jax.lax.map`` so that a full 8.1-million-pixel frame runs in bounded memory;
the same compiled program runs on CPU or GPU.  ``outputs`` asks for more than the
BRDF (each term, the pixel geometry), ``devices`` splits the rows over several
devices; :func:`evaluate_pixels` is the differentiable evaluation at arbitrary
pixel indices (for losses and gradients).
"""

from __future__ import annotations

import functools
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike

from ..runtime.export_cache import exportable
from .conditions import Conditions
from .detector import Detector, PixelGrid
from .geometry import Directions
from .terms import AbstractTerm, Model

__all__ = [
    "Conditions",
    "OUTPUTS",
    "pixel_directions",
    "sample_directions",
    "evaluate_pixels",
    "render",
    "render_frame",
    "render_sharded",
    "render_geometry",
    "cast",
]

Precision = Literal["float32", "float64"]

#: What :func:`render` can return besides the BRDF: each term, and the pixel geometry.
OUTPUTS: tuple[str, ...] = ("brdf", "terms", "theta_s", "phi_s", "omega")


def pixel_directions(detector: Detector, frame: Conditions, n_h: ArrayLike, n_v: ArrayLike) -> Directions:
    """Pixel directions in the sample frame (scatter frame rotated by ``-phi_ref`` about z)."""
    dirs = detector.directions(n_h, n_v, frame.theta_i)
    return dirs.rotated_z(-frame.phi_ref)


#: The older name of :func:`pixel_directions` ("sample" is the posterior package).
sample_directions = pixel_directions


def evaluate_pixels(
    model: AbstractTerm, frame: Conditions, detector: Detector, n_h: ArrayLike, n_v: ArrayLike
) -> Array:
    """BRDF (sr^-1) at pixel indices ``n_h, n_v`` (any broadcastable shapes); differentiable."""
    return model(pixel_directions(detector, frame, n_h, n_v), frame.wavelength)


def cast(tree: Any, dtype: Any) -> Any:
    """Cast every floating-point leaf of a pytree (NumPy or JAX) to ``dtype`` as a JAX array."""

    def f(x):
        if eqx.is_array(x) and jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
            return jnp.asarray(x, dtype=dtype)
        return x

    return jax.tree_util.tree_map(f, tree)


def resolve_dtype(precision: Precision | Any) -> Any:
    name = np.dtype(precision).name if not isinstance(precision, str) else precision
    if name not in ("float32", "float64"):
        raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
    if name == "float64" and not jax.config.jax_enable_x64:
        raise ValueError(
            "precision 'float64' needs 64-bit JAX: call jax.config.update('jax_enable_x64', True) "
            "before creating arrays (brdfjax never flips this process-wide switch for you)"
        )
    return jnp.float64 if name == "float64" else jnp.float32


def _default_rows(n_rows: int, n_cols: int, chunk_pixels: int) -> int:
    """Rows per chunk: at most ``chunk_pixels`` pixels, balanced so padding is under one row per chunk."""
    rows = int(max(1, min(chunk_pixels // max(n_cols, 1), n_rows)))
    n_chunks = -(-n_rows // rows)
    return -(-n_rows // n_chunks)


@eqx.filter_jit
def map_rows(fn, args, n_h: Array, n_v: Array, rows_per_chunk: int):
    """Apply ``fn(args, n_h_row_vector, n_v_scalar) -> pytree of (n_cols,)`` to every row, in chunks."""
    n_rows = n_v.shape[0]
    n_chunks = -(-n_rows // rows_per_chunk)
    pad = n_chunks * rows_per_chunk - n_rows
    nv = jnp.concatenate([n_v, jnp.broadcast_to(n_v[-1:], (pad,))]) if pad else n_v
    per_row = jax.vmap(lambda v: fn(args, n_h, v))

    out = jax.lax.map(per_row, nv.reshape(n_chunks, rows_per_chunk))
    return jax.tree_util.tree_map(lambda a: a.reshape((n_chunks * rows_per_chunk,) + a.shape[2:])[:n_rows], out)


def _host_leaves(tree: Any) -> Any:
    """Plain Python numbers in a pytree as NumPy scalars (so that jit traces them instead of baking them in)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, float | int) and not isinstance(x, bool) else x, tree)


@eqx.filter_jit
def _program(fn, args, n_h, n_v, rows_per_chunk: int, dtype):
    """One compiled program per call signature: casts the (float64) leaves to ``dtype`` inside it.

    Casting on the host instead costs one small device operation per leaf
    and call (4-9 ms for a model's parameters, the time of a small grid).
    """
    args = cast(args, dtype)
    return map_rows(fn, args, jnp.asarray(n_h, dtype), jnp.asarray(n_v, dtype), rows_per_chunk)


#: :func:`_program` through its exported program when :mod:`brdfjax.runtime.export_cache` is on (a later process
#: skips tracing the frame's program)
_run = exportable("render", _program)


def _pixel_values(args, n_h_row, n_v):
    model, frame, detector, per_term = args
    # vmap over the columns of one row: one pixel at a time from the model's point of view.
    def one(h):
        dirs = pixel_directions(detector, frame, h, n_v)
        if per_term:
            return model.term_values(dirs, frame.wavelength)
        return model(dirs, frame.wavelength)

    return jax.vmap(one)(n_h_row)


def _prepare(detector: Detector | None, grid: PixelGrid | None, step: int, roi, precision):
    detector = Detector.seed() if detector is None else detector
    grid = detector.grid(step, roi) if grid is None else grid
    dtype = resolve_dtype(precision)
    return detector, grid, dtype


def render(
    model: AbstractTerm,
    frame: Conditions,
    detector: Detector | None = None,
    *,
    step: int = 1,
    roi: tuple[int, int, int, int] | None = None,
    grid: PixelGrid | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 20,
    per_term: bool = False,
    outputs: str | tuple[str, ...] | None = None,
    devices: Any = None,
) -> Array | dict[str, Array]:
    """Evaluate ``model`` on a frame: BRDF in sr^-1, shape ``(rows, cols)`` of the pixel grid.

    ``step``/``roi`` (or an explicit ``grid``) select the pixels; the default
    is the full seed array.  ``chunk_pixels`` bounds the pixels evaluated at
    once (memory grows linearly with it).  ``per_term=True`` returns a dict of
    each term of a :class:`~brdfjax.core.terms.Model` instead of the sum.

    ``outputs``: ``None`` (the BRDF array), ``"all"`` or names from :data:`OUTPUTS`
    (``"brdf"``, ``"terms"``: ``{name: image}``, ``"theta_s"``, ``"phi_s"`` (rad),
    ``"omega"`` (sr)): a dict of those, from one compiled program (``model`` may be
    ``None`` for the geometry alone).  ``devices``: ``"all"`` or a list of devices
    splits the frame's rows over them (a one-axis mesh and ``jax.shard_map``; the
    same values, sharded by rows; the BRDF output only).
    """
    if outputs is not None:
        names = OUTPUTS if outputs == "all" else ((outputs,) if isinstance(outputs, str) else tuple(outputs))
        bad = [n for n in names if n not in OUTPUTS]
        if bad or not names:
            raise ValueError(f"render: unknown output(s) {bad or names!r}; known: {', '.join(OUTPUTS)} or 'all'")
        if devices is not None or per_term:
            raise ValueError("render: outputs= goes with neither devices= nor per_term= (ask for 'terms' instead)")
        kw = dict(step=step, roi=roi, grid=grid, precision=precision, chunk_pixels=chunk_pixels)
        if model is None or set(names) <= {"theta_s", "phi_s", "omega"}:
            if model is None and not set(names) <= {"theta_s", "phi_s", "omega"}:
                raise ValueError(f"render: outputs {names!r} need a model (model=None gives the geometry alone)")
            values = render_geometry(frame, detector, **kw)
        else:
            values = render_frame(model, frame, detector, **kw)
        return {n: values[n] for n in names}
    if devices is not None:
        if per_term:
            raise ValueError("render: devices= renders the BRDF only (per_term=False)")
        return render_sharded(model, frame, detector, step=step, roi=roi, grid=grid, precision=precision,
                              chunk_pixels=chunk_pixels, devices=None if devices == "all" else devices)
    detector, grid, dtype = _prepare(detector, grid, step, roi, precision)
    if per_term and not hasattr(model, "term_values"):
        raise TypeError("render(per_term=True) needs a brdfjax Model (a named sum of terms)")
    rows = _default_rows(grid.n_v.size, grid.n_h.size, chunk_pixels)
    args = (*_host_leaves((model, frame, detector)), per_term)
    return _run(_pixel_values, args, grid.n_h, grid.n_v, rows, dtype)


def render_sharded(
    model: AbstractTerm,
    frame: Conditions,
    detector: Detector | None = None,
    *,
    step: int = 1,
    roi: tuple[int, int, int, int] | None = None,
    grid: PixelGrid | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 20,
    devices: Any = None,
) -> Array:
    """:func:`render` with the frame's rows split over ``devices`` (default: every visible device).

    A one-axis :class:`jax.sharding.Mesh` over the devices; ``jax.shard_map``
    gives each device a contiguous block of rows (the rows are padded to a
    multiple of the device count by repeating the last one), which it
    evaluates with the same chunked program as :func:`render`.  The result is
    a ``(rows, cols)`` array sharded by rows (the same values as
    :func:`render`: each pixel is computed by the same arithmetic).
    """
    detector, grid, dtype = _prepare(detector, grid, step, roi, precision)
    devices = tuple(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    n_rows = grid.n_v.size
    per_device = -(-n_rows // n_dev)
    n_v = np.asarray(grid.n_v, np.float64)
    n_v = np.concatenate([n_v, np.full(per_device * n_dev - n_rows, n_v[-1])])
    rows = _default_rows(per_device, grid.n_h.size, chunk_pixels)
    mesh, program = _sharded_program(devices, rows)
    args = cast((model, frame, detector), dtype)
    nv = jax.device_put(jnp.asarray(n_v, dtype), NamedSharding(mesh, PartitionSpec("rows")))
    return program(args, jnp.asarray(grid.n_h, dtype), nv)[:n_rows]


@functools.lru_cache(maxsize=16)
def _sharded_program(devices: tuple, rows: int):
    """The mesh over ``devices`` and one jitted shard_map program for it: traced once per model structure and
    grid shape, not once per call (the model's arrays are arguments, its static parts the jit's key)."""
    mesh = Mesh(np.array(devices), ("rows",))

    @eqx.filter_jit
    def program(args, n_h, nv):
        dyn, static = eqx.partition(args, eqx.is_array)

        def local(dyn, n_h, nv_block):
            return map_rows(_pixel_values, (*eqx.combine(dyn, static), False), n_h, nv_block, rows)

        spec = PartitionSpec("rows")
        return jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec(), spec), out_specs=spec)(
            dyn, n_h, nv
        )

    return mesh, program


def _geometry_values(args, n_h_row, n_v):
    frame, detector = args

    def one(h):
        theta_s, phi_s = detector.angles(h, n_v, detector.arm_angle(frame.theta_i))
        return {"theta_s": theta_s, "phi_s": phi_s, "omega": detector.solid_angle(h, n_v)}

    return jax.vmap(one)(n_h_row)


def render_geometry(
    frame: Conditions,
    detector: Detector | None = None,
    *,
    step: int = 1,
    roi: tuple[int, int, int, int] | None = None,
    grid: PixelGrid | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 20,
) -> dict[str, Array]:
    """Per-pixel ``theta_s``, ``phi_s`` (rad) and solid angle ``omega`` (sr) of a frame's grid."""
    detector, grid, dtype = _prepare(detector, grid, step, roi, precision)
    rows = _default_rows(grid.n_v.size, grid.n_h.size, chunk_pixels)
    return _run(_geometry_values, _host_leaves((frame, detector)), grid.n_h, grid.n_v, rows, dtype)


def _frame_values(args, n_h_row, n_v):
    model, frame, detector = args

    def one(h):
        dirs = pixel_directions(detector, frame, h, n_v)
        terms = model.term_values(dirs, frame.wavelength)
        values = list(terms.values())
        theta_s, phi_s = detector.angles(h, n_v, detector.arm_angle(frame.theta_i))
        return {
            "brdf": sum(values[1:], values[0]),
            "terms": terms,
            "theta_s": theta_s,
            "phi_s": phi_s,
            "omega": detector.solid_angle(h, n_v),
        }

    return jax.vmap(one)(n_h_row)


def render_frame(
    model: AbstractTerm,
    frame: Conditions,
    detector: Detector | None = None,
    *,
    step: int = 1,
    roi: tuple[int, int, int, int] | None = None,
    grid: PixelGrid | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 20,
) -> dict[str, Any]:
    """Everything ``brdfjax simulate`` writes for a frame, from one compiled program.

    Returns ``{"brdf", "terms": {name: image}, "theta_s", "phi_s", "omega"}``,
    each ``(rows, cols)``: the model's sum (the terms added in order, as the
    model adds them), each term of a :class:`~brdfjax.core.terms.Model`, and the
    pixel geometry of :func:`render_geometry`.  A model that is not a
    ``Model`` gives a single term named ``"model"``.
    """
    detector, grid, dtype = _prepare(detector, grid, step, roi, precision)
    if not hasattr(model, "term_values"):
        model = Model(terms={"model": model})
    rows = _default_rows(grid.n_v.size, grid.n_h.size, chunk_pixels)
    return _run(_frame_values, _host_leaves((model, frame, detector)), grid.n_h, grid.n_v, rows, dtype)
