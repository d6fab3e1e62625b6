"""Figures of the model: BRDF maps (paper Fig. 3/8), diffuse curves (Fig. 5) and the colour of
the reflected light (Fig. 7). Degrees on every axis [conventions §1]; matplotlib's Agg backend.

These take physical parameters, not fits, so notebooks and the report share them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

DEG = np.pi / 180


def _brdf_jit(*args: Any) -> Any:
    """`model.brdf`, compiled once per call shape (eager evaluation is ~10x slower here)."""
    import jax

    from stairfit import model

    return jax.jit(model.brdf)(*args)


def brdf_map(
    beta2_deg: Sequence[float],
    n: complex | float = 1.46,
    sigma_deg: float = 0.0,
    step_deg: float = 0.5,
    title: str | None = None,
) -> Figure:
    """Paper Fig. 3 (sigma = 0: reflectance ratios on the lobe lines) or Fig. 8 (broadened
    density, 1/rad) on a theta_i x theta_o grid, one panel per wedge [conventions §3, §4]."""
    from matplotlib.colors import PowerNorm

    from stairfit import model

    grid = np.arange(-90, 90 + step_deg / 2, step_deg)
    fig, axes = plt.subplots(1, len(beta2_deg), figsize=(4.2 * len(beta2_deg), 3.8), squeeze=False)
    for ax, b in zip(axes[0], beta2_deg, strict=True):
        if sigma_deg > 0:
            ti, to = np.meshgrid(grid * DEG, grid * DEG, indexing="ij")
            img = np.asarray(_brdf_jit(ti, to, b * DEG, n, sigma_deg * DEG))
            im = ax.imshow(
                img.T, origin="lower", extent=(-90, 90, -90, 90), cmap="magma", norm=PowerNorm(0.5)
            )
            label = "rho (1/rad)"
        else:  # the delta lobes as coloured lines
            lobes = model.sharp_lobes(grid * DEG, b * DEG, n)
            to, ratio = np.rad2deg(np.asarray(lobes.theta_o)), np.asarray(lobes.ratio)
            keep = ratio > 0
            ti = np.broadcast_to(grid[:, None], ratio.shape)
            ax.set_facecolor("black")
            im = ax.scatter(
                ti[keep], to[keep], c=ratio[keep], s=2, cmap="magma", norm=PowerNorm(0.5, vmin=0)
            )
            ax.set(xlim=(-90, 90), ylim=(-90, 90), aspect="equal")
            label = "reflectance ratio"
        ax.set(xlabel="theta_i (deg)", ylabel="theta_o (deg)", title=f"wedge {b:g} deg")
        fig.colorbar(im, ax=ax, label=label, shrink=0.85)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def diffuse_curves(
    beta2_deg: Sequence[float],
    n: complex | float = 1.46,
    sigma_deg: float = 0.0,
    cosine_weighted: bool = False,
    step_deg: float = 0.25,
) -> Figure:
    """Paper Fig. 5: reflectance under diffuse light against viewing angle, plus the flat
    material (dimensionless) [conventions §4]."""
    from stairfit import model

    to = np.arange(-90, 90 + step_deg / 2, step_deg) * DEG
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for b in beta2_deg:
        if sigma_deg > 0:
            d = model.diffuse_broadened(to, b * DEG, n, sigma_deg * DEG, cosine_weighted)
        else:
            d = model.diffuse_sharp(to, b * DEG, n, cosine_weighted)
        ax.plot(to / DEG, np.asarray(d), label=f"{b:g} deg")
    flat = np.asarray(model.flat_reflectance(to, n))
    if cosine_weighted:
        flat = flat * np.cos(to)
    ax.plot(to / DEG, flat, "-.", color="0.5", label="material")
    ax.set(xlabel="theta_o (deg)", ylabel="reflectance", xlim=(-90, 90))
    ax.legend(title="wedge", fontsize="small")
    fig.tight_layout()
    return fig


def reflected_colours(
    beta2_deg: Sequence[float],
    dispersion: object,
    delta_n: float = 0.0,
    sigma_deg: float = 5.0,
    theta_o_deg: Sequence[float] = tuple(range(-80, 81, 10)),
    illuminants: Sequence[str] = ("D65", "A"),
) -> Figure:
    """Paper Fig. 7: the colour of diffusely lit light reflected towards each viewing angle,
    per wedge and for the flat material, under each illuminant [conventions §8].

    Each swatch is the sRGB colour of the reflected light; one common exposure per illuminant
    maps the brightest swatch to display white, so brightness differences remain visible.
    """
    import jax

    from stairfit import model
    from stairfit.model import spectral

    lam = spectral.VISIBLE_NM
    n = np.asarray(model.refractive_index(dispersion, lam, delta_n))
    to = np.asarray(theta_o_deg, float) * DEG
    rows = [*(f"{b:g} deg" for b in beta2_deg), "material"]
    fig, axes = plt.subplots(
        1,
        len(illuminants),
        figsize=(0.45 * len(to) * len(illuminants) + 1.5, 0.5 * len(rows) + 1.2),
        squeeze=False,
    )
    # one compiled evaluation for all wedges (the spectra do not depend on the illuminant)
    diffuse = jax.jit(jax.vmap(model.diffuse_broadened, in_axes=(None, 0, None, None)))
    b2 = np.asarray(beta2_deg, float) * DEG
    spectra = list(np.asarray(diffuse(to[:, None], b2, n[None, :], sigma_deg * DEG)))
    spectra.append(np.asarray(model.flat_reflectance(to[:, None], n[None, :])))
    for ax, ill in zip(axes[0], illuminants, strict=True):
        w = spectral.xyz_weights(ill, lam)
        xyz = np.stack([s @ w.T for s in spectra])  # (rows, angles, 3)
        exposure = 0.9 / max(float(xyz[..., 1].max()), 1e-12)
        ax.imshow(spectral.xyz_to_srgb(xyz, exposure), aspect="auto")
        ax.set_xticks(range(len(to)), [f"{t:g}" for t in theta_o_deg], fontsize="x-small")
        ax.set_yticks(range(len(rows)), rows, fontsize="small")
        ax.set(xlabel="theta_o (deg)", title=f"illuminant {ill}")
    fig.tight_layout()
    return fig


def save(fig: Figure, path: Path, dpi: int = 120) -> Path:
    """Save a figure as PNG and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
