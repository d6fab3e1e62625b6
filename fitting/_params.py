"""Physical parameters: one record each, their transforms, priors and the model variants
[conventions §5, §7, §9].

Every fit works in an *unconstrained* vector `z`; one transform per parameter maps it to the
physical value `x` and is shared by least squares and the posterior (docs/fitting.md):

| parameter          | unit | bounds        | transform                                      |
|--------------------|------|---------------|------------------------------------------------|
| `sigma_rad`        | rad  | `> 0`         | `x = exp(z)`                                   |
| `delta_n`          | 1    | (`n > 1`)     | `x = z` (identity; a normal prior)             |
| `edge_radius_um`   | um   | `[0, r_max]`  | `x = r_max (1 + sin z) / 2`, `z in [-pi/2, pi/2]` |
| `scale`            | *    | `> 0`         | `x = exp(z)`                                   |
| `floor`            | *    | `>= 0`        | `x = z` (bound: active set + prior support)    |
| `model_error_frac` | 1    | `>= 0`        | `x = abs(z)` (the likelihood depends on `x^2`) |
| `fillet_radius_um` | um   | `[0, r_max-r]`| `x = (r_max - r) (1 + sin z) / 2`, `z` as above |

(*) `scale` and `floor` are in the units of the measured relative radiance [conventions §9].
`r_max` is the scene's `min(l1, l2)` over the used wedges and `r` the physical edge radius
(fixed or free), so the tip arc and the fillet always fit together on every wedge
(`stairfit.model.max_fillet_radius`, docs/rounded.md §1): the fillet's transform is the edge
radius's, on the room the tips leave. It is the one transform that reads another slot, so
`to_physical` applies it after the fixed values are in place.
The table is data here too: `PARAMETERS` holds one `ParamInfo` per row, and `Layout` turns it
into one `Parameter` record per entry of `z` (a shared width, one width per wedge, then the
others), so that no code needs to know where in `z` a parameter lives.

The three parameters whose natural value is *on* their bound (a sharp edge, no floor, no model
error) use transforms that reach the bound at a finite `z` (the sine is MINUIT's transform for
doubly bounded parameters): a logit or log would send `z` to infinity and least squares would
never converge when the data favour the bound. A least-squares optimum on a bound is detected
and the parameter fixed there (an active set, `_identify.py`); the posterior keeps `z` in
the prior's support.
A fixed parameter never goes through its transform: it keeps its exact physical value (so a
fixed floor or edge radius can be exactly 0).
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


class Transform(enum.StrEnum):
    """How a parameter's unconstrained coordinate `z` maps to its physical value `x`."""

    LOG = "log"
    """`x = exp(z)`: positive parameters."""
    IDENTITY = "identity"
    """`x = z`."""
    SIN = "sin"
    """`x = r_max (1 + sin z) / 2`, `z in [-pi/2, pi/2]`: the edge radius in `[0, r_max]`."""
    ABS = "abs"
    """`x = abs(z)`: the model-error fraction (the likelihood depends on `x^2` only)."""
    SIN_REST = "sin_rest"
    """`x = (r_max - r) (1 + sin z) / 2`, `z in [-pi/2, pi/2]`, `r` the value of the `SIN`
    slot: the fillet radius in `[0, r_max - r]`."""


LOG, IDENTITY, SIN, ABS = Transform.LOG, Transform.IDENTITY, Transform.SIN, Transform.ABS
SIN_REST = Transform.SIN_REST


class ParamInfo(NamedTuple):
    """What one physical parameter is (a row of the module table).

    `bounds` are physical (`math.inf` for an open end; the edge radius's upper bound is the
    scene's `r_max`, filled in by `Problem.parameters`). `on_bound`: the parameter's natural
    value may lie on its lower bound (sharp edges, no floor, no model error), so an optimum
    there is fixed on it (the active set) and a value within one standard error of it is
    flagged. `optional`: switched on and off by the model ladder (`Variant`).
    """

    name: str
    unit: str
    transform: Transform
    bounds: tuple[float, float]
    on_bound: bool = False
    optional: bool = False


