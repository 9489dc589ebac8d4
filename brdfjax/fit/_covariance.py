"""Parameter covariance from the weighted Jacobian at the optimum (NumPy float64).

With the residuals ``r = (log f - log d) / sigma_rel`` already weighted by
each point's uncertainty, the Gauss-Newton approximation of the inverse
Hessian of ``chi^2 / 2`` gives the covariance of the solver coordinates ``v``

    C_v = s^2 (J^T J)^-1,        J = d r / d v at the optimum,

and, through ``x = g(u0 + scale v)``, of the parameters in stored units
``C_x = D C_v D`` with ``D = diag(scale * g'(u))`` (first-order propagation
through the reparametrisation).  The choice of ``s^2``:

- ``absolute=True`` (the default when every point carries a ``sigma_rel``):
  ``s^2 = 1``: the uncertainties are taken at face value, and the reduced
  chi^2 reported beside says whether they are right (``scipy``'s
  ``absolute_sigma=True``);
- ``absolute=False`` (tables without uncertainties, weighted 1): ``s^2 =
  chi^2 / dof``, the residual variance stands in for the unknown noise.

``J^T J`` is inverted through the SVD of ``J``; singular values below
``rcond`` times the largest mark directions the data do not determine: the
parameters with weight on them get an infinite sigma and NaN correlations,
and are named in the result's warnings.  With a robust loss ``J`` is the
Jacobian of the reweighted residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Covariance", "covariance"]


@dataclass(frozen=True)
class Covariance:
    """Covariance of the free parameters in stored units, their sigmas and correlations."""

    matrix: np.ndarray  # (p, p)
    sigma: np.ndarray  # (p,)
    correlation: np.ndarray  # (p, p)
    rank: int
    undetermined: tuple[int, ...]  # indices of parameters on undetermined directions
    factor: float  # s^2
    # indices of parameters whose transform's derivative dx/dv is not finite at the solution (a parameter
    # stored as a log or a logit that ran to an extreme): their sigma is infinite, their correlations NaN
    saturated: tuple[int, ...] = ()


def covariance(
    jac_v: np.ndarray,
    dx_dv: np.ndarray,
    chi2_reduced: float,
    absolute: bool,
    rcond: float = 1e-10,
) -> Covariance:
    """``C_x = s^2 D (J^T J)^-1 D`` (see the module docstring); ``dx_dv = scale * g'(u)``."""
    J = np.asarray(jac_v, dtype=np.float64)
    p = J.shape[1]
    if p == 0:
        empty = np.zeros((0, 0))
        return Covariance(empty, np.zeros(0), empty, 0, (), 1.0)
    factor = 1.0 if absolute else (float(chi2_reduced) if np.isfinite(chi2_reduced) else np.nan)
    if not np.all(np.isfinite(J)):
        nan = np.full((p, p), np.nan)
        return Covariance(nan, np.full(p, np.nan), nan, 0, tuple(range(p)), factor)
    _, s, vt = np.linalg.svd(J, full_matrices=False)
    keep = s > rcond * (s[0] if s.size else 0.0)
    rank = int(keep.sum())
    v = vt.T
    inv_s2 = np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)
    cov_v = (v * inv_s2) @ v.T
    undetermined = tuple(int(i) for i in np.nonzero(np.any(np.abs(v[:, ~keep]) > 1e-8, axis=1))[0]) if rank < p else ()
    d = np.asarray(dx_dv, dtype=np.float64)
    bad = ~np.isfinite(d)
    d = np.where(bad, 0.0, d)  # inf * 0 would be NaN (and a RuntimeWarning) across the whole row
    with np.errstate(over="ignore", invalid="ignore"):  # a huge finite dx/dv overflows its variance
        cov = factor * cov_v * np.outer(d, d)
    bad |= ~np.isfinite(np.diag(cov))
    saturated = tuple(int(i) for i in np.nonzero(bad)[0])
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sigma, sigma)
    for i in saturated:
        cov[i, :] = cov[:, i] = np.nan
        cov[i, i] = np.inf
    for i in tuple(undetermined) + saturated:
        sigma[i] = np.inf
        corr[i, :] = np.nan
        corr[:, i] = np.nan
    np.fill_diagonal(corr, [1.0 if i not in undetermined and i not in saturated else np.nan for i in range(p)])
    return Covariance(cov, sigma, corr, rank, undetermined, factor, saturated)
