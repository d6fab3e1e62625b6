"""`[specimen.metadata]`: free key = value pairs, strings or numbers (issue 16)."""

from __future__ import annotations

import copy
import datetime
from pathlib import Path

import pytest
import tomli_w
from test_scene import GOOD

from stairfit.errors import UserError
from stairfit.scene import load_scene


def _scene_with(tmp_path: Path, metadata: object) -> Path:
    data = copy.deepcopy(GOOD)
    data["specimen"]["metadata"] = metadata
    path = tmp_path / "scene.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def test_metadata_keeps_strings_and_numbers_in_file_order(tmp_path: Path) -> None:
    meta = {"printer": "MK4", "nozzle_temperature_c": 215, "lot": "A-17", "speed_mm_s": 42.5}
    scene = load_scene(_scene_with(tmp_path, meta))
    assert scene.specimen.metadata == (
        ("printer", "MK4"),
        ("nozzle_temperature_c", 215),
        ("lot", "A-17"),
        ("speed_mm_s", 42.5),
    )


def test_metadata_is_optional(tmp_path: Path) -> None:
    path = tmp_path / "scene.toml"
    path.write_text(tomli_w.dumps(GOOD))
    assert load_scene(path).specimen.metadata == ()


@pytest.mark.parametrize(
    ("value", "fragment"),
    [
        (True, "must be a string or a number"),
        ({"model": "MK4"}, "is a table"),
        ([1, 2], "is a list"),
        (datetime.date(2026, 1, 2), 'quote it: "2026-01-02"'),
    ],
    ids=["bool", "table", "list", "date"],
)
def test_bad_metadata_value_names_the_file_the_field_and_the_fix(
    tmp_path: Path, value: object, fragment: str
) -> None:
    with pytest.raises(UserError) as err:
        load_scene(_scene_with(tmp_path, {"printer": value}))
    message = str(err.value)
    assert message.startswith(f"{tmp_path / 'scene.toml'}: specimen.metadata.printer: "), message
    assert fragment in message
    assert "\n" not in message


def test_metadata_that_is_not_a_table_is_refused(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"specimen\.metadata: must be a table of key = value"):
        load_scene(_scene_with(tmp_path, "MK4"))


def test_input_files_are_the_scene_and_photos_as_absolute_paths(tmp_path: Path) -> None:
    path = tmp_path / "scene.toml"
    path.write_text(tomli_w.dumps(GOOD))
    files = load_scene(path).input_files()
    root = tmp_path.resolve()
    assert files == (root / "scene.toml", root / "a.dng", root / "b.dng")
