"""A fit problem's points split over devices (``jax.sharding``): the residuals of a full frame on all devices.

:func:`shard_problem` places every per-point array of a
:class:`~brdfjax.fit._problem.Problem` (pixel indices, data, weights) on a
one-axis :class:`jax.sharding.Mesh` over the devices, split along the points,
and replicates the rest (models, detector, parameters).  The residual
function and the solvers are unchanged: under ``jit``, XLA's SPMD partitioner
runs the model on each device's points and gathers only where the program
needs it (the footprint's FFT, the final concatenation).  Arrays whose point
count does not divide by the device count stay replicated (stacked frames are
padded to a multiple of 256 points, so they divide by 2, 4, 8 ... devices).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._problem import Problem

__all__ = ["shard_problem"]


def shard_problem(problem: Problem, devices: Any = None) -> Problem:
    """``problem`` with its per-point arrays split over ``devices`` (default: every visible device)."""
    devices = list(jax.devices() if devices is None else devices)
    mesh = Mesh(np.array(devices), ("points",))
    n_dev = len(devices)
    replicated = NamedSharding(mesh, PartitionSpec())

    def place(tree: Any, n_points: int, axis: int) -> Any:
        def put(x):
            if not eqx.is_array(x):
                return x
            if x.ndim > axis and x.shape[axis] == n_points and n_points % n_dev == 0:
                return jax.device_put(x, NamedSharding(mesh, PartitionSpec(*([None] * axis), "points")))
            return jax.device_put(x, replicated)

        return jax.tree_util.tree_map(put, tree)

    if problem.stack is not None:
        blocks = place(problem.stack.blocks, int(problem.stack.blocks.data.shape[1]), 1)  # (frames, points)
        stack = type(problem.stack)(blocks, jax.device_put(problem.stack.valid, replicated))
        return eqx.tree_at(lambda p: p.stack, problem, stack)
    blocks = tuple(place(b, int(b.data.shape[0]), 0) for b in problem.blocks)
    return eqx.tree_at(lambda p: p.blocks, problem, blocks)
