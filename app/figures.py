"""Figures of the model: BRDF maps (paper Fig. 3/8), diffuse curves (Fig. 5) and the colour of
the reflected light (Fig. 7). Degrees on every axis [conventions §1].

Every figure is a plain `matplotlib.figure.Figure`, drawn on the Agg canvas by `save`: nothing
here selects a backend or registers figures with pyplot, so importing this module changes no
global state (a notebook keeps its backend; show a returned figure by making it a cell's
last expression, or `display(fig)`).

These take physical parameters, not fits, so notebooks and the report share them.

Speed (issue 6: the report is part of the user's wait): every model evaluation of a figure is
one compiled call (eagerly, JAX compiles every operation as a program of its own), and the
figures place their axes with fixed margins in inches (`fixed_layout`) instead of
`tight_layout`, which measures every tick label and then makes `savefig` draw the figure twice.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatterSciNotation, LogLocator
from numpy.typing import NDArray

if TYPE_CHECKING:
    import jax

from .fileio import named_error

DEG = np.pi / 180
PNG_COMPRESS_LEVEL = 1
"""zlib level of the PNGs: with RGB instead of RGBA, the report's figures encode in about half
the time of matplotlib's RGBA at level 6, for files a few percent larger."""
SPECTRUM_STEP_NM = 20.0
"""Wavelength step at which `reflected_spectra` evaluates a dispersive material before linear
interpolation onto the 5 nm grid: the reflected spectra are smooth in wavelength (dispersive
PLA, sigma 1-20 deg: at most 7e-4 of the peak, 0.04 of one 8-bit sRGB step;
tests/app/test_figures.py)."""


# --- layout ---------------------------------------------------------------------------------


def fixed_layout(
    fig: Figure,
    nrows: int,
    ncols: int,
    left: float = 0.75,
    right: float = 0.2,
    bottom: float = 0.55,
    top: float = 0.4,
    wspace: float = 0.8,
    hspace: float = 0.8,
) -> None:
    """Place a grid of subplots with margins and gaps in inches (room for labels and titles).

    The fixed-size replacement of `tight_layout`: the same inches hold whatever the figure
    size, and matplotlib need not lay out every tick label twice to find them.
    """
    w, h = fig.get_size_inches()
    ax_w = (w - left - right - (ncols - 1) * wspace) / ncols
    ax_h = (h - bottom - top - (nrows - 1) * hspace) / nrows
    fig.subplots_adjust(
        left=left / w,
        right=1 - right / w,
        bottom=bottom / h,
        top=1 - top / h,
        wspace=wspace / ax_w,
        hspace=hspace / ax_h,
    )


_SUPERSCRIPT = str.maketrans(
    "0123456789-", "\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079\u207b"
)


class PlainLogFormatter(LogFormatterSciNotation):
    """Log-axis labels `10⁵`, `2×10⁴` as plain text: matplotlib's default choice of labels and
    look, without mathtext, whose parser is slow to build on first use.

    A panel spanning less than a decade gets its minor ticks from matplotlib's linear fallback
    (`LogLocator` hands over to `AutoLocator`: 1.1, 1.2, ... x 10⁵), so the coefficient keeps
    the digits the tick needs (`1.2×10⁵`, not `10⁵` on every tick).
    """

    def __call__(self, x: float, pos: int | None = None) -> str:
        if not super().__call__(x, pos) or x <= 0:  # the default leaves this tick unlabelled
            return ""
        exponent = math.floor(math.log10(x) + 1e-9)
        coeff = float(f"{x / 10.0**exponent:.4g}")  # 4 digits: no float noise (1.1000000001)
        if coeff >= 10.0:  # x a hair below a decade, e.g. 9.99995e4 -> 10⁵
            exponent, coeff = exponent + 1, coeff / 10.0
        power = "10" + str(exponent).translate(_SUPERSCRIPT)
        return power if coeff == 1 else f"{coeff:g}\u00d7{power}"


def log_y(ax: Axes) -> None:
    """Logarithmic y axis with minor ticks at 2 and 5 per decade and plain-text labels (every
    minor tick of matplotlib's default costs a tick object: ~1/3 of a panel's drawing)."""
    ax.set_yscale("log")
    ax.yaxis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
    ax.yaxis.set_major_formatter(PlainLogFormatter())
    ax.yaxis.set_minor_formatter(PlainLogFormatter(labelOnlyBase=False))


# --- compiled model evaluations -------------------------------------------------------------