PARAMETERS: tuple[ParamInfo, ...] = (
    ParamInfo("sigma_rad", "rad", LOG, (0.0, math.inf)),
    ParamInfo("delta_n", "1", IDENTITY, (-math.inf, math.inf), optional=True),
    ParamInfo("edge_radius_um", "um", SIN, (0.0, math.inf), on_bound=True, optional=True),
    ParamInfo("scale", "radiance units x rad", LOG, (0.0, math.inf)),
    ParamInfo("floor", "radiance units", IDENTITY, (0.0, math.inf), on_bound=True, optional=True),
    ParamInfo("model_error_frac", "1", ABS, (0.0, math.inf), on_bound=True),
    ParamInfo("fillet_radius_um", "um", SIN_REST, (0.0, math.inf), on_bound=True, optional=True),
)
"""Every physical parameter, in the order of `Params` and of the unconstrained vector.
`scale` multiplies a density in 1/rad [conventions §4, §9]."""

PARAM_INFO: dict[str, ParamInfo] = {p.name: p for p in PARAMETERS}
"""`PARAMETERS` by name."""

PARAM_NAMES: tuple[str, ...] = tuple(PARAM_INFO)
"""The names of `PARAMETERS`, in order."""

OPTIONAL_FEATURES: tuple[str, ...] = tuple(p.name for p in PARAMETERS if p.optional)
"""The parameters the model-selection ladder switches on and off (besides per-wedge sigma)."""

FILLET = "fillet_radius_um"
"""The optional parameter the ladder does not combine with every other (its rungs are few and
explicit: `FILLET_RUNGS`); the others span all combinations."""

ALWAYS_FREE: frozenset[str] = frozenset({"sigma_rad", "scale"})
"""Free in every ladder variant: the simplest model a scene needs is sharp steps, one sigma, the
material's index and a scale."""

Z_CLIP = 60.0
"""`exp` and `logistic` arguments are clipped to +-Z_CLIP: a guard against overflow when a
solver step wanders far (exp(60) ~ 1e26); it is never active at a sensible optimum."""

N_MIN = 1.0001
"""The real part of the refractive index is held at or above this value [conventions §6]."""


def clamp_index(n: ArrayLike) -> Array:
    """The refractive index with its real part held at >= `N_MIN` [conventions §6]: a guard for
    far-off solver steps and for `delta_n` far below the material's index."""
    n = jnp.asarray(n)
    if jnp.iscomplexobj(n):
        return jnp.maximum(jnp.real(n), N_MIN) + 1j * jnp.imag(n)
    return jnp.maximum(n, N_MIN)


class Params(NamedTuple):
    """Physical parameters of the measurement model [conventions §5, §7, §9].

    `sigma_rad` is the Gaussian broadening width in radians: a scalar, or one value per wedge
    (shape `(n_wedges,)`, in the order of `wedge_index`). `delta_n` is the offset added to the
    material's real index [conventions §7]. `edge_radius_um` is the radius of the rounded layer
    edges in micrometres (0 = sharp steps). `scale` and `floor` convert the density to a relative
    radiance: `value = scale cos(theta_i) rho / cos(theta_o) + floor cos(theta_i)`
    [conventions §9]. `model_error_frac` is the fractional model error added in quadrature to
    each row's standard error. `fillet_radius_um` is the radius of the concave fillets between
    layers in micrometres (0 = sharp concave corners; `r + r_f <= min(l1, l2)` on every wedge,
    docs/rounded.md §1, §11); last, so that positional construction of the others is unchanged.
    """

    sigma_rad: float | np.ndarray = float(np.deg2rad(5.0))
    delta_n: float = 0.0
    edge_radius_um: float = 0.0
    scale: float = 1.0
    floor: float = 0.0
    model_error_frac: float = 0.0
    fillet_radius_um: float = 0.0

    def sigma_per_wedge(self, n_wedges: int) -> np.ndarray:
        """`sigma_rad` as an array of one width per wedge."""
        sigma = np.asarray(self.sigma_rad, dtype=float)
        if sigma.ndim == 0:
            return np.full(n_wedges, float(sigma))
        if sigma.shape != (n_wedges,):
            raise ValueError(
                f"sigma_rad has shape {sigma.shape}; give one value or one per wedge ({n_wedges})"
            )
        return sigma.copy()


