"""The near lamp in the scene file (issue 40): its position per photo, size and checks."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import tomli_w

from stairfit.errors import UserError
from stairfit.scene import load_scene

BASE = {
    "version": 1,
    "specimen": {
        "layer_um": 150.0,
        "wedges": [{"name": "w30", "angle_deg": 30.0, "roi_px": [[10, 10], [90, 10], [90, 90]]}],
    },
    "light": {"illuminant": "D65", "shape": "disk", "diameter_mm": 6.0, "distance_mm": 500.0},
    "photos": [
        {"file": "a.dng", "light_deg": 20.0, "view_deg": 30.0},
        {"file": "b.dng", "light_position_mm": [10.0, -70.0, 400.0], "view_deg": 10.0},
    ],
}


def _load(tmp_path: Path, data: dict):
    p = tmp_path / "scene.toml"
    p.write_text(tomli_w.dumps(data))
    return load_scene(p)


def test_lamp_positions_follow_light_deg_or_the_photos_own_point(tmp_path):
    scene = _load(tmp_path, BASE)
    a, b = scene.photos
    # conventions §1: a positive light_deg puts the lamp on the downhill (-x) side
    x, y, z = scene.lamp_position_mm(a)
    assert (x, y, z) == pytest.approx((-500 * math.sin(math.radians(20)), 0.0,
                                       500 * math.cos(math.radians(20))))  # fmt: skip
    assert scene.lamp_position_mm(b) == (10.0, -70.0, 400.0)
    # the derived direction about y of a photo given only a point
    assert b.light_deg == pytest.approx(math.degrees(math.atan2(-10.0, 400.0)))
    # the physical size becomes the angle seen from the origin: 2 atan(3 / 500)
    assert scene.light.angular_diameter_deg == pytest.approx(math.degrees(2 * math.atan(0.006)))
    assert scene.light.near


def test_a_distant_light_has_no_position(tmp_path):
    data = copy.deepcopy(BASE)
    data["light"] = {"angular_diameter_deg": 1.0}
    del data["photos"][1]
    scene = _load(tmp_path, data)
    assert scene.lamp_position_mm(scene.photos[0]) is None
    assert not scene.light.near


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"position_mm": [0, 0, 500]}, "either distance_mm or position_mm"),
        ({"angular_diameter_deg": 1.0}, "either diameter_mm or angular_diameter_deg"),
        ({"distance_mm": None}, "needs the lamp's distance_mm or position_mm"),
        ({"diameter_mm": 600.0}, "not smaller than the lamp's distance"),
        ({"distance_mm": -5.0}, "light.distance_mm"),
        ({"distance_mm": None, "position_mm": [0, 0, -10]}, "above the base"),
        ({"distance_mm": None, "position_mm": [0, 0]}, "must be [x, y, z]"),
        ({"distance_mm": None, "position_mm": [0, float("nan"), 9]}, "must be finite"),
    ],
)
def test_bad_lamp_fields_are_one_line_errors(tmp_path, change, message):
    data = copy.deepcopy(BASE)
    for key, value in change.items():
        if value is None:
            del data["light"][key]
        else:
            data["light"][key] = value
    with pytest.raises(UserError) as e:
        _load(tmp_path, data)
    assert message in str(e.value)
    assert "\n" not in str(e.value)


def test_a_photo_gives_light_deg_or_a_lamp_point_not_both(tmp_path):
    data = copy.deepcopy(BASE)
    data["photos"][1]["light_deg"] = 0.0
    with pytest.raises(UserError, match=r"photos\[1\].light_position_mm: give either light_deg"):
        _load(tmp_path, data)


def test_the_plate_albedo_is_read_checked_and_a_fit_without_it_says_so(tmp_path):
    """`[specimen] plate_albedo` (docs/scene.md "A near lamp"): default 0, which a lab fit
    notes as the plate's light left out; outside [0, 1] a one-line error naming the field."""
    from stairfit.pipeline import plate_notes

    scene = _load(tmp_path, BASE)
    assert scene.specimen.plate_albedo == 0.0
    (note,) = plate_notes(scene.specimen)
    assert "plate_albedo" in note
    data = copy.deepcopy(BASE)
    data["specimen"]["plate_albedo"] = 0.03
    assert _load(tmp_path, data).specimen.plate_albedo == 0.03
    assert plate_notes(_load(tmp_path, data).specimen) == []
    data["specimen"]["plate_albedo"] = 1.5
    with pytest.raises(UserError, match=r"specimen\.plate_albedo") as err:
        _load(tmp_path, data)
    assert "\n" not in str(err.value)
