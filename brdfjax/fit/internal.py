"""The fit engine's inner API for brdfjax's other packages (sample, diagnose).

As ``optimistix.internal`` does, this module names the pieces of the fit
engine that other packages of brdfjax build on but a user fitting a model does
not need: the traced problem, the parameter layout and its entries, the
solver and loss registries, unit helpers and block naming.  Everything here
is documented and stable within brdfjax; the modules it comes from
(``brdfjax.fit._*``) stay private.

- :class:`Problem`: the fit problem as one pytree (residuals, Jacobian, losses);
- :func:`as_param`: a parameter specification (dict, tuple or :class:`~brdfjax.fit.Param`) as a ``Param``;
- :func:`param_problems`, :func:`check_param`, :data:`SPEC_KEYS`: the data-independent rules of a
  specification, written once for the Python API and the TOML config;
- :func:`prepare_problem`: the traced :class:`Problem` of a model, data and spec with a solver (what
  :func:`brdfjax.fit.fit` solves; the public likelihood object is :func:`brdfjax.fit.prepare`);
- :func:`block_names`: the unique names of a list of data blocks, as the fit reports them;
- :func:`get_solver`, :data:`LOSSES`: the solver and robust-loss registries;
- :func:`natural_unit`, :func:`to_natural`: the reported unit of a stored one (rad -> deg) and its factor;
- :data:`FRAME_PARAMETERS`: the frame parameters a fit may free (``theta_i``, ``phi_ref``), with units;
- :func:`lobe_parameters`, :func:`lobe_term`, :func:`lobe_fwhm`, :func:`table_step`: a model's microfacet
  lobes (each lobe of a multi_lobe term), the term that holds one lobe alone, a lobe's angular FWHM and a table's angular step at its peak (the unresolved-peak check).
"""

from ._common import FRAME_PARAMETERS as FRAME_PARAMETERS, natural_unit as natural_unit, to_natural as to_natural
from ._params import SPEC_KEYS as SPEC_KEYS, as_param as as_param, check_param as check_param, param_problems as param_problems
from ._prepare import block_names as block_names, prepare as prepare_problem
from ._problem import Problem as Problem
from ._residuals import LOSSES as LOSSES
from ._resolution import (
    lobe_fwhm as lobe_fwhm,
    lobe_parameters as lobe_parameters,
    lobe_term as lobe_term,
    table_step as table_step,
)
from ._reweight import model_noise_weights as model_noise_weights, warm_params as warm_params
from ._solvers import get_solver as get_solver

__all__ = [
    "warm_params",
    "model_noise_weights",
    "FRAME_PARAMETERS",
    "LOSSES",
    "SPEC_KEYS",
    "Problem",
    "as_param",
    "block_names",
    "check_param",
    "get_solver",
    "lobe_fwhm",
    "lobe_parameters",
    "lobe_term",
    "natural_unit",
    "param_problems",
    "prepare_problem",
    "table_step",
    "to_natural",
]
