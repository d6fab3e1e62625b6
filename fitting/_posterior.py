"""Posterior sampling with emcee around a least-squares fit [conventions §9, §10].

`log_likelihood`, `log_prior` and `log_probability` are module-level functions of the free
unconstrained parameters; one `jax.jit(jax.vmap(log_probability))` evaluates all walkers at
once (`emcee.EnsembleSampler(..., vectorize=True)`). Priors are on the *physical* parameters:
`log_prior` adds `log |dx/dz|` of each transform. Seeds are explicit and recorded; the chain is
saved atomically to an `.npz` file after every chunk, and a run can be resumed from it.
"""

from __future__ import annotations

import hashlib
import math
import os
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._errors import FitError, FitInputError, FitWarning, emit
from ._forward import Data, Static, log_likelihood_z, physical
from ._least_squares import FitResult
from ._params import SIN, Prior, in_support, log_abs_jacobian, to_physical

CHAIN_FORMAT_VERSION = 1
"""Version of the chain file layout (docs/fitting.md, "Chain file")."""

PriorSpec = tuple[tuple[int, Prior], ...]
"""Hashable (slot, prior) pairs of the free slots: static configuration of the posterior."""


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
    x = to_physical(z, static.kinds, data.r_max_um)
    jac = log_abs_jacobian(z, static.kinds, data.r_max_um)
    total = jnp.asarray(0.0, dtype=z.dtype)
    for slot, prior in priors:
        total = total + prior.log_pdf(x[slot]) + jac[slot]
    return jnp.where(in_support(z, static.kinds), total, -jnp.inf)


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


_batched_log_probability = jax.jit(
    jax.vmap(log_probability, in_axes=(0, None, None, None, None, None)), static_argnums=(1, 2)
)
"""All walkers at once; compiled once per scene shape, variant and prior specification."""

_batched_physical = jax.jit(jax.vmap(physical, in_axes=(0, None, None)), static_argnums=(1,))


@dataclass(frozen=True)
class PosteriorResult:
    """The outcome of `sample_posterior` (immutable; `report()` prints it).

    Attributes:
        names: free parameters, in the order of every array below.
        seed: the seed given (walker ball and emcee's generator both derive from it).
        n_walkers, n_steps: walkers and steps per walker in the whole chain (resumes included).
        tau: integrated autocorrelation time per parameter (steps), `emcee.autocorr`,
            computed with `tol=0` on the whole chain; `tau_max` its maximum.
        converged: True when `n_steps > tau_factor * tau_max` and tau changed by less than
            `tau_rtol` since the previous chunk; False means the step limit was hit.
        burn_in: steps discarded (`ceil(burn_tau * tau_max)`); thin: `max(1, floor(thin_frac *
            min(tau)))`.
        n_samples: kept samples (walkers x thinned steps); n_independent: `n_walkers x
            (n_steps - burn_in) / tau_max`.
        acceptance_fraction: mean over walkers; acceptance_per_walker: per walker.
        samples: `(n_samples, n_params)` physical values after burn-in and thinning.
        median, p16, p84, p2_5, p97_5: percentiles per parameter (physical units).
        ls_value, ls_stderr: the least-squares estimate and standard error per parameter.
        width_ratio: `((p84 - p16) / 2) / ls_stderr`: posterior width over LS standard error.
        chain_path: the chain file (None if not saved).
        warnings: structured warnings (also emitted).
        elapsed_s: wall time of this call; sampling_s: time spent in emcee.
    """

    names: tuple[str, ...]
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
    median: np.ndarray = field(repr=False)
    p16: np.ndarray = field(repr=False)
    p84: np.ndarray = field(repr=False)
    p2_5: np.ndarray = field(repr=False)
    p97_5: np.ndarray = field(repr=False)
    ls_value: np.ndarray = field(repr=False)
    ls_stderr: np.ndarray = field(repr=False)
    width_ratio: np.ndarray = field(repr=False)
    chain_path: Path | None = None
    warnings: tuple[FitWarning, ...] = ()
    elapsed_s: float = 0.0
    sampling_s: float = 0.0

    def report(self) -> str:
        """Plain-text summary: chain diagnostics and the percentile table."""
        lines = [
            f"posterior (emcee, {self.n_walkers} walkers x {self.n_steps} steps, seed "
            f"{self.seed}): {'converged' if self.converged else 'NOT CONVERGED'}; tau_max = "
            f"{self.tau_max:.3g} steps, burn-in {self.burn_in}, thin {self.thin}, "
            f"{self.n_independent:.0f} independent samples, acceptance "
            f"{self.acceptance_fraction:.2f}",
            f"  {'parameter':<28} {'median':>12} {'16%':>12} {'84%':>12} {'2.5%':>12} "
            f"{'97.5%':>12} {'width/LS':>9}",
        ]
        for i, n in enumerate(self.names):
            lines.append(
                f"  {n:<28} {self.median[i]:>12.6g} {self.p16[i]:>12.6g} {self.p84[i]:>12.6g} "
                f"{self.p2_5[i]:>12.6g} {self.p97_5[i]:>12.6g} {self.width_ratio[i]:>9.3g}"
            )
        if self.chain_path is not None:
            lines.append(f"  chain: {self.chain_path}")
        for w in self.warnings:
            lines.append(f"  warning ({w.code}): {w.message}")
        return "\n".join(lines)