DEFAULTS = Params()
"""Values used for fixed parameters unless the caller gives others: sigma 5 deg (the paper's
Fig. 8), delta_n 0, sharp edges, scale 1, no floor, no model error, no fillets."""


# --- priors ---------------------------------------------------------------------------------
# A prior's numbers are pytree leaves (NamedTuple fields) and `log_pdf` takes them traced: the
# compiled log priors get them as data (`split_priors`), so that a scene's data-derived priors
# (the floor's scale, the radii's bound) do not make a program of their own.


class Normal(NamedTuple):
    """Normal prior `N(mean, sd)` on the physical value."""

    mean: float
    sd: float

    def log_pdf(self, x: ArrayLike) -> Array:
        """Log density at the physical value `x`."""
        u = (jnp.asarray(x) - self.mean) / self.sd
        return -0.5 * u * u - jnp.log(self.sd * math.sqrt(2.0 * math.pi))

    def width(self) -> tuple[str, float]:
        """(space, standard deviation) used by the identifiability rule."""
        return "linear", self.sd


class HalfNormal(NamedTuple):
    """Half-normal prior on `x >= 0` with scale `sd` (the sd of the parent normal)."""

    sd: float

    def log_pdf(self, x: ArrayLike) -> Array:
        """Log density at `x` (`-inf` for `x < 0`)."""
        x = jnp.asarray(x)
        u = x / self.sd
        val = -0.5 * u * u + jnp.log(math.sqrt(2.0 / math.pi) / self.sd)
        return jnp.where(x >= 0.0, val, -jnp.inf)

    def width(self) -> tuple[str, float]:
        """(space, standard deviation) of the half-normal: `sd sqrt(1 - 2/pi)`."""
        return "linear", self.sd * math.sqrt(1.0 - 2.0 / math.pi)


class Uniform(NamedTuple):
    """Uniform prior on `[lower, upper]`."""

    lower: float
    upper: float

    def log_pdf(self, x: ArrayLike) -> Array:
        """Log density at `x` (`-inf` outside the interval)."""
        x = jnp.asarray(x)
        inside = (x >= self.lower) & (x <= self.upper)
        return jnp.where(inside, -jnp.log(self.upper - self.lower), -jnp.inf)

    def width(self) -> tuple[str, float]:
        """(space, standard deviation) of the uniform: `(upper - lower) / sqrt(12)`."""
        return "linear", (self.upper - self.lower) / math.sqrt(12.0)


class LogUniform(NamedTuple):
    """Log-uniform (Jeffreys) prior `p(x) ~ 1/x` on `[lower, upper]`, `lower > 0`."""

    lower: float
    upper: float

    def log_pdf(self, x: ArrayLike) -> Array:
        """Log density at `x` (`-inf` outside the interval)."""
        x = jnp.asarray(x)
        inside = (x >= self.lower) & (x <= self.upper)
        x_safe = jnp.where(inside, x, 1.0)
        val = -jnp.log(x_safe) - jnp.log(jnp.log(self.upper / self.lower))
        return jnp.where(inside, val, -jnp.inf)

    def width(self) -> tuple[str, float]:
        """(space, standard deviation of ln x): `ln(upper / lower) / sqrt(12)`."""
        return "log", math.log(self.upper / self.lower) / math.sqrt(12.0)


Prior = Normal | HalfNormal | Uniform | LogUniform


