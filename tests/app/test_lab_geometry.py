"""The lab geometry of a scene (issue 40): each face's 3-D directions from the lamp, the camera
and the face points, which model the fit uses, and the lamp's disk rule."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from stairfit.errors import UserError
from stairfit.imaging import MeasurementRow
from stairfit.lab import LAMP_DISK, lab_choice, lab_geometry, reference_distance_mm
from stairfit.pipeline import check_kernel, check_kernel_name, offered_kernels
from stairfit.scene import load_scene

SCENE = {
    "version": 1,
    "specimen": {
        "layer_um": 150.0,
        "wedges": [
            {"name": "w30", "angle_deg": 30.0,
             "face_mm": [[-10, -10], [10, -10], [10, 10], [-10, 10]]},
            {"name": "w60", "angle_deg": 60.0,
             "face_mm": [[-10, 40], [10, 40], [10, 60], [-10, 60]]},
        ],
    },
    "light": {"shape": "disk", "diameter_mm": 6.0, "distance_mm": 500.0},
    "camera": {"focal_length_px": 4500.0},
    "markers": {"dictionary": "DICT_4X4_50",
                "marker": [{"id": 0, "corners_mm": [[-30, -90], [-30, -72], [-12, -72],
                                                    [-12, -90]]}]},
    "photos": [{"file": "a.dng", "light_deg": -20.0, "view_deg": 30.0}],
}  # fmt: skip


def _scene(tmp_path: Path, data: dict):
    (tmp_path / "a.dng").write_bytes(b"x")
    p = tmp_path / "scene.toml"
    p.write_text(tomli_w.dumps(data))
    return load_scene(p)


def _row(wedge: str, points: str = "", camera: str = "") -> MeasurementRow:
    values = {f.name: None for f in dataclasses.fields(MeasurementRow)}
    values.update(photo="a.dng", wedge=wedge, channel="G", value=1.0, stderr=0.1, flag="",
                  view_spread=1.0, face_points_mm=points, camera_mm=camera,
                  radiometry="")  # fmt: skip
    return MeasurementRow(**values)


def _face_frame(v: np.ndarray, beta2_deg: float) -> np.ndarray:
    """Written from conventions §11: a rotation about y by the wedge angle."""
    b = math.radians(beta2_deg)
    return np.array([v[0] * math.cos(b) + v[2] * math.sin(b), v[1],
                     -v[0] * math.sin(b) + v[2] * math.cos(b)])  # fmt: skip


def test_directions_irradiance_and_weights_of_a_placed_face(tmp_path):
    scene = _scene(tmp_path, SCENE)
    points = "0 50 17.32 0.25;5 45 25.98 0.75"
    camera = "450 -20 779.4"
    geo = lab_geometry(scene, [_row("w60", points, camera), _row("w60", points, camera)])
    assert geo.key.tolist() == [0, 0] and geo.wedge.tolist() == [1]
    lamp = np.array(scene.lamp_position_mm(scene.photos[0]))
    d_ref = reference_distance_mm(scene)
    assert d_ref == pytest.approx(500.0)
    for j, (p, w) in enumerate((([0, 50, 17.32], 0.25), ([5, 45, 25.98], 0.75))):
        p = np.array(p, float)
        to_lamp = lamp - p
        expect_i = _face_frame(to_lamp / np.linalg.norm(to_lamp), 60.0)
        to_cam = np.array([450, -20, 779.4]) - p
        expect_o = _face_frame(to_cam / np.linalg.norm(to_cam), 60.0)
        np.testing.assert_allclose(geo.w_i[0, j], expect_i, atol=1e-12)
        np.testing.assert_allclose(geo.w_o[0, j], expect_o, atol=1e-12)
        assert geo.weight[0, j] == pytest.approx(w)
        assert geo.irradiance[0, j] == pytest.approx((d_ref / np.linalg.norm(to_lamp)) ** 2)
    # out of the plane: the lamp and camera see this face from y != 0
    assert abs(geo.w_i[0, 0, 1]) > 0.05 and abs(geo.w_o[0, 0, 1]) > 0.05


def test_a_face_without_points_falls_back_to_its_outline_centre(tmp_path):
    scene = _scene(tmp_path, SCENE)
    geo = lab_geometry(scene, [_row("w30")])
    lamp = np.array(scene.lamp_position_mm(scene.photos[0]))
    centre = np.array([0.0, 0.0, 10.0 * math.tan(math.radians(30))])
    to_lamp = lamp - centre
    np.testing.assert_allclose(geo.w_i[0, 0], _face_frame(to_lamp / np.linalg.norm(to_lamp), 30),
                               atol=1e-12)  # fmt: skip
    # no camera centre: the camera is at infinity along view_deg
    v = math.radians(30.0)
    np.testing.assert_allclose(geo.w_o[0, 0], _face_frame(np.array([math.sin(v), 0, math.cos(v)]),
                                                          30.0), atol=1e-12)  # fmt: skip


def test_a_near_lamp_needs_the_faces_position(tmp_path):
    data = copy.deepcopy(SCENE)
    for w in data["specimen"]["wedges"]:
        del w["face_mm"]
        w["roi_px"] = [[10, 10], [90, 10], [90, 90]]
    del data["markers"]
    scene = _scene(tmp_path, data)
    with pytest.raises(UserError, match="needs each face's position"):
        lab_geometry(scene, [_row("w30")])


@pytest.mark.parametrize(
    ("light", "geometry", "use", "warns"),
    [
        ({"diameter_mm": 6.0, "distance_mm": 500.0}, "auto", True, False),
        ({"angular_diameter_deg": 0.5}, "auto", False, True),  # out of the plane, distant
        ({"angular_diameter_deg": 0.5}, "lab", True, False),
        ({"diameter_mm": 6.0, "distance_mm": 500.0}, "in_plane", False, True),
    ],
)
def test_which_model_of_the_directions_the_fit_uses(tmp_path, light, geometry, use, warns):
    data = copy.deepcopy(SCENE)
    data["light"] = {"shape": "disk", **light}
    data["fit"] = {"geometry": geometry}
    scene = _scene(tmp_path, data)
    rows = [_row("w60", "0 50 17.32 1", "450 -20 779.4")]
    choice = lab_choice(scene, rows)
    assert choice.use is use
    assert (choice.warning is not None) is warns
    if warns:
        assert "\n" not in choice.warning and "[fit] geometry" in choice.warning
    # `--kernel`: a microfacet kernel only where the fit uses the lab model
    check_kernel(scene, "gaussian")
    if use:
        check_kernel(scene, "beckmann")
    else:
        with pytest.raises(UserError, match="fitted in one plane"):
            check_kernel(scene, "ggx")


def test_the_kernels_a_fit_compares() -> None:
    """Every kernel of the lab model (probed), the in-plane model's Gaussian, or the one given
    with `--kernel` alone (no probes); an unknown name is refused."""
    from stairfit import model

    assert offered_kernels(True, None) == model.LAB_KERNELS and len(model.LAB_KERNELS) == 3
    assert offered_kernels(False, None) == ("gaussian",)
    assert offered_kernels(True, "ggx") == ("ggx",)
    for name in model.LAB_KERNELS:
        check_kernel_name(name)
    with pytest.raises(UserError, match="unknown facet kernel 'GGX'"):
        check_kernel_name("GGX")


def test_an_in_plane_scene_needs_no_lab_model_and_gets_no_warning(tmp_path):
    data = copy.deepcopy(SCENE)
    data["light"] = {"angular_diameter_deg": 0.5}
    scene = _scene(tmp_path, data)
    rows = [_row("w30", "0 0 5 1", "450 0 779.4")]  # the face and camera in the plane y = 0
    choice = lab_choice(scene, rows)
    assert not choice.use and choice.warning is None


def test_the_lamp_disk_rule_integrates_cubics_exactly():
    x, y, w = (np.array(c) for c in zip(*LAMP_DISK, strict=True))
    assert w.sum() == pytest.approx(1.0)
    # means over the unit disk: <1> = 1, <x^2> = <y^2> = 1/4, odd moments and <x^2 y> = 0
    for f, mean in ((x**2, 0.25), (y**2, 0.25), (x, 0), (x * y, 0), (x**3, 0), (x**2 * y, 0)):
        assert float(np.sum(w * f)) == pytest.approx(mean, abs=1e-12)
