"""Fillets at the edges of the program (issue 15): `stairfit simulate/demo --fillet-radius-um`,
the scene file's `[truth]`, and the report's truth table.

The limit is checked against the closed form `r + r_f <= min(l1, l1 cot beta2)` written out
here [conventions §2], not against the program's own `max_fillet_radius`. Nothing here renders
photos (the rendering is tested against the filleted model in test_simulate_fillet_render.py).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tomli_w
from test_scene import GOOD

from stairfit import fitting, simulation
from stairfit.cli import build_parser, main
from stairfit.errors import UserError
from stairfit.report import _truth_html, truth_records
from stairfit.scene import TRUTH_FIELDS, load_scene

USER_ERROR = 2
LAYER_UM = 150.0
FINEST_DEG = 60.0  # of the simulator's wedges 10-60 deg the 60 deg cell is the smallest


@pytest.fixture(autouse=True)
def _no_persistent_jax_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("STAIRFIT_JAX_CACHE", "off")


def _room_um(beta2_deg: float, layer_um: float = LAYER_UM) -> float:
    """min(l1, l2), l2 = l1 cot beta2: what tip arc and fillet share [conventions §2]."""
    return min(layer_um, layer_um / math.tan(math.radians(beta2_deg)))


def _settings(edge_radius_um: float, fillet_radius_um: float) -> simulation.SimulationSettings:
    """The simulator's settings with these radii, checked as `simulate` checks them."""
    truth = simulation.Truth(edge_radius_um=edge_radius_um, fillet_radius_um=fillet_radius_um)
    settings = simulation.SimulationSettings(truth=truth)
    simulation.check_radii(settings)
    return settings


def test_truth_fields_match_the_simulator():
    # one list of truth parameters: what simulate renders from is what [truth] may hold
    assert tuple(f.name for f in dataclasses.fields(simulation.Truth)) == TRUTH_FIELDS


def test_fillet_flag_lands_in_the_scene_truth(tmp_path):
    from stairfit._specimen_layout import SpecimenLayout

    s = _settings(20.0, 12.5)
    assert s.truth.fillet_radius_um == 12.5
    layout = SpecimenLayout(s.wedges_deg)
    photos = [{"file": f"p{k}.dng", "view_deg": v, "roi_px": {}} for k, v in enumerate(s.views_deg)]
    text = simulation._compact_arrays(tomli_w.dumps(simulation._scene_dict(s, layout, photos)))
    (tmp_path / "scene.toml").write_text(text)
    truth = load_scene(tmp_path).truth
    assert truth is not None
    assert truth.fillet_radius_um == 12.5 and truth.edge_radius_um == 20.0
    assert truth.sigma_deg == s.truth.sigma_deg and truth.scale == s.truth.scale


def test_demo_takes_the_fillet_flag(tmp_path, capsys):
    args = build_parser("demo").parse_args(["demo", "OUT", "--fillet-radius-um", "7"])
    assert args.fillet_radius_um == 7.0
    # the flag reaches the simulator's settings: a fillet that does not fit is refused there
    out = tmp_path / "demo"
    status = main(["demo", str(out), "--megapixels", "0.5", "--fillet-radius-um", "87"])
    err = capsys.readouterr().err
    assert status == USER_ERROR and "r + r_f <= min(l1, l2) = 86.6025 um" in err, err
    assert not out.exists()


def test_the_largest_fillet_is_the_closed_form():
    r = 30.0
    largest = _room_um(FINEST_DEG) - r  # 150 cot 60 deg - 30 = 56.60 um
    assert _settings(30.0, largest)
    with pytest.raises(UserError, match=r"give at most 56\.6025"):
        _settings(30.0, largest * (1 + 1e-9))


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--fillet-radius-um", "-1"], r"--fillet-radius-um: -1 is negative; give a radius >= 0"),
        (["--fillet-radius-um", "nan"], r"--fillet-radius-um: must be a finite number"),
        (["--fillet-radius-um", "inf"], r"--fillet-radius-um: must be a finite number"),
        (
            ["--edge-radius-um", "30", "--fillet-radius-um", "60"],
            r"--fillet-radius-um: 60 um does not fit beside --edge-radius-um 30 in the 60 deg "
            r"wedge's cell .*give at most 56\.6025 um",
        ),
        (["--fillet-radius-um", "87"], r"r \+ r_f <= min\(l1, l2\) = 86\.6025 um"),
    ],
)
def test_bad_fillet_flag_is_one_line_without_traceback(tmp_path, capsys, flags, message):
    out = tmp_path / "photos"
    status = main(["simulate", str(out), "--megapixels", "0.5", "--views", "3", *flags])
    err = capsys.readouterr().err
    assert status == USER_ERROR
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert re.search(message, err), err
    assert not out.exists()


def _scene_with_truth(tmp_path: Path, **truth: object) -> Path:
    d = copy.deepcopy(GOOD)
    d["truth"] = truth
    p = tmp_path / "scene.toml"
    p.write_text(tomli_w.dumps(d))
    return p