def _fingerprint(fit: FitResult, data: Data) -> str:
    """Hash of everything the log probability depends on (to refuse resuming a different fit)."""
    h = hashlib.sha256()
    for name in ("theta_i", "theta_o", "beta2", "layer_um", "value", "stderr", "use", "r_n",
                 "r_w", "free", "x_fixed", "sigma_source"):  # fmt: skip
        h.update(np.ascontiguousarray(np.asarray(getattr(data, name))).tobytes())
    h.update(repr((fit.names, fit.problem.priors, fit.problem.aperture)).encode())
    return h.hexdigest()[:32]


def _seeds(seed: int) -> tuple[np.random.Generator, np.random.RandomState]:
    """The walker-ball generator and emcee's RandomState, both derived from one seed."""
    ball_ss, emcee_ss = np.random.SeedSequence(seed).spawn(2)
    rs = np.random.RandomState(int(emcee_ss.generate_state(1, dtype=np.uint32)[0]))
    return np.random.default_rng(ball_ss), rs


def _save_chain(path: Path, payload: dict[str, np.ndarray]) -> None:
    """Write the chain atomically: a temporary file in the same folder, then `os.replace`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # not tempfile.mkstemp: its 0600 would stay on the chain file; 0666 less the umask instead
    tmp = str(path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp"))
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_chain(path: str | Path) -> dict[str, np.ndarray]:
    """Read a chain file written by `sample_posterior` (see docs/fitting.md for the fields)."""
    path = Path(path)
    if not path.is_file():
        raise FitInputError(f"chain file {path} does not exist; run sample_posterior first")
    with np.load(path, allow_pickle=False) as f:
        out = {k: f[k] for k in f.files}
    version = int(out.get("format_version", -1))
    if version != CHAIN_FORMAT_VERSION:
        raise FitInputError(
            f"chain file {path}: format_version {version} is not {CHAIN_FORMAT_VERSION}; "
            "start a new chain"
        )
    return out


def sample_posterior(
    fit: FitResult,
    *,
    n_walkers: int | None = None,
    seed: int = 0,
    chunk_steps: int = 500,
    max_steps: int = 20_000,
    tau_factor: float = 50.0,
    tau_rtol: float = 0.1,
    burn_tau: float = 3.0,
    thin_frac: float = 0.5,
    ball_scale: float = 1e-2,
    chain_path: str | Path | None = None,
    resume: bool = False,
    progress: bool = False,
    emit_warnings: bool = True,
) -> PosteriorResult:
    """Sample the posterior of the free parameters of a least-squares fit with emcee.

    Walkers (default `max(32, 4 x n_params)`, even) start in a ball of `ball_scale` least-squares
    standard errors around the optimum (in the unconstrained coordinates; points outside the
    prior's support are redrawn). The sampler runs in chunks of `chunk_steps` until the chain
    is longer than `tau_factor` integrated autocorrelation times and tau has settled (relative
    change < `tau_rtol`), or `max_steps` is reached (then a warning). Burn-in and thinning come
    from tau. With `chain_path` the chain is saved after every chunk; `resume=True` continues
    the chain in that file from its last walker positions and random state (the file must
    belong to the same fit; the seed recorded there is kept).
    """
    import emcee  # here, not at import: emcee imports scipy.stats (0.5-2 s; issue 14)

    t_start = time.perf_counter()
    if not fit.success or fit.covariance_z is None or fit.problem is None or fit.spec is None:
        raise FitError(
            "the posterior starts from a converged least-squares fit with a covariance; this "
            f"fit has none ({fit.message}); fix the least-squares fit first"
        )
    if chunk_steps < 1 or max_steps < chunk_steps:
        raise FitInputError("need chunk_steps >= 1 and max_steps >= chunk_steps")
    problem = fit.problem
    static = problem.static_for(fit.spec)
    data = problem.arrays_for(fit.spec)
    slots = np.asarray(fit.free_slots, dtype=int)
    p = slots.size
    lay = problem.layout
    priors: PriorSpec = tuple(
        (int(k), getattr(problem.priors, lay.param_of_slot(int(k)))) for k in slots
    )
    # The least-squares solver may end a sine slot (the edge radius) outside the principal
    # branch that the posterior's support is defined on; the same physical value inside it is
    # arcsin(sin z).
    z_fit = np.asarray(fit.z, dtype=float).copy()
    for k, kind in enumerate(static.kinds):
        if kind == SIN:
            z_fit[k] = float(np.arcsin(np.sin(z_fit[k])))
    base_z = jnp.asarray(z_fit)
    slots_j = jnp.asarray(slots)

    fingerprint = _fingerprint(fit, data)
    path = None if chain_path is None else Path(chain_path)
    walkers = n_walkers or max(32, 4 * p)
    walkers += walkers % 2
    if walkers < 2 * p:
        raise FitInputError(f"n_walkers = {walkers}; emcee needs at least 2 x {p} walkers")

    def log_prob_batch(theta: np.ndarray) -> np.ndarray:
        out = _batched_log_probability(jnp.asarray(theta), static, priors, data, base_z, slots_j)
        return np.array(out)  # a writable copy: walkers outside the support are re-drawn

    prev_z = np.zeros((0, walkers, p))
    prev_lp = np.zeros((0, walkers))
    prev_acc = np.zeros(walkers)
    if resume:
        if path is None:
            raise FitInputError("resume=True needs chain_path (the file to continue)")
        saved = load_chain(path)
        if str(saved["fingerprint"]) != fingerprint:
            raise FitInputError(
                f"chain file {path} belongs to a different fit (data, variant or priors "
                "differ); give another chain_path or resume=False"
            )
        prev_z, prev_lp = saved["chain_z"], saved["log_prob"]
        prev_acc = saved["n_accepted"].astype(float)
        walkers = prev_z.shape[1]
        seed = int(saved["seed"])
        rng_state = (
            "MT19937",
            saved["rng_keys"],
            int(saved["rng_pos"]),
            int(saved["rng_has_gauss"]),
            float(saved["rng_cached_gaussian"]),
        )
        state = emcee.State(prev_z[-1], log_prob=prev_lp[-1], random_state=rng_state)
    else:
        ball_rng, rs = _seeds(seed)
        se = np.sqrt(np.diag(fit.covariance_z))
        centre = z_fit[slots]
        start = centre + ball_scale * se * ball_rng.standard_normal((walkers, p))
        lp0 = log_prob_batch(start)
        for _ in range(100):
            bad = ~np.isfinite(lp0)
            if not np.any(bad):
                break
            start[bad] = centre + ball_scale * se * ball_rng.standard_normal((bad.sum(), p))
            lp0[bad] = log_prob_batch(start[bad])
        else:
            raise FitError(
                "could not place the walkers inside the prior's support around the "
                "least-squares optimum; check the priors against the fitted values"
            )
        state = emcee.State(start, log_prob=lp0, random_state=rs.get_state())

    sampler = emcee.EnsembleSampler(walkers, p, log_prob_batch, vectorize=True)
    sampler.random_state = state.random_state
    if not np.array_equal(sampler.random_state[1], state.random_state[1]):
        raise FitError("emcee did not accept the random state; cannot guarantee reproducibility")

    tau = np.full(p, np.inf)
    converged = False
    t_sample = 0.0
    records: list[FitWarning] = []
    while True:
        done = prev_z.shape[0] + sampler.iteration
        n_run = min(chunk_steps, max_steps - done)
        if n_run <= 0:
            break
        t0 = time.perf_counter()
        state = sampler.run_mcmc(state, n_run, progress=progress)
        t_sample += time.perf_counter() - t0
        chain_z = np.concatenate([prev_z, sampler.get_chain()], axis=0)
        tau_new = emcee.autocorr.integrated_time(chain_z, tol=0)
        settled = bool(np.all(np.abs(tau_new - tau) < tau_rtol * tau_new))
        tau = tau_new
        if path is not None:
            log_prob = np.concatenate([prev_lp, sampler.get_log_prob()], axis=0)
            accepted = prev_acc + sampler.backend.accepted
            _save_chain(path, _payload(fit, static, data, chain_z, log_prob, accepted, seed,
                                       sampler.random_state, fingerprint, tau))  # fmt: skip
        if chain_z.shape[0] > tau_factor * np.max(tau) and settled:
            converged = True
            break

    chain_z = np.concatenate([prev_z, sampler.get_chain()], axis=0)
    accepted = prev_acc + sampler.backend.accepted
    n_steps = chain_z.shape[0]
    tau_max = float(np.max(tau))
    if not converged:
        records.append(
            FitWarning(
                "chain_too_short",
                None,
                f"the chain reached max_steps = {max_steps} with {n_steps} steps, which is not "
                f"longer than {tau_factor:g} x tau_max = {tau_factor * tau_max:.0f} (or tau has "
                "not settled); the percentiles are less reliable — raise max_steps or resume",
            )
        )
    acc = accepted / n_steps
    if not 0.15 <= float(np.mean(acc)) <= 0.75:
        records.append(
            FitWarning(
                "low_acceptance",
                None,
                f"mean acceptance fraction {np.mean(acc):.2f} is outside [0.15, 0.75]; the "
                "sampler may be mixing poorly",
            )
        )
    burn = min(math.ceil(burn_tau * tau_max), n_steps - 1)
    thin = max(1, int(thin_frac * float(np.min(tau))))
    kept_z = chain_z[burn::thin].reshape(-1, p)
    samples = _to_physical_samples(kept_z, static, data, base_z, slots)
    q = np.percentile(samples, [2.5, 16, 50, 84, 97.5], axis=0)
    ls_se = np.asarray(fit.stderrs)
    result = PosteriorResult(
        names=fit.names,
        seed=int(seed),
        n_walkers=walkers,
        n_steps=n_steps,
        tau=tau,
        tau_max=tau_max,
        converged=converged,
        burn_in=burn,
        thin=thin,
        n_samples=int(samples.shape[0]),
        n_independent=float(walkers * (n_steps - burn) / tau_max),
        acceptance_fraction=float(np.mean(acc)),
        acceptance_per_walker=acc,
        samples=samples,
        median=q[2],
        p16=q[1],
        p84=q[3],
        p2_5=q[0],
        p97_5=q[4],
        ls_value=fit.values,
        ls_stderr=ls_se,
        width_ratio=0.5 * (q[3] - q[1]) / ls_se,
        chain_path=path,
        warnings=tuple(records),
        elapsed_s=time.perf_counter() - t_start,
        sampling_s=t_sample,
    )
    if emit_warnings:
        emit(result.warnings)
    return result


PHYSICAL_BLOCK = 2048
"""Samples are converted to physical values in blocks of this many rows (the last one padded),
so that one compiled program serves chains of every length (a chain file is written after every
chunk; converting the growing chain in one call recompiled for every new length)."""


def _to_physical_samples(
    kept_z: np.ndarray, static: Static, data: Data, base_z: Array, slots: np.ndarray
) -> np.ndarray:
    """Physical values of the free slots for unconstrained samples `(n, p)`."""
    n = kept_z.shape[0]
    if n == 0:
        return np.zeros((0, slots.size))
    n_pad = -n % PHYSICAL_BLOCK
    padded = np.concatenate([kept_z, np.repeat(kept_z[-1:], n_pad, axis=0)], axis=0)
    out = []
    for block in padded.reshape(-1, PHYSICAL_BLOCK, kept_z.shape[1]):
        full = jnp.broadcast_to(base_z, (PHYSICAL_BLOCK, base_z.shape[0]))
        full = full.at[:, jnp.asarray(slots)].set(jnp.asarray(block))
        out.append(np.asarray(_batched_physical(full, static, data))[:, slots])
    return np.concatenate(out, axis=0)[:n]


def _payload(
    fit: FitResult,
    static: Static,
    data: Data,
    chain_z: np.ndarray,
    log_prob: np.ndarray,
    accepted: np.ndarray,
    seed: int,
    rng_state: tuple,
    fingerprint: str,
    tau: np.ndarray,
) -> dict[str, np.ndarray]:
    """The arrays of a chain file (docs/fitting.md, "Chain file")."""
    slots = np.asarray(fit.free_slots, dtype=int)
    n, w, p = chain_z.shape
    chain = _to_physical_samples(chain_z.reshape(-1, p), static, data, jnp.asarray(fit.z), slots)
    return {
        "format_version": np.asarray(CHAIN_FORMAT_VERSION),
        "names": np.asarray(fit.names),
        "chain": chain.reshape(n, w, p),
        "chain_z": chain_z,
        "log_prob": log_prob,
        "n_accepted": np.asarray(accepted),
        "seed": np.asarray(seed),
        "rng_keys": np.asarray(rng_state[1], dtype=np.uint32),
        "rng_pos": np.asarray(rng_state[2]),
        "rng_has_gauss": np.asarray(rng_state[3]),
        "rng_cached_gaussian": np.asarray(rng_state[4]),
        "free_slots": slots,
        "ls_z": np.asarray(fit.z),
        "tau": np.asarray(tau),
        "fingerprint": np.asarray(fingerprint),
        "variant": np.asarray(fit.variant.name),
    }