class Priors(NamedTuple):
    """Priors on the physical parameters (docs/fitting.md). `None` = derived from the data.

    * `sigma_rad`: log-uniform on [1e-3, 1.5] rad (0.06 to 86 deg); applies to every per-wedge
      width too.
    * `delta_n`: normal, mean 0, sd 0.1 (polymers span n = 1.3 to 1.7).
    * `edge_radius_um`: `None` = uniform on [0, r_max] of the scene.
    * `scale`: log-uniform on [1e-12, 1e12] (scale-free; no information).
    * `floor`: `None` = half-normal with sd = the largest used measured value.
    * `model_error_frac`: half-normal with sd 0.1 (model errors of a few per cent).
    * `fillet_radius_um`: `None` = uniform on [0, r_max] of the scene (the joint support with
      the edge radius is the triangle `r + r_f <= r_max`, which the transform enforces).
    """

    sigma_rad: Prior = LogUniform(1e-3, 1.5)
    delta_n: Prior = Normal(0.0, 0.1)
    edge_radius_um: Prior | None = None
    scale: Prior = LogUniform(1e-12, 1e12)
    floor: Prior | None = None
    model_error_frac: Prior = HalfNormal(0.1)
    fillet_radius_um: Prior | None = None

    def resolved(self, r_max_um: float, value_max: float) -> Priors:
        """Fill the data-derived priors: `edge_radius_um`, `fillet_radius_um` and `floor`."""
        return self._replace(
            edge_radius_um=self.edge_radius_um or Uniform(0.0, float(r_max_um)),
            floor=self.floor or HalfNormal(float(value_max)),
            fillet_radius_um=self.fillet_radius_um or Uniform(0.0, float(r_max_um)),
        )


# --- one record per entry of the unconstrained vector -----------------------------------------


def parameter_label(name: str, wedge: int | None = None, wedge_deg: float | None = None) -> str:
    """Human-readable name of a parameter: `sigma_rad`, `sigma_rad[2]`, `sigma_rad[2: 30 deg]`
    (wedge 2, a 30-degree wedge). For display only: code identifies a parameter by its
    `(param, wedge)`, never by this text."""
    if wedge is None:
        return name
    if wedge_deg is None:
        return f"{name}[{wedge}]"
    return f"{name}[{wedge}: {wedge_deg:g} deg]"


class Parameter(NamedTuple):
    """One entry of the unconstrained vector `z` (lmfit's `Parameter`, for this model).

    `param`: the physical parameter (a name of `PARAMETERS`); `wedge`: the wedge whose own
    width this is (`None` for the shared width and every other parameter); `slot`: its index
    in `z`; `unit`, `transform`, `bounds` (physical; the edge radius's upper bound is the
    scene's `r_max` once resolved); `prior` (resolved against the data, or None before);
    `free`: fitted (True) or held at its fixed value (False); `wedge_deg`: the wedge angle, for
    the label.
    """

    param: str
    wedge: int | None
    slot: int
    unit: str
    transform: Transform
    bounds: tuple[float, float]
    prior: Prior | None = None
    free: bool = False
    wedge_deg: float | None = None

    @property
    def info(self) -> ParamInfo:
        """The parameter's row of `PARAMETERS`."""
        return PARAM_INFO[self.param]

    def label(self, name: str | None = None) -> str:
        """Display name (`parameter_label`), optionally under another `name` (e.g. `sigma_deg`
        for a width shown in degrees)."""
        return parameter_label(name or self.param, self.wedge, self.wedge_deg)


def _record(param: str, wedge: int | None, slot: int) -> Parameter:
    info = PARAM_INFO[param]
    return Parameter(param, wedge, slot, info.unit, info.transform, info.bounds)


class Layout(NamedTuple):
    """The entries of the unconstrained vector `z` for a scene with `n_wedges` wedges.

    Slot 0 is the shared width, slots `1 .. n_wedges` the per-wedge widths, then the other
    parameters in `PARAMETERS` order. A variant leaves the slots it does not use fixed; their
    Jacobian columns are zero. This class is the only place that knows the slot numbers.
    """

    n_wedges: int

    @property
    def size(self) -> int:
        """Length of `z`."""
        return self.n_wedges + len(PARAMETERS)

    def parameters(self) -> tuple[Parameter, ...]:
        """One record per slot, in slot order (priors and free flags not yet resolved)."""
        widths = [_record("sigma_rad", None, 0)]
        widths += [_record("sigma_rad", w, 1 + w) for w in range(self.n_wedges)]
        rest = [_record(name, None, self.slot(name)) for name in PARAM_NAMES[1:]]
        return (*widths, *rest)

    def slot(self, param: str, wedge: int | None = None) -> int:
        """Slot of `param` (of wedge `wedge`'s own width when `param` is `sigma_rad`)."""
        if param == "sigma_rad":
            return 0 if wedge is None else 1 + wedge
        return self.n_wedges + PARAM_NAMES.index(param)

    @property
    def kinds(self) -> tuple[Transform, ...]:
        """Transform of each slot."""
        return tuple(p.transform for p in self.parameters())

    def unpack(self, x: Array, sigma_source: Array) -> Params:
        """Physical slot values `x` as `Params`: `sigma_rad` one width per wedge (each wedge's
        from the slot `sigma_source` names), the others scalars."""
        names = PARAM_NAMES[1:]
        return Params(x[sigma_source], *(x[self.slot(name)] for name in names))