def test_scene_truth_reads_back(tmp_path):
    # GOOD's wedges are 10 and 45 deg on 150 um layers: min(l1, l2) = 150 um for both
    cap = _room_um(45.0)
    scene = load_scene(
        _scene_with_truth(tmp_path, edge_radius_um=100.0, fillet_radius_um=cap - 100)
    )
    assert scene.truth.items() == (("edge_radius_um", 100.0), ("fillet_radius_um", cap - 100))
    assert load_scene(_scene_with_truth(tmp_path, sigma_deg=6)).truth.sigma_deg == 6.0
    d = copy.deepcopy(GOOD)
    (tmp_path / "scene.toml").write_text(tomli_w.dumps(d))
    assert load_scene(tmp_path).truth is None


def test_truth_example_in_docs_is_valid(tmp_path):
    import tomllib

    from conftest import REPO

    text = (REPO / "docs" / "scene.md").read_text()
    block = re.search(r"```toml\n(\[truth\]\n.*?)```", text, re.S).group(1)
    scene = load_scene(_scene_with_truth(tmp_path, **tomllib.loads(block)["truth"]))
    assert [k for k, _ in scene.truth.items()] == list(TRUTH_FIELDS)


@pytest.mark.parametrize(
    ("truth", "message"),
    [
        ({"fillet_radius_um": -2.0}, r"truth\.fillet_radius_um: -2\.0 is negative; give a value"),
        ({"fillet_radius_um": math.nan}, r"truth\.fillet_radius_um: must be a finite number"),
        ({"fillet_radius_um": math.inf}, r"truth\.fillet_radius_um: must be a finite number"),
        ({"fillet_radius_um": "15"}, r"truth\.fillet_radius_um: must be a number"),
        (
            {"edge_radius_um": 100.0, "fillet_radius_um": 60.0},
            r"truth\.fillet_radius_um: 60 um does not fit beside truth\.edge_radius_um = 100 um"
            r" on wedge 'w10' .*min\(l1, l2\) = 150 um.*give at most 50 um",
        ),
        ({"fillet_radius_um": 150.5}, r"truth\.fillet_radius_um: 150\.5 um does not fit"),
        ({"edge_radius_um": 151.0}, r"truth\.edge_radius_um: 151 um does not fit"),
        ({"fillet_radius": 5.0}, r"truth\.fillet_radius: unknown field; did you mean "),
        ({"sigma_deg": 0.0}, r"truth\.sigma_deg: 0\.0 is outside \(0, 90\] deg"),
    ],
)
def test_bad_scene_truth_is_one_line_naming_file_field_and_fix(tmp_path, truth, message):
    p = _scene_with_truth(tmp_path, **truth)
    with pytest.raises(UserError, match=message) as err:
        load_scene(p)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


def test_bad_scene_truth_through_the_command_line(tmp_path, capsys):
    _scene_with_truth(tmp_path, edge_radius_um=100.0, fillet_radius_um=60.0)
    status = main(["fit", str(tmp_path), "--output", str(tmp_path / "fit")])
    err = capsys.readouterr().err
    assert status == USER_ERROR
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "truth.fillet_radius_um" in err and "give at most 50 um" in err
    assert not (tmp_path / "fit").exists()


def _outcome(truth: dict[str, float], free: tuple[str, ...]) -> SimpleNamespace:
    """The parts of a FitOutcome `truth_records` and `fixed_parameters` read."""
    from stairfit.scene import SceneTruth

    params = fitting.Params(edge_radius_um=3.0, floor=0.0)
    fit = SimpleNamespace(variant=SimpleNamespace(free=free, per_wedge_sigma=False), params=params)
    return SimpleNamespace(
        scene=SimpleNamespace(truth=SceneTruth(**truth)), selection=SimpleNamespace(fit=fit)
    )


def test_truth_table_pairs_true_and_fitted_values():
    records = [
        {
            "name": "edge_radius_um",
            "parameter": "edge_radius_um",
            "least_squares": {"value": 29.0, "stderr": 1.5},
        },
        *(
            {
                "name": f"sigma_deg[{k}: {b} deg]",
                "parameter": "sigma_rad",
                "least_squares": {"value": v, "stderr": 0.1},
                "posterior": {"median": v, "p2_5": v - 0.2, "p97_5": v + 0.2},
            }
            for k, (b, v) in enumerate(((10, 5.9), (45, 6.2)))
        ),
    ]
    truth = {"sigma_deg": 6.0, "edge_radius_um": 30.0, "floor": 0.0, "fillet_radius_um": 15.0}
    out = truth_records(_outcome(truth, ("sigma_rad", "edge_radius_um")), records)
    by_name = {t["name"]: t for t in out}
    assert by_name["edge_radius_um"] == pytest.approx(
        {**by_name["edge_radius_um"], "true": 30.0, "fitted": 29.0, "stderr": 1.5}
    )
    assert [by_name[f"sigma_deg[{k}: {b} deg]"]["true"] for k, b in ((0, 10), (1, 45))] == [6, 6]
    assert by_name["floor"]["status"] == "fixed" and by_name["floor"]["fitted"] == 0.0
    fillet = by_name["fillet_radius_um"]
    assert fillet["true"] == 15.0
    assert fillet["status"] == "fixed" and fillet["fitted"] == 0.0  # the Params default
    page = _truth_html({"truth": out})
    assert page.count("<tr>") == 1 + len(out)
    assert "fixed at 0" in page and "29 &plusmn; 1.5" in page
    assert _truth_html({"truth": []}) == ""
    assert np.isfinite([t["true"] for t in out]).all()
