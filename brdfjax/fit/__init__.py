"""Inverse fitting: brdfjax models fitted to detector frames and goniometer tables.

``lik = prepare(model, data, params, **options)`` is the likelihood that
:func:`fit`, :func:`brdfjax.sample.sample` and :func:`brdfjax.diagnose.diagnose`
share (:class:`Likelihood`); ``fit(lik, solver=...)`` or
``fit(model, data, params)`` fits any :class:`~brdfjax.Model` to one or many
:class:`FrameData` (BRDF frames on a pixel grid with ``sigma_rel`` and a
mask) and :class:`TableData` (goniometer samples), jointly, with parameters
shared across frames or per frame, bounds by reparametrisation, log-space
residuals weighted by each point's uncertainty, an optional robust loss and
instrument function, and 1-sigma uncertainties from the weighted Jacobian.
See the module docstrings of ``_params``, ``_residuals``, ``_covariance``,
``_solvers`` and ``_auto_init`` for the conventions.

:func:`read_frame_data` / :func:`frame_data_from_reduced` turn reduced frames
(``brdfjax reduce`` output) into :class:`FrameData`; :mod:`brdfjax.fit.config`
is the TOML fit config behind ``brdfjax fit CONFIG --out DIR``
(``load_fit_config``, ``build_fit_job``, ``run_fit``).
"""

from ..io.blocks import FrameData as FrameData, TableData as TableData
from ..io.tables import (
    CANONICAL_COLUMNS as CANONICAL_COLUMNS,
    Screen as Screen,
    check_mirror as check_mirror,
    export_table as export_table,
    make_table as make_table,
    read_astm_e1392 as read_astm_e1392,
    read_cornell_brdf as read_cornell_brdf,
    read_merl_inplane as read_merl_inplane,
    read_table as read_table,
)
from ._auto_init import (
    INITIALIZERS as INITIALIZERS,
    fit_amplitudes as fit_amplitudes,
    get_initializer as get_initializer,
    init_solar_cell as init_solar_cell,
    init_specular_lambertian as init_specular_lambertian,
)
from ._common import FitInputError as FitInputError
from ._covariance import Covariance as Covariance, covariance as covariance
from ._fit import FIRST_STAGES as FIRST_STAGES, fit as fit, versions as versions
from ._frames_io import (
    detector_from_attrs as detector_from_attrs,
    frame_data_from_reduced as frame_data_from_reduced,
    read_frame_data as read_frame_data,
)
from ._likelihood import LIKELIHOOD_OPTIONS as LIKELIHOOD_OPTIONS, Likelihood as Likelihood, prepare as prepare
from ._params import TRANSFORMS as TRANSFORMS, Param as Param
from ._residuals import (
    LOSSES as LOSSES,
    irls_weights as irls_weights,
    robust_residuals as robust_residuals,
)
from ._result import BlockSummary as BlockSummary, FitResult as FitResult, ParameterEstimate as ParameterEstimate
from ._sharding import shard_problem as shard_problem
from ._solvers import (
    LBFGSB as LBFGSB,
    SOLVERS as SOLVERS,
    AbstractSolver as AbstractSolver,
    LevenbergMarquardt as LevenbergMarquardt,
    SolveOutcome as SolveOutcome,
    SolveStatus as SolveStatus,
    get_solver as get_solver,
)
from ._synthetic import render_noisy_frames as render_noisy_frames
