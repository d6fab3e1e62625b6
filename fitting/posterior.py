"""Posteriors of a least-squares fit with emcee: sampling, its options and result, the chain file.

A submodule of its own, imported explicitly (`from stairfit.fitting import posterior`): it
imports emcee, which imports SciPy, a cost that `import stairfit.fitting` and a fit without a
posterior need not pay (issue 14). Settings, moves, diagnostics and the chain file's format:
docs/fitting.md.
"""

from ._chain import CHAIN_FORMAT_VERSION as CHAIN_FORMAT_VERSION
from ._chain import ChainBackend as ChainBackend
from ._chain import ChainInfo as ChainInfo
from ._chain import load_chain as load_chain
from ._posterior import MOVES as MOVES
from ._posterior import LaplaceMove as LaplaceMove
from ._posterior import PosteriorOptions as PosteriorOptions
from ._posterior import PosteriorResult as PosteriorResult
from ._posterior import log_likelihood as log_likelihood
from ._posterior import log_prior as log_prior
from ._posterior import log_probability as log_probability
from ._posterior import sample_posterior as sample_posterior
