"""The scene file: validation messages name the file, the field and the fix (issue 6)."""

from __future__ import annotations

from pathlib import Path

import pytest
import tomli_w

from stairfit.errors import UserError
from stairfit.scene import load_scene

GOOD = {
    "version": 1,
    "angles_relative_to": "base",
    "specimen": {
        "layer_um": 150.0,
        "material": "pla",
        "wedges": [
            {"name": "w10", "angle_deg": 10.0, "roi_px": [[10, 10], [90, 10], [90, 90], [10, 90]]},
            {"name": "w45", "angle_deg": 45.0, "roi_px": [[110, 10], [190, 10], [190, 90]]},
        ],
    },
    "light": {"illuminant": "D65", "angular_diameter_deg": 1.0},
    "camera": {"sensitivity": "Nikon 5100 (NPL)"},
    "photos": [
        {"file": "a.dng", "light_deg": 0.0, "view_deg": 30.0},
        {"file": "b.dng", "light_deg": 10.0, "view_deg": -20.0, "exposure_time_s": 0.5},
    ],
}


def _write(tmp_path: Path, data: dict) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(tomli_w.dumps(data))
    return p


def _mutate(path: list, value=None, delete: bool = False) -> dict:
    import copy

    d = copy.deepcopy(GOOD)
    node = d
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


def test_good_scene_loads_and_converts_base_angles_to_face_angles(tmp_path):
    scene = load_scene(_write(tmp_path, GOOD).parent)  # a folder works too
    assert [w.name for w in scene.specimen.wedges] == ["w10", "w45"]
    w10, w45 = scene.specimen.wedges
    # conventions §1 in the base frame: theta_i = light - beta2, theta_o = view + beta2
    assert scene.face_angles_deg(scene.photos[0], w10) == (-10.0, 40.0)
    assert scene.face_angles_deg(scene.photos[1], w45) == (-35.0, 25.0)
    assert scene.photos[1].exposure_time_s == 0.5


def test_wedges_turned_away_are_left_out_of_a_photo(tmp_path):
    from stairfit.scene import visible

    d = _mutate(["photos", 0, "view_deg"], 50.0)  # 45-degree face seen at 95 deg: behind
    scene = load_scene(_write(tmp_path, d))
    w10, w45 = scene.specimen.wedges
    assert visible(scene, scene.photos[0], w10)
    assert not visible(scene, scene.photos[0], w45)
    d["photos"][0]["roi_px"] = {"w45": [[1, 1], [5, 1], [5, 5]]}  # an ROI for an unseen face
    with pytest.raises(UserError, match=r"roi_px\.w45: this photo cannot see wedge 'w45'"):
        load_scene(_write(tmp_path, d))


def test_a_photo_that_sees_no_face_is_left_out_and_named_unless_every_photo_is(tmp_path):
    """A photo in which no face is both lit and seen holds no measurement: it is left out of
    the scene with its reason in `left_out` (which fit and measure print), and the other photos
    are kept; only a scene whose every photo is blind is refused, in one line."""
    d = _mutate(["photos", 0, "light_deg"], -85.0)  # lit from 95 and 130 deg: behind both
    scene = load_scene(_write(tmp_path, d))
    assert [p.file for p in scene.photos] == ["b.dng"]
    (note,) = scene.left_out
    assert "'a.dng' left out" in note and "light_deg -85.0" in note
    assert load_scene(_write(tmp_path, GOOD)).left_out == ()
    d["photos"][1]["light_deg"] = -85.0
    with pytest.raises(UserError, match=r"photos\[0\]: no wedge face is both lit and visible") as e:
        load_scene(_write(tmp_path, d))
    assert "nor in any other" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("path", "value", "delete", "message"),
    [
        (
            ["photos", 0, "view_dge"],
            3.0,
            False,
            r"photos\[0\]\.view_dge: unknown field; did you mean 'view_deg'",
        ),
        (
            ["specimen", "layr_um"],
            3.0,
            False,
            r"specimen\.layr_um: unknown field; did you mean 'layer_um'",
        ),
        (["specimen", "layer_um"], None, True, r"specimen\.layer_um: missing"),
        (["photos"], None, True, r"photos: missing or empty"),
        (["specimen", "wedges", 0, "angle_deg"], 95.0, False, r"angle_deg: 95.0 is outside"),
        (["photos", 0, "view_deg"], "thirty", False, r"view_deg: must be a number"),
        (["light", "illuminant"], "D66", False, r"light\.illuminant: unknown illuminant"),
        (["camera", "sensitivity"], "Brownie", False, r"camera\.sensitivity: unknown camera"),
        (["specimen", "material"], "pla-bodurov", False, r"did you mean 'pla-bodurov2016'"),
        (["photos", 1, "file"], "a.dng", False, r"listed twice"),
        (["specimen", "wedges", 1, "name"], "w10", False, r"duplicate wedge name"),
        (["version"], 2, False, r"version: is 2"),
        (["angles_relative_to"], "camera", False, r'use "base" or "face"'),
        (["specimen", "wedges", 0, "roi_px"], [[1, 2]], False, r"at least 3 \[x, y\] points"),
        (["specimen", "wedges", 0, "roi_px"], None, True, r"no ROI for wedge 'w10'"),
    ],
)
def test_bad_scene_fields_are_one_line_errors_naming_file_and_field(
    tmp_path, path, value, delete, message
):
    p = _write(tmp_path, _mutate(path, value, delete))
    with pytest.raises(UserError, match=message) as err:
        load_scene(p)
    text = str(err.value)
    assert text.startswith(str(p))
    assert "\n" not in text


