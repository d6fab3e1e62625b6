"""Correlated channels whitened per ROI (issue 13; docs/fitting.md §Correlated channels).

The three channels of one ROI share its texture, so their errors are correlated; the fit
whitens each group of rows (`Observations.roi_index`) with `C = S R S (+ diag((f m)^2))`. These
tests check the whitening against the explicit quadratic form `r^T C^-1 r` (numpy's own
solve), the clipping of non-positive-definite measured correlations, a fit's calibration on
data with a known 3 x 3 noise covariance drawn here (not by the code under test), that
independent rows are fitted as before, finite gradients at correlations of +-1, and the
validation messages.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import fitting
from stairfit.fitting import _whiten
from stairfit.fitting._core import start_vectors
from stairfit.fitting._forward import log_likelihood_z, residuals
from stairfit.fitting._problem import prepare, spec_for

DEG = math.pi / 180


# --- the whitening against the explicit quadratic form ----------------------------------------


def _random_groups(rng: np.random.Generator, n_groups: int, corr_of) -> dict:
    """Rows of `n_groups` ROIs with 1-3 used channels each, random stderrs, extra variances,
    residuals and each ROI's correlations from `corr_of(rng)` (three numbers)."""
    cols: dict[str, list] = {k: [] for k in ("use", "roi", "ch", "corr", "se", "extra", "r")}
    for g in range(n_groups):
        c = corr_of(rng)
        used = rng.permutation(3)[: rng.integers(1, 4)]
        for ch in range(3):
            cols["use"].append(ch in used)
            cols["roi"].append(g)
            cols["ch"].append(ch)
            cols["corr"].append(c)
            cols["se"].append(rng.uniform(0.1, 2.0))
            cols["extra"].append(rng.uniform(0.0, 1.0))
            cols["r"].append(rng.normal())
    return {k: np.asarray(v) for k, v in cols.items()}


def _explicit(t: dict, clip) -> tuple[float, float]:
    """(sum r^T C^-1 r, sum log det C) over the groups with numpy's solve and slogdet; `clip`
    maps the correlation matrix of a group's used channels to the one the fit should use."""
    quad = logdet = 0.0
    for g in np.unique(t["roi"]):
        rows = np.flatnonzero((t["roi"] == g) & t["use"])
        rows = rows[np.argsort(t["ch"][rows])]
        c = t["corr"][rows[0]]
        r_full = np.array([[1, c[0], c[1]], [c[0], 1, c[2]], [c[1], c[2], 1]], float)
        ch = t["ch"][rows]
        s = t["se"][rows]
        cov = np.outer(s, s) * clip(r_full[np.ix_(ch, ch)]) + np.diag(t["extra"][rows])
        quad += float(t["r"][rows] @ np.linalg.solve(cov, t["r"][rows]))
        logdet += float(np.linalg.slogdet(cov)[1])
    return quad, logdet


def _whitened(t: dict) -> tuple[float, float]:
    groups = _whiten.group_arrays(t["use"], t["roi"], t["ch"], t["corr"])
    args = (jnp.asarray(groups.rows), jnp.asarray(groups.mask), jnp.asarray(groups.corr))
    chol = _whiten.group_cholesky(jnp.asarray(t["se"]), jnp.asarray(t["extra"]), *args)
    w = _whiten.whiten(chol, jnp.asarray(t["r"]), args[0], args[1])
    logdet = 2.0 * float(jnp.sum(_whiten.log_diag(chol, args[1])))
    return float(jnp.sum(w * w)), logdet


def _psd_corr(rng: np.random.Generator) -> np.ndarray:
    """A random well-conditioned correlation matrix's three pairwise entries."""
    a = rng.normal(size=(3, 5))
    cov = a @ a.T
    d = 1 / np.sqrt(np.diag(cov))
    r = cov * np.outer(d, d)
    return np.array([r[0, 1], r[0, 2], r[1, 2]])


def test_whitening_equals_explicit_quadratic_form_for_psd_correlations() -> None:
    rng = np.random.default_rng(1)
    t = _random_groups(rng, 40, _psd_corr)
    mats = [_whiten.correlation_matrix(*c) for c in t["corr"]]
    assert min(np.linalg.eigvalsh(m).min() for m in mats) > _whiten.EIGEN_FLOOR  # no clipping
    quad, logdet = _explicit(t, lambda r: r)
    q_w, ld_w = _whitened(t)
    assert q_w == pytest.approx(quad, rel=1e-10)
    assert ld_w == pytest.approx(logdet, rel=1e-10, abs=1e-10)


