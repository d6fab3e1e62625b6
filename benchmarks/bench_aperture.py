"""Benchmark: the light-aperture average across a kink of the lobe weights (issue 12).

The sharp lobe weights have kinks in theta_i at `-beta2`, `90 deg - 2 beta2` and
`90 deg - beta2` [conventions §3] (and the node clip at `+-90 deg`, conventions §9). A Gauss rule
with the same offsets on every row converges slowly (about `1 / n^2`) where the light's interval
`theta_i +- h` holds one. This compares light-node rules on the sharp model's band density (one
wavelength, index 1.57, a point view) averaged over the light:

* `plain`: the rule before issue 12's fix: Gauss-Legendre in the offset `x = (t - theta_i) / h`
  for the uniform light, Gauss-Chebyshev of the 2nd kind for the disk (semicircle `sqrt(1-x^2)`).
* `split`: the interval cut at the kink (at its middle where it holds none) into two pieces,
  `ceil(n/2)` nodes on the longer piece and `floor(n/2)` on the other: Gauss-Legendre in `x`
  (uniform) or in `phi` with `x = cos(phi)` and weight `sin^2(phi)` (disk).
* `hybrid`: `plain` on rows without a kink inside the interval, `split` on the others.
* `model`: what `stairfit.model.light_nodes` places (the rule chosen from this benchmark).

The reference is a dense midpoint rule in `x` with `--dense` cells (the disk's cells weighted by
their exact semicircle mass), independent of the rules under test; its own error is estimated
against half as many cells and reported. Errors: the band density relative to itself (rows whose
density is at least 1e-3 of its curve's maximum over theta_o) and the radiance with a diffuse
floor (`floor / scale = 0.002`, the independent renderer's, conventions §9) relative to itself,
at every row. Rows are split into "kink" rows (a kink inside the light's interval or at its end)
and the others. Grid: beta2 10/20/30/45/60 deg; theta_i at each kink and at offsets 0.5, 0.9 and
1 half-width either side of it, plus -30/0/30 deg; theta_o -80..80 deg in steps of 20 plus
+-80; sigma 2/6/12 deg; light half-widths 0.1/0.3/1/3 deg; both shapes; n = 1..8.

    python benchmarks/bench_aperture.py [--dense 2000] [--out benchmarks/results/aperture.md]
    python benchmarks/bench_aperture.py --timing [--repeats 30]

`--timing`: the run-time cost on the fit's grid instead. `fitting._forward._sharp_grid_impl`
(per-row light nodes) against a copy of it with the fixed offsets it had before (the baseline),
timed interleaved in the same run (`_timing.interleaved_medians`), value and the two-direction
Jacobian the fit's custom JVP takes; compilation reported apart. Grid: the paper setup's
(6 wedges lit at theta_i = 0, 16 views, 3 channels, one wavelength each), a 0.6-deg round light
and a face spread of 1 deg, 2 and 3 nodes per axis (the balanced and accurate presets').
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.special

from stairfit import model
from stairfit.fitting import _forward

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import first_call_seconds, interleaved_medians

jax.config.update("jax_enable_x64", True)

DEG = np.pi / 180
INDEX = 1.57
FLOOR_OVER_SCALE = 0.002
BETA2_DEG = (10.0, 20.0, 30.0, 45.0, 60.0)
OFFSETS_HW = (0.0, -0.5, 0.5, -0.9, 0.9, -1.0, 1.0)
GENERIC_TI_DEG = (-30.0, 0.0, 30.0)
THETA_O_DEG = (-80.0, -60.0, -40.0, -20.0, 0.0, 20.0, 40.0, 60.0, 80.0)
SIGMA_DEG = (2.0, 6.0, 12.0)
HALF_WIDTH_DEG = (0.1, 0.3, 1.0, 3.0)
SHAPES = ("uniform", "disk")
NODES = tuple(range(1, 9))
DENSITY_CUTOFF = 1e-3
RULES = ("plain", "split", "hybrid", "hybrid_gj") + (
    ("model",) if hasattr(model, "light_nodes") else ()
)


def kinks_rad(beta2: float) -> np.ndarray:
    """Where the integrand has a kink in theta_i [conventions §3, §9]."""
    return np.array([-beta2, np.pi / 2 - 2 * beta2, np.pi / 2 - beta2, np.pi / 2, -np.pi / 2])


@jax.jit
def integrand(t: jax.Array, b2: jax.Array, sigma: jax.Array, to: jax.Array) -> jax.Array:
    """Band density summed over the lobes at light angle `t` (clipped to the hemisphere)."""
    t = jnp.clip(t, -jnp.pi / 2, jnp.pi / 2)
    ratio = model.lobe_weights(t, b2) * model.lobe_fresnel(t, b2, INDEX)
    kern = model.hemisphere_gaussian(to[..., None], model.lobe_directions(t, b2), sigma[..., None])
    return jnp.sum(ratio * kern, axis=-1)


def plain_rule(n: int, shape: str) -> tuple[np.ndarray, np.ndarray]:
    """Offsets x in [-1, 1] and weights (sum 1) of the rule before the fix."""
    if shape == "disk":
        k = np.arange(1, n + 1)
        x, w = np.cos(k * np.pi / (n + 1)), np.sin(k * np.pi / (n + 1)) ** 2
    else:
        x, w = np.polynomial.legendre.leggauss(n)
    return x, w / w.sum()


def piece(
    a: float, b: float, m: int, shape: str, exact_mass: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """m Gauss-Legendre nodes on one piece: [a, b] in x (uniform) or in phi (disk). With
    `exact_mass` (disk), the piece's weights are scaled to its exact semicircle mass, and one
    node sits at the piece's centroid (the one-point Gauss rule of the weight)."""
    if m == 0:
        return np.zeros(0), np.zeros(0)
    g, wg = np.polynomial.legendre.leggauss(m)
    u = 0.5 * (a + b) + 0.5 * (b - a) * g
    w = 0.5 * (b - a) * wg
    if shape != "disk":
        return u, w / 2.0
    x, w = np.cos(u), w * np.sin(u) ** 2
    if exact_mass:
        mass = 0.5 * ((b - np.sin(b) * np.cos(b)) - (a - np.sin(a) * np.cos(a)))
        w = w * mass / w.sum() if w.sum() > 0 else np.full(m, mass / m)
        if m == 1:
            x = np.array([(np.sin(b) ** 3 - np.sin(a) ** 3) / 3.0 / mass]) if mass > 0 else x
    return x, w / (np.pi / 2)