# --- transforms -------------------------------------------------------------------------------


def _rest_of(kinds: Sequence[str], x: Array, r_max_um: ArrayLike) -> Array:
    """`r_max - r`, `r` the value of the `SIN` slot in `x` (the room a `SIN_REST` slot gets)."""
    r = x[list(kinds).index(SIN)] if SIN in kinds else 0.0
    return jnp.maximum(jnp.asarray(r_max_um) - r, 0.0)


def to_physical(
    z: Array,
    kinds: Sequence[str],
    r_max_um: ArrayLike,
    fixed: tuple[Array, Array] | None = None,
) -> Array:
    """Map the unconstrained vector to physical values slot by slot (see the module table).

    `fixed = (free, x_fixed)`: slots not free take their fixed physical value (before the
    `SIN_REST` slot reads the edge radius, so a fixed radius bounds a free fillet)."""
    out = []
    for k, kind in enumerate(kinds):
        if kind == LOG:
            out.append(jnp.exp(jnp.clip(z[k], -Z_CLIP, Z_CLIP)))
        elif kind in (SIN, SIN_REST):
            out.append(jnp.asarray(r_max_um) * 0.5 * (1.0 + jnp.sin(z[k])))
        elif kind == ABS:
            out.append(jnp.abs(z[k]))
        else:
            out.append(z[k])
    x = jnp.stack(out)
    if fixed is not None:
        x = jnp.where(fixed[0], x, fixed[1])
    if SIN_REST in kinds:
        k = list(kinds).index(SIN_REST)
        x_k = _rest_of(kinds, x, r_max_um) * 0.5 * (1.0 + jnp.sin(z[k]))
        x = x.at[k].set(x_k if fixed is None else jnp.where(fixed[0][k], x_k, fixed[1][k]))
    return x


def in_support(z: Array, kinds: Sequence[str]) -> Array:
    """False where a sine slot leaves its principal branch `[-pi/2, pi/2]` (posterior only)."""
    ok = jnp.asarray(True)
    for k, kind in enumerate(kinds):
        if kind in (SIN, SIN_REST):
            ok = ok & (jnp.abs(z[k]) <= 0.5 * jnp.pi)
    return ok


def log_abs_jacobian(
    z: Array, kinds: Sequence[str], r_max_um: ArrayLike, fixed: tuple[Array, Array] | None = None
) -> Array:
    """`log |dx/dz|` of each slot's transform (the prior's change of variables).

    For `abs` the map is two-to-one; the density of `z` is `p(|z|) / 2`, hence `-log 2`. The
    `SIN_REST` slot's `x` also depends on the `SIN` slot's `z`, but the Jacobian matrix is then
    triangular, so its log-determinant is still the sum of these diagonal terms.
    """
    out = []
    x = to_physical(z, kinds, r_max_um, fixed) if SIN_REST in kinds else None
    for k, kind in enumerate(kinds):
        if kind == LOG:
            out.append(z[k])
        elif kind in (SIN, SIN_REST):
            room = jnp.asarray(r_max_um) if kind == SIN else _rest_of(kinds, x, r_max_um)
            c = jnp.cos(z[k])
            pos = (c > 0) & (room > 0)
            out.append(jnp.where(pos, jnp.log(0.5 * jnp.where(pos, room * c, 1.0)), -jnp.inf))
        elif kind == ABS:
            out.append(jnp.full_like(z[k], -math.log(2.0)))
        else:
            out.append(jnp.zeros_like(z[k]))
    return jnp.stack(out)


