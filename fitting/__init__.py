"""Fitting the staircase model to measured radiance: least squares, posteriors, model choice.

Public API (everything else is internal). Conventions: docs/conventions.md; design, priors,
transforms and the selection rule: docs/fitting.md.
"""

from ._errors import BoundaryWarning as BoundaryWarning
from ._errors import ConvergenceWarning as ConvergenceWarning
from ._errors import FitError as FitError
from ._errors import FitInputError as FitInputError
from ._errors import FitWarning as FitWarning
from ._errors import FitWarningCategory as FitWarningCategory
from ._errors import UnidentifiedParameterWarning as UnidentifiedParameterWarning
from ._least_squares import DEFAULT_SIGMA_STARTS_RAD as DEFAULT_SIGMA_STARTS_RAD
from ._least_squares import IDENTIFIABILITY_THRESHOLD as IDENTIFIABILITY_THRESHOLD
from ._least_squares import SOLVERS as SOLVERS
from ._least_squares import Estimate as Estimate
from ._least_squares import FitResult as FitResult
from ._least_squares import fit_least_squares as fit_least_squares
from ._observations import Observations as Observations
from ._observations import Spectral as Spectral
from ._observations import spectral_setup as spectral_setup
from ._params import DEFAULT_LADDER as DEFAULT_LADDER
from ._params import DEFAULTS as DEFAULTS
from ._params import PARAM_NAMES as PARAM_NAMES
from ._params import PARAM_UNITS as PARAM_UNITS
from ._params import SIMPLEST as SIMPLEST
from ._params import HalfNormal as HalfNormal
from ._params import LogUniform as LogUniform
from ._params import Normal as Normal
from ._params import Params as Params
from ._params import Priors as Priors
from ._params import Uniform as Uniform
from ._params import Variant as Variant
from ._params import variant as variant
from ._posterior import CHAIN_FORMAT_VERSION as CHAIN_FORMAT_VERSION
from ._posterior import PosteriorResult as PosteriorResult
from ._posterior import load_chain as load_chain
from ._posterior import log_likelihood as log_likelihood
from ._posterior import log_prior as log_prior
from ._posterior import log_probability as log_probability
from ._posterior import sample_posterior as sample_posterior
from ._problem import Problem as Problem
from ._problem import max_edge_radius_um as max_edge_radius_um
from ._problem import prepare as prepare
from ._problem import rounded_model_available as rounded_model_available
from ._selection import CRITERIA as CRITERIA
from ._selection import DEFAULT_THRESHOLD as DEFAULT_THRESHOLD
from ._selection import ComparisonRow as ComparisonRow
from ._selection import Selection as Selection
from ._selection import select_model as select_model
from ._simulate import STANDARD_WEDGES_DEG as STANDARD_WEDGES_DEG
from ._simulate import Design as Design
from ._simulate import Noise as Noise
from ._simulate import predict as predict
from ._simulate import simulate_observations as simulate_observations
from ._simulate import standard_design as standard_design
