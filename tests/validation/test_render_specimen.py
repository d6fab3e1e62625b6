"""The path-traced specimen with the fitted material's RGL tables (app/render) against the
stepped-mesh render of the same scene (tests/pbr_photos.py: real staircase meshes, Mitsuba's
`pplastic`), face by face, and against the model evaluated exactly at every pixel.

Three numbers per face (mean over the pixels 3 px inside its outline, the G channel):
`render / model`: the renderer (our scene, camera, lamp and tables; direct light only) against
the model itself at each pixel's light and view directions: what rendering adds;
`model / stepped` the model's own error against the stepped meshes (its physics, not the
renderer's; up to 17% on the 60-deg face seen at 70 deg, see docs/render.md "Accuracy");
`render / stepped` the whole chain."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="mitsuba (the render extra) is not installed")

import pbr_photos as pb

from stairfit import render
from stairfit.render import _render, _scene
from stairfit.scene import load_scene


def model_direct(setup: pb.PbrSetup, material: render.Material, cam: pb.Pinhole, k: int,
                 mask: np.ndarray, lamp: np.ndarray) -> np.ndarray:  # fmt: skip
    """The model's radiance per unit E_ref (1/sr) averaged over the face pixels in `mask`:
    each pixel's ray meets the face's mean plane; light from the lamp's centre with the
    inverse-square irradiance, `p cos_i / cos_o` [conventions §11]. Direct light only."""
    v, u = np.nonzero(mask)
    d = np.stack(cam.rays(u.astype(float), v.astype(float)), -1)
    beta2 = setup.wedges_deg[k]
    n = pb.face_normal(beta2)
    p0 = pb.face_corners(setup, k)[0]
    points = cam.centre + (((p0 - cam.centre) @ n) / (d @ n))[:, None] * d
    to_lamp = lamp - points
    dist = np.linalg.norm(to_lamp, axis=1)
    w_i = np.array([pb.base_to_face(x, beta2) for x in to_lamp / dist[:, None]])
    to_cam = cam.centre - points
    w_o = np.array([pb.base_to_face(x, beta2) for x in to_cam / np.linalg.norm(to_cam, axis=1)[
        :, None]])  # fmt: skip
    p = render.density(material, beta2, w_i, w_o)
    irradiance = (setup.lamp_reference_mm / dist) ** 2
    return (p * (irradiance * w_i[:, 2] / w_o[:, 2])[:, None]).mean(axis=0)


@pytest.mark.slow
def test_render_of_the_specimen_face_by_face(tmp_path: Path) -> None:
    """Two views of the six wedges (the small set's camera and lamp, 600 x 400 px, 64 samples):
    with the default tables the render reproduces the model within 3% on every face (direct
    light), and the whole chain matches the stepped-mesh render within 3% on every face where
    the model itself does (within 2%); elsewhere its difference is the model's, within 3%.
    The stepped meshes are rendered with Mitsuba's polarised variant, as the model tracks s and
    p through the two-bounce path: rendered unpolarised they were 8-11% darker on the 30- and
    40-deg faces at -40 deg, where that path carries the light."""
    setup = pb.fast_setup(variant="scalar_spectral_polarized")
    folder = tmp_path / "lab"
    truth = pb.render_folder(folder, setup, seed=3, keep_render=True)
    scene = load_scene(folder)
    material = render.Material(setup.distribution, ((0.0, math.atan(setup.alpha)),),
                               setup.edge_radius_um, setup.layer_um, (setup.index,) * 3,
                               setup.body_diffuse)  # fmt: skip
    mi = _scene.mitsuba("scalar_rgb")
    tables = _render.material_tables(material, list(setup.wedges_deg), tmp_path / "tables",
                                     render.DEFAULT_RESOLUTION, lambda _: None)  # fmt: skip
    shapes = _render.specimen_shapes(mi, scene, tables, material, setup.plate_albedo)
    rows = []
    for i, (_light, view) in enumerate(setup.photos):
        cam = pb.camera_for(setup, view)
        ours = _scene.Camera(cam.rotation, cam.centre, cam.focal_px, (cam.cx, cam.cy),
                             setup.width, setup.height)  # fmt: skip
        lamp = _scene.scene_lamp(scene, scene.photos[i])
        lit = {**shapes, **_scene.lamp_shapes(lamp)}
        direct = _scene.render(mi, lit, ours, 64, 2, 21 + i)
        full = _scene.render(mi, lit, ours, 64, setup.max_depth, 31 + i)
        stepped = pb.load_render(folder, i).radiance
        for k, beta2 in enumerate(setup.wedges_deg):
            if not truth["photos"][i]["faces"][pb.wedge_name(beta2)]:
                continue
            mask = pb.face_mask(cam, pb.face_corners(setup, k), 3.0, setup.width, setup.height)
            exact = model_direct(setup, material, cam, k, mask, lamp.position)[1]
            d, f, s = (img[mask].mean(axis=0)[1] for img in (direct, full, stepped))
            rows.append((view, beta2, d / exact, exact * (f / d) / s, f / s))
    table = json.dumps([[round(x, 3) for x in r] for r in rows])
    render_vs_model = np.array([r[2] for r in rows])
    model_vs_stepped = np.array([r[3] for r in rows])
    chain = np.array([r[4] for r in rows])
    assert len(rows) == 12
    assert np.all(np.abs(render_vs_model - 1.0) < 0.03), table
    good = np.abs(model_vs_stepped - 1.0) < 0.02
    assert good.sum() >= 5, table
    assert np.all(np.abs(chain[good] - 1.0) < 0.03), table
    assert np.all(np.abs(chain - model_vs_stepped) < 0.03), table
