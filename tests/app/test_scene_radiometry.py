"""Scene fields for flat fields, dark frames and HDR brackets (issue 12): read, listed, and
every mistake one line naming the file, the field and the fix (exit status 2 from the CLI)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from stairfit import imaging
from stairfit.cli import main
from stairfit.errors import UserError
from stairfit.imaging import synthetic
from stairfit.scene import load_scene

ROI = [[10, 10], [90, 10], [90, 90], [10, 90]]
GOOD = {
    "version": 1,
    "angles_relative_to": "face",
    "specimen": {
        "layer_um": 150.0,
        "wedges": [{"name": "w10", "angle_deg": 10.0, "roi_px": ROI}],
    },
    "photos": [
        {"file": "a.dng", "light_deg": 0.0, "view_deg": 30.0},
        {
            "file": ["b1.dng", "b2.dng", "b3.dng"],
            "light_deg": 0.0,
            "view_deg": -20.0,
            "exposure_time_s": [0.01, 0.04, 0.16],
            "iso": 100,
        },
    ],
    "calibration": {"flat_field": ["flat1.dng", "flat2.dng"], "dark_frames": "dark.dng"},
}


def _write(tmp_path: Path, data: dict) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(tomli_w.dumps(data))
    return p


def test_brackets_and_calibration_frames_are_read(tmp_path: Path) -> None:
    scene = load_scene(_write(tmp_path, GOOD))
    a, b = scene.photos
    assert a.files == ("a.dng",) and a.bracket == ()
    assert b.file == "b1.dng" and b.files == ("b1.dng", "b2.dng", "b3.dng")
    assert b.exposure_time_s == 0.01 and b.iso == 100
    assert [(m.exposure_time_s, m.iso) for m in b.bracket] == [(0.04, 100), (0.16, 100)]
    assert scene.calibration is not None
    assert scene.calibration.flat_field == ("flat1.dng", "flat2.dng")
    assert scene.calibration.dark_frames == ("dark.dng",)
    names = ["scene.toml", "a.dng", "b1.dng", "b2.dng", "b3.dng", "flat1.dng", "flat2.dng"]
    names.append("dark.dng")
    assert scene.input_files() == tuple((tmp_path / n).resolve() for n in names)
    fields = [f for f, _, _ in scene.input_fields()]
    assert fields[:2] == ["photos[0].file", "photos[1].file[0]"]
    assert fields[-1] == "calibration.dark_frames[0]"


def _set(path: list, value: object) -> dict:
    d = copy.deepcopy(GOOD)
    node = d
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return d


TWICE = r"'b1.dng' is listed twice"
BAD_FIELDS = [
    (["photos", 1, "file"], [], r"photos\[1\]\.file: must be a file name or a list"),
    (["photos", 1, "file"], ["b1.dng", 3, "b3.dng"], r"photos\[1\]\.file: must be a file name"),
    (["photos", 1, "exposure_time_s"], [0.01, 0.04], r"exposure_time_s: lists 2 values for 3"),
    (["photos", 1, "exposure_time_s"], [0.01, 0.04, -1.0], r"exposure_time_s: -1.0 is outside"),
    (["photos", 1, "file"], ["b1.dng", "b2.dng", "b1.dng"], r"photos\[1\]\.file\[2\]: " + TWICE),
    (
        ["calibration", "dark_frames"],
        "a.dng",
        r"calibration\.dark_frames\[0\]: 'a.dng' is listed twice \(also as photos\[0\]\.file\)",
    ),
    (
        ["calibration", "flat_feild"],
        ["x.dng"],
        r"calibration\.flat_feild: unknown field; did you mean 'flat_field'",
    ),
    (["calibration"], {}, r"calibration: give flat_field"),
    (
        ["calibration", "flat_field"],
        "../flat.dng",
        r"calibration\.flat_field\[0\]: '\.\./flat\.dng' is outside the photo folder",
    ),
    (
        ["photos", 1, "file"],
        ["b1.dng", "b2.dng", "./a.dng"],
        r"photos\[1\]\.file\[2\]: '\./a\.dng' is the same file as photos\[0\]\.file 'a\.dng'",
    ),
    (["calibration", "flat_degree"], 30, r"calibration\.flat_degree: 30 is outside"),
]


@pytest.mark.parametrize(("path", "value", "message"), BAD_FIELDS)
def test_bad_radiometry_fields_are_one_line_errors(
    tmp_path: Path, path: list, value: object, message: str
) -> None:
    p = _write(tmp_path, _set(path, value))
    with pytest.raises(UserError, match=message) as err:
        load_scene(p)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


EXPOSURE = imaging.Exposure(exposure_time_s=1 / 100, f_number=8.0, iso=200)


def _photo(path: Path, size: tuple[int, int] = (100, 100), level: float = 500.0) -> None:
    synthetic.render_photo(
        size, {}, {}, EXPOSURE, background=np.full(3, level * EXPOSURE.scale), seed=1
    ).write_dng(path)


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """A folder whose scene is fine apart from what each test breaks."""
    for name in ("a.dng", "b1.dng", "b2.dng", "b3.dng"):
        _photo(tmp_path / name)
    for name in ("flat1.dng", "flat2.dng"):
        _photo(tmp_path / name, level=6000.0)
    synthetic.render_photo((100, 100), {}, {}, EXPOSURE, background=np.zeros(3), seed=2).write_dng(
        tmp_path / "dark.dng"
    )
    return tmp_path


def _fit(folder: Path, capsys: pytest.CaptureFixture[str]) -> str:
    code = main(["fit", str(folder), "-o", str(folder.parent / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err
    assert not (folder.parent / "out").exists()
    return err


def test_missing_calibration_file_is_named(folder: Path, capsys: pytest.CaptureFixture) -> None:
    data = _set(["calibration", "flat_field"], ["flat1.dng", "flat9.dng"])
    _write(folder, data)
    err = _fit(folder, capsys)
    assert "scene.toml: calibration.flat_field[1]: 'flat9.dng' is not in" in err
    assert "remove it from the list" in err


def test_a_dark_frame_that_is_a_device_is_refused_before_reading(
    folder: Path, capsys: pytest.CaptureFixture
) -> None:
    """The hostile-input checks of photo files (tests/app/test_cli_hostile.py) cover every input
    file: a dark frame that links to /dev/zero would otherwise be read forever."""
    (folder / "dark.dng").unlink()
    (folder / "dark.dng").symlink_to("/dev/zero")
    _write(folder, GOOD)
    err = _fit(folder, capsys)
    assert "dark_frames[0]: 'dark.dng' is a link to /dev/zero, a character device" in err


def test_missing_bracket_member_is_named(folder: Path, capsys: pytest.CaptureFixture) -> None:
    (folder / "b3.dng").unlink()
    _write(folder, GOOD)
    err = _fit(folder, capsys)
    assert "scene.toml: photos[1].file[2]: 'b3.dng' is not in" in err


def test_flat_field_of_another_size_is_named(folder: Path, capsys: pytest.CaptureFixture) -> None:
    _photo(folder / "flat2.dng", size=(120, 80), level=6000.0)
    _write(folder, GOOD)
    err = _fit(folder, capsys)
    assert "calibration.flat_field[1] 'flat2.dng': 120 x 80 px" in err


def test_saturated_flat_field_is_named(folder: Path, capsys: pytest.CaptureFixture) -> None:
    _photo(folder / "flat1.dng", level=30000.0)
    _write(folder, GOOD)
    err = _fit(folder, capsys)
    assert "calibration.flat_field[0] 'flat1.dng'" in err and "saturated" in err
    assert "shorter exposure" in err