def _spectra_at(
    theta_o: jax.Array, beta2: jax.Array, n: jax.Array, sigma: jax.Array, diffuse_nodes: int
) -> jax.Array:  # traced by `_compiled`
    """(wedges + 1, angles, len(n)): `diffuse_broadened` per wedge, then the flat material."""
    import jax.numpy as jnp

    from stairfit import model

    wedges = model.diffuse_broadened(
        theta_o[None, :, None], beta2[:, None, None], n[None, None, :], sigma, n_nodes=diffuse_nodes
    )
    flat = model.flat_reflectance(theta_o[:, None], n[None, :])
    return jnp.concatenate([wedges, flat[None].astype(wedges.dtype)])


def _curves_at(
    theta_o: jax.Array,
    beta2: jax.Array,
    n: jax.Array,
    sigma: jax.Array,
    broadened: bool,
    cosine_weighted: bool,
) -> jax.Array:  # traced by `_compiled`
    """(wedges + 1, angles): the diffuse integral per wedge (`diffuse_broadened` if `broadened`,
    else `diffuse_sharp`), then the flat material (times cos theta_o if `cosine_weighted`)."""
    import jax.numpy as jnp

    from stairfit import model

    to, b2 = theta_o[None, :], beta2[:, None]
    if broadened:
        wedges = model.diffuse_broadened(to, b2, n, sigma, cosine_weighted)
    else:
        wedges = model.diffuse_sharp(to, b2, n, cosine_weighted)
    flat = model.flat_reflectance(theta_o, n)
    if cosine_weighted:
        flat = flat * jnp.cos(theta_o)
    return jnp.concatenate([wedges, flat[None].astype(wedges.dtype)])


@functools.cache
def _compiled(name: str) -> Callable[..., Any]:  # an array, or a NamedTuple of them
    """The compiled model evaluations of the figures, built once per process (eager JAX would
    compile every operation separately)."""
    import jax

    from stairfit import model

    if name == "spectra":
        return jax.jit(_spectra_at, static_argnames=("diffuse_nodes",))
    if name == "curves":
        return jax.jit(_curves_at, static_argnames=("broadened", "cosine_weighted"))
    return jax.jit(getattr(model, name))


@functools.lru_cache(maxsize=16)
def _compiled_index(kind: type, dispersion: object) -> Callable[..., jax.Array]:
    """`model.refractive_index` compiled for one dispersion model (keyed by its type too:
    NamedTuples of different types can compare equal)."""
    import jax

    from stairfit import model

    return jax.jit(functools.partial(model.refractive_index, dispersion))


def refractive_index(dispersion: object, wavelength_nm: NDArray, delta_n: float) -> NDArray:
    """`model.refractive_index` as NumPy [conventions §7], compiled once per (hashable)
    dispersion model."""
    from stairfit import model

    try:
        compiled = _compiled_index(type(dispersion), dispersion)
    except TypeError:  # unhashable: evaluate eagerly
        return np.asarray(model.refractive_index(dispersion, wavelength_nm, delta_n))
    return np.asarray(compiled(wavelength_nm, delta_n))


def _grid_dtype(float32: bool) -> type:
    return np.float32 if float32 else np.float64


def brdf_images(
    beta2_deg: Sequence[float],
    n: complex | float,
    sigma_deg: float,
    step_deg: float = 0.5,
    float32: bool = False,
) -> tuple[NDArray, NDArray]:
    """`rho(theta_i, theta_o)` (1/rad) on a `step_deg` grid over [-90, 90] deg, one image per
    wedge, in one compiled call [conventions §4, §5]; returns (grid in deg, images (wedge,
    theta_i, theta_o))."""
    grid = np.arange(-90, 90 + step_deg / 2, step_deg)
    rad = (grid * DEG).astype(_grid_dtype(float32))
    b2 = (np.asarray(beta2_deg, float) * DEG).astype(rad.dtype)
    img = _compiled("brdf")(
        rad[None, :, None], rad[None, None, :], b2[:, None, None], n, sigma_deg * DEG
    )
    return grid, np.asarray(img, float)


