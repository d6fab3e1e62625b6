"""A fit folder's material: `results.json` and the scene it was fitted to, as a `Material`.

A fit folder (`stairfit fit DIR`, default `DIR-fit`) holds results.json but not the scene file;
the scene (layer thickness, wedges, lamp, camera, markers) is read from the photo folder, which
is DIR next to DIR-fit unless given, and checked against the fit's record of it (its SHA-256).
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from stairfit.errors import StairfitWarning, UserError

from ._material import Material

if TYPE_CHECKING:
    from stairfit._jsontypes import JSONObject
    from stairfit.scene import Scene


class FitFolder(NamedTuple):
    """A fit folder read for rendering: its results, the scene and the material."""

    folder: Path
    results: JSONObject
    scene: Scene
    material: Material


def photo_folder(fit: Path, photos: Path | None) -> Path:
    """The photo folder of fit folder `fit`: `photos` when given, else the sibling whose name
    is `fit`'s without its "-fit" (the fit's default output name)."""
    if photos is not None:
        return photos
    if fit.name.endswith("-fit") and (fit.parent / fit.name[: -len("-fit")]).is_dir():
        return fit.parent / fit.name[: -len("-fit")]
    raise UserError(
        f"{fit}: cannot tell which photo folder this fit came from (results.json names the "
        "scene file, not its folder, and there is no sibling without '-fit'); give it with "
        "--photos DIR"
    )


def read_results(fit: Path) -> JSONObject:
    """`fit/results.json`, or UserError naming what is wrong."""
    path = fit / "results.json"
    if not path.is_file():
        raise UserError(f"{fit}: no results.json; give a folder written by `stairfit fit`")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: not readable as JSON ({e}); run `stairfit fit` again") from None


def read_fit(fit: str | Path, photos: str | Path | None = None) -> FitFolder:
    """The fit folder `fit` with its scene (from `photo_folder`) and material
    (`material_from_results`). Warns when the scene file is not the one the fit read."""
    from stairfit.outcome import sha256_of
    from stairfit.scene import load_scene

    fit = Path(fit)
    results = read_results(fit)
    folder = photo_folder(fit, None if photos is None else Path(photos))
    scene = load_scene(folder)
    recorded = results.get("inputs", {}).get("scene", {}).get("sha256")
    if recorded and recorded != sha256_of(scene.path):
        warnings.warn(
            f"{scene.path} is not the scene file the fit in {fit} read (its SHA-256 differs); "
            "the render uses it as it is now",
            StairfitWarning,
            stacklevel=2,
        )
    return FitFolder(fit, results, scene, material_from_results(results, scene))


def _value(record: JSONObject) -> float:
    return float(record["least_squares"]["value"])


def material_from_results(results: JSONObject, scene: Scene) -> Material:
    """The material a fit found (docs/render.md, "From a fit"): the kernel of
    `directions.facets` ("gaussian" for an in-plane fit), the widths (per wedge when fitted per
    wedge), the edge radius, the index per channel (`spectral.index_n`, `index_k`) plus
    `delta_n`, the body's albedo `pi floor / scale` and the photos' scale.

    An in-plane fit's `scale` also absorbed the out-of-plane density of the Gaussian lab model
    at 0, `line_gaussian(0, 0, sigma)` [conventions §11], so its photo scale is `scale` divided
    by that. Fillets are not in the 3-D model: a fitted fillet radius is left out, with a
    warning."""
    from stairfit import model

    params = {(p["parameter"], p.get("wedge")): p for p in results.get("parameters", [])}
    fixed = results.get("fixed_parameters", {})
    directions = results.get("directions", {})
    lab = directions.get("model") == "lab"
    kernel = directions.get("facets", "gaussian") if lab else "gaussian"
    wedges = scene.specimen.wedges
    widths = []
    for (name, wedge), rec in params.items():
        if name == "sigma_rad":
            angle = 0.0 if wedge is None else wedges[int(wedge)].angle_deg
            widths.append((angle, math.radians(_value(rec))))
    if not widths:
        raise UserError("results.json: no fitted width (sigma_deg); run `stairfit fit` again")

    def get(name: str, default: float = 0.0) -> float:
        if (name, None) in params:
            return _value(params[(name, None)])
        return float(fixed.get(name, default) or 0.0)

    fillet = get("fillet_radius_um")
    if fillet > 0.0:
        warnings.warn(
            f"the fit has fillets of radius {fillet:.3g} um in the concave corners; the 3-D "
            "model has none, so the render leaves them out",
            StairfitWarning,
            stacklevel=2,
        )
    spectral = results.get("spectral", {})
    n_re = spectral.get("index_n") or [1.5, 1.5, 1.5]
    n_im = spectral.get("index_k") or [0.0] * len(n_re)
    dn = get("delta_n")
    index = tuple(complex(a + dn, b) for a, b in zip(n_re, n_im, strict=True))
    scale = get("scale", 1.0)
    if not lab:
        sigma = widths[0][1] if len(widths) == 1 else sum(w for _, w in widths) / len(widths)
        scale = scale / float(model.line_gaussian(0.0, 0.0, sigma))
    albedo = math.pi * get("floor") / scale if scale > 0 else 0.0
    chosen = results.get("model_selection", {}).get("chosen", "?")
    return Material(
        kernel=kernel,
        widths=tuple(sorted(widths)),
        edge_radius_um=get("edge_radius_um"),
        layer_um=float(scene.specimen.layer_um),
        index=index,
        body_albedo=min(max(albedo, 0.0), 1.0),
        photo_scale=scale,
        source=f"Fitted by stairfit {results.get('stairfit_version', '')} ('{chosen}').",
    ).check()