def split_rule(
    n: int, shape: str, k: float | None, exact_mass: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Two pieces meeting at x = k (the middle when None); the longer gets ceil(n/2) nodes."""
    if n == 1:
        return np.zeros(1), np.ones(1)
    if shape == "disk":
        c = np.pi / 2 if k is None else math.acos(k)
        ends = ((0.0, c), (c, np.pi))
    else:
        c = 0.0 if k is None else k
        ends = ((-1.0, c), (c, 1.0))
    lengths = [b - a for a, b in ends]
    order = np.argsort(lengths)[::-1]
    counts = {int(order[0]): (n + 1) // 2, int(order[1]): n // 2}
    parts = [piece(*ends[j], counts[j], shape, exact_mass) for j in range(2)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def jacobi_split(n: int, k: float) -> tuple[np.ndarray, np.ndarray]:
    """The disk's two pieces [-1, k] and [k, 1], each with the Gauss-Jacobi rule of its end's
    square root (`(1+y)^(1/2)` left, `(1-y)^(1/2)` right), the other root (smooth on the piece)
    evaluated at the nodes; each piece's weights scaled to its exact semicircle mass and a
    one-node piece's node at its exact centroid. The longer piece gets ceil(n/2) nodes."""
    if n == 1:
        return np.zeros(1), np.ones(1)
    sgn, kp = (-1.0 if k > 0 else 1.0), -abs(k)
    mass = 0.5 * (kp * math.sqrt(1 - kp * kp) + math.asin(kp))  # int_0^kp sqrt(1-x^2) dx
    moment = (1 - kp * kp) ** 1.5 / 3
    parts = []
    for m, (alpha, beta), lo, hi, pmass, pmoment in (
        ((n + 1) // 2, (0.5, 0.0), kp, 1.0, np.pi / 4 - mass, moment),
        (n // 2, (0.0, 0.5), -1.0, kp, np.pi / 4 + mass, -moment),
    ):
        y, wy = scipy.special.roots_jacobi(m, alpha, beta)
        half = 0.5 * (hi - lo)
        x = lo + half * (1 + y)
        w = half**1.5 * wy * np.sqrt(1 + x if alpha else 1 - x)
        if alpha or 1 + kp > 1e-3:  # a tiny short piece keeps its Gauss-Jacobi mass
            w = w * pmass / w.sum()
            x = np.array([pmoment / pmass]) if m == 1 else x
        parts.append((x, w))
    x = sgn * np.concatenate([p[0] for p in parts])
    w = np.concatenate([p[1] for p in parts])
    return x, w / w.sum()


def inside_kink(ti: float, b2: float, hw: float) -> float | None:
    """The kink nearest theta_i within the light's interval (closed), as x; else None."""
    x = (kinks_rad(b2) - ti) / hw
    x = x[np.abs(x) <= 1.0 + 1e-12]
    return None if x.size == 0 else float(np.clip(x[np.argmin(np.abs(x))], -1.0, 1.0))


def rule_nodes(rule: str, n: int, shape: str, ti: float, b2: float, hw: float):
    """Light angles and weights of one rule on one row."""
    k = inside_kink(ti, b2, hw)
    if rule == "plain" or (rule.startswith("hybrid") and (k is None or abs(k) >= 1.0)):
        x, w = plain_rule(n, shape)
    elif rule == "hybrid_gj" and shape == "disk":
        x, w = jacobi_split(n, k)
    elif rule in ("split", "hybrid", "hybrid_gj"):
        x, w = split_rule(n, shape, None if k is None or abs(k) >= 1.0 else k)
    else:  # the model's
        ap = model.Aperture(hw, 0.0, n, light_shape=shape)
        t, w = model.light_nodes(jnp.asarray([ti]), jnp.asarray([b2]), ap)
        # light index outer, viewing index inner (a zero viewing spread: n equal copies)
        return np.asarray(t)[0].reshape(n, -1)[:, 0], np.asarray(w)[0].reshape(n, -1).sum(axis=1)
    return ti + hw * x, w


def dense_reference(shape: str, ti: float, hw: float, cells: int):
    """Midpoint cells in x; the disk's cells weighted by their exact semicircle mass."""
    edges = np.linspace(-1.0, 1.0, cells + 1)
    mid = 0.5 * (edges[1:] + edges[:-1])
    if shape == "disk":
        cdf = (edges * np.sqrt(1 - edges**2) + np.arcsin(edges)) / np.pi + 0.5
        w = np.diff(cdf)
    else:
        w = np.full(cells, 1.0 / cells)
    return ti + hw * mid, w


def light_configs() -> list[tuple[float, float, float, str, bool]]:
    """(beta2, theta_i, half-width, shape, kink row) of every light configuration."""
    out = []
    for b2 in np.array(BETA2_DEG) * DEG:
        for hw in np.array(HALF_WIDTH_DEG) * DEG:
            tis = [ti * DEG for ti in GENERIC_TI_DEG]
            for kink in kinks_rad(b2)[:3]:
                tis += [kink + o * hw for o in OFFSETS_HW]
            for ti in tis:
                if abs(ti) > 89.0 * DEG:
                    continue
                for shape in SHAPES:
                    out.append((b2, ti, hw, shape, inside_kink(ti, b2, hw) is not None))
    return out


def average(t: np.ndarray, w: np.ndarray, b2: float) -> np.ndarray:
    """Light-averaged density on the (sigma, theta_o) grid."""
    sig = jnp.asarray(SIGMA_DEG)[:, None, None] * DEG
    to = jnp.asarray(THETA_O_DEG)[None, :, None] * DEG
    f = integrand(jnp.asarray(t)[None, None, :], jnp.full((1, 1, 1), b2), sig, to)
    return np.asarray(f) @ w


def run(dense: int) -> dict:
    configs = light_configs()
    rules = RULES
    rows = []  # (shape, kink, rule, n, rel density err array, rel radiance err array)
    ref_err = 0.0
    to = np.array(THETA_O_DEG)[None, :] * DEG
    cases_4580 = {}
    for b2, ti, hw, shape, kink in configs:
        ref = average(*dense_reference(shape, ti, hw, dense), b2)
        half = average(*dense_reference(shape, ti, hw, dense // 2), b2)
        spec_scale = np.cos(ti) / np.cos(to)
        rad_ref = spec_scale * ref + FLOOR_OVER_SCALE * np.cos(ti)
        big = ref >= DENSITY_CUTOFF * ref.max(axis=1, keepdims=True)
        ref_err = max(ref_err, float(np.max(np.abs(half - ref)[big] / ref[big])))
        for rule in rules:
            for n in NODES:
                q = average(*rule_nodes(rule, n, shape, ti, b2, hw), b2)
                d = np.abs(q - ref)[big] / ref[big]
                r = np.abs(spec_scale * (q - ref)) / rad_ref
                rows.append((shape, kink, rule, n, d, r.ravel(), hw))
                if abs(b2 - 45 * DEG) < 1e-9 and abs(ti) < 1e-12 and abs(hw - 0.3 * DEG) < 1e-9:
                    j = THETA_O_DEG.index(80.0)
                    s = SIGMA_DEG.index(6.0)
                    cases_4580[(shape, rule, n)] = (
                        (q[s, j] - ref[s, j]) / ref[s, j],
                        spec_scale[0, j] * (q[s, j] - ref[s, j]) / rad_ref[s, j],
                    )
    return {"rows": rows, "ref_err": ref_err, "n_configs": len(configs), "c4580": cases_4580}


def summary(res: dict) -> str:
    lines = [
        "# Light-aperture quadrature across a kink (benchmarks/bench_aperture.py)",
        "",
        f"{res['n_configs']} light configurations x {len(SIGMA_DEG)} sigma x "
        f"{len(THETA_O_DEG)} theta_o; reference: dense midpoint, its own error (against half "
        f"the cells) at most {res['ref_err']:.1e} relative on the density rows counted.",
        "",
        "Max (and 95th percentile) relative error of the band density (rows >= 1e-3 of their "
        "curve's maximum) and of the radiance with the diffuse floor (floor/scale = "
        f"{FLOOR_OVER_SCALE}), per light shape, row kind and rule, against n light nodes.",
    ]
    sections = [(s, k, HALF_WIDTH_DEG[-1]) for s in SHAPES for k in (True, False)]
    sections += [(s, True, 1.0) for s in SHAPES]
    for shape, kink, hw_max in sections:
        if True:
            small = f", half-width <= {hw_max} deg" if hw_max < HALF_WIDTH_DEG[-1] else ""
            lines += ["", f"## {shape} light, {'kink' if kink else 'no-kink'} rows{small}", ""]
            lines.append("| rule | quantity | " + " | ".join(f"n={n}" for n in NODES) + " |")
            lines.append("|---|---|" + "---|" * len(NODES))
            for rule in RULES:
                for qi, qname in ((4, "density"), (5, "radiance")):
                    cells = []
                    for n in NODES:
                        sel = [
                            r[qi]
                            for r in res["rows"]
                            if r[:4] == (shape, kink, rule, n) and r[6] <= hw_max * DEG + 1e-12
                        ]
                        v = np.concatenate(sel)
                        cells.append(f"{v.max():.1e} ({np.percentile(v, 95):.1e})")
                    lines.append(f"| {rule} | {qname} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## The issue's case: beta2 45 deg, theta_i 0 (its kink 90 - 2 beta2), theta_o 80 deg,"
        " sigma 6 deg, half-width 0.3 deg",
        "",
        "| shape | rule | " + " | ".join(f"n={n}" for n in NODES) + " |",
        "|---|---|" + "---|" * len(NODES),
    ]
    for shape in SHAPES:
        for rule in RULES:
            cells = [f"{100 * res['c4580'][(shape, rule, n)][0]:+.2f}%" for n in NODES]
            lines.append(f"| {shape} | {rule} (density) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plain_sharp_grid(
    sigma_k: jax.Array, dn: jax.Array, aperture: model.Aperture, g: _forward.EvaluationGrid
) -> jax.Array:
    """`_forward._sharp_grid_impl` as it was before issue 12 (the same light offsets on every
    row, static weights; the direct-Fresnel branch): the timing baseline."""
    di, do, dw = (jnp.asarray(a, g.r_ti.dtype) for a in aperture.nodes())
    ti = model.node_angles(g.r_ti, di)
    to = _forward._view_nodes(g, do, aperture)
    b2 = g.r_b2[:, None]
    weight = model.lobe_weights(ti, b2)
    kernel = model.hemisphere_gaussian(
        to[..., None], model.lobe_directions(ti, b2)[:, None], sigma_k[:, None, None, None]
    )
    n = g.r_n + dn
    fresnel = model.lobe_fresnel(ti[:, :, None, None], b2[:, :, None, None], n)
    band = jnp.einsum("ck,rmckl->rmcl", g.r_w, fresnel)
    return jnp.einsum("rml,rtml,rmcl,m->rtc", weight, kernel, band, dw)


def timing(repeats: int) -> str:
    """Ratio of the new grid evaluation's time to the old one's (value + 2-direction JVP)."""
    b2 = jnp.asarray([10.0, 20.0, 30.0, 40.0, 45.0, 60.0]) * DEG
    to = jnp.linspace(-80.0, 80.0, 16)[None, :] * DEG
    g = _forward.EvaluationGrid(
        r_ti=jnp.zeros(6), r_b2=b2, r_n=jnp.full((3, 1), INDEX), r_w=jnp.ones((3, 1)),
        r_to=to, r_so=jnp.ones_like(to), r_geo=jnp.zeros((6, 1), int), g_ti=jnp.zeros(1),
        g_b2=jnp.zeros(1), g_layer=jnp.zeros(1),
    )  # fmt: skip
    sigma = jnp.full(6, 6.0 * DEG)
    lines = [
        "## Run-time cost on the fit's grid (`--timing`)",
        "",
        "| nodes per axis | new / old (value + JVP) | compile new / old (s) |",
        "|---|---|---|",
    ]
    for n in (2, 3):
        ap = model.Aperture(0.3 * DEG, 0.5 * DEG, n, foreshortened=True, light_shape="disk")
        fns = {}
        compile_s = {}
        for name, impl in (("new", _forward._sharp_grid_impl), ("old", _plain_sharp_grid)):

            def value_and_jvp(eps: jax.Array, impl=impl, ap=ap) -> tuple[jax.Array, jax.Array]:
                return jax.jvp(lambda e: impl(sigma + e[0], e[1], ap, g), (eps,), (jnp.ones(2),))

            f = jax.jit(value_and_jvp)
            eps = jnp.zeros(2)
            compile_s[name] = first_call_seconds(lambda f=f, eps=eps: f(eps))
            fns[name] = lambda f=f, eps=eps: f(eps)
        med = interleaved_medians(fns, repeats)
        lines.append(
            f"| {n} | {med['new'] / med['old']:.2f} ({1e6 * med['new']:.0f} / "
            f"{1e6 * med['old']:.0f} us) | {compile_s['new']:.2f} / {compile_s['old']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dense", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--timing", action="store_true")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    text = timing(args.repeats) if args.timing else summary(run(args.dense))
    print(text)
    if args.out:  # the timing table is appended to the accuracy tables
        with args.out.open("a" if args.timing else "w") as fh:
            fh.write(("\n" if args.timing else "") + text)


if __name__ == "__main__":
    main()
