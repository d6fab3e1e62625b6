"""One compilation for every scene of one design (issue 14).

A fit's arrays are padded to shape buckets (`_problem.bucket`: the evaluation keys, the
geometry entries and the groups of correlated rows), and the priors' numbers are data of the
compiled log priors (`_params.split_priors`). A second scene of the same design, with other
values, another ROI flagged (one group fewer) and so another data-derived floor prior, then
compiles none of the fit's and the posterior's programs: with the CLI's persistent cache a new
scene of a known design fits as fast as a second run of the same one. The padding changes no
number: a fit and its log posterior with and without it agree.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import jax
import numpy as np
import pytest

from stairfit import fitting
from stairfit.fitting import _posterior, _problem, posterior
from stairfit.fitting._whiten import group_arrays

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)
VARIANT = fitting.variant("dn_floor_me", "delta_n", "floor", "model_error_frac")
CORR = (0.5, 0.4, 0.3)
FIT_PROGRAMS = ("_solve_one", "evaluate", "batched_log_probability", "log_prior_split")
"""The programs a fit, its posterior and its Laplace evidence compile (`jit(name)`)."""


def _scene(
    seed: int, gain: float, flagged_roi: int | None, spread: float = 1.0
) -> tuple[fitting.Observations, ...]:
    """Two wedges x 5 views x 3 channels, each photo x wedge a group of 3 correlated rows;
    values scaled by `gain` (the floor's prior scales with the largest value); the rows of ROI
    `flagged_roi` excluded; every row's viewing spread `spread` (a share of the aperture's)."""
    spec = fitting.spectral_setup("pla", sampling="effective")
    design = fitting.Design((20.0, 45.0), (20.0,) * 5, (-60.0, -30.0, 0.0, 30.0, 60.0))
    obs = fitting.simulate_observations(TRUTH, design, spec, fitting.Noise(0.02), seed=seed)
    roi = obs.photo_index * 100 + obs.wedge_index
    use = np.ones(obs.n_rows, bool) if flagged_roi is None else roi != flagged_roi
    corr = dict(zip(("corr_01", "corr_02", "corr_12"), CORR, strict=True))
    arrays = {**obs._asdict(), "value": obs.value * gain, "stderr": obs.stderr * gain,
              "view_spread": np.full(obs.n_rows, spread)}  # fmt: skip
    obs = fitting.Observations.from_arrays(**{**arrays, "roi_index": roi, "use": use, **corr})
    return obs, spec


@contextmanager
def _compiled() -> Iterator[list[str]]:
    """The names of the programs XLA compiles inside the block."""
    names: list[str] = []

    def listener(event: str, duration: float, **kw: object) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(str(kw.get("fun_name", "")))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def _fit_and_sample(obs: fitting.Observations, spec: fitting.Spectral) -> fitting.FitResult:
    fit = fitting.fit_least_squares(obs, spec, VARIANT, emit_warnings=False)
    assert fit.success, fit.message
    posterior.sample_posterior(fit, seed=0, chunk_steps=20, max_steps=40, emit_warnings=False)
    assert fit.laplace_log_evidence is not None
    return fit


def test_bucket_rounds_up_by_at_most_7_or_a_quarter() -> None:
    previous = 0
    for n in range(1, 5000):
        b = _problem.bucket(n)
        assert b >= n and b % 8 == 0 and b >= previous, n
        assert b - n <= max(7, n // 4), n
        previous = b
    assert (_problem.bucket(54), _problem.bucket(130)) == (56, 160)  # the docstring's examples


def test_a_second_scene_of_the_design_compiles_no_fit_or_posterior_program() -> None:
    (a, spec), (b, _) = _scene(1, 1.0, None), _scene(2, 1.3, flagged_roi=101)
    corr = np.stack([a.corr_01, a.corr_02, a.corr_12], axis=1)
    groups = [group_arrays(o.use, o.roi_index, o.channel_index, corr).rows.shape[0] for o in (a, b)]
    assert groups == [10, 9]  # unpadded, the two scenes' arrays differ in shape
    fit_a = _fit_and_sample(a, spec)
    with _compiled() as names:
        fit_b = _fit_and_sample(b, spec)
    priors = [next(p.prior for p in f.parameters if p.param == "floor") for f in (fit_a, fit_b)]
    assert priors[0] != priors[1]  # a static prior specification would differ too
    assert fit_a.problem.data.grp_rows.shape == fit_b.problem.data.grp_rows.shape
    again = [n for n in names if n.removeprefix("jit(").removesuffix(")") in FIT_PROGRAMS]
    assert again == [], again


def test_the_padding_changes_no_number(monkeypatch: pytest.MonkeyPatch) -> None:
    obs, spec = _scene(3, 1.0, flagged_roi=1, spread=0.6)
    padded = fitting.fit_least_squares(obs, spec, VARIANT, emit_warnings=False)
    monkeypatch.setattr(_problem, "bucket", lambda n: n)
    plain = fitting.fit_least_squares(obs, spec, VARIANT, emit_warnings=False)
    d0, d1 = plain.problem.data, padded.problem.data
    assert d1.grp_rows.shape[0] > d0.grp_rows.shape[0] and d1.r_ti.shape[0] > d0.r_ti.shape[0]
    assert padded.success and plain.success
    # the same optimum; the two programs sum in different orders (last-bit differences), and
    # the solver's steps carry them
    np.testing.assert_allclose(padded.values, plain.values, rtol=1e-9)
    np.testing.assert_allclose(padded.stderrs, plain.stderrs, rtol=1e-6)
    np.testing.assert_allclose(padded.chi2, plain.chi2, rtol=1e-9)
    # the log posterior at the same walkers, to rounding
    t0, t1 = _posterior.target(plain), _posterior.target(padded)
    rng = np.random.default_rng(0)
    theta = t0.base_z[t0.slots] + 0.01 * rng.standard_normal((8, t0.slots.size))
    np.testing.assert_allclose(t1.log_prob(theta), t0.log_prob(theta), rtol=1e-12)
    # a chain file written before the padding resumes: the fingerprint leaves it out (the
    # groups and the per-key viewing spreads, both padded here, are part of it)
    assert d1.r_so.shape[0] > d0.r_so.shape[0] > 1 and not np.all(np.asarray(d0.r_so) == 1.0)
    assert t1.fingerprint == t0.fingerprint
