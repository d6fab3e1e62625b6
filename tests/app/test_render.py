"""`stairfit render FITDIR` (app/commands/render.py, docs/render.md) on photos path-traced by
Mitsuba 3 from stepped meshes (tests/pbr_photos.py, its small set): every photographed view
rendered from the pose the markers give, beside the photo, in report.html; a printed sphere
(tests/data) with the staircase of each point's angle to the build axis; outputs that never
replace what the command did not make."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="mitsuba (the render extra) is not installed")

import pbr_photos as pb

from stairfit.cli import main
from stairfit.outcome import sha256_of

SPHERE = Path(__file__).resolve().parents[1] / "data" / "printed_sphere.obj"


def fit_folder(photos: Path, setup: pb.PbrSetup) -> Path:
    """A fit folder as `stairfit fit` writes it (results.json, report.html, its marker), holding
    the renderer's own parameters as the fitted ones (the fit itself is tested elsewhere):
    GGX facets (width atan(alpha)), the edge radius, the index, `scale` the camera's constant
    and `floor` the body's albedo over pi times it [docs/render.md "From a fit"]."""
    fit = photos.with_name(f"{photos.name}-fit")
    fit.mkdir()

    def param(name: str, parameter: str, value: float) -> dict:
        return {"name": name, "parameter": parameter, "wedge": None,
                "least_squares": {"value": value, "stderr": None}}  # fmt: skip

    results = {
        "stairfit_version": "0.1.0",
        "inputs": {"scene": {"file": "scene.toml", "sha256": sha256_of(photos / "scene.toml")}},
        "model_selection": {"chosen": "rounded+floor"},
        "directions": {"model": "lab", "facets": setup.distribution},
        "parameters": [
            param("sigma_deg", "sigma_rad", math.degrees(math.atan(setup.alpha))),
            param("edge_radius_um", "edge_radius_um", setup.edge_radius_um),
            param("scale", "scale", setup.k_cam),
            param("floor", "floor", setup.k_cam * setup.body_diffuse / math.pi),
        ],
        "fixed_parameters": {"delta_n": 0.0, "fillet_radius_um": 0.0},
        "spectral": {"index_n": [setup.index] * 3, "index_k": [0.0] * 3},
    }
    (fit / "results.json").write_text(json.dumps(results))
    (fit / "report.html").write_text(
        "<!doctype html><html><body><h1>stairfit report</h1>\n"
        '<p style="color:#777">stairfit 0.1.0</p></body></html>\n'
    )
    (fit / ".stairfit-output").write_text('{"made_by": "stairfit", "command": "fit"}')
    return fit


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, pb.PbrSetup]:
    """The small physically based set (two photos lit from 20 deg) and its fit folder."""
    root = tmp_path_factory.mktemp("render")
    setup = pb.fast_setup()
    photos = root / "lab"
    pb.render_folder(photos, setup, seed=3)
    return photos, fit_folder(photos, setup), setup


@pytest.fixture(scope="module")
def rendered(lab) -> tuple[Path, Path, pb.PbrSetup, int]:
    photos, fit, setup = lab
    code = main(["render", str(fit), "--quality", "draft", "--spp", "8", "--downscale", "1",
                 "--threads", "2", "--quiet"])  # fmt: skip
    return photos, fit, setup, code


def detect_markers(png: Path) -> dict[int, np.ndarray]:
    """The ArUco markers (DICT_4X4_50) found in an 8-bit image, upscaled 3 times first: id ->
    (4, 2) corners in the image's pixels."""
    import cv2

    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    big = cv2.resize(img, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC)
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(big)
    return {} if ids is None else {int(i): c[0] / 3.0 for i, c in zip(ids.ravel(), corners,
                                                                       strict=True)}  # fmt: skip