def test_missing_and_invalid_scene_file(tmp_path):
    with pytest.raises(UserError, match="no scene file"):
        load_scene(tmp_path)
    (tmp_path / "scene.toml").write_text("version = 1\n[specimen\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_scene(tmp_path)


def test_explicit_index_table(tmp_path):
    d = _mutate(["specimen", "material"], None, delete=True)
    d["specimen"]["index"] = {"model": "cauchy", "a": 1.45, "b_um2": 0.004}
    scene = load_scene(_write(tmp_path, d))
    assert float(scene.specimen.index.build()(500.0)) == pytest.approx(1.466)
    d["specimen"]["index"] = {"model": "constant", "n": 0.9}
    with pytest.raises(UserError, match=r"specimen\.index: gives n\(380 nm\) = 0\.9"):
        load_scene(_write(tmp_path, d))


def test_annotated_example_in_docs_is_valid(tmp_path):
    import re

    from conftest import REPO

    text = (REPO / "docs" / "scene.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    (tmp_path / "scene.toml").write_text(block)
    scene = load_scene(tmp_path)
    assert scene.specimen.wedges[0].name == "w10"
    assert scene.markers is not None and scene.reference is not None
    assert scene.photos[0].exposure_time_s == 1.0


def test_simulated_scene_reads_back(tmp_path):
    # the scene writer (simulate) and the reader agree; no photos are rendered here
    import tomli_w

    from stairfit._specimen_layout import SpecimenLayout
    from stairfit.simulation import SimulationSettings, _compact_arrays, _scene_dict

    s = SimulationSettings()
    layout = SpecimenLayout(s.wedges_deg)
    photos = [{"file": f"p{k}.dng", "view_deg": v, "roi_px": {}} for k, v in enumerate(s.views_deg)]
    text = _compact_arrays(tomli_w.dumps(_scene_dict(s, layout, photos)))
    (tmp_path / "scene.toml").write_text(text)
    scene = load_scene(tmp_path)
    assert len(scene.photos) == len(s.views_deg)
    assert [w.angle_deg for w in scene.specimen.wedges] == list(s.wedges_deg)
    assert scene.specimen.wedges[2].face_mm == (
        (0.0, 52.0),
        (20.0, 52.0),
        (20.0, 72.0),
        (0.0, 72.0),
    )


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (["light", "shape"], "round", r'light\.shape: .round. is not one of: "uniform" .*"disk"'),
        (["camera", "plane_of_incidence"], "up",
         r'camera\.plane_of_incidence: .up. is not one of: "vertical"'),
        (["camera", "plane_of_incidence"], 1, r"camera\.plane_of_incidence: must be"),
    ],
)  # fmt: skip
def test_light_shape_and_plane_of_incidence_are_checked(tmp_path, path, value, message):
    """The two choice fields: a one-line error naming the file, the field and the choices;
    defaults "uniform" and "vertical"."""
    with pytest.raises(UserError, match=message) as err:
        load_scene(_write(tmp_path, _mutate(path, value)))
    assert str(tmp_path / "scene.toml") in str(err.value) and "\n" not in str(err.value)
    scene = load_scene(_write(tmp_path, GOOD))
    assert (scene.light.shape, scene.camera.plane_of_incidence) == ("uniform", "vertical")
    disk = load_scene(_write(tmp_path, _mutate(["light", "shape"], "disk")))
    assert disk.light.shape == "disk"
