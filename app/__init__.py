"""stairfit: fit a physical, differentiable model of the FDM staircase to RAW photographs.

Subpackages: `stairfit.model` (the forward model, pure JAX), `stairfit.fitting` (least squares,
posteriors, model selection), `stairfit.imaging` (RAW decoding, ROIs, radiance). This package
holds the command line and the pieces that join them. Conventions: docs/conventions.md.
"""

__version__ = "0.1.0"
