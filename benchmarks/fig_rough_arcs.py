"""docs/figures/rough_arcs_grazing_view.png: a 65-deg wedge's density near a grazing view, the
3-D tracer (tests/raytrace3d.py) against the lab model with the rough arcs' single reflection
counted where the camera sees the arc (`arc_single_seen`) and, for comparison, where its mirror
ray escapes (the rounded model's `tip` lobe spread by the kernel, as before). Prints the ratios
per bin. Usage: `python benchmarks/fig_rough_arcs.py OUT.png` (about a minute)."""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
from raytrace import Staircase  # noqa: E402
from raytrace3d import Rough, direction, trace3d  # noqa: E402

from stairfit import model  # noqa: E402
from stairfit.model._lab_rounded import _along, _band, _rounded_band  # noqa: E402

BETA2_DEG, LAYER_UM, RADIUS_UM = 65.0, 200.0, 40.0
ALPHA, KIND, LIGHT_DEG, INDEX = 0.1, "beckmann", -33.0, 1.53
EDGES = np.arange(50.0, 89.01, 1.5)
T = np.linspace(-0.6, 0.6, 601)


def binned(fn: Callable[[np.ndarray], jax.Array]) -> np.ndarray:
    """`fn(w_o)` (1/sr) integrated over `t_o` and averaged over each bin of the view."""
    c = np.sqrt(1.0 - T**2)
    out = []
    for a, b in itertools.pairwise(EDGES):
        views = a + (np.arange(5) + 0.5) * (b - a) / 5
        w_o = np.stack([np.stack([c * np.sin(np.radians(v)), T, c * np.cos(np.radians(v))], -1)
                        for v in views])  # fmt: skip
        out.append(np.mean(np.trapezoid(np.asarray(fn(w_o)), T, axis=-1)))
    return np.array(out)


def main(out: Path) -> None:
    b2 = math.radians(BETA2_DEG)
    w_i = direction(LIGHT_DEG, 0.0, light=True)
    st = Staircase(BETA2_DEG, LAYER_UM, tip_radius_um=RADIUS_UM)
    tr = trace3d(st, w_i, INDEX, rough=Rough(ALPHA, KIND), n_rays=400_000, seed=1)
    th = np.degrees(np.arctan2(tr.w_o[:, 0], tr.w_o[:, 2]))
    power = [tr.power[(th >= a) & (th < b)].sum() for a, b in itertools.pairwise(EDGES)]
    traced = np.array(power) / math.radians(1.5)

    def now(w_o: np.ndarray) -> jax.Array:
        return model.lab_density_rounded(w_i, w_o, b2, INDEX, ALPHA, LAYER_UM, RADIUS_UM, KIND)

    def before(w_o: np.ndarray) -> jax.Array:
        inc, view = model.projected_incidence(w_i), model.projected_view(w_o)
        geo = model.rounded_geometry(inc.theta, b2, LAYER_UM, RADIUS_UM)
        arcs = geo._replace(delta_weight=jnp.zeros_like(geo.delta_weight))
        full = jnp.full(view.theta.shape, 1.0)
        rho = _rounded_band(arcs, inc.theta * full, view.theta, b2 * full, _band(INDEX, None),
                            math.sqrt(2.0) * ALPHA * full, inc.t * full)  # fmt: skip
        w_ib = jnp.broadcast_to(jnp.asarray(w_i), w_o.shape)
        flats = model.rounded_flats(w_i, w_o, b2, INDEX, ALPHA, LAYER_UM, RADIUS_UM, KIND)
        return flats + rho * _along(w_ib, jnp.asarray(w_o), ALPHA * full, KIND)

    d_now, d_before = binned(now), binned(before)
    mid = 0.5 * (EDGES[1:] + EDGES[:-1])
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.plot(mid, traced, "ko", ms=4, label="3-D tracer (4e5 rays, 1.5-deg bins)")
    ax.plot(mid, d_now, "C0-", label="model: arcs counted where the camera sees them (now)")
    ax.plot(mid, d_before, "C3--", label="model: arcs counted where their mirror ray escapes")
    ax.set_xlabel("projected view angle theta_o' (deg from the face normal)")
    ax.set_ylabel("reflected power per radian of theta_o'")
    title = (f"{BETA2_DEG:g}-deg wedge, {LAYER_UM:g}-um layers, {RADIUS_UM:g}-um tips, "
             f"{KIND} alpha {ALPHA:g}, light {-LIGHT_DEG:g} deg uphill")  # fmt: skip
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    for m, a, b, c in zip(mid, traced, d_now, d_before, strict=True):
        if a > 0:
            print(f"{m:5.2f} deg: tracer {a:.5f}, model / tracer {b / a:.3f} (before {c / a:.3f})")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