def _clipped_by_hand(r: np.ndarray, floor: float) -> np.ndarray:
    """The documented clipping, written out: eigenvalues raised to `floor`, unit diagonal."""
    lam, v = np.linalg.eigh(r)
    a = v @ np.diag(np.maximum(lam, floor)) @ v.T
    d = np.sqrt(np.diag(a))
    return a / np.outer(d, d)


def test_non_psd_correlations_are_clipped_and_whitened_exactly() -> None:
    """Pairwise estimates such as (0.9, 0.9, -0.9) have no covariance matrix: the fit uses the
    clipped one, positive definite with unit diagonal, and whitens with it exactly. The
    clipping is of the used channels' matrix: a group of two keeps a valid pair as measured."""
    rng = np.random.default_rng(2)

    def bad(rng: np.random.Generator) -> np.ndarray:
        return rng.choice([-1.0, 1.0], 3) * rng.uniform(0.85, 1.0, 3)

    t = _random_groups(rng, 40, bad)
    n_bad = sum(np.linalg.eigvalsh(_whiten.correlation_matrix(*c)).min() < 0 for c in t["corr"])
    assert n_bad > 10  # the test really exercises the clipping
    for c in t["corr"][::3]:
        clipped = _whiten.clip_correlation(_whiten.correlation_matrix(*c))
        np.testing.assert_allclose(np.diag(clipped), 1.0, atol=1e-15)
        np.testing.assert_allclose(clipped, clipped.T, atol=1e-15)
        floor = _whiten.EIGEN_FLOOR
        assert np.linalg.eigvalsh(clipped).min() >= floor / (3 + floor) * (1 - 1e-9)
        by_hand = _clipped_by_hand(_whiten.correlation_matrix(*c), floor)
        np.testing.assert_allclose(clipped, by_hand, atol=1e-12)
    # a group's clipping concerns the channels it has (a valid pair stays as measured)
    quad, logdet = _explicit(t, lambda r: _clipped_by_hand(r, _whiten.EIGEN_FLOOR))
    q_w, ld_w = _whitened(t)
    assert q_w == pytest.approx(quad, rel=1e-8)
    assert ld_w == pytest.approx(logdet, rel=1e-8, abs=1e-8)


def test_a_positive_definite_correlation_is_not_changed_by_clipping() -> None:
    r = _whiten.correlation_matrix(0.5, 0.3, 0.2)
    np.testing.assert_array_equal(_whiten.clip_correlation(r), r)


# --- fits on data with a known 3 x 3 noise covariance -----------------------------------------

TRUTH = fitting.Params(sigma_rad=6 * DEG, delta_n=0.0, scale=1.0, floor=0.0)
CORR = (0.9, 0.8, 0.85)
"""The ROIs' channel correlations of the calibration test (R-G, R-B, G-B): texture-like."""
N_DATASETS = 100


def _design() -> fitting.Design:
    """2 wedges (20, 45 deg) x 9 views x the camera's three channels: 18 ROIs, 54 rows."""
    views = tuple(np.linspace(-70, 70, 9))
    return fitting.Design((20.0, 45.0), (20.0,) * 9, views, channels=(0, 1, 2))


def _correlated_noise(obs: fitting.Observations, seed: int) -> np.ndarray:
    """Per photo x wedge, `S L_R eps` with `R` from `CORR` (drawn here, not by stairfit)."""
    r = np.array([[1, CORR[0], CORR[1]], [CORR[0], 1, CORR[2]], [CORR[1], CORR[2], 1]])
    chol = np.linalg.cholesky(r)
    rng = np.random.default_rng(seed)
    noise = np.zeros(obs.n_rows)
    roi = obs.photo_index * 100 + obs.wedge_index
    for g in np.unique(roi):
        rows = np.flatnonzero(roi == g)
        rows = rows[np.argsort(obs.channel_index[rows])]
        noise[rows] = obs.stderr[rows] * (chol @ rng.standard_normal(3))
    return noise


def _datasets(spec: fitting.Spectral) -> list[tuple[fitting.Observations, fitting.Observations]]:
    """(correlated, same data marked independent) for each seed."""
    base = fitting.simulate_observations(TRUTH, _design(), spec, fitting.Noise(0.02), seed=0)
    clean = fitting.model_radiance(TRUTH, base, spec)
    roi = base.photo_index * 100 + base.wedge_index
    out = []
    for seed in range(N_DATASETS):
        value = clean + _correlated_noise(base, seed)
        indep = fitting.Observations.from_arrays(**{**base._asdict(), "value": value})
        corr = dict(zip(("corr_01", "corr_02", "corr_12"), CORR, strict=True))
        grouped = fitting.Observations.from_arrays(
            **{**base._asdict(), "value": value, "roi_index": roi, **corr}
        )
        out.append((grouped, indep))
    return out