def reflected_spectra(
    beta2_deg: Sequence[float],
    dispersion: object,
    delta_n: float = 0.0,
    sigma_deg: float = 5.0,
    theta_o_deg: Sequence[float] = tuple(range(-80, 81, 10)),
    diffuse_nodes: int = 6,
    float32: bool = False,
) -> NDArray:
    """Diffuse-lighting reflectance spectra on `spectral.VISIBLE_NM`, shape (wedges + 1,
    angles, wavelengths): one row per wedge (broadened by `sigma_deg`), the flat material last
    [conventions §4, §7, §8]. Dimensionless.

    A wavelength-independent index is evaluated once; a dispersive one every
    `SPECTRUM_STEP_NM` and interpolated linearly in wavelength.
    """
    from stairfit.model import spectral

    lam = spectral.VISIBLE_NM
    n = refractive_index(dispersion, lam, delta_n)
    if np.all(n == n[0]):
        idx = np.array([0])
    else:
        every = max(1, round(SPECTRUM_STEP_NM / float(lam[1] - lam[0])))
        idx = np.unique(np.r_[np.arange(0, lam.size, every), lam.size - 1])
    real = _grid_dtype(float32)
    nodes = n[idx].astype(_narrow(n.dtype)) if float32 else n[idx]
    to = (np.asarray(theta_o_deg, float) * DEG).astype(real)
    b2 = (np.asarray(beta2_deg, float) * DEG).astype(real)
    at_nodes = np.asarray(
        _compiled("spectra")(to, b2, nodes, real(sigma_deg * DEG), diffuse_nodes=diffuse_nodes),
        float,
    )
    # linear interpolation in wavelength as a matrix (a single node: a constant spectrum)
    weights = np.stack([np.interp(lam, lam[idx], e) for e in np.eye(idx.size)])
    return at_nodes @ weights


def _narrow(dtype: np.dtype) -> type:
    """The single-precision type of a real or complex dtype."""
    return np.complex64 if np.issubdtype(dtype, np.complexfloating) else np.float32


# --- figures --------------------------------------------------------------------------------


def brdf_map(
    beta2_deg: Sequence[float],
    n: complex | float = 1.46,
    sigma_deg: float = 0.0,
    step_deg: float = 0.5,
    title: str | None = None,
    float32: bool = False,
) -> Figure:
    """Paper Fig. 3 (sigma = 0: reflectance ratios on the lobe lines) or Fig. 8 (broadened
    density, 1/rad) on a theta_i x theta_o grid, one panel per wedge [conventions §3, §4].
    `float32` evaluates the density in single precision (a preset's `float32_figures`)."""
    from matplotlib.colors import PowerNorm

    fig = Figure(figsize=(4.2 * len(beta2_deg), 3.8))
    axes = fig.subplots(1, len(beta2_deg), squeeze=False)
    if sigma_deg > 0:
        _, images = brdf_images(beta2_deg, n, sigma_deg, step_deg, float32)
    else:
        grid = np.arange(-90, 90 + step_deg / 2, step_deg)
        lobes = _compiled("sharp_lobes")(
            grid[None, :] * DEG, np.asarray(beta2_deg, float)[:, None] * DEG, n
        )
        to_all = np.rad2deg(np.asarray(lobes.theta_o))
        ratio_all = np.asarray(lobes.ratio)
    for k, (ax, b) in enumerate(zip(axes[0], beta2_deg, strict=True)):
        if sigma_deg > 0:
            im = ax.imshow(
                images[k].T,
                origin="lower",
                extent=(-90, 90, -90, 90),
                cmap="magma",
                norm=PowerNorm(0.5),
            )
            label = "rho (1/rad)"
        else:  # the delta lobes as coloured lines
            to, ratio = to_all[k], ratio_all[k]
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
    # the colourbar labels stand right of each cell: room for them in `right` and `wspace`
    fixed_layout(fig, 1, len(beta2_deg), top=0.75 if title else 0.4, right=0.7, wspace=1.3)
    return fig


def diffuse_curve_values(
    beta2_deg: Sequence[float],
    n: complex | float,
    sigma_deg: float,
    cosine_weighted: bool,
    theta_o_deg: Sequence[float] | NDArray,
) -> NDArray:
    """The curves of `diffuse_curves` at viewing angles `theta_o_deg` (degrees), shape
    (wedges + 1, angles): one row per wedge, the flat material last; dimensionless
    [conventions §1, §4]. One compiled program for all wedges (evaluated eagerly, JAX compiled
    each operation on its own; benchmarks/bench_notebooks.py). A ValueError names an argument
    outside its range: wedges strictly between 0 and 90 deg, viewing angles within [-90, 90],
    `sigma_deg` >= 0."""
    b2 = np.atleast_1d(np.asarray(beta2_deg, float))
    to = np.atleast_1d(np.asarray(theta_o_deg, float))
    for name, values, ok in (
        ("beta2_deg", b2, (b2 > 0) & (b2 < 90)),
        ("theta_o_deg", to, (to >= -90) & (to <= 90)),
        ("sigma_deg", np.atleast_1d(float(sigma_deg)), np.atleast_1d(float(sigma_deg) >= 0)),
    ):
        bad = values[~(ok & np.isfinite(values))]
        if bad.size:
            raise ValueError(
                f"diffuse_curve_values: {name} = {bad[0]:g} is outside its range (wedges in "
                "(0, 90) deg, viewing angles in [-90, 90] deg, sigma_deg >= 0); fix the value"
            )
    out = _compiled("curves")(
        to * DEG, b2 * DEG, n, float(sigma_deg) * DEG,
        broadened=sigma_deg > 0, cosine_weighted=cosine_weighted,
    )  # fmt: skip
    return np.asarray(out, float)


