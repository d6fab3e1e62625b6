"""The forward model as fits see it: one module-level function of (z, args).

optimistix compiles a solve once per *function identity* and argument structure, so the
residuals are a module-level function of the unconstrained vector `z` and `args = (Static,
Data)`: `Static` holds hashable configuration (transform kinds, which forward, the aperture),
`Data` only arrays. Which parameters are free, their fixed values and the tying of per-wedge
widths are arrays in `Data`, so every variant of the sharp model on one scene shares a single
compilation [conventions §1-§9].

Only what the scene needs is evaluated: the lobe geometry and broadening once per distinct
(theta_i, wedge, theta_o) for all channels, the Fresnel factors at the wavelengths each channel
sees.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from stairfit import model

from ._params import Layout, Params, clamp_index, to_physical
from ._whiten import group_cholesky, log_diag, scatter, whiten

light_nodes = jax.jit(model.light_nodes, static_argnums=2)
"""`stairfit.model.light_nodes` as one compiled program per aperture, for the concrete grids the
fit and the simulator prepare (evaluated op by op it dispatched about 40 small programs)."""


class Static(NamedTuple):
    """Hashable configuration of a forward evaluation (part of the compilation key).

    `layout`: the slots of `z` (their parameters and transforms). `rounded`: use the
    rounded-edge model (needed when the edge radius is free or non-zero). `model_error`: the
    per-row variance includes `(model_error_frac * model)^2` and the residuals carry its
    log-determinant. `correlated`: some rows share a group (an ROI's channels) with correlated
    errors, and residuals are whitened per group (`_whiten`); False: every row is independent
    (the plain `(value - model) / sd`). `aperture`: finite light/patch sizes [conventions §9].
    `resolution`: the rounded model's resolution setting (`None` = its default). `filleted`:
    the rounded model plus concave fillets (`stairfit.model.brdf_filleted`; needed when the
    fillet radius is free or non-zero; implies `rounded`). `fillet_rays`: the fillet
    correction's rays per period (`None` = `stairfit.model.FILLET_RAYS`; docs/rounded.md §11).
    """

    layout: Layout
    rounded: bool = False
    model_error: bool = False
    correlated: bool = False
    aperture: model.Aperture = model.Aperture()
    resolution: int | None = None
    filleted: bool = False
    fillet_rays: int | None = None


class Resolution(NamedTuple):
    """The model's quadrature knobs as a fit takes them (`resolution=` of `fit_least_squares`,
    `select_model`, `model_radiance`, ...): `rounded`, the rounded model's resolution
    (`None` = `stairfit.model.ROUNDED_RESOLUTION`), and `fillet_rays`, the fillet correction's
    rays per period (`None` = `stairfit.model.FILLET_RAYS`; docs/rounded.md §11). A plain int
    there is the rounded resolution alone."""

    rounded: int | None = None
    fillet_rays: int | None = None


def resolution_parts(resolution: int | Resolution | None) -> tuple[int | None, int | None]:
    """`(rounded resolution, fillet rays)` of a `resolution=` argument (None: the default)."""
    if isinstance(resolution, Resolution):
        return resolution.rounded, resolution.fillet_rays
    return resolution, None


class Data(NamedTuple):
    """Arrays of one fit (traced; changing them never recompiles).

    Per row (N): angles (rad), `beta2`, `layer_um` (read only by a posterior's fingerprint),
    `value`, `stderr`, `use` (1.0 or 0.0). Both models are evaluated on a grid whose lobe
    geometry and broadening do not depend on the channel: per key (R; distinct (theta_i, wedge),
    or (theta_i, wedge, theta_o), see `_problem.evaluation_grid`) `r_ti`, `r_b2`, `r_wedge`, and
    the viewing angles `r_to` either as a grid shared by all keys `(1, T)` or one per key
    `(R, 1)`, with `r_so` (`(R, T)` or `(R, 1)`): the share of the aperture's viewing spread
    each (key, view) sees (its ROI's `view_spread`); every key is evaluated for all channels,
    `r_n` and `r_w` `(C, K)`; each row reads `[r_key, r_t, r_c]`. Distinct (theta_i at each
    aperture node, beta2, layer_um) (G): `g_ti`, `g_b2`, `g_layer`, indexed by `r_geo` (key,
    node). Per slot of `z` (P): `free`, `x_fixed` (physical values of fixed slots). Per wedge
    (W): `sigma_source` (slot holding that wedge's
    width). `r_max_um`: upper bound of the edge radius. Per group of correlated rows (Gr, padded
    to 3 slots; `_whiten.GroupArrays`): `grp_rows`, `grp_mask`, `grp_corr`.
    """

    theta_i: Float[Array, " N"]
    theta_o: Float[Array, " N"]
    beta2: Float[Array, " N"]
    layer_um: Float[Array, " N"]
    value: Float[Array, " N"]
    stderr: Float[Array, " N"]
    use: Float[Array, " N"]
    r_key: Int[Array, " N"]
    r_t: Int[Array, " N"]
    r_c: Int[Array, " N"]
    r_ti: Float[Array, " R"]
    r_b2: Float[Array, " R"]
    r_wedge: Int[Array, " R"]
    r_n: Array
    r_w: Float[Array, "C K"]
    r_to: Float[Array, "R1 T"]
    r_so: Float[Array, "R1 T"]
    r_geo: Int[Array, "R M"]
    g_ti: Float[Array, " G"]
    g_b2: Float[Array, " G"]
    g_layer: Float[Array, " G"]
    free: Bool[Array, " P"]
    x_fixed: Float[Array, " P"]
    sigma_source: Int[Array, " W"]
    r_max_um: Float[Array, ""]
    grp_rows: Int[Array, "Gr 3"]
    grp_mask: Float[Array, "Gr 3"]
    grp_corr: Float[Array, "Gr 3 3"]


def physical(z: Array, static: Static, data: Data) -> Array:
    """Physical value of every slot: free slots through their transform, fixed ones as given."""
    z_safe = jnp.where(data.free, z, 0.0)
    return to_physical(z_safe, static.layout.kinds, data.r_max_um, (data.free, data.x_fixed))


class EvaluationGrid(NamedTuple):
    """The (key, view, channel) grid both the sharp and the rounded model are evaluated on
    (a subset of `Data`; see there)."""

    r_ti: Array
    r_b2: Array
    r_n: Array
    r_w: Array
    r_to: Array
    r_so: Array
    r_geo: Array
    g_ti: Array
    g_b2: Array
    g_layer: Array


def _view_nodes(g: EvaluationGrid, do: Array, aperture: model.Aperture) -> Array:
    """Viewing angles at the aperture nodes, `(R|1, T, M)`: each (key, view)'s spread is the
    aperture's narrowed by its ROI's share `r_so` [conventions §9]."""
    return model.node_angles(g.r_to, g.r_so[..., None] * do[None, None, :], aperture.foreshortened)


def _rounded_impl(
    sigma_k: Array, dn: Array, radius_um: Array, cfg: tuple, g: EvaluationGrid
) -> Array:
    """Band- and aperture-averaged rounded density on the (key, view, channel) grid,
    `(R, T, C)`."""
    aperture, resolution = cfg
    do = jnp.asarray(aperture.nodes()[1], g.r_ti.dtype)
    ti, dw = model.light_nodes(g.r_ti, g.r_b2, aperture)  # (R, M) each: per-key light nodes
    to = jnp.swapaxes(_view_nodes(g, do, aperture), -1, -2)  # (R|1, M, T)
    n = clamp_index(g.r_n + dn).reshape(-1)  # (C K): every channel's samples on one axis
    res = model.ROUNDED_RESOLUTION if resolution is None else resolution
    # geometry once per distinct (theta_i, beta2, layer) (G of them), then gathered to the keys
    geo = model.rounded_geometry(g.g_ti, g.g_b2, g.g_layer, radius_um, resolution=res)
    geo = jax.tree_util.tree_map(lambda a: a[g.r_geo][:, :, None, None], geo)  # (R, M, 1, 1, ..)
    rho = model.brdf_rounded_from_geometry(
        geo,
        ti[:, :, None, None],
        to[..., None],
        g.r_b2[:, None, None, None],
        n,
        sigma_k[:, None, None, None],
    )  # (R, M, T, C K)
    rho = rho.reshape(*rho.shape[:-1], *g.r_w.shape)
    band = jnp.einsum("ck,rmtck->rmtc", g.r_w, rho)
    dw = dw[:, :, None] * model.view_conversion(g.r_to[:, None, :], to)  # (R, M, T)
    return jnp.einsum("rmtc,rmt->rtc", band, dw)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def rounded_grid_density(
    sigma_k: Array, dn: Array, radius_um: Array, cfg: tuple, g: EvaluationGrid
) -> Array:
    """`_rounded_impl` with a JVP that differentiates the rounded model once per call.

    Each output element depends on one width (its key's), on `delta_n` and on the radius, so
    three directional derivatives (all widths together, `delta_n`, radius) give the whole
    Jacobian; a Jacobian over every slot of `z` then costs three directions instead of one per
    slot. The grid arrays `g` are data (their tangents are ignored).
    """
    return _rounded_impl(sigma_k, dn, radius_um, cfg, g)


@rounded_grid_density.defjvp
def _rounded_grid_jvp(cfg: tuple, primals: tuple, tangents: tuple) -> tuple[Array, Array]:
    sigma_k, dn, radius_um, g = primals
    t_sigma, t_dn, t_r, _ = tangents

    def f(eps: Array) -> Array:
        return _rounded_impl(sigma_k + eps[0], dn + eps[1], radius_um + eps[2], cfg, g)

    eps0 = jnp.zeros(3, dtype=sigma_k.dtype)
    value, jac = _value_and_jac(f, eps0)
    d_sigma, d_dn, d_r = jac[..., 0], jac[..., 1], jac[..., 2]
    return value, d_sigma * t_sigma[:, None, None] + d_dn * t_dn + d_r * t_r


def _value_and_jac(f, eps0: Array) -> tuple[Array, Array]:  # noqa: ANN001
    """Value and forward-mode Jacobian of `f` at `eps0` (a few directions, one linearisation;
    the Jacobian's last axis is the direction)."""
    value, lin = jax.linearize(f, eps0)
    jac = jax.vmap(lin, out_axes=-1)(jnp.eye(eps0.shape[0], dtype=eps0.dtype))
    return value, jac


def _value_and_jac_forward(f, eps0: Array) -> tuple[Array, Array]:  # noqa: ANN001
    """As `_value_and_jac`, by `jax.jvp` in each direction (vmapped) instead of one
    linearisation: a linearised `lax.scan` keeps every step's intermediates for its linear
    part, which undid the fillet correction's chunking over the rays (`FILLET_CHUNK_BYTES`)."""
    value, jac = jax.vmap(lambda t: jax.jvp(f, (eps0,), (t,)), out_axes=(None, -1))(
        jnp.eye(eps0.shape[0], dtype=eps0.dtype)
    )
    return value, jac


SHARP_FRESNEL_DIRECT_MAX_K = 4
"""With at most this many wavelength samples per channel, the sharp grid evaluates the Fresnel
factors at every (key, aperture node, channel) directly; with more, once per distinct geometry
(`g_ti`, `g_b2`) and gathers them (a gather costs about as much as a few Fresnel evaluations)."""


def _sharp_grid_impl(
    sigma_k: Array, dn: Array, aperture: model.Aperture, g: EvaluationGrid
) -> Array:
    """Band- and aperture-averaged sharp density on the (key, view, channel) grid, `(R, T, C)`.

    The same quantity as `stairfit.model.band_density` [conventions §4, §5, §8, §9], laid out
    like the rounded model's grid: the lobe weights and broadening depend on (theta_i, wedge,
    theta_o) and are shared by the channels; only the Fresnel factors depend on the channel.
    """
    do = jnp.asarray(aperture.nodes()[1], g.r_ti.dtype)
    ti, dw = model.light_nodes(g.r_ti, g.r_b2, aperture)  # (R, M) each: per-key light nodes
    to = _view_nodes(g, do, aperture)  # (R|1, T, M)
    b2 = g.r_b2[:, None]
    weight = model.lobe_weights(ti, b2)  # (R, M, 3)
    kernel = model.hemisphere_gaussian(
        to[..., None], model.lobe_directions(ti, b2)[:, None], sigma_k[:, None, None, None]
    )  # (R, T, M, 3)
    n = clamp_index(g.r_n + dn)  # (C, K)
    if n.shape[1] <= SHARP_FRESNEL_DIRECT_MAX_K:
        fresnel = model.lobe_fresnel(ti[:, :, None, None], b2[:, :, None, None], n)  # (R,M,C,K,3)
        band = jnp.einsum("ck,rmckl->rmcl", g.r_w, fresnel)
    else:
        fresnel = model.lobe_fresnel(g.g_ti[:, None, None], g.g_b2[:, None, None], n)  # (G,C,K,3)
        band = jnp.einsum("ck,gckl->gcl", g.r_w, fresnel)[g.r_geo]  # (R, M, C, 3)
    dw = dw[:, None, :] * model.view_conversion(g.r_to[..., None], to)  # (R, T, M)
    return jnp.einsum("rml,rtml,rmcl,rtm->rtc", weight, kernel, band, dw)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def sharp_grid_density(
    sigma_k: Array, dn: Array, aperture: model.Aperture, g: EvaluationGrid
) -> Array:
    """`_sharp_grid_impl` with a JVP that needs two directional derivatives, whatever the
    number of parameters: each element depends on its key's width only, and on `delta_n`, so
    one direction with every width moved at once and one along `delta_n` give the whole
    Jacobian. The grid arrays `g` are data (their tangents are ignored)."""
    return _sharp_grid_impl(sigma_k, dn, aperture, g)


@sharp_grid_density.defjvp
def _sharp_grid_jvp(
    aperture: model.Aperture, primals: tuple, tangents: tuple
) -> tuple[Array, Array]:
    sigma_k, dn, g = primals
    t_sigma, t_dn, _ = tangents

    def f(eps: Array) -> Array:
        return _sharp_grid_impl(sigma_k + eps[0], dn + eps[1], aperture, g)

    value, jac = _value_and_jac(f, jnp.zeros(2, dtype=sigma_k.dtype))
    return value, jac[..., 0] * t_sigma[:, None, None] + jac[..., 1] * t_dn


def _grid(data: Data) -> EvaluationGrid:
    return EvaluationGrid(
        data.r_ti, data.r_b2, data.r_n, data.r_w, data.r_to, data.r_so,
        data.r_geo, data.g_ti, data.g_b2, data.g_layer,
    )  # fmt: skip


def sharp_density(sigma_w: Array, dn: Array, data: Data, aperture: model.Aperture) -> Array:
    """Band- and aperture-averaged density (1/rad) of the sharp model at every row.

    Evaluated on the (key, view, channel) grid (`sharp_grid_density`), then read per row;
    `sigma_w` holds one width per wedge.
    """
    dens = sharp_grid_density(sigma_w[data.r_wedge], dn, aperture, _grid(data))
    return dens[data.r_key, data.r_t, data.r_c]


def rounded_density(
    sigma_w: Array, dn: Array, radius_um: Array, data: Data, static: Static
) -> Array:
    """Band- and aperture-averaged density (1/rad) of the rounded-edge model at every row.

    `stairfit.model.brdf_rounded` at every wavelength sample of the channel, contracted with
    the channel weights [conventions §8]; the aperture is averaged as in `band_density`.
    Evaluated once per (theta_i, wedge) key and viewing angle for all channels, then gathered.
    """
    dens = rounded_grid_density(
        sigma_w[data.r_wedge], dn, radius_um, (static.aperture, static.resolution), _grid(data)
    )
    return dens[data.r_key, data.r_t, data.r_c]


def _fillet_impl(
    sigma_k: Array, dn: Array, rays: model.FilletRays, cfg: tuple, g: EvaluationGrid
) -> Array:
    """Band- and aperture-averaged fillet correction on the (key, view, channel) grid,
    `(R, T, C)`, from the rays traced once per distinct geometry (`rays`, leading axis G):
    `stairfit.model.fillet_ray_power` at every channel's index samples, gathered to the keys'
    aperture nodes, contracted over (lane, ray) with the hemisphere Gaussians of the rays'
    directions (docs/rounded.md §11) [conventions §5, §8, §9]."""
    aperture = cfg[0]
    do = jnp.asarray(aperture.nodes()[1], g.r_ti.dtype)
    _, dw = model.light_nodes(g.r_ti, g.r_b2, aperture)  # (R, M): per-key light weights
    to = _view_nodes(g, do, aperture)  # (R|1, T, M)
    n = clamp_index(g.r_n + dn).reshape(-1)  # (C K)

    def part(r: model.FilletRays) -> Array:  # (R, M, T, C K) from some of the rays
        lead1 = jax.tree_util.tree_map(lambda a: a[:, None], r)  # (G, 1, 2, n[, B])
        w = model.fillet_ray_power(lead1, n)[g.r_geo]  # (R, M, C K, 2, n)
        th = r.theta_o[g.r_geo]  # (R, M, 2, n)
        kern = model.hemisphere_gaussian(
            jnp.swapaxes(to, -1, -2)[..., None, None],
            th[:, :, None],
            sigma_k[:, None, None, None, None],
        )  # (R, M, T, 2, n)
        return jnp.einsum("rmkpn,rmtpn->rmtk", w, kern)

    n_rays = rays.weight.shape[-1]
    per_ray = _fillet_bytes_per_ray(g, to.shape[-2], n.size, rays.weight.dtype.itemsize)
    size = _ray_chunk(n_rays, per_ray)
    if size == n_rays:
        rho = part(rays)
    else:  # chunk by chunk: one pass would hold (R, M, C K, 2, n) at once
        keys, nodes, views = g.r_geo.shape[0], g.r_geo.shape[1], to.shape[-2]
        zero = jnp.zeros((keys, nodes, views, n.size), sigma_k.dtype)
        rho, _ = jax.lax.scan(lambda acc, r: (acc + part(r), None), zero,
                              model.split_rays(rays, size))  # fmt: skip
    rho = rho.reshape(*rho.shape[:-1], *g.r_w.shape)
    band = jnp.einsum("ck,rmtck->rmtc", g.r_w, rho)
    conv = model.view_conversion(g.r_to[..., None], to)  # (R|1, T, M)
    dw = dw[:, :, None] * jnp.swapaxes(conv, -1, -2)  # (R, M, T)
    return jnp.einsum("rmtc,rmt->rtc", band, dw)


FILLET_CHUNK_BYTES = 64 * 2**20
"""The fillet correction's contraction over the rays holds, per ray, the ray power at every
(key, light node, index sample, lane) and the kernel at every (key, light node, view, lane);
above this many bytes for all rays at once it is summed over chunks of rays (`lax.scan`), so
that the accurate knobs (5 nm sampling, 4096 rays) on a photo folder, which would need tens of
GB in one pass, fit in memory; the balanced ones stay in one pass."""


def _fillet_bytes_per_ray(g: EvaluationGrid, views: int, samples: int, itemsize: int) -> int:
    """Bytes per ray of `_fillet_impl`'s arrays: the power per geometry and gathered to the keys'
    light nodes, the kernel (two lanes each)."""
    keys, nodes = g.r_geo.shape
    geometries = g.g_ti.shape[0]
    return 2 * itemsize * (keys * nodes * (samples + views) + geometries * samples)


def _ray_chunk(n_rays: int, bytes_per_ray: int, budget: int | None = None) -> int:
    """The rays per chunk: all of them when they fit `budget` (default `FILLET_CHUNK_BYTES`),
    else the largest divisor of `n_rays` that does (at least 1)."""
    budget = FILLET_CHUNK_BYTES if budget is None else budget
    if n_rays * bytes_per_ray <= budget:
        return n_rays
    fit = max(budget // max(bytes_per_ray, 1), 1)
    return max(d for d in range(1, min(fit, n_rays) + 1) if n_rays % d == 0)


def _fillet_rays(
    g: EvaluationGrid, radius_um: Array, fillet_um: Array, cfg: tuple
) -> model.FilletRays:
    """The rays of each distinct geometry (G) at radii (`radius_um`, `fillet_um`), scalars or
    one per geometry."""
    r, rf = jnp.broadcast_arrays(radius_um, fillet_um, g.g_ti)[:2]
    return model.fillet_rays(g.g_ti, g.g_b2, g.g_layer, r, rf, rays=cfg[2], bounces=cfg[3])


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def filleted_grid_density(
    sigma_k: Array, dn: Array, radius_um: Array, fillet_um: Array, cfg: tuple, g: EvaluationGrid
) -> Array:
    """The rounded grid density plus the fillet correction, `(R, T, C)`; `cfg = (aperture,
    resolution, rays, bounces)`. The rays are traced once per distinct geometry (G), not per
    key, view or channel.

    JVP in four directions (all widths together, `delta_n`, `r`, `r_f`, as
    `rounded_grid_density`): the rounded part and the correction's widths and index
    derivatives by forward mode with the rays fixed (they do not move a ray); the correction's
    `r` and `r_f` derivatives by differences between traces at
    `stairfit.model.fillet_difference_points` (docs/rounded.md §11), four extra traces of the G
    geometries whatever the number of parameters. The grid arrays `g` are data."""
    rays = _fillet_rays(g, radius_um, fillet_um, cfg)
    return _rounded_impl(sigma_k, dn, radius_um, cfg[:2], g) + _fillet_impl(
        sigma_k, dn, rays, cfg, g
    )


@filleted_grid_density.defjvp
def _filleted_grid_jvp(cfg: tuple, primals: tuple, tangents: tuple) -> tuple[Array, Array]:
    """Four ray pairs traced in one batched call (one tracer in the compiled program, issue
    14): the primal `(r, r_f)` against `(r, 0)`; `r`'s upper and lower points, each against its
    own `r_f = 0`; and `r_f`'s upper point against its lower one directly (the difference of
    the two corrections, `stairfit.model.fillet_rays`)."""
    sigma_k, dn, radius_um, fillet_um, g = primals
    t_sigma, t_dn, t_r, t_rf, _ = tangents
    radii = jnp.broadcast_arrays(radius_um, fillet_um, g.g_ti)[:2]
    pts = model.fillet_difference_points(g.g_ti, g.g_b2, g.g_layer, *radii)
    (r_lo, r_hi), (f_lo, f_hi) = pts[3], pts[4]
    r, rf = radii
    zero = jnp.zeros_like(rf)
    r_at = jnp.stack([r, r_hi, r_lo, r])
    rf_at = jnp.stack([rf, rf, rf, f_hi])
    stack = lambda a: jnp.broadcast_to(a, r_at.shape)  # noqa: E731
    rays_all = model.fillet_rays(
        stack(g.g_ti), stack(g.g_b2), stack(g.g_layer), r_at, rf_at, rays=cfg[2], bounces=cfg[3],
        other_fillet_um=jnp.stack([zero, zero, zero, f_lo]),
    )  # fmt: skip
    rays = jax.tree_util.tree_map(lambda a: a[0], rays_all)

    def rounded(eps: Array) -> Array:
        return _rounded_impl(sigma_k + eps[0], dn + eps[1], radius_um + eps[2], cfg[:2], g)

    def fillet(eps: Array) -> Array:  # the rays fixed: widths and index only
        return _fillet_impl(sigma_k + eps[0], dn + eps[1], rays, cfg, g)

    value, jac = _value_and_jac(rounded, jnp.zeros(3, dtype=sigma_k.dtype))
    value_f, jac_f = _value_and_jac_forward(fillet, jnp.zeros(2, dtype=sigma_k.dtype))
    value = value + value_f
    d_sigma, d_dn, d_r = jac[..., 0] + jac_f[..., 0], jac[..., 1] + jac_f[..., 1], jac[..., 2]
    tangent = d_sigma * t_sigma[:, None, None] + d_dn * t_dn + d_r * t_r
    moved = jax.tree_util.tree_map(lambda a: a[1:], rays_all)
    c = jax.vmap(lambda rr: _fillet_impl(sigma_k, dn, rr, cfg, g))(moved)  # (3, R, T, C)
    key_geo = g.r_geo[:, 0]  # a key's aperture nodes share its wedge and layer, so its steps
    for slope, t, (lo, hi) in ((c[0] - c[1], t_r, pts[3]), (c[2], t_rf, pts[4])):
        tangent = tangent + slope * model.difference_scale(lo, hi, t)[key_geo, None, None]
    return value, tangent


def filleted_density(p: Params, data: Data, static: Static) -> Array:
    """Band- and aperture-averaged density (1/rad) of the filleted model at every row
    (`filleted_grid_density`, then read per row; `p.sigma_rad` one width per wedge). Unlike
    `stairfit.model.brdf_filleted` the sum is not clipped at 0 per wavelength and node (the
    rounded part is): the two differ only where the correction's quadrature noise exceeds
    the density, in far tails."""
    rays = model.FILLET_RAYS if static.fillet_rays is None else static.fillet_rays
    cfg = (static.aperture, static.resolution, rays, model.FILLET_BOUNCES)
    dens = filleted_grid_density(
        p.sigma_rad[data.r_wedge], p.delta_n, p.edge_radius_um, p.fillet_radius_um, cfg, _grid(data)
    )
    return dens[data.r_key, data.r_t, data.r_c]


def model_values(z: Array, static: Static, data: Data) -> tuple[Array, Params]:
    """(model relative radiance per row, physical parameters) [conventions §9]; the widths in
    the returned `Params` are one per wedge."""
    p = static.layout.unpack(physical(z, static, data), data.sigma_source)
    if static.filleted:
        dens = filleted_density(p, data, static)
    elif static.rounded:
        dens = rounded_density(p.sigma_rad, p.delta_n, p.edge_radius_um, data, static)
    else:
        dens = sharp_density(p.sigma_rad, p.delta_n, data, static.aperture)
    return model.radiance(dens, data.theta_i, data.theta_o, p.scale, p.floor), p


def variance(m: Array, p: Params, static: Static, data: Data) -> Array:
    """Per-row variance `stderr^2 + (model_error_frac * model)^2` (or `stderr^2`): the
    diagonal of the covariance."""
    extra = model_error_variance(m, p, static)
    return data.stderr**2 if extra is None else data.stderr**2 + extra


def model_error_variance(m: Array, p: Params, static: Static) -> Array | None:
    """Per-row `(model_error_frac * model)^2`, or None without the model-error term."""
    return (p.model_error_frac * m) ** 2 if static.model_error else None


def cholesky(extra_var: Array | None, data: Data) -> Array:
    """Per group, the Cholesky factor of `S R S + diag(extra_var)` (`_whiten.group_cholesky`)."""
    return group_cholesky(data.stderr, extra_var, data.grp_rows, data.grp_mask, data.grp_corr)


def whitened(resid: Array, chol: Array, data: Data) -> Array:
    """`L^-1 (value - model)` per group, `(Gr, 3)` (`_whiten.whiten`)."""
    return whiten(chol, resid, data.grp_rows, data.grp_mask)


def _log_det_excess(chol: Array, data: Data) -> Array:
    """Per group, `log det C - log det (S R S) >= 0`: what the model-error term adds."""
    chol0 = cholesky(None, data)
    return 2.0 * jnp.sum(log_diag(chol, data.grp_mask) - log_diag(chol0, data.grp_mask), axis=1)


def _sqrt_pos(a: Array) -> Array:
    """`sqrt(a)` for `a > 0`, else 0, with finite derivatives at 0 (double where)."""
    pos = a > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, a, 1.0)), 0.0)


def residuals(z: Array, args: tuple[Static, Data]) -> Array:
    """Whitened residuals for optimistix: the module-level function every fit shares.

    Independent rows: `use * (value - model) / sqrt(variance)`; with the model-error term, a
    second block `use * sqrt(log(variance / stderr^2))` makes the sum of squares equal to
    `-2 log L + const`, so that least squares is maximum likelihood (docs/fitting.md).
    Correlated rows (`static.correlated`): `L^-1 (value - model)` per group, and with the
    model-error term one entry per group, `sqrt(log det C - log det S R S)`.
    """
    static, data = args
    m, p = model_values(z, static, data)
    if static.correlated:
        chol = cholesky(model_error_variance(m, p, static), data)
        w = whitened(data.value - m, chol, data).ravel()
        if not static.model_error:
            return w
        return jnp.concatenate([w, _sqrt_pos(_log_det_excess(chol, data))])
    var = variance(m, p, static, data)
    r = data.use * (data.value - m) / jnp.sqrt(var)
    if not static.model_error:
        return r
    extra = _sqrt_pos(jnp.log(var / data.stderr**2))
    return jnp.concatenate([r, data.use * extra])


def log_likelihood_z(z: Array, static: Static, data: Data) -> Array:
    """Gaussian log-likelihood of the used rows at `z` (full normalisation)."""
    m, p = model_values(z, static, data)
    if static.correlated:
        chol = cholesky(model_error_variance(m, p, static), data)
        return correlated_log_likelihood(whitened(data.value - m, chol, data), chol, data)
    var = variance(m, p, static, data)
    terms = (data.value - m) ** 2 / var + jnp.log(2.0 * jnp.pi * var)
    return -0.5 * jnp.sum(data.use * terms)


def correlated_log_likelihood(w: Array, chol: Array, data: Data) -> Array:
    """`-(1/2) [sum w^2 + log det C + n log 2 pi]` from the whitened residuals `w` and the
    groups' Cholesky factors (`n` the used rows)."""
    n = jnp.sum(data.grp_mask)
    logdet = 2.0 * jnp.sum(log_diag(chol, data.grp_mask))
    return -0.5 * (jnp.sum(w * w) + logdet + n * jnp.log(2.0 * jnp.pi))


def mean_and_log_variance(z: Array, static: Static, data: Data) -> tuple[Array, Array]:
    """(model, log variance) per row: what the Fisher information is built from."""
    m, p = model_values(z, static, data)
    return m, jnp.log(variance(m, p, static, data))


@functools.partial(jax.jit, static_argnums=2)
def measurement_whitened(resid: Array, data: Data, correlated: bool) -> Array:
    """Per row, `resid` (e.g. value - model) whitened with the measurement covariance alone
    (no model-error term): `resid / stderr` for independent rows, each row's component of
    `L0^-1 resid` (`S R S = L0 L0^T` per group) for correlated ones; 0 for unused rows. Called
    on concrete arrays (reports, the accuracy check), so compiled once here rather than op by
    op."""
    if not correlated:
        return jnp.where(data.use > 0, resid / data.stderr, 0.0)
    w = whitened(resid, cholesky(None, data), data)
    return scatter(w, data.grp_rows, resid.shape[0])