def _pulls(fits: list[fitting.FitResult]) -> np.ndarray:
    """(dataset, parameter) pulls against the truth; parameters sigma, delta_n, scale."""
    truth = {"sigma_rad": TRUTH.sigma_rad, "delta_n": TRUTH.delta_n, "scale": TRUTH.scale}
    out = []
    for f in fits:
        assert f.success and f.stderrs is not None, f.message
        out.append([(e.value - truth[e.param]) / e.stderr for e in f.estimates])
    return np.asarray(out)


def test_correlated_noise_gives_calibrated_pulls_and_coverage() -> None:
    """100 datasets with noise of a known 3 x 3 channel covariance (correlations 0.8-0.9).

    Stated bounds (3 sigma of the sampling distribution for 100 datasets): each parameter's
    pull sd within 1 +- 3/sqrt(200) = [0.79, 1.21]; 95% intervals (|pull| < 1.96) cover the
    truth in at least 95 - 3 x 2.2 = 89 datasets; 68% intervals (|pull| < 1) in 68 +- 3 x 4.7
    = [54, 82]; the mean chi^2 within dof +- 3 sqrt(2 dof / 100). The same data fitted as
    independent rows give a scale pull sd above 1.3 (the common-mode error counted as three
    independent ones), so the test can tell the two error models apart.
    """
    spec = fitting.spectral_setup("pla-bodurov2016", sampling="effective")
    variant = fitting.variant("sharp+delta_n", "delta_n")
    opts = fitting.LeastSquaresOptions(sigma_starts_rad=(TRUTH.sigma_rad,), emit_warnings=False)
    pairs = _datasets(spec)
    fits = [fitting.fit_least_squares(g, spec, variant, opts) for g, _ in pairs]
    pulls = _pulls(fits)
    assert pulls.shape == (N_DATASETS, 3)
    sd = pulls.std(axis=0, ddof=1)
    assert np.all((sd > 0.79) & (sd < 1.21)), dict(zip(fits[0].names, sd, strict=True))
    cover95 = np.sum(np.abs(pulls) < 1.96, axis=0)
    cover68 = np.sum(np.abs(pulls) < 1.0, axis=0)
    assert np.all(cover95 >= 89), cover95
    assert np.all((cover68 >= 54) & (cover68 <= 82)), cover68
    dof = fits[0].dof
    chi2 = np.array([f.chi2 for f in fits])
    assert abs(chi2.mean() - dof) < 3 * math.sqrt(2 * dof / N_DATASETS), (chi2.mean(), dof)
    naive = _pulls([fitting.fit_least_squares(i, spec, variant, opts) for _, i in pairs[:40]])
    k = fits[0].index("scale")
    assert naive[:, k].std(ddof=1) > 1.3, naive.std(axis=0, ddof=1)


# --- independent rows, as before ---------------------------------------------------------------


def test_independent_rows_take_the_plain_path_and_ungrouped_zero_correlation_agrees() -> None:
    """Without groups the fit is today's: no whitening (`correlated` False), the residuals are
    `(value - model) / stderr` exactly; groups whose correlations are 0 give the same fit to
    rounding."""
    spec = fitting.spectral_setup("pla", sampling="effective")
    obs = fitting.simulate_observations(TRUTH, _design(), spec, fitting.Noise(0.02), seed=3)
    plain = fitting.fit_least_squares(obs, spec, emit_warnings=False)
    assert plain.problem is not None and not plain.problem.correlated
    resid = (obs.value - plain.model) / obs.stderr
    np.testing.assert_array_equal(plain.residuals, resid)
    assert plain.chi2 == pytest.approx(float(np.sum(resid**2)), rel=1e-14)
    unique = obs._replace(roi_index=np.arange(obs.n_rows))  # one group per row: independent
    assert not prepare(unique, spec).correlated
    roi = obs.photo_index * 100 + obs.wedge_index
    grouped = fitting.Observations.from_arrays(**{**obs._asdict(), "roi_index": roi})
    fit = fitting.fit_least_squares(grouped, spec, emit_warnings=False)
    assert fit.problem is not None and fit.problem.correlated
    np.testing.assert_allclose(fit.values, plain.values, rtol=1e-9)
    np.testing.assert_allclose(fit.covariance, plain.covariance, rtol=1e-8)
    assert fit.chi2 == pytest.approx(plain.chi2, rel=1e-10)
    assert fit.log_likelihood == pytest.approx(plain.log_likelihood, rel=1e-12)
    np.testing.assert_allclose(fit.residuals, plain.residuals, atol=1e-9)


# --- gradients at correlations of +-1 ----------------------------------------------------------


