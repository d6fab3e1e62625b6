"""`stairfit simulate` with real-world effects (issue 12): vignetting with flat-field photos,
dark frames with a wrong black-level tag, HDR brackets and one fixed exposure for all views.

The fast test measures a simulated folder (no fit) with and without its corrections against
the simulator's truth; the slow ones fit whole folders through the CLI and compare the fitted
floor and scale with the truth, with and without the flat field.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from stairfit import imaging
from stairfit.cli import main
from stairfit.imaging_specs import photo_specs
from stairfit.scene import load_scene

EFFECTS = [
    "--vignetting", "0.15", "--flat-field", "2", "--dark-frames", "2",
    "--black-error-dn", "6", "--bracket", "3", "--fixed-exposure",
]  # fmt: skip


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("session") / "photos"
    args = ["simulate", str(folder), "--megapixels", "2.0", "--views", "5", "--quiet"]
    assert main([*args, *EFFECTS]) == 0
    return folder


def test_a_session_with_every_effect_is_written_and_declared(session: Path) -> None:
    scene = load_scene(session)
    assert scene.calibration is not None
    assert scene.calibration.flat_field == ("FLAT_01.dng", "FLAT_02.dng")
    assert scene.calibration.dark_frames == ("DARK_01.dng", "DARK_02.dng")
    assert all(len(p.files) == 3 for p in scene.photos)
    frames = [imaging.decode_raw(session / f) for f in scene.photos[0].files]
    times = [f.exif_exposure_time_s for f in frames]
    assert times[1] == pytest.approx(4 * times[0]) and times[2] == pytest.approx(16 * times[0])
    # one fixed exposure (bracket) for every view
    assert {imaging.decode_raw(session / p.file).exif_exposure_time_s for p in scene.photos} == {
        times[0]
    }
    truth = json.loads((session / "truth.json").read_text())
    assert truth["settings"]["effects"]["vignetting"] == 0.15


def _measure(session: Path, strip: str | None) -> tuple[np.ndarray, np.ndarray]:
    scene = load_scene(session)
    specs = photo_specs(scene)
    if strip == "calibration":
        specs = [dataclasses.replace(s, calibration=None) for s in specs]
    table = imaging.measure_photos(specs, imaging.ExtractionSettings(), max_workers=1)
    truth = np.array(json.loads((session / "truth.json").read_text())["face_radiance"]["values"])
    photos = [p.file for p in scene.photos]
    wedges = [w.name for w in scene.specimen.wedges]
    pulls, rel = [], []
    for r in table:
        if r.flag or r.saturated_fraction > 0:
            continue
        t = truth[photos.index(r.photo), wedges.index(r.wedge), "RGB".index(r.channel)]
        pulls.append((r.value - t) / r.stderr)
        rel.append(r.value / t - 1)
    return np.array(pulls), np.array(rel)


def test_corrected_measurements_agree_with_the_truth(session: Path) -> None:
    """Dark frames, flat field and bracket: the ROI means agree with the rendered radiance
    within their errors; without dark and flat, the 15% vignetting and the 6 DN black-level
    error bias them by many standard errors."""
    pulls, rel = _measure(session, None)
    assert np.abs(rel).max() < 0.03
    assert pulls.size >= 80  # 5 photos x 6 wedges x 3 channels, less faces turned away
    # about 85 pulls, texture at 1.5 px (pull width up to ~1.2, docs/imaging.md)
    assert abs(pulls.mean()) < 0.4 and 0.7 < pulls.std(ddof=1) < 1.4
    raw_pulls, raw_rel = _measure(session, "calibration")
    assert np.median(np.abs(raw_pulls)) > 3
    assert raw_rel.min() < -0.02


def _fit(tmp_path: Path, folder: Path, name: str) -> dict:
    out = tmp_path / name
    assert main(["fit", str(folder), "-o", str(out), "--quiet", "--no-posterior"]) == 0
    return json.loads((out / "results.json").read_text())


def _ls(results: dict, name: str) -> tuple[float, float]:
    rec = next(p for p in results["parameters"] if p["name"] == name)
    return rec["least_squares"]["value"], rec["least_squares"]["stderr"]


@pytest.mark.slow
def test_vignetting_biases_floor_and_scale_unless_flat_fielded(tmp_path: Path) -> None:
    """15% vignetting: without the flat field the fitted floor and scale are biased by more than
    3 standard errors; with it, they are within 3 of the truth."""
    folder = tmp_path / "photos"
    args = ["simulate", str(folder), "--megapixels", "2", "--views", "9", "--quiet"]
    assert main([*args, "--vignetting", "0.15", "--flat-field", "2"]) == 0
    truth = json.loads((folder / "truth.json").read_text())["parameters"]
    corrected = _fit(tmp_path, folder, "with-flat")
    scene = tomllib.loads((folder / "scene.toml").read_text())
    del scene["calibration"]
    (folder / "scene.toml").write_text(tomli_w.dumps(scene))
    plain = _fit(tmp_path, folder, "without-flat")
    for label, results in (("with the flat field", corrected), ("without", plain)):
        for name in ("scale", "floor"):
            value, se = _ls(results, name)
            rel, pull = 100 * (value / truth[name] - 1), (value - truth[name]) / se
            print(f"{label}: {name} {value:.6g} +- {se:.3g} ({rel:+.2f}%, {pull:+.1f} sd)")
    for name in ("scale", "floor"):
        value, se = _ls(corrected, name)
        assert abs(value - truth[name]) < 3 * se, (name, value, se)
    biased = [abs(_ls(plain, n)[0] - truth[n]) / _ls(plain, n)[1] for n in ("scale", "floor")]
    assert max(biased) > 3, biased


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--vignetting", "0.9", "--vignetting: 0.9 is outside [0, 0.6]"),
        ("--flat-field", "-1", "--flat-field: give 0 to 64 frames"),
        ("--bracket", "9", "--bracket: 9 is outside [1, 5]"),
        ("--black-error-dn", "nan", "--black-error-dn: nan is outside"),
    ],
)
def test_bad_effect_options_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str, message: str
) -> None:
    for command in ("simulate", "demo"):
        assert main([command, str(tmp_path / command), f"{option}={value}", "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err, err
        assert not (tmp_path / command).exists()


def test_dark_views_get_the_longest_exposure_not_an_absurd_one() -> None:
    """`stairfit simulate --floor 0` crashed (struct.error writing ExposureTime): a view whose
    faces are all but black (1e-24, or 0) asked for a 1e29 s exposure. Every exposure is now at
    most MAX_EXPOSURE_S, a bracket keeps its 4x steps, and a normal view still puts its
    brightest face between a third of a stop below half of the raw range and half of it."""
    from stairfit.simulation import (
        MAX_EXPOSURE_S,
        SessionEffects,
        SimulationSettings,
        _sensor,
        view_exposures,
    )

    radiance = np.zeros((3, 2, 3))
    radiance[1] = 1e-24
    radiance[2, 0] = 5.0e5
    settings = SimulationSettings(effects=SessionEffects(bracket=3))
    exposures = view_exposures(settings, radiance)
    times = np.array([[e.exposure_time_s for e in view] for view in exposures])
    assert np.all(np.isfinite(times)) and times.max() <= MAX_EXPOSURE_S
    np.testing.assert_allclose(times[:, 1:] / times[:, :-1], 4.0)
    sensor = _sensor(settings.effects)
    half = 0.5 * (sensor.white - sensor.black_level)
    peak_dn = 5.0e5 * exposures[2][0].exposure_time_s / exposures[2][0].f_number ** 2
    assert half * 2 ** (-1 / 3) <= peak_dn <= half


def test_exposure_tags_that_do_not_fit_a_rational_are_one_line_errors(tmp_path: Path) -> None:
    """A long exposure with a fraction (5000.3 s) is written within 1 ppm (its denominator is
    kept small enough that the numerator fits 32 bits); one that cannot be written at all is an
    ImagingError, not a struct.error."""
    import exifread

    from stairfit.imaging import synthetic

    mosaic = np.full((48, 64), 2000, np.uint16)
    ok = imaging.Exposure(5000.3, 5.6, 100)
    with open(synthetic.write_dng(tmp_path / "a.dng", mosaic, exposure=ok), "rb") as fh:
        tag = exifread.process_file(fh, details=False)["EXIF ExposureTime"].values[0]
    # read with exifread: decode_raw treats more than an hour as implausible (issue 42)
    assert float(tag) == pytest.approx(5000.3, rel=1e-6)
    huge = imaging.Exposure(1e29, 5.6, 100)
    with pytest.raises(imaging.ImagingError, match="does not fit an EXIF RATIONAL"):
        synthetic.write_dng(tmp_path / "b.dng", mosaic, exposure=huge)
    assert not (tmp_path / "b.dng").exists()


@pytest.mark.slow
def test_simulate_with_no_floor_writes_a_folder(tmp_path: Path) -> None:
    """The reported command, `stairfit simulate --floor 0`, at a small size: exit 0, and the
    darkest views at the longest exposure."""
    from stairfit.simulation import MAX_EXPOSURE_S

    folder = tmp_path / "photos"
    argv = ["simulate", str(folder), "--floor", "0", "--megapixels", "0.3", "--views", "3"]
    assert main([*argv, "--quiet"]) == 0
    scene = load_scene(folder)
    times = [imaging.decode_raw(folder / p.file).exif_exposure_time_s for p in scene.photos]
    assert max(times) == pytest.approx(MAX_EXPOSURE_S, rel=0.26)  # rounded down a third stop