def test_every_view_is_rendered_beside_its_photo(rendered) -> None:
    """Both photos: a photo PNG, a render PNG and EXR, the six tables; in the render the
    markers are where the photo shows them (the camera pose the markers gave: each marker's
    centre within half a pixel of the 300 x 200 px images),
    and each face's mean (renders.json) is the photo's within the model's own error against
    the stepped mesh (up to 17% on these faces, tests/validation/test_render_specimen.py) and the
    draft tables' (up to 15%), the median within 10%: a wrong unit, cosine or lamp would be off by
    far more."""
    _photos, fit, setup, code = rendered
    assert code == 0
    out = fit / "renders"
    record = json.loads((out / "renders.json").read_text())
    assert [v["photo"] for v in record["views"]] == ["DSC_0001.dng", "DSC_0002.dng"]
    assert sorted(p.name for p in (out / "materials").iterdir()) == sorted(
        f"wedge_{b:.4g}deg.bsdf" for b in setup.wedges_deg
    )
    ratios = []
    for v in record["views"]:
        for key in ("photo_png", "render_png", "render_exr"):
            assert (out / v[key]).is_file()
        photo, render = detect_markers(out / v["photo_png"]), detect_markers(out / v["render_png"])
        assert len(photo) >= 3 and set(photo) <= set(render)
        for k in photo:  # a marker's centre within half a pixel, its corners within 1.5 px
            shift = photo[k] - render[k]
            assert np.abs(shift.mean(axis=0)).max() < 0.5, (v["photo"], k, shift)
            assert np.abs(shift).max() < 1.5, (v["photo"], k, shift)
        ratios += [f["render"][1] / f["photo"][1] for f in v["faces"] if f["photo"]]
    assert len(ratios) == 12 and all(0.7 < r < 1.35 for r in ratios), ratios
    assert abs(np.median(ratios) - 1.0) < 0.1, ratios


def test_the_report_shows_photo_and_render_side_by_side(rendered) -> None:
    _photos, fit, _setup, _code = rendered
    html = (fit / "report.html").read_text()
    assert html.count("stairfit render: start") == 1 and "stairfit 0.1.0" in html
    for stem in ("DSC_0001", "DSC_0002"):
        assert f"renders/{stem}_photo.png" in html and f"renders/{stem}_render.png" in html
    assert html.index("stairfit render: start") < html.index('<p style="color:#777">stairfit')


def test_an_earlier_render_is_replaced_only_with_force(rendered, capsys) -> None:
    """Without --force an existing renders folder is kept (exit 2, one line); with --force it
    is replaced and its tables reused; the report keeps one renders section; a renders folder
    that stairfit did not make is never replaced."""
    _photos, fit, _setup, _code = rendered
    args = ["render", str(fit), "--quality", "draft", "--spp", "2", "--downscale", "2",
            "--view", "DSC_0002.dng"]  # fmt: skip
    assert main(args) == 2
    assert "already exists" in capsys.readouterr().err
    assert main([*args, "--force"]) == 0
    err = capsys.readouterr().err
    assert err.count("reused wedge_") == 6
    record = json.loads((fit / "renders" / "renders.json").read_text())
    assert [v["photo"] for v in record["views"]] == ["DSC_0002.dng"]
    assert (fit / "report.html").read_text().count("stairfit render: start") == 1
    mine = fit / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    assert main([*args, "--force", "-o", str(mine)]) == 2
    assert (mine / "notes.txt").read_text() == "keep"


def test_a_printed_sphere_takes_each_points_staircase(lab, capsys) -> None:
    """The sphere in tests/data rendered at 64 x 64 px: one table per wedge-angle node the
    sphere needs (0.5 to 89.5 deg every 30), the sphere lit and finite, the sky unseen."""
    _photos, fit, _setup = lab
    code = main(["render", str(fit), "--mesh", str(SPHERE), "--build-axis", "z", "--size",
                 "64", "--spp", "8", "--quality", "draft", "--step-deg", "30"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    out = fit / "renders-printed_sphere"
    assert len(list((out / "materials").glob("*.bsdf"))) == 4
    import mitsuba as mi

    img = np.array(mi.Bitmap(str(out / "printed_sphere_render.exr")))
    assert img.shape[:2] == (64, 64) and np.all(np.isfinite(img))
    assert img[32, 32].max() > 0 and img[0, 0].max() == 0.0


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--build-axis", "1 2", "--mesh", str(SPHERE)], "--build-axis"),
        (["--mesh", "nowhere.obj"], "no such file"),
        (["--spp", "0"], "--spp"),
        (["--view", "DSC_9999.dng"], "no photo"),
    ],
)
def test_bad_options_are_one_line_errors(lab, capsys, extra: list[str], message: str) -> None:
    _photos, fit, _setup = lab
    code = main(["render", str(fit), "--quality", "draft", "-o", str(fit / "x"), *extra])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_a_folder_without_results_is_refused(tmp_path: Path, capsys) -> None:
    assert main(["render", str(tmp_path)]) == 2
    assert "no results.json" in capsys.readouterr().err