def from_physical(x: float, kind: str, r_max_um: float, edge_radius_um: float = 0.0) -> float:
    """Inverse transform for one value (used for starting points); `edge_radius_um` is the
    physical edge radius a `SIN_REST` (fillet) value is bounded by."""
    if kind == LOG:
        return float(np.clip(np.log(max(x, np.exp(-Z_CLIP))), -Z_CLIP, Z_CLIP))
    if kind in (SIN, SIN_REST):
        room = r_max_um - (edge_radius_um if kind == SIN_REST else 0.0)
        if room <= 0:
            return -0.5 * np.pi
        return float(np.arcsin(np.clip(2.0 * x / room - 1.0, -1.0, 1.0)))
    if kind == ABS:
        return float(abs(x))
    return float(x)


def dx_dz(
    z: np.ndarray, kinds: Sequence[str], r_max_um: float, edge_radius_um: float = 0.0
) -> np.ndarray:
    """Derivative of each transform at `z` in its own coordinate (the diagonal of
    `dx_matrix`); `edge_radius_um` is the physical edge radius bounding a `SIN_REST` slot."""
    out = np.ones(len(kinds))
    for k, kind in enumerate(kinds):
        if kind == LOG:
            out[k] = np.exp(np.clip(z[k], -Z_CLIP, Z_CLIP))
        elif kind == SIN:
            out[k] = 0.5 * r_max_um * np.cos(z[k])
        elif kind == SIN_REST:
            out[k] = 0.5 * max(r_max_um - edge_radius_um, 0.0) * np.cos(z[k])
        elif kind == ABS:
            out[k] = 1.0 if z[k] >= 0 else -1.0
    return out


def dx_matrix(
    z: np.ndarray, kinds: Sequence[str], r_max_um: float, free: np.ndarray, edge_radius_um: float
) -> np.ndarray:
    """`dx/dz` as a matrix (for the delta method): `dx_dz` on the diagonal, and the fillet's
    dependence on a free edge radius, `dx_f / dz_r = -(1 + sin z_f) / 2 * dr / dz_r`."""
    d = dx_dz(z, kinds, r_max_um, edge_radius_um)
    out = np.diag(d)
    if SIN_REST in kinds and SIN in kinds:
        f, r = list(kinds).index(SIN_REST), list(kinds).index(SIN)
        if free[r]:
            out[f, r] = -0.5 * (1.0 + np.sin(z[f])) * d[r]
    return out


PriorSpec = tuple[tuple[int, Prior], ...]
"""Hashable (slot, prior) pairs of the free slots: static configuration of a posterior."""


def log_prior_z(
    z: Array,
    kinds: Sequence[str],
    r_max_um: ArrayLike,
    priors: PriorSpec,
    fixed: tuple[Array, Array] | None = None,
) -> Array:
    """Log prior density of the free slots in the unconstrained coordinates: `sum over (slot,
    prior) of [log p(x) + log |dx/dz|]` (priors are stated on the physical values). The one
    home of that sum: the posterior and the Laplace evidence both use it. `fixed` as in
    `to_physical` (needed when a fixed edge radius bounds a free fillet)."""
    x = to_physical(z, kinds, r_max_um, fixed)
    jac = log_abs_jacobian(z, kinds, r_max_um, fixed)
    total = jnp.asarray(0.0, dtype=z.dtype)
    for slot, prior in priors:
        total = total + prior.log_pdf(x[slot]) + jac[slot]
    return total


@functools.lru_cache(maxsize=8)  # the sampler asks for the same specification at every call
def split_priors(priors: PriorSpec) -> tuple[tuple[int, ...], tuple[Prior, ...]]:
    """`(slots, distributions)` of a prior specification, for a compiled function: the slots
    (and the distributions' kinds, their pytree structure) are its static configuration, the
    distributions' numbers (float64 leaves) its data. Before, the whole specification was
    static, and the floor's prior, whose scale is the scene's largest measured value, gave
    every new scene a posterior program of its own (issue 14)."""
    slots = tuple(int(slot) for slot, _ in priors)
    dists = tuple(type(p)(*(np.float64(v) for v in p)) for _, p in priors)
    return slots, dists


def log_prior_split(
    z: Array,
    kinds: Sequence[str],
    r_max_um: ArrayLike,
    slots: tuple[int, ...],
    dists: tuple[Prior, ...],
    fixed: tuple[Array, Array] | None = None,
) -> Array:
    """`log_prior_z` with the specification as `split_priors` gives it."""
    return log_prior_z(z, kinds, r_max_um, tuple(zip(slots, dists, strict=True)), fixed)


