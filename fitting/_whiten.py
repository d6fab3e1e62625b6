"""Correlated rows: the one home of the whitening formula (docs/fitting.md §Correlated channels).

The rows of one ROI (one photo x wedge, up to three channels) share its texture, so their
errors are correlated. A *group* is such a set of rows; a row without a group is a group of its
own. Per group, the covariance of its values is

    C = S R S + diag((f m)^2)

with `S = diag(stderr)`, `R` the group's channel correlation matrix (clipped to be positive
definite, `clip_correlation`) and `(f m)^2` the model-error term when it is on. With the
Cholesky factor `C = L L^T`, the whitened residual is `w = L^-1 (value - model)`: its squares sum
to `r^T C^-1 r`, and `log det C = 2 sum log diag L`. Groups are padded to three slots (a padded
slot has unit variance, no correlation and a zero residual), so the Cholesky factors are one
batch of small 3 x 3s inside the JAX program.

Numpy (preparation, once per scene): `clip_correlation`, `group_arrays`. JAX (every
evaluation): `group_cholesky`, `whiten`, `scatter`, `grouped_fisher`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float, Int
from numpy.typing import NDArray

GROUP_SIZE = 3
"""Slots per group: the camera's three channels."""

EIGEN_FLOOR = 1e-3
"""Smallest eigenvalue a group's correlation matrix keeps (`clip_correlation`). Measured
correlations are estimated pair by pair, so their matrix need not be positive semi-definite; a
floor of 1e-3 (of a trace of 3) keeps every Cholesky factor well conditioned and limits the
weight any combination of a group's channels can get to 1000 x its variance from the stderrs
alone (e.g. |corr| = 1 is treated as 0.999)."""

PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2))
"""The channel pairs of the three correlation columns `corr_01`, `corr_02`, `corr_12`."""


def correlation_matrix(c01: float, c02: float, c12: float) -> NDArray:
    """The 3 x 3 correlation matrix of channels 0, 1, 2 from its three pairwise entries."""
    r = np.eye(GROUP_SIZE)
    for (a, b), c in zip(PAIRS, (c01, c02, c12), strict=True):
        r[a, b] = r[b, a] = c
    return r


def clip_correlation(r: NDArray, floor: float = EIGEN_FLOOR) -> NDArray:
    """A positive definite correlation matrix near `r` (symmetric, unit diagonal, |entries|<=1).

    The eigenvalues of `r` below `floor` are raised to it and the result is rescaled to a unit
    diagonal (`D^-1/2 A D^-1/2`, so each row keeps its own stderr); a matrix whose eigenvalues
    are all at least `floor` is returned unchanged. The rescaled matrix's smallest eigenvalue
    is at least `floor / (1 + 2 + floor)` (its diagonal before rescaling is at most 3 + floor).
    """
    r = 0.5 * (np.asarray(r, float) + np.asarray(r, float).T)
    lam, vec = np.linalg.eigh(r)
    if lam.min() >= floor:
        return r
    a = (vec * np.maximum(lam, floor)) @ vec.T
    d = 1.0 / np.sqrt(np.diag(a))
    out = a * np.outer(d, d)
    np.fill_diagonal(out, 1.0)
    return out


class GroupArrays(NamedTuple):
    """The groups of a table, padded to `GROUP_SIZE` slots (Gr groups).

    `rows` `(Gr, 3)`: the row of each slot (real slots first, in channel order; padded slots
    point at row 0); `mask` `(Gr, 3)`: 1.0 for a real slot; `corr` `(Gr, 3, 3)`: the clipped
    correlation matrix of the real slots, the identity on padded ones."""

    rows: NDArray
    mask: NDArray
    corr: NDArray

    @property
    def correlated(self) -> bool:
        """True when some group holds more than one row (else every row is independent)."""
        return bool(np.any(self.mask.sum(axis=1) > 1))


