"""Figure: with rounded layer edges the 30 and 60 degree wedges stop being mirror images.

The paper's Fig. 9 geometry: theta_i = 0, 5-degree Gaussian broadening, n = 1.46, 150 um
layers. The 60-degree wedge is drawn mirrored (its rho at -theta_o), so that the sharp model's
symmetry shows as two identical curves [conventions §1-§5]. Top row: the in-plane reflectance
density rho (1/rad) for r = 0 and two radii, the same r on both wedges. Bottom row: their
ratio, 60 (mirrored) / 30: above 1 where the finer 60-degree cell, on which one radius weighs
sqrt(3) times more, scatters more off its lobes, below 1 at its dimmer facet lobe (the
direction the paper's photographs suggest, Sec. 3.3; docs/rounded.md §9). Degrees on the axes.

    python benchmarks/figure_rounded.py [--out docs/figures/rounded_30_vs_60.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from stairfit import model

DEG = np.pi / 180
LAYER_UM = 150.0
N_INDEX = 1.46
SIGMA_DEG = 5.0
THETA_I_DEG = 0.0
RADII_UM = (0.0, 30.0, 60.0)
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "figures" / "rounded_30_vs_60.png"


def curves(radius_um: float, theta_o_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rho (1/rad) of the 30-degree wedge at theta_o and of the 60-degree one at -theta_o."""
    fn = jax.jit(model.brdf_rounded)
    to = jnp.asarray(theta_o_deg * DEG)
    ti = THETA_I_DEG * DEG
    rho30 = fn(ti, to, 30 * DEG, N_INDEX, SIGMA_DEG * DEG, LAYER_UM, radius_um)
    rho60 = fn(-ti, -to, 60 * DEG, N_INDEX, SIGMA_DEG * DEG, LAYER_UM, radius_um)
    return np.asarray(rho30), np.asarray(rho60)


def figure() -> Figure:
    """The 2 x len(RADII_UM) panel figure."""
    to = np.linspace(-90.0, 90.0, 721)
    fig, axes = plt.subplots(
        2, len(RADII_UM), figsize=(4.3 * len(RADII_UM), 6.2), sharex=True, squeeze=False
    )
    top = 0.0
    for j, r in enumerate(RADII_UM):
        a, b = curves(r, to)
        top = max(top, float(a.max()), float(b.max()))
        ax = axes[0, j]
        ax.plot(to, a, color="tab:blue", lw=1.6, label="30 deg wedge")
        ax.plot(to, b, color="tab:red", lw=1.2, ls="--", label="60 deg wedge, mirrored")
        r_max60 = float(model.max_edge_radius(60 * DEG, LAYER_UM))
        kind = "sharp" if r == 0 else f"r/l1 = {r / LAYER_UM:.2g}, r/r_max(60) = {r / r_max60:.2g}"
        ax.set_title(f"edge radius {r:g} um ({kind})", fontsize=10)
        ax.set_ylabel("rho (1/rad)" if j == 0 else "")
        # (left out where rho 30 is below 1e-5 of its peak: a ratio of Gaussian tails)
        ratio = np.where(a > 1e-5 * a.max(), b / np.where(a > 0, a, 1.0), np.nan)
        ax2 = axes[1, j]
        ax2.axhline(1.0, color="0.6", lw=0.8)
        ax2.axhline(np.sqrt(3.0), color="0.6", lw=0.8, ls=":")
        ax2.plot(to, ratio, color="k", lw=1.2)
        ax2.set_ylim(0.5, 2.2)
        ax2.set_ylabel("rho 60 (mirrored) / rho 30" if j == 0 else "")
        if j == len(RADII_UM) - 1:
            ax2.text(-88, np.sqrt(3.0) + 0.03, "sqrt(3): the cells' size ratio", fontsize=8)
    for ax in axes[0]:
        ax.set_ylim(0.0, 1.08 * top)
        ax.set_xlim(-90, 90)
        ax.set_xticks(np.arange(-90, 91, 30))
    axes[0, 0].legend(loc="upper left", fontsize=8)
    fig.supxlabel("theta_o (deg) of the 30 deg wedge; the 60 deg wedge is shown at -theta_o")
    fig.suptitle(
        f"theta_i = {THETA_I_DEG:g} deg, sigma = {SIGMA_DEG:g} deg, n = {N_INDEX:g}, "
        f"l1 = {LAYER_UM:g} um: rounded edges break the 30/60 deg mirror symmetry",
        fontsize=11,
    )
    fig.tight_layout()
    return fig


def main() -> None:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="PNG to write")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)  # [conventions §10]
    fig = figure()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120)
    plt.close(fig)
    print(args.out)


if __name__ == "__main__":
    main()