# --- model variants -------------------------------------------------------------------------


class Variant(NamedTuple):
    """One model of the ladder: which parameters are free (the rest are fixed).

    `free` is a set of names from `PARAM_NAMES`; `per_wedge_sigma` gives every wedge its own
    broadening width instead of one shared `sigma_rad`. `kernel`: how the facets spread their
    light in the lab model (`stairfit.model.LAB_KERNELS`: "gaussian", the paper's broadening,
    with `sigma_rad` its width; "ggx" or "beckmann", microfacet facets, with `sigma_rad` holding
    their roughness alpha). Free versus fixed is metadata here; the values of fixed parameters
    come from a `Params` given to the fit (default `DEFAULTS`).
    """

    name: str
    free: frozenset[str]
    per_wedge_sigma: bool = False
    kernel: str = "gaussian"

    @property
    def features(self) -> tuple[str, ...]:
        """The optional features switched on (for tables), in `OPTIONAL_FEATURES` order."""
        out = tuple(f for f in OPTIONAL_FEATURES if f in self.free)
        return (*out, "sigma_per_wedge") if self.per_wedge_sigma else out

    def with_free(self, *names: str, model_error: bool = False) -> Variant:
        """A copy with more free parameters (and the model-error term if asked)."""
        extra = set(names) | ({"model_error_frac"} if model_error else set())
        return self._replace(free=self.free | frozenset(extra))


def variant(name: str, *features: str, per_wedge_sigma: bool = False) -> Variant:
    """A ladder variant: `sigma_rad` and `scale` free plus the named optional `features`."""
    unknown = set(features) - set(PARAM_NAMES)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; known: {PARAM_NAMES}")
    return Variant(name, ALWAYS_FREE | frozenset(features), per_wedge_sigma)


_SHORT = {"delta_n": "delta_n", "edge_radius_um": "edge", "floor": "floor", FILLET: "fillet"}
"""How the optional features appear in ladder names."""


def _ladder() -> tuple[Variant, ...]:
    """Every combination of the optional features, then per-wedge sigma on top of each."""
    out = []
    combined = tuple(f for f in OPTIONAL_FEATURES if f != FILLET)
    for per_wedge in (False, True):
        for mask in range(2 ** len(combined)):
            feats = tuple(f for k, f in enumerate(combined) if mask >> k & 1)
            parts = ["sharp" if "edge_radius_um" not in feats else "rounded"]
            parts += [_SHORT[f] for f in feats if f != "edge_radius_um"]
            if per_wedge:
                parts.append("sigma_per_wedge")
            out.append(variant("+".join(parts), *feats, per_wedge_sigma=per_wedge))
    return tuple(sorted(out, key=lambda v: (v.per_wedge_sigma, len(v.free))))


FILLET_RUNGS: tuple[Variant, ...] = (
    variant("rounded+fillet", "edge_radius_um", FILLET),
    variant("rounded+floor+fillet", "edge_radius_um", "floor", FILLET),
)
"""The fillet rungs (docs/fitting.md §4): the tip radius and the fillet radius free, without
and with a floor, one shared sigma, the material's index. Two, not the eight combinations:
each costs a filleted compilation (shared by both) and solves several times slower than a
rounded one; the fillet refines the rounded profile, so it is offered on the rounded variants
the sharp-or-rounded ladder most often ends on (an unresolved floor is the other common
misfit), and `rounded+fillet` is the parent of `rounded+floor+fillet`."""

DEFAULT_LADDER: tuple[Variant, ...] = _ladder() + FILLET_RUNGS
"""The default model ladder: the 8 combinations of {delta_n, edge radius, floor} with one
shared sigma, then the same 8 with one sigma per wedge, ordered from simple to rich, then the
two `FILLET_RUNGS`. Names look like `sharp`, `sharp+delta_n`, `rounded+floor`,
`sharp+delta_n+sigma_per_wedge`, `rounded+floor+fillet`."""

SIMPLEST = DEFAULT_LADDER[0]
"""`sharp`: sharp steps, one sigma, the material's index, a scale."""