def diffuse_curves(
    beta2_deg: Sequence[float],
    n: complex | float = 1.46,
    sigma_deg: float = 0.0,
    cosine_weighted: bool = False,
    step_deg: float = 0.25,
) -> Figure:
    """Paper Fig. 5: reflectance under diffuse light against viewing angle, plus the flat
    material (dimensionless) [conventions §4]."""
    to_deg = np.arange(-90, 90 + step_deg / 2, step_deg)
    curves = diffuse_curve_values(beta2_deg, n, sigma_deg, cosine_weighted, to_deg)
    fig = Figure(figsize=(6.5, 4))
    ax = fig.subplots()
    for b, d in zip(beta2_deg, curves[:-1], strict=True):
        ax.plot(to_deg, d, label=f"{b:g} deg")
    ax.plot(to_deg, curves[-1], "-.", color="0.5", label="material")
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
    diffuse_nodes: int = 6,
    float32: bool = False,
) -> Figure:
    """Paper Fig. 7: the colour of diffusely lit light reflected towards each viewing angle,
    per wedge and for the flat material, under each illuminant [conventions §8].

    Each swatch is the sRGB colour of the reflected light; one common exposure per illuminant
    maps the brightest swatch to display white, so brightness differences remain visible.
    `diffuse_nodes` and `float32` are a preset's `diffuse_nodes` and `float32_figures`.
    """
    from stairfit.model import spectral

    spectra = reflected_spectra(
        beta2_deg, dispersion, delta_n, sigma_deg, theta_o_deg, diffuse_nodes, float32
    )
    rows = [*(f"{b:g} deg" for b in beta2_deg), "material"]
    n_to = len(theta_o_deg)
    fig = Figure(figsize=(0.45 * n_to * len(illuminants) + 1.5, 0.5 * len(rows) + 1.2))
    axes = fig.subplots(1, len(illuminants), squeeze=False)
    for ax, ill in zip(axes[0], illuminants, strict=True):
        xyz = spectra @ spectral.xyz_weights(ill).T  # (rows, angles, 3)
        exposure = 0.9 / max(float(xyz[..., 1].max()), 1e-12)
        ax.imshow(spectral.xyz_to_srgb(xyz, exposure), aspect="auto")
        ax.set_xticks(range(n_to), [f"{t:g}" for t in theta_o_deg], fontsize="x-small")
        ax.set_yticks(range(len(rows)), rows, fontsize="small")
        ax.set(xlabel="theta_o (deg)", title=f"illuminant {ill}")
    fixed_layout(fig, 1, len(illuminants), left=0.75, right=0.1, bottom=0.5, top=0.3, wspace=0.8)
    return fig


SaveFigure = Callable[[Figure, Path], Path]
"""What draws a figure and writes it to a path (`save`)."""


def save(fig: Figure, path: Path, dpi: int = 120) -> Path:
    """Save a figure as an opaque RGB PNG (zlib level `PNG_COMPRESS_LEVEL`) and close it.

    Drawn on the Agg canvas and written by Pillow without the alpha channel: a quarter less
    to compress than `savefig`'s RGBA, the same pixels (the figure background is opaque). A
    figure pyplot manages (made with `plt.subplots`, e.g. in a notebook) is closed in pyplot
    too; stairfit's own figures are plain `Figure`s and never touch pyplot.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    managed = getattr(fig.canvas, "manager", None) is not None
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.set_dpi(dpi)
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        rgb = np.asarray(canvas.buffer_rgba())[..., :3]
        Image.fromarray(rgb).save(
            path, format="png", compress_level=PNG_COMPRESS_LEVEL, dpi=(dpi, dpi)
        )
    except OSError as e:  # a full disk: name the figure (Pillow's write names no file)
        raise named_error(e, path, path) from e
    finally:
        if managed:  # pyplot made it, so pyplot is already imported
            import matplotlib.pyplot as plt

            plt.close(fig)
    return path
