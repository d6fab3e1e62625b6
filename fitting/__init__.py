"""Fitting the staircase model to measured radiance: least squares, posteriors, model choice.

Public API (everything else is internal). Conventions: docs/conventions.md; design, priors,
transforms and the selection rule: docs/fitting.md.

The posterior (`sample_posterior`, its options and result, the chain file) is the submodule
`stairfit.fitting.posterior`, imported explicitly: it imports emcee, which imports SciPy, a cost
that a fit without a posterior and every `import stairfit.fitting` need not pay (issue 14).
"""

from ._accuracy import ACCURACY_LIMIT as ACCURACY_LIMIT
from ._accuracy import NumericalError as NumericalError
from ._accuracy import numerical_error as numerical_error
from ._core import SOLVERS as SOLVERS
from ._core import fisher_information as fisher_information
from ._core import step_gflop as step_gflop
from ._curves import DENSE_STEP_RAD as DENSE_STEP_RAD
from ._curves import ModelCurve as ModelCurve
from ._curves import model_at as model_at
from ._curves import model_curves as model_curves
from ._diagnostics import ESS_MIN as ESS_MIN
from ._diagnostics import RHAT_MAX as RHAT_MAX
from ._errors import BoundaryWarning as BoundaryWarning
from ._errors import ConvergenceWarning as ConvergenceWarning
from ._errors import FitError as FitError
from ._errors import FitInputError as FitInputError
from ._errors import FitWarning as FitWarning
from ._errors import FitWarningCategory as FitWarningCategory
from ._errors import UnconstrainedError as UnconstrainedError
from ._errors import UnidentifiedParameterWarning as UnidentifiedParameterWarning
from ._forward import Resolution as Resolution
from ._identify import IDENTIFIABILITY_THRESHOLD as IDENTIFIABILITY_THRESHOLD
from ._jacobian import model_jacobian as model_jacobian
from ._lab import LabGeometry as LabGeometry
from ._least_squares import DEFAULT_SIGMA_STARTS_RAD as DEFAULT_SIGMA_STARTS_RAD
from ._least_squares import LeastSquaresOptions as LeastSquaresOptions
from ._least_squares import fit_least_squares as fit_least_squares
from ._misfit import Assessment as Assessment
from ._misfit import ResidualGroup as ResidualGroup
from ._misfit import Status as Status
from ._misfit import chi2_p_value as chi2_p_value
from ._misfit import describe_fit as describe_fit
from ._misfit import measurement_residuals as measurement_residuals
from ._observations import Observations as Observations
from ._observations import Spectral as Spectral
from ._observations import spectral_setup as spectral_setup
from ._params import DEFAULT_LADDER as DEFAULT_LADDER
from ._params import DEFAULTS as DEFAULTS
from ._params import FILLET as FILLET
from ._params import FILLET_RUNGS as FILLET_RUNGS
from ._params import PARAM_NAMES as PARAM_NAMES
from ._params import PARAMETERS as PARAMETERS
from ._params import SIMPLEST as SIMPLEST
from ._params import HalfNormal as HalfNormal
from ._params import LogUniform as LogUniform
from ._params import Normal as Normal
from ._params import Parameter as Parameter
from ._params import ParamInfo as ParamInfo
from ._params import Params as Params
from ._params import Priors as Priors
from ._params import Transform as Transform
from ._params import Uniform as Uniform
from ._params import Variant as Variant
from ._params import parameter_label as parameter_label
from ._params import variant as variant
from ._problem import Problem as Problem
from ._problem import max_edge_radius_um as max_edge_radius_um
from ._problem import prepare as prepare
from ._result import Estimate as Estimate
from ._result import FitResult as FitResult
from ._selection import CRITERIA as CRITERIA
from ._selection import DEFAULT_THRESHOLD as DEFAULT_THRESHOLD
from ._selection import ROUNDED_RUNGS as ROUNDED_RUNGS
from ._selection import ComparisonRow as ComparisonRow
from ._selection import Rounding as Rounding
from ._selection import Selection as Selection
from ._selection import budget_untried as budget_untried
from ._selection import fillet_needed as fillet_needed
from ._selection import not_fitted_row as not_fitted_row
from ._selection import parents_of as parents_of
from ._selection import rounding_needed as rounding_needed
from ._selection import select_model as select_model
from ._simulate import STANDARD_WEDGES_DEG as STANDARD_WEDGES_DEG
from ._simulate import Design as Design
from ._simulate import Noise as Noise
from ._simulate import model_radiance as model_radiance
from ._simulate import simulate_observations as simulate_observations
from ._simulate import standard_design as standard_design