# compiled once for all four correlations (they are data): eagerly, the first case took 17 s
_ll_and_grad = jax.jit(jax.value_and_grad(log_likelihood_z), static_argnums=(1,))
_residual_jacobian = jax.jit(
    lambda z, static, data: jax.jacfwd(residuals)(z, (static, data)), static_argnums=(1,)
)


@pytest.mark.parametrize(
    "corr", [(1.0, 1.0, 1.0), (-1.0, -1.0, 1.0), (0.999999, 0.999999, 0.999999), (1.0, -1.0, 1.0)]
)
def test_gradients_are_finite_at_extreme_correlations(corr: tuple[float, float, float]) -> None:
    """Singular (and, for (1, -1, 1), impossible) measured correlations: the clipped matrix keeps
    the log-likelihood, the residuals and their derivatives finite, with the model-error term
    (inside the Cholesky) on and at zero."""
    spec = fitting.spectral_setup("pla", sampling="effective")
    obs = fitting.simulate_observations(TRUTH, _design(), spec, fitting.Noise(0.02), seed=4)
    roi = obs.photo_index * 100 + obs.wedge_index
    c = dict(zip(("corr_01", "corr_02", "corr_12"), corr, strict=True))
    obs = fitting.Observations.from_arrays(**{**obs._asdict(), "roi_index": roi, **c})
    problem = prepare(obs, spec)
    spec_v = spec_for(fitting.variant("me", "delta_n", "model_error_frac"), problem)
    static, data = problem.static_for(spec_v), problem.arrays_for(spec_v)
    assert static.correlated and static.model_error
    z0 = jnp.asarray(start_vectors(problem, spec_v, (TRUTH.sigma_rad,))[0])
    k = problem.layout.slot("model_error_frac")
    for z in (z0, z0.at[k].set(-30.0)):  # 2% model error, and practically none
        ll, grad = _ll_and_grad(z, static, data)
        jac = _residual_jacobian(z, static, data)
        assert np.isfinite(float(ll))
        assert np.all(np.isfinite(np.asarray(grad))) and np.any(np.asarray(grad) != 0)
        assert np.all(np.isfinite(np.asarray(jac)))


# --- validation ----------------------------------------------------------------------------------


def _rows(**override: object) -> list[dict]:
    base = {"theta_i_deg": 20.0, "theta_o_deg": 10.0, "beta2_deg": 30.0, "layer_um": 200.0,
            "wedge_index": 0, "value": 1.0, "stderr": 0.1, "roi_index": 0,
            "corr_01": 0.5, "corr_02": 0.4, "corr_12": 0.3}  # fmt: skip
    rows = [{**base, "channel_index": c} for c in range(3)]
    for key, value in override.items():
        name, i = key.rsplit("_", 1)
        rows[int(i)][name] = value
    return rows


@pytest.mark.parametrize(
    ("override", "fragments"),
    [
        ({"channel_index_2": 1}, ("row 2", "channel_index", "twice", "roi_index")),
        ({"corr_01_1": 0.6}, ("row 1", "corr_01", "differs", "same correlations")),
        ({"corr_12_0": 1.5, "corr_12_1": 1.5, "corr_12_2": 1.5}, ("corr_12", "[-1, 1]")),
        ({"corr_02_0": float("nan")}, ("row 0", "corr_02", "[-1, 1]", "0 if it is unknown")),
        ({"channel_index_2": 3}, ("row 2", "channel_index", "above 2")),
    ],
)
def test_bad_groups_are_refused_with_the_row_field_and_fix(override: dict, fragments) -> None:
    with pytest.raises(fitting.FitInputError) as err:
        fitting.Observations.from_rows(_rows(**override))
    msg = str(err.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, (f, msg)


def test_groups_are_optional_and_single_rows_need_no_correlation() -> None:
    """Old tables (no roi_index, no corr_*) are independent rows; a group with one used row
    may carry an unknown (NaN) correlation; unused rows leave their group."""
    rows = [{k: v for k, v in r.items() if k != "roi_index" and not k.startswith("corr")}
            for r in _rows()]  # fmt: skip
    obs = fitting.Observations.from_rows(rows)
    np.testing.assert_array_equal(obs.roi_index, -1)
    np.testing.assert_array_equal(obs.corr_01, 0.0)
    lone = _rows(corr_01_0=float("nan"), corr_01_1=float("nan"), corr_01_2=float("nan"),
                 use_1=False, use_2=False)  # fmt: skip
    obs = fitting.Observations.from_rows(lone)
    assert obs.roi_index.tolist() == [0, -1, -1]
    assert np.all(np.isfinite(obs.corr_01))
