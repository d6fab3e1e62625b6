"""Posterior sampling with emcee around a least-squares fit [conventions §9, §10].

`log_likelihood`, `log_prior` and `log_probability` are module-level functions of the free
unconstrained parameters; one `jax.jit(jax.vmap(log_probability))` evaluates all walkers at
once (`emcee.EnsembleSampler(..., vectorize=True)`). Priors are on the *physical* parameters:
`log_prior` adds `log |dx/dz|` of each transform. Seeds are explicit and recorded; the chain
lives in a `ChainBackend` (`_chain.py`), saved atomically after every chunk, and a run resumes
from it with `run_mcmc(None, n)`.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import emcee
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _export
from ._chain import ChainBackend, ChainInfo
from ._diagnostics import (
    ESS_MIN,
    RHAT_MAX,
    Diagnostics,
    chain_diagnostics,
    diagnostic_warnings,
    display_factors,
    inference_data,
    variable_names,
    write_netcdf,
)
from ._errors import FitError, FitInputError, FitWarning, emit, with_overrides
from ._forward import Data, Static, log_likelihood_z, physical
from ._params import (
    ABS,
    SIN,
    SIN_REST,
    Parameter,
    Prior,
    PriorSpec,
    in_support,
    log_prior_z,
    split_priors,
)
from ._result import FitResult


def _full_z(theta: Array, base_z: Array, free_slots: Array) -> Array:
    return base_z.at[free_slots].set(theta)


def log_prior(
    theta: Array, static: Static, priors: PriorSpec, data: Data, base_z: Array, free_slots: Array
) -> Array:
    """Log prior density of the free unconstrained parameters `theta`.

    `sum over free slots of [log p(x) + log |dx/dz|]`: priors are stated on the physical
    values; `-inf` outside their support (and outside the sine's principal branch).
    """
    z = _full_z(theta, base_z, free_slots)
    fixed = (data.free, data.x_fixed)
    total = log_prior_z(z, static.layout.kinds, data.r_max_um, priors, fixed)
    return jnp.where(in_support(z, static.layout.kinds), total, -jnp.inf)


def log_likelihood(
    theta: Array, static: Static, data: Data, base_z: Array, free_slots: Array
) -> Array:
    """Gaussian log-likelihood of the used rows at the free parameters `theta`."""
    return log_likelihood_z(_full_z(theta, base_z, free_slots), static, data)


def log_probability(
    theta: Array, static: Static, priors: PriorSpec, data: Data, base_z: Array, free_slots: Array
) -> Array:
    """`log_prior + log_likelihood`; `-inf` where the prior is zero (NaN is never hidden)."""
    lp = log_prior(theta, static, priors, data, base_z, free_slots)
    ll = log_likelihood(theta, static, data, base_z, free_slots)
    return jnp.where(jnp.isfinite(lp), lp + ll, -jnp.inf)


def batched_log_probability(
    theta: Array,
    static: Static,
    prior_slots: tuple[int, ...],
    prior_dists: tuple[Prior, ...],
    data: Data,
    base_z: Array,
    free_slots: Array,
) -> Array:
    """`log_probability` of every walker (rows of `theta`), the priors as `split_priors` gives
    them."""
    priors = tuple(zip(prior_slots, prior_dists, strict=True))
    one = functools.partial(log_probability, static=static, priors=priors, data=data,
                            base_z=base_z, free_slots=free_slots)  # fmt: skip
    return jax.vmap(one)(theta)


_batched_log_probability = jax.jit(batched_log_probability, static_argnums=(1, 2))
"""All walkers at once; compiled once per scene shape, variant, free slots and their priors'
kinds (the priors' numbers are data: a new scene's floor prior needs no program of its own)."""

DIAGNOSE_GROWTH = 1.5
"""After a failed R-hat / ESS check the next one waits until the chain is this many times
longer (the check costs about a second on a long chain; R-hat - 1 falls about as 1 / length)."""

TAU_RELIABLE = 50.0
"""emcee's `get_autocorr_time` trusts its estimate only on chains longer than 50 tau (it raises
otherwise; the stopping rule uses `integrated_time(tol=0)`, which does not)."""


def _block_physical(block: Array, base_z: Array, slots: Array, static: Static, data: Data) -> Array:
    """Physical values of the free slots for one block of unconstrained samples `(B, p)`: the
    samples scattered into the full parameter vector, transformed, and the free slots read back
    (all inside one compiled program: eagerly, every scatter would be a dispatch of its own)."""
    full = jnp.broadcast_to(base_z, (block.shape[0], base_z.shape[0])).at[:, slots].set(block)
    return jax.vmap(physical, in_axes=(0, None, None))(full, static, data)[:, slots]


_batched_physical = jax.jit(_block_physical, static_argnums=(3,))


LAPLACE_DF = 5.0
"""Degrees of freedom of the Student-t proposal of the "laplace" moves: heavier tails than the
Laplace approximation's Gaussian, so that a posterior a little wider than it still mixes (an
independence sampler whose proposal is lighter-tailed than the target sticks in the tails)."""

LAPLACE_SCALE = 1.15
"""The proposal's scale over the least-squares covariance. On the test suite's small problem
(4 parameters, delta_n and scale correlated -0.98) scales 1.0 / 1.15 / 1.3 with 5 degrees of
freedom accepted 78% / 70% / 57% of the proposals, tau 1.6 / 1.9 / 2.3 steps; 1.15 leaves room
for a posterior somewhat wider than the least-squares estimate (docs/fitting.md §5)."""

LAPLACE_WEIGHT = 0.8
"""Share of the "laplace" moves' steps that are independence proposals; the rest are emcee's
differential-evolution moves, which explore where the Laplace approximation is poor."""


class LaplaceMove(emcee.moves.MHMove):
    """Independence Metropolis-Hastings proposals from the Laplace approximation of the
    posterior: every walker proposes a draw `x' = mean + L g sqrt(df / c)` (`g` standard normal,
    `c` chi^2 with `df` degrees of freedom, `L L^T = scale^2 cov`), a multivariate Student-t
    that does not depend on the walker's position, accepted with the Metropolis-Hastings factor
    `log q(x) - log q(x')` (emcee's `MHMove` convention). Exact for any proposal (detailed
    balance holds whatever `mean` and `cov` are); efficient when the posterior is close to the
    least-squares Gaussian, as for most stairfit fits: tau about 1.5-2.5 steps against 13-17
    for the differential-evolution moves. Each walker is its own Markov chain, so split R-hat
    across walkers keeps its meaning. `random` is emcee's seeded RandomState (reproducible).

    `mirror`: coordinates whose sign the posterior does not see (the model-error fraction,
    `x = |z|`: its posterior in `z` has two mirror-image modes). Each draw's sign there is
    flipped with probability 1/2, so the proposal is the even mixture of the Student-t and its
    mirror images and visits both modes (without it a walker in the far mode never leaves it).
    """

    def __init__(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        df: float = LAPLACE_DF,
        scale: float = LAPLACE_SCALE,
        mirror: tuple[int, ...] = (),
    ) -> None:
        self.mean = np.asarray(mean, dtype=float)
        self.chol = scale * _cholesky(np.asarray(cov, dtype=float))
        self.df = float(df)
        self.mirror = tuple(int(k) for k in mirror)
        super().__init__(self._propose)

    def _log_t(self, x: np.ndarray) -> np.ndarray:
        d = np.linalg.solve(self.chol, (x - self.mean).T)
        m = np.sum(d * d, axis=0)
        return -0.5 * (self.df + x.shape[1]) * np.log1p(m / self.df)

    def log_q(self, x: np.ndarray) -> np.ndarray:
        """Log proposal density of the rows of `x`, up to a constant (the mean of the
        Student-t over every sign pattern of the `mirror` coordinates)."""
        terms = []
        for signs in itertools.product((1.0, -1.0), repeat=len(self.mirror)):
            y = x.copy()
            y[:, list(self.mirror)] *= signs
            terms.append(self._log_t(y))
        return np.logaddexp.reduce(np.stack(terms), axis=0)

    def draw(self, n: int, random: np.random.RandomState) -> np.ndarray:
        """`n` draws from the proposal."""
        g = random.standard_normal((n, self.mean.size))
        c = random.chisquare(self.df, size=n)
        x = self.mean + (g @ self.chol.T) * np.sqrt(self.df / c)[:, None]
        for k in self.mirror:
            x[:, k] *= np.where(random.random_sample(n) < 0.5, -1.0, 1.0)
        return x

    def _propose(
        self, coords: np.ndarray, random: np.random.RandomState
    ) -> tuple[np.ndarray, np.ndarray]:
        new = self.draw(coords.shape[0], random)
        return new, self.log_q(coords) - self.log_q(new)


def _cholesky(cov: np.ndarray) -> np.ndarray:
    """Cholesky factor of a covariance; a matrix that is not positive definite (a parameter the
    data barely constrain) gets its eigenvalues clipped to 1e-12 of the largest first."""
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(0.5 * (cov + cov.T))
        w = np.clip(w, 1e-12 * max(float(np.max(w)), 1e-300), None)
        return np.linalg.cholesky((v * w) @ v.T)


MOVES = {
    "laplace": "independence Metropolis-Hastings proposals from a Student-t (5 degrees of "
    "freedom) around the least-squares optimum with 1.15^2 x its covariance (stairfit "
    "LaplaceMove on emcee's MHMove, 80%) mixed with differential evolution (emcee DEMove, 20%)",
    "de": "differential evolution (emcee DEMove, 80%) mixed with its snooker variant "
    "(DESnookerMove, 20%)",
    "stretch": "the affine-invariant stretch move (emcee's default StretchMove)",
}
"""The proposal moves `PosteriorOptions.moves` can name. "laplace" is the default: on the demo
scene (2 MP x 9 views, sharp+floor) the same R-hat / ESS thresholds pass after a few hundred
steps instead of about 1800 ("de", tau 13-17 steps) or 6800 ("stretch", tau 50), with the same
medians and intervals (docs/fitting.md §5). "de" and "stretch" need nothing but the ensemble
(affine invariant); "laplace" also uses the least-squares covariance."""


def _moves(name: str, t: Target) -> list[tuple[emcee.moves.Move, float]] | None:
    """emcee's `moves` argument for `PosteriorOptions.moves` (None: emcee's default)."""
    if name == "stretch":
        return None
    if name == "laplace":
        w = LAPLACE_WEIGHT
        return [(laplace_move(t), w), (emcee.moves.DEMove(), 1.0 - w)]
    return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]


def laplace_move(t: Target) -> LaplaceMove:
    """The `LaplaceMove` of a posterior target: centred at the least-squares optimum of the free
    slots, with its covariance in the unconstrained coordinates (`Target.cov_z`)."""
    kinds = t.static.layout.kinds
    mirror = tuple(i for i, k in enumerate(t.slots) if kinds[k] == ABS)
    return LaplaceMove(t.base_z[t.slots], t.cov_z, mirror=mirror)


class PosteriorOptions(NamedTuple):
    """How `sample_posterior` samples (every field is also a keyword of `sample_posterior`).

    `n_walkers` (default `max(32, 4 x n_params)`, even); `seed` (the walker ball and emcee's
    generator both derive from it); the sampler runs in chunks of `chunk_steps` until the chain
    is longer than `tau_factor` integrated autocorrelation times, tau changed by less than
    `tau_rtol` since the previous chunk, and every parameter's split R-hat is below `rhat_max`
    and its bulk and tail ESS at least `ess_min` (after burn-in; checked once the tau rule
    holds, then whenever the chain has grown by `DIAGNOSE_GROWTH`), or `max_steps` is reached;
    burn-in `burn_tau x tau_max` steps, thinning `thin_frac x tau_min`; walkers start in a ball
    of `ball_scale` least-squares standard errors around the optimum ("de", "stretch") or as
    draws from the Laplace proposal ("laplace"). `rhat_max = inf` and `ess_min = 0` stop on the
    tau rule alone (the warnings keep the field's thresholds). `moves`: the proposal, a key of
    `MOVES` ("laplace", the default, "de" or "stretch").
    """

    n_walkers: int | None = None
    seed: int = 0
    chunk_steps: int = 500
    max_steps: int = 20_000
    tau_factor: float = 50.0
    tau_rtol: float = 0.1
    burn_tau: float = 3.0
    thin_frac: float = 0.5
    ball_scale: float = 1e-2
    rhat_max: float = RHAT_MAX
    ess_min: float = ESS_MIN
    moves: str = "laplace"

    def updated(self, **overrides: Any) -> PosteriorOptions:
        """A copy with `overrides` (field names; a `TypeError` for an unknown one)."""
        return with_overrides(self, "posterior", overrides)


@dataclass(frozen=True)
class PosteriorResult:
    """The outcome of `sample_posterior` (immutable; `report()` prints it).

    Attributes:
        names: display labels of the free parameters, in the order of every array below.
        parameters: their records (`fitting.Parameter`: `param`, `wedge`, unit, prior, ...).
        seed: the seed given (walker ball and emcee's generator both derive from it).
        n_walkers, n_steps: walkers and steps per walker in the whole chain (resumes included).
        tau: integrated autocorrelation time per parameter (steps), `emcee.autocorr`,
            computed with `tol=0` on the whole chain; `tau_max` its maximum.
        converged: True when `n_steps > tau_factor * tau_max`, tau changed by less than
            `tau_rtol` since the previous chunk, and R-hat and ESS passed `rhat_max` and
            `ess_min` (`PosteriorOptions`); False means the step limit was hit.
        burn_in: steps discarded (`ceil(burn_tau * tau_max)`); thin: `max(1, floor(thin_frac *
            min(tau)))`.
        n_samples: kept samples (walkers x thinned steps); n_independent: `n_walkers x
            (n_steps - burn_in) / tau_max`.
        acceptance_fraction: mean over walkers; acceptance_per_walker: per walker.
        samples: `(n_samples, n_params)` physical values after burn-in and thinning.
        chain: the whole chain in physical values `(n_steps, n_walkers, n_params)`, before
            burn-in and thinning; log_prob: its log posterior `(n_steps, n_walkers)` (what
            diagnostics such as split R-hat or an ArviZ `InferenceData` are built from).
        median, p16, p84, p2_5, p97_5: percentiles per parameter (physical units).
        ls_value, ls_stderr: the least-squares estimate and standard error per parameter.
        width_ratio: `((p84 - p16) / 2) / ls_stderr`: posterior width over LS standard error.
        rhat, ess_bulk, ess_tail: rank-normalised split R-hat and the bulk / tail effective
            sample sizes per parameter after burn-in (ArviZ, walkers as chains; `_diagnostics`);
            a parameter with R-hat >= 1.01 or an ESS below 400 has a warning.
        tau_reliable: the chain is at least `TAU_RELIABLE` x tau_max long, where emcee
            considers its autocorrelation estimate reliable (shorter chains stop on the
            `tau_factor` rule with a rougher tau; R-hat and ESS are the convergence checks).
        chain_path: the chain file (None if not saved).
        warnings: structured warnings (also emitted).
        elapsed_s: wall time of this call; sampling_s: time spent in emcee.
    """

    names: tuple[str, ...]
    parameters: tuple[Parameter, ...]
    seed: int
    n_walkers: int
    n_steps: int
    tau: np.ndarray
    tau_max: float
    converged: bool
    burn_in: int
    thin: int
    n_samples: int
    n_independent: float
    acceptance_fraction: float
    acceptance_per_walker: np.ndarray = field(repr=False)
    samples: np.ndarray = field(repr=False)
    chain: np.ndarray = field(repr=False)
    log_prob: np.ndarray = field(repr=False)
    median: np.ndarray = field(repr=False)
    p16: np.ndarray = field(repr=False)
    p84: np.ndarray = field(repr=False)
    p2_5: np.ndarray = field(repr=False)
    p97_5: np.ndarray = field(repr=False)
    ls_value: np.ndarray = field(repr=False)
    ls_stderr: np.ndarray = field(repr=False)
    width_ratio: np.ndarray = field(repr=False)
    rhat: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    ess_bulk: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    ess_tail: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    tau_reliable: bool = False
    chain_path: Path | None = None
    warnings: tuple[FitWarning, ...] = ()
    elapsed_s: float = 0.0
    sampling_s: float = 0.0
    moves: str = "laplace"

    def inference_data(self, degrees: bool = False) -> Any:
        """The chain as an `arviz.InferenceData`: `posterior` after burn-in and
        `warmup_posterior` (each variable `(chain = walker, draw = step)`, physical units in
        its `units` attribute, named by `_diagnostics.variable_names`: `sigma_rad`,
        `sigma_rad_w2`, `delta_n`, ...), `sample_stats.lp` (log posterior); `degrees=True`
        writes widths in degrees as `sigma_deg` (the CLI's files [conventions §1])."""
        names = variable_names(self.parameters, degrees)
        factors, units = display_factors(self.parameters, degrees)
        attrs = {
            "labels": list(self.names),
            "seed": int(self.seed),
            "burn_in": int(self.burn_in),
            "sampler": f"emcee EnsembleSampler ({MOVES[self.moves]}); ArviZ chains are emcee "
            "walkers",
            "source": "stairfit.fitting.posterior.sample_posterior",
        }
        chain = self.chain * factors
        return inference_data(chain, self.log_prob, self.burn_in, names, units, attrs)

    def to_netcdf(self, path: str | Path, degrees: bool = False) -> Path:
        """Write `inference_data(degrees)` to `path` (e.g. `chain.nc`; netCDF-4 through
        h5netcdf, written atomically) for `arviz.from_netcdf`; returns the path.
        docs/fitting.md §5 ("Diagnostics")."""
        return write_netcdf(self.inference_data(degrees), path)

    def index(self, param: str, wedge: int | None = None) -> int:
        """Position of the parameter `(param, wedge)` in every array of this result."""
        for i, p in enumerate(self.parameters):
            if (p.param, p.wedge) == (param, wedge):
                return i
        raise KeyError(f"({param!r}, {wedge!r}) is not a parameter of this posterior")

    def report(self) -> str:
        """Plain-text summary: chain diagnostics and the percentile table."""
        lines = [
            f"posterior (emcee, {self.moves} moves, {self.n_walkers} walkers x {self.n_steps} "
            f"steps, seed {self.seed}): {'converged' if self.converged else 'NOT CONVERGED'}; "
            "tau_max = "
            f"{self.tau_max:.3g} steps, burn-in {self.burn_in}, thin {self.thin}, "
            f"{self.n_independent:.0f} independent samples, acceptance "
            f"{self.acceptance_fraction:.2f}",
            f"  {'parameter':<28} {'median':>12} {'16%':>12} {'84%':>12} {'2.5%':>12} "
            f"{'97.5%':>12} {'width/LS':>9} {'R-hat':>7} {'ESS b/t':>11}",
        ]
        for i, n in enumerate(self.names):
            lines.append(
                f"  {n:<28} {self.median[i]:>12.6g} {self.p16[i]:>12.6g} {self.p84[i]:>12.6g} "
                f"{self.p2_5[i]:>12.6g} {self.p97_5[i]:>12.6g} {self.width_ratio[i]:>9.3g} "
                f"{self.rhat[i]:>7.4f} {self.ess_bulk[i]:>5.0f}/{self.ess_tail[i]:<5.0f}"
            )
        if self.chain_path is not None:
            lines.append(f"  chain: {self.chain_path}")
        for w in self.warnings:
            lines.append(f"  warning ({w.code}): {w.message}")
        return "\n".join(lines)


# --- the problem emcee samples ------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _program_key(static: Static, prior_slots: tuple[int, ...]) -> str:
    """The exported log posterior's static key (`_export.call`; the priors' kinds are in the
    arguments' tree structure), made once per configuration rather than at each of the
    sampler's hundreds of calls."""
    return repr((static, prior_slots))


class Target(NamedTuple):
    """What the posterior of one fit is evaluated on: the compiled configuration, the arrays,
    the least-squares optimum `base_z` (every slot, sine slots on their principal branch), the
    free slots and their priors, the fingerprint of it all (for resuming), and the least-squares
    covariance of the free slots at `base_z` (`cov_z`, the "laplace" moves' proposal)."""

    fit: FitResult
    static: Static
    data: Data
    priors: PriorSpec
    base_z: np.ndarray
    slots: np.ndarray
    fingerprint: str
    cov_z: np.ndarray
    batch: int = 0
    """Calls with fewer walkers are padded to this many (the ensemble): emcee's differential-
    evolution moves evaluate half the ensemble, the Laplace move all of it, the start's redraws
    any number; one compiled program serves them all (each batch size compiled its own)."""

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """Log posterior of walkers `theta` `(n_walkers, p)`, a writable numpy array."""
        n = theta.shape[0]
        if n < self.batch:  # pad with copies of the first walker; their values are dropped
            theta = np.concatenate([theta, np.repeat(theta[:1], self.batch - n, axis=0)])
        # NumPy arrays go to the compiled program as they are (its C++ dispatch transfers
        # them): `jnp.asarray` of the three was a large part of each call, and the sampler
        # makes thousands of calls (same values either way; same program keys;
        # benchmarks/bench_posterior_calls.py)
        prior_slots, dists = split_priors(self.priors)
        out = _export.call(
            "log_probability",
            lambda th, p, d, z, s: _batched_log_probability(th, self.static, prior_slots, p, d,
                                                            z, s),
            _program_key(self.static, prior_slots),
            (theta, dists, self.data, self.base_z, self.slots),
            lambda leaves: leaves[0],
        )  # fmt: skip
        return np.array(out)[:n]  # a writable copy: walkers outside the support are re-drawn

    def physical(self, kept_z: np.ndarray) -> np.ndarray:
        """Physical values of the free slots for unconstrained samples `(n, p)`."""
        return _to_physical_samples(kept_z, self.static, self.data, self.base_z, self.slots)

    def chain_info(self, seed: int) -> ChainInfo:
        """The description a new chain file of this fit records."""
        params = self.fit.parameters
        return ChainInfo(
            names=self.fit.names,
            parameters=tuple(p.param for p in params),
            wedges=tuple(-1 if p.wedge is None else p.wedge for p in params),
            seed=int(seed),
            free_slots=self.slots,
            ls_z=np.asarray(self.fit.z),
            fingerprint=self.fingerprint,
            variant=self.fit.variant.name,
        )


def _fingerprint(fit: FitResult, data: Data) -> str:
    """Hash of everything the log probability depends on (to refuse resuming a different fit)."""
    h = hashlib.sha256()
    for name in ("theta_i", "theta_o", "beta2", "layer_um", "value", "stderr", "use", "r_n",
                 "r_w", "free", "x_fixed", "sigma_source"):  # fmt: skip
        h.update(np.ascontiguousarray(np.asarray(getattr(data, name))).tobytes())
    # without the shape buckets' padding (`_problem.bucket`): a chain written before the
    # padding still resumes (padded groups are empty and last; padded keys come after the
    # real ones, which every row's `r_key` names)
    if fit.problem.correlated:  # independent rows keep the fingerprint they always had
        real = np.asarray(data.grp_mask).sum(axis=1) > 0
        for name in ("grp_rows", "grp_mask", "grp_corr"):
            h.update(np.ascontiguousarray(np.asarray(getattr(data, name))[real]).tobytes())
    r_so = np.asarray(data.r_so)
    if r_so.shape[0] > 1:
        r_so = r_so[: int(np.max(np.asarray(data.r_key))) + 1]
    if not np.all(r_so == 1.0):  # whole-face spreads keep their fingerprint
        h.update(np.ascontiguousarray(r_so).tobytes())
    h.update(repr((fit.names, fit.problem.priors, fit.problem.aperture)).encode())
    return h.hexdigest()[:32]


def target(fit: FitResult) -> Target:
    """The posterior's target of a converged least-squares fit (`FitError` otherwise)."""
    if not fit.success or fit.covariance_z is None or fit.problem is None or fit.spec is None:
        raise FitError(
            "the posterior starts from a converged least-squares fit with a covariance; this "
            f"fit has none ({fit.message}); fix the least-squares fit first"
        )
    static, data = fit.problem.static_for(fit.spec), fit.problem.arrays_for(fit.spec)
    # The least-squares solver may end a sine slot (the edge radius) outside the principal
    # branch that the posterior's support is defined on; the same physical value inside it is
    # arcsin(sin z). Where that turns the slope dx/dz over (cos z changes sign), the covariance
    # of the slot changes the sign of its correlations.
    z = np.asarray(fit.z, dtype=float).copy()
    flip = np.ones(z.size)
    for k, kind in enumerate(static.layout.kinds):
        if kind in (SIN, SIN_REST):
            flip[k] = 1.0 if np.cos(z[k]) >= 0 else -1.0
            z[k] = float(np.arcsin(np.sin(z[k])))
    priors = tuple((p.slot, p.prior) for p in fit.parameters)
    slots = np.asarray(fit.free_slots, dtype=int)
    f = flip[slots]
    cov = np.asarray(fit.covariance_z, dtype=float) * np.outer(f, f)
    return Target(fit, static, data, priors, z, slots, _fingerprint(fit, data), cov)


# --- walkers, seeds, resuming -------------------------------------------------------------------


def _seeds(seed: int) -> tuple[np.random.Generator, np.random.RandomState]:
    """The walker-ball generator and emcee's RandomState, both derived from one seed."""
    ball_ss, emcee_ss = np.random.SeedSequence(seed).spawn(2)
    rs = np.random.RandomState(int(emcee_ss.generate_state(1, dtype=np.uint32)[0]))
    return np.random.default_rng(ball_ss), rs


def _walker_count(requested: int | None, p: int) -> int:
    walkers = requested or max(32, 4 * p)
    walkers += walkers % 2
    if walkers < 2 * p:
        raise FitInputError(f"n_walkers = {walkers}; emcee needs at least 2 x {p} walkers")
    return walkers


def _initial_state(t: Target, walkers: int, opts: PosteriorOptions) -> emcee.State:
    """Walkers in a ball of `ball_scale` least-squares standard errors around the optimum, or,
    for the "laplace" moves, draws from their proposal (the chain then starts close to its
    stationary distribution); points outside the prior's support are redrawn. emcee's random
    state is seeded."""
    ball_rng, rs = _seeds(opts.seed)
    p = t.slots.size
    se = np.sqrt(np.diag(t.cov_z))
    centre = t.base_z[t.slots]
    if opts.moves == "laplace":
        q = laplace_move(t)
        rand = np.random.RandomState(int(ball_rng.integers(2**32)))

        def draw(n: int) -> np.ndarray:
            return q.draw(n, rand)
    else:

        def draw(n: int) -> np.ndarray:
            return centre + opts.ball_scale * se * ball_rng.standard_normal((n, p))

    start = draw(walkers)
    lp0 = t.log_prob(start)
    for _ in range(100):
        bad = ~np.isfinite(lp0)
        if not np.any(bad):
            return emcee.State(start, log_prob=lp0, random_state=rs.get_state())
        start[bad] = draw(int(bad.sum()))
        lp0[bad] = t.log_prob(start[bad])
    raise FitError(
        "could not place the walkers inside the prior's support around the least-squares "
        "optimum; check the priors against the fitted values"
    )


def _resumed(t: Target, path: Path | None) -> ChainBackend:
    """The backend of the chain file to continue (`FitInputError` if missing or foreign)."""
    if path is None:
        raise FitInputError("resume=True needs chain_path (the file to continue)")
    backend = ChainBackend.load(path)
    if backend.info.fingerprint != t.fingerprint:
        raise FitInputError(
            f"chain file {path} belongs to a different fit (data, variant or priors differ); "
            "give another chain_path or resume=False"
        )
    return backend


class _Guarded:
    """The log posterior as emcee calls it, holding back any exception raised inside it.

    emcee wraps the likelihood in a bare `except:` that prints the walkers' parameters and a
    traceback to stdout before re-raising, also for Ctrl-C and a SIGTERM turned into an
    exception. Here an exception (of any kind) is kept and every walker gets -inf, which
    emcee rejects quietly; `reraise` raises it once emcee has returned.
    """

    def __init__(self, log_prob: Callable[[np.ndarray], np.ndarray]) -> None:
        self._log_prob = log_prob
        self.error: BaseException | None = None

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        if self.error is None:
            try:
                return self._log_prob(theta)
            except BaseException as e:  # raised again by `reraise`
                self.error = e
        return np.full(theta.shape[0], -np.inf)

    def reraise(self) -> None:
        """Raise the exception held back, if any."""
        if self.error is not None:
            error, self.error = self.error, None
            raise error


def _sampler(
    t: Target, opts: PosteriorOptions, path: Path | None, resume: bool
) -> tuple[emcee.EnsembleSampler, emcee.State | None, int]:
    """(sampler, initial state or None when resuming, the seed the chain belongs to); the
    sampler's log posterior is `_Guarded` (`sampler.log_prob_fn.f`)."""
    p = t.slots.size
    if resume:
        backend = _resumed(t, path)
        t = t._replace(batch=backend.nwalkers)
        sampler = emcee.EnsembleSampler(backend.nwalkers, p, _Guarded(t.log_prob),
                                        vectorize=True, backend=backend,
                                        moves=_moves(opts.moves, t))  # fmt: skip
        return sampler, None, backend.info.seed
    walkers = _walker_count(opts.n_walkers, p)
    t = t._replace(batch=walkers)
    state = _initial_state(t, walkers, opts)
    backend = ChainBackend(t.chain_info(opts.seed), path)
    sampler = emcee.EnsembleSampler(
        walkers, p, _Guarded(t.log_prob), vectorize=True, backend=backend,
        moves=_moves(opts.moves, t),
    )  # fmt: skip
    sampler.random_state = state.random_state
    if not np.array_equal(sampler.random_state[1], state.random_state[1]):
        raise FitError("emcee did not accept the random state; cannot guarantee reproducibility")
    return sampler, state, opts.seed


# --- sampling -----------------------------------------------------------------------------------


class _Run(NamedTuple):
    """The chain's autocorrelation times, whether it converged, the time spent in emcee, and
    the last R-hat / ESS check (`diagnostics` of the chain `diagnosed` steps long, or None)."""

    tau: np.ndarray
    converged: bool
    sampling_s: float
    diagnostics: Diagnostics | None = None
    diagnosed: int = 0
    chain: np.ndarray | None = None
    """The whole chain in physical values, converted chunk by chunk (None: no chunk ran)."""


def _burn_in(tau: np.ndarray, n_steps: int, opts: PosteriorOptions) -> int:
    """`ceil(burn_tau x tau_max)`, leaving at least one step."""
    return min(math.ceil(opts.burn_tau * float(np.max(tau))), n_steps - 1)


def _diagnostics_pass(d: Diagnostics, opts: PosteriorOptions) -> bool:
    """Every parameter has R-hat below `rhat_max` and bulk and tail ESS of at least `ess_min`."""
    ess = np.minimum(d.ess_bulk, d.ess_tail)
    return bool(np.all(d.rhat < opts.rhat_max) and np.all(ess >= opts.ess_min))


def _run_chunks(
    sampler: emcee.EnsembleSampler,
    state: emcee.State | None,
    t: Target,
    opts: PosteriorOptions,
    progress: bool,
) -> _Run:
    """Run in chunks of `chunk_steps` (the first from `state`, every later one, and every one of
    a resumed chain, from where emcee stopped: `run_mcmc(None, n)`), saving the chain after
    each, until it is converged (`PosteriorOptions`) or `max_steps` long.

    Each chunk's new steps alone are converted to physical values (the whole chain each time
    made the conversion quadratic in the chain's length). Tau is estimated after every chunk
    until the first R-hat / ESS check; after a failed check only once the chain has reached the
    next check's length (`DIAGNOSE_GROWTH`), where "settled" compares it with the estimate of
    the previous chunk at which it was computed."""
    from tqdm import tqdm

    backend: ChainBackend = sampler.backend
    # one bar for the whole chain (emcee's own draws a new bar for every chunk)
    bar = tqdm(desc="posterior", unit="step", disable=not progress, initial=backend.iteration)
    with bar:  # closed also when interrupted, so that the next message starts a line
        return _chunks(sampler, state, t, opts, bar)


def _chunks(
    sampler: emcee.EnsembleSampler,
    state: emcee.State | None,
    t: Target,
    opts: PosteriorOptions,
    bar: Any,
) -> _Run:
    """`_run_chunks`'s loop, advancing `bar`."""
    backend: ChainBackend = sampler.backend
    guarded: _Guarded = sampler.log_prob_fn.f
    tau = np.full(t.slots.size, np.inf)
    spent, check_at, last = 0.0, 0, _Run(tau, False, 0.0)
    done = backend.get_chain() if backend.iteration else None
    chain = None if done is None else _physical_chain(t, done)
    while (n_run := min(opts.chunk_steps, opts.max_steps - backend.iteration)) > 0:
        t0 = time.perf_counter()
        try:
            sampler.run_mcmc(state, n_run, progress=False)
        finally:
            guarded.reraise()  # Ctrl-C or a SIGTERM inside the likelihood, raised here
        spent += time.perf_counter() - t0
        bar.update(n_run)
        state = None
        chain_z = backend.get_chain()
        new = _physical_chain(t, chain_z[0 if chain is None else chain.shape[0] :])
        chain = new if chain is None else np.concatenate([chain, new])
        n, check = chain_z.shape[0], False
        if n >= check_at:
            tau_new = emcee.autocorr.integrated_time(chain_z, tol=0)
            settled = bool(np.all(np.abs(tau_new - tau) < opts.tau_rtol * tau_new))
            tau = tau_new
            check = n > opts.tau_factor * np.max(tau) and settled
        if backend.path is not None:
            backend.save(chain, tau)
        last = last._replace(tau=tau, sampling_s=spent, chain=chain)
        bar.set_postfix_str(f"tau {np.max(tau):.3g}", refresh=False)
        if check:
            d = chain_diagnostics(chain, _burn_in(tau, n, opts))
            last = last._replace(diagnostics=d, diagnosed=n)
            bar.set_postfix_str(f"tau {np.max(tau):.3g}, R-hat {np.max(d.rhat):.4f}")
            if _diagnostics_pass(d, opts):
                return last._replace(converged=True)
            check_at = math.ceil(DIAGNOSE_GROWTH * n)
    return last


def _physical_chain(t: Target, chain_z: np.ndarray) -> np.ndarray:
    """The chain `(n_steps, n_walkers, p)` in physical values."""
    n, w, p = chain_z.shape
    return t.physical(chain_z.reshape(-1, p)).reshape(n, w, p)


def _diagnostic_warnings(
    run: _Run, n_steps: int, acceptance: float, opts: PosteriorOptions
) -> tuple[FitWarning, ...]:
    """`chain_too_short` (the step limit was hit) and `low_acceptance` (outside 0.15-0.75)."""
    out = []
    if not run.converged:
        limit = opts.tau_factor * float(np.max(run.tau))
        out.append(
            FitWarning(
                "chain_too_short",
                None,
                f"the chain reached max_steps = {opts.max_steps} with {n_steps} steps, which is "
                f"not longer than {opts.tau_factor:g} x tau_max = {limit:.0f} (or tau has "
                "not settled, or R-hat / ESS have not passed); the percentiles are less "
                "reliable — raise max_steps or resume",
            )
        )
    if not 0.15 <= acceptance <= 0.75:
        out.append(
            FitWarning(
                "low_acceptance",
                None,
                f"mean acceptance fraction {acceptance:.2f} is outside [0.15, 0.75]; the "
                "sampler may be mixing poorly",
            )
        )
    return tuple(out)


def _summary(
    t: Target, backend: ChainBackend, run: _Run, seed: int, opts: PosteriorOptions, t0: float
) -> PosteriorResult:
    """Burn-in, thinning, percentiles and diagnostics of the finished chain (`t0`: when the
    call started)."""
    chain_z = backend.get_chain()
    n_steps, walkers, p = chain_z.shape
    tau_max = float(np.max(run.tau))
    acc = backend.accepted / n_steps
    burn = _burn_in(run.tau, n_steps, opts)
    thin = max(1, int(opts.thin_frac * float(np.min(run.tau))))
    have = run.chain is not None and run.chain.shape[0] == n_steps
    chain = run.chain if have else _physical_chain(t, chain_z)
    samples = chain[burn::thin].reshape(-1, p)
    q = np.percentile(samples, [2.5, 16, 50, 84, 97.5], axis=0)
    ls_se = np.asarray(t.fit.stderrs)
    same = run.diagnostics is not None and run.diagnosed == n_steps
    diag = run.diagnostics if same else chain_diagnostics(chain, burn)
    checks = diagnostic_warnings(diag, t.fit.names)
    return PosteriorResult(
        names=t.fit.names,
        parameters=t.fit.parameters,
        seed=int(seed),
        n_walkers=walkers,
        n_steps=n_steps,
        tau=run.tau,
        tau_max=tau_max,
        converged=run.converged,
        burn_in=burn,
        thin=thin,
        n_samples=int(samples.shape[0]),
        n_independent=float(walkers * (n_steps - burn) / tau_max),
        acceptance_fraction=float(np.mean(acc)),
        acceptance_per_walker=acc,
        samples=samples,
        chain=chain,
        log_prob=backend.get_log_prob(),
        median=q[2],
        p16=q[1],
        p84=q[3],
        p2_5=q[0],
        p97_5=q[4],
        ls_value=t.fit.values,
        ls_stderr=ls_se,
        width_ratio=0.5 * (q[3] - q[1]) / ls_se,
        rhat=diag.rhat,
        ess_bulk=diag.ess_bulk,
        ess_tail=diag.ess_tail,
        tau_reliable=bool(n_steps >= TAU_RELIABLE * tau_max),
        chain_path=backend.path,
        warnings=_diagnostic_warnings(run, n_steps, float(np.mean(acc)), opts) + checks,
        elapsed_s=time.perf_counter() - t0,
        sampling_s=run.sampling_s,
        moves=opts.moves,
    )


def sample_posterior(
    fit: FitResult,
    options: PosteriorOptions | None = None,
    *,
    chain_path: str | Path | None = None,
    resume: bool = False,
    progress: bool = False,
    emit_warnings: bool = True,
    **option_overrides: Any,
) -> PosteriorResult:
    """Sample the posterior of the free parameters of a least-squares fit with emcee.

    `options` (`PosteriorOptions`; any field may also be given as a keyword, e.g. `seed=3`,
    `max_steps=2000`) set the walkers, the seed, the chunked stopping rule, burn-in and
    thinning. Walkers start in a ball around the optimum in the unconstrained coordinates; the
    sampler runs in chunks until the chain is longer than `tau_factor` autocorrelation times and
    tau has settled, or `max_steps` is reached (then a warning). With `chain_path` the chain
    is saved after every chunk; `resume=True` continues the chain in that file from its last
    walker positions and random state (the file must belong to the same fit; the seed recorded
    there is kept).
    """
    t_start = time.perf_counter()
    opts = (options or PosteriorOptions()).updated(**option_overrides)
    t = target(fit)
    if opts.chunk_steps < 1 or opts.max_steps < opts.chunk_steps:
        raise FitInputError("need chunk_steps >= 1 and max_steps >= chunk_steps")
    if opts.moves not in MOVES:
        raise FitInputError(f"moves = {opts.moves!r}: use one of {', '.join(map(repr, MOVES))}")
    path = None if chain_path is None else Path(chain_path)
    sampler, state, seed = _sampler(t, opts, path, resume)
    run = _run_chunks(sampler, state, t, opts, progress)
    result = _summary(t, sampler.backend, run, seed, opts, t_start)
    if emit_warnings:
        emit(result.warnings)
    return result


PHYSICAL_BLOCK = 2048
"""Samples are converted to physical values in blocks of this many rows (the last one padded),
so that one compiled program serves chains of every length (a chain file is written after every
chunk; converting the growing chain in one call recompiled for every new length)."""


def _to_physical_samples(
    kept_z: np.ndarray, static: Static, data: Data, base_z: np.ndarray, slots: np.ndarray
) -> np.ndarray:
    """Physical values of the free slots for unconstrained samples `(n, p)`."""
    n = kept_z.shape[0]
    if n == 0:
        return np.zeros((0, slots.size))
    n_pad = -n % PHYSICAL_BLOCK
    padded = np.concatenate([kept_z, np.repeat(kept_z[-1:], n_pad, axis=0)], axis=0)
    out = []
    base, free = jnp.asarray(base_z), jnp.asarray(slots)
    for block in padded.reshape(-1, PHYSICAL_BLOCK, kept_z.shape[1]):
        out.append(np.asarray(_batched_physical(jnp.asarray(block), base, free, static, data)))
    return np.concatenate(out, axis=0)[:n]
