"""`stairfit measure` (issue 12): decode and measure only; named patches; a real colour chart."""

from __future__ import annotations

import csv
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from stairfit import imaging
from stairfit.cli import main
from stairfit.errors import UserError
from stairfit.scene import load_scene


@pytest.fixture(autouse=True)
def _no_persistent_jax_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("STAIRFIT_JAX_CACHE", "off")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three photos of 0.5 MP (views -80, -30, 20 deg) whose scene places the ROIs by the
    markers alone, except in the -80 deg view, where the markers are too foreshortened (1.2 px
    per cell) and the simulator's own roi_px stay, as a user would draw them."""
    folder = tmp_path_factory.mktemp("measure") / "photos"
    argv = ["simulate", str(folder), "--megapixels", "0.5", "--views", "3", "--quiet"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("STAIRFIT_JAX_CACHE", "off")
        assert main([*argv, "--exposure-tags", "ifd0"]) == 0
    raw = tomllib.loads((folder / "scene.toml").read_text())
    for p in raw["photos"][1:]:
        del p["roi_px"]
    (folder / "scene.toml").write_text(tomli_w.dumps(raw))
    return folder


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _edit(folder: Path, change) -> None:
    raw = tomllib.loads((folder / "scene.toml").read_text())
    change(raw)
    (folder / "scene.toml").write_text(tomli_w.dumps(raw))


def test_measure_writes_measurements_previews_and_a_report(simulated, tmp_path, capsys) -> None:
    out = tmp_path / "m"
    assert main(["measure", str(simulated), "-o", str(out), "--quiet", "--no-cache"]) == 0
    terminal = capsys.readouterr().out
    names = sorted(p.name for p in simulated.glob("*.dng"))
    for name in names:
        assert f"{name}: " in terminal and (out / "previews" / f"{name}.png").is_file()
    assert "exposure from ifd0" in terminal and "markers 0 1 2 3 (affine" in terminal
    table = imaging.MeasurementTable.read_csv(out / "measurements.csv")
    assert table.photos() == tuple(names)
    assert {r.exposure_source for r in table} == {"ifd0"}
    photos = _rows(out / "photos.csv")
    assert [p["status"] for p in photos] == ["measured"] * 3
    markers = _rows(out / "markers.csv")
    assert markers[0]["note"] == "pixel ROIs only (markers not used)"
    assert all(m["marker_ids"] == "0 1 2 3" and float(m["rms_px"]) < 1.5 for m in markers[1:])
    report = (out / "report.html").read_text()
    assert all(name in report for name in names) and "previews/" in report
    # nothing is fitted: no results.json, no figures
    assert not (out / "results.json").exists() and not (out / "figures").exists()


def test_failed_photos_are_reported_and_exit_2(simulated, tmp_path, capsys) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in simulated.iterdir():
        if p.suffix == ".dng":
            (photos / p.name).symlink_to(p)
    (photos / "scene.toml").write_text((simulated / "scene.toml").read_text())

    def markers_only(raw: dict) -> None:  # the -80 deg view too
        raw["photos"][0].pop("roi_px")

    _edit(photos, markers_only)
    out = tmp_path / "m"
    status = main(["measure", str(photos), "-o", str(out), "--quiet", "--no-cache"])
    captured = capsys.readouterr()
    assert status == 2
    line = captured.err.strip()
    assert len(line.splitlines()) == 1 and line.startswith("stairfit measure: error: ")
    assert "1 of 3 photos could not be measured" in line and "report.html" in line
    assert "'IMG_0001.dng': found 1 of the layout's 4 ArUco markers" in line
    assert "px per cell" in line and "foreshortened to 0.17" in line and "roi_px" in line
    # the report says so, and the failed photo still has a preview to draw roi_px on
    status_words = [p["status"].split(":")[0] for p in _rows(out / "photos.csv")]
    assert status_words == ["failed", "measured", "measured"]
    assert (out / "previews" / "IMG_0001.dng.png").is_file()
    assert "IMG_0001.dng: FAILED" in captured.out


CHART = {  # ColorChecker bottom row in colorchart.dng: centres read off a preview (raw px)
    "white 9.5 (.05 D)": (705, 931),
    "neutral 8 (.23 D)": (811, 928),
    "neutral 6.5 (.44 D)": (920, 924),
    "neutral 5 (.70 D)": (1031, 923),
    "neutral 3.5 (1.05 D)": (1141, 921),
    "black 2 (1.5 D)": (1255, 920),
}


def _chart_scene(folder: Path) -> None:
    def box(x: int, y: int) -> list[list[int]]:
        return [[x - 30, y - 25], [x + 30, y - 25], [x + 30, y + 25], [x - 30, y + 25]]

    scene = {
        "version": 1,
        "patches": [{"name": n, "roi_px": box(*c)} for n, c in CHART.items()],
        "extraction": {"erode_px": 4},
        # Magic Lantern wrote no exposure tags (README of ../shared/data/raw): overrides
        "photos": [{"file": "colorchart.dng", "exposure_time_s": 1.0, "f_number": 1.0, "iso": 100}],
    }
    (folder / "scene.toml").write_text(tomli_w.dumps(scene))


@pytest.mark.shared_data
def test_colour_chart_neutrals_are_linear_in_reflectance(shared_data, tmp_path, capsys) -> None:
    """The real Canon file: its six neutral patches against the ColorChecker's published
    luminance Y (colour-science's `CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]`,
    X-Rite's xyY values): a straight line (an offset allowed for flare) with R^2 >= 0.999 in
    every channel. Measured: R 0.9992, G 0.9996, B 0.9999."""
    import colour

    photos = tmp_path / "chart"
    photos.mkdir()
    (photos / "colorchart.dng").symlink_to(shared_data / "raw" / "colorchart.dng")
    _chart_scene(photos)
    out = tmp_path / "m"
    assert main(["measure", str(photos), "-o", str(out), "--quiet"]) == 0
    assert "colorchart.dng: 6 ROIs, none flagged; exposure from scene" in capsys.readouterr().out
    table = imaging.MeasurementTable.read_csv(out / "measurements.csv")
    data = colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"].data
    luminance = np.array([data[n][2] for n in CHART])
    for channel in "RGB":
        value = np.array(
            [next(r.value for r in table if r.wedge == n and r.channel == channel) for n in CHART]
        )
        design = np.column_stack([np.ones(len(value)), luminance])
        coef, *_ = np.linalg.lstsq(design, value, rcond=None)
        r2 = 1 - np.sum((value - design @ coef) ** 2) / np.sum((value - value.mean()) ** 2)
        assert r2 >= 0.999, (channel, r2, value)
        assert abs(coef[0]) < 0.02 * coef[1], (channel, coef)  # offset under 2% of white


GREY = {"name": "grey", "roi_px": [[1, 1], [9, 1], [9, 9]]}
TRIANGLE = [[0, 0], [1, 0], [1, 1]]


def _patch_scene(tmp_path: Path, *patches: dict) -> Path:
    scene = {"version": 1, "patches": list(patches) or [GREY], "photos": [{"file": "a.dng"}]}
    (tmp_path / "scene.toml").write_text(tomli_w.dumps(scene))
    return tmp_path / "scene.toml"


def test_patch_scenes_are_validated(tmp_path) -> None:
    scene = load_scene(_patch_scene(tmp_path), measure_only=True)
    assert scene.specimen is None and [p.name for p in scene.patches] == ["grey"]
    assert scene.photos[0].view_deg is None  # no wedges: no angles needed
    with pytest.raises(UserError, match=r"patches: named patches are measured by 'stairfit"):
        load_scene(_patch_scene(tmp_path))  # not for fit
    cases = [
        ({"name": "g", "face_mm": TRIANGLE}, r"patches\[0\]\.face_mm: needs a \[markers\]"),
        (GREY | {"face_mm": TRIANGLE}, r"patches\[0\]: give either roi_px"),
        ({"name": "g"}, r"patches\[0\]: give either roi_px"),
        (GREY | {"nme": "x"}, r"patches\[0\]\.nme: unknown field; did you mean 'name'\?"),
        ({"name": "g", "roi_px": [[1, 1], [2, 2]]}, r"patches\[0\]\.roi_px: must be a list"),
        ({"roi_px": TRIANGLE}, r"patches\[0\]\.name: missing"),
    ]
    for patch, message in cases:
        with pytest.raises(UserError, match=message):
            load_scene(_patch_scene(tmp_path, patch), measure_only=True)


def test_patch_names_must_be_unique(tmp_path) -> None:
    with pytest.raises(UserError, match=r"patches\[1\]\.name: 'grey' is already"):
        load_scene(_patch_scene(tmp_path, GREY, GREY), measure_only=True)
