"""The posterior's chain file (fitting/_chain.py): saved atomically after every chunk, read
back whole, and resumed to exactly the chain of one uninterrupted run; a chain of another fit,
or a missing file, is refused. The format: docs/fitting.md, "Chain file"."""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting
from stairfit.fitting import posterior

VARIANT, _small = zoo.POSTERIOR_VARIANT, zoo.posterior_scene


@pytest.fixture(scope="module")
def fit() -> fitting.FitResult:
    return zoo.posterior_fit()


_short = zoo.short_chain


def test_chain_file_reloads_and_resume_continues_exactly(fit, tmp_path):
    path = tmp_path / "chain.npz"
    first = _short(fit, seed=3, max_steps=200, chain_path=path)
    saved = posterior.load_chain(path)
    assert saved["chain_z"].shape == (200, first.n_walkers, 4)
    assert saved["chain"].shape == (200, first.n_walkers, 4)
    assert saved["log_prob"].shape == (200, first.n_walkers)
    assert tuple(saved["names"]) == fit.names and int(saved["seed"]) == 3
    assert int(saved["format_version"]) == posterior.CHAIN_FORMAT_VERSION
    assert not list(tmp_path.glob("*.tmp"))  # atomic write: no temporary file left behind
    # resuming to 400 steps gives exactly the chain of one uninterrupted 400-step run
    resumed = _short(fit, seed=999, max_steps=400, chain_path=path, resume=True)
    assert resumed.seed == 3 and resumed.n_steps == 400
    straight = _short(fit, seed=3, max_steps=400, chain_path=tmp_path / "straight.npz")
    np.testing.assert_array_equal(
        posterior.load_chain(path)["chain_z"],
        posterior.load_chain(tmp_path / "straight.npz")["chain_z"],
    )
    np.testing.assert_array_equal(resumed.acceptance_per_walker, straight.acceptance_per_walker)


def test_resume_refuses_a_different_fit_or_missing_file(fit, tmp_path):
    path = tmp_path / "chain.npz"
    _short(fit, seed=1, max_steps=100, chain_path=path)
    obs, spec = _small(22)
    other = fitting.fit_least_squares(obs, spec, VARIANT)
    with pytest.raises(fitting.FitInputError, match="belongs to a different fit"):
        posterior.sample_posterior(other, chain_path=path, resume=True)
    with pytest.raises(fitting.FitInputError, match="does not exist"):
        posterior.sample_posterior(fit, chain_path=tmp_path / "none.npz", resume=True)