def group_arrays(
    use: NDArray, group: NDArray, channel: NDArray, corr: NDArray, floor: float = EIGEN_FLOOR
) -> GroupArrays:
    """Groups of the used rows: rows with the same `group >= 0` form one (at most one row per
    channel 0-2, validated by `Observations`), every other used row is a group of its own.
    `corr` `(N, 3)`: the pairwise correlations `corr_01, corr_02, corr_12` of each row's
    group."""
    used = np.flatnonzero(use)
    keys: dict[int, list[int]] = {}
    singles: list[list[int]] = []
    for i in used:
        if group[i] >= 0:
            keys.setdefault(int(group[i]), []).append(int(i))
        else:
            singles.append([int(i)])
    members = [sorted(m, key=lambda i: channel[i]) for m in keys.values()] + singles
    n = max(len(members), 1)
    rows = np.zeros((n, GROUP_SIZE), dtype=np.int64)
    mask = np.zeros((n, GROUP_SIZE))
    mats = np.broadcast_to(np.eye(GROUP_SIZE), (n, GROUP_SIZE, GROUP_SIZE)).copy()
    for g, m in enumerate(members):
        k = len(m)
        rows[g, :k], mask[g, :k] = m, 1.0
        if k > 1:
            full = correlation_matrix(*corr[m[0]])
            ch = channel[m]
            mats[g, :k, :k] = clip_correlation(full[np.ix_(ch, ch)], floor)
    return GroupArrays(rows, mask, mats)


def group_cholesky(
    stderr: Float[Array, " N"],
    extra_var: Float[Array, " N"] | None,
    rows: Int[Array, "Gr 3"],
    mask: Float[Array, "Gr 3"],
    corr: Float[Array, "Gr 3 3"],
) -> Float[Array, "Gr 3 3"]:
    """Lower Cholesky factors of `C = S R S + diag(extra_var)` per group (padded slots: 1)."""
    s = jnp.where(mask > 0, stderr[rows], 1.0)
    cov = s[:, :, None] * corr * s[:, None, :]
    if extra_var is not None:
        e = jnp.where(mask > 0, extra_var[rows], 0.0)
        cov = cov + e[:, :, None] * jnp.eye(GROUP_SIZE, dtype=cov.dtype)[None]
    return jnp.linalg.cholesky(cov)


def whiten(
    chol: Float[Array, "Gr 3 3"],
    resid: Float[Array, " N"],
    rows: Int[Array, "Gr 3"],
    mask: Float[Array, "Gr 3"],
) -> Float[Array, "Gr 3"]:
    """`L^-1 r` per group (zero on padded slots)."""
    r = jnp.where(mask > 0, resid[rows], 0.0)
    return jsl.solve_triangular(chol, r[..., None], lower=True)[..., 0] * mask


def log_diag(chol: Float[Array, "Gr 3 3"], mask: Float[Array, "Gr 3"]) -> Float[Array, "Gr 3"]:
    """`log diag L` on the real slots (0 on padded ones); `sum = (1/2) log det C`."""
    d = jnp.diagonal(chol, axis1=-2, axis2=-1)
    ok = mask > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, d, 1.0)), 0.0)  # safe log on padded slots


def scatter(w: Float[Array, "Gr 3"], rows: Int[Array, "Gr 3"], n_rows: int) -> Array:
    """Per row, the whitened residual of its slot (0 for rows in no group)."""
    return jnp.zeros(n_rows, dtype=w.dtype).at[rows.ravel()].add(w.ravel())


def grouped_fisher(
    chol: Float[Array, "Gr 3 3"],
    jac_mean: Float[Array, "N P"],
    jac_var: Float[Array, "N P"],
    rows: Int[Array, "Gr 3"],
    mask: Float[Array, "Gr 3"],
) -> Float[Array, "P P"]:
    """Fisher information of Gaussian groups with mean `m(z)` and covariance `C(z)` whose
    z-dependence is on the diagonal only (the model-error term): `sum_groups [Jm^T C^-1 Jm +
    (1/2) Jv^T (C^-1 o C^-1) Jv]`, `Jm`, `Jv` the groups' rows of the Jacobians of the mean and
    of the diagonal variance, `o` the elementwise product (tr(C^-1 dC_a C^-1 dC_b) with
    diagonal `dC`)."""
    ok = (mask > 0)[..., None]
    jm = jnp.where(ok, jac_mean[rows], 0.0)
    jv = jnp.where(ok, jac_var[rows], 0.0)
    wm = jsl.solve_triangular(chol, jm, lower=True)
    eye = jnp.broadcast_to(jnp.eye(GROUP_SIZE, dtype=chol.dtype), chol.shape)
    linv = jsl.solve_triangular(chol, eye, lower=True)
    prec = jnp.einsum("gki,gkj->gij", linv, linv)
    info_mean = jnp.einsum("gkp,gkq->pq", wm, wm)
    info_var = 0.5 * jnp.einsum("gip,gij,gjq->pq", jv, prec * prec, jv)
    return info_mean + info_var
