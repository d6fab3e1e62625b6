"""`stairfit predict --edge-radius-um R`: the rounded-edge model on the command line (issue 5).

The CLI is run in-process through `stairfit.cli.main`. Checked: the CSV's layout and units
(degrees in, rho in 1/rad out: its integral over theta_o is the total reflectance that the
independent ray tracer measures), its wiring to `model.brdf_rounded` (each grid axis in its
place), r = 0 as the sharp model, the paths table of `--lobes`, and one-line errors with exit
status 2 for radii that do not fit a requested wedge.
"""

from __future__ import annotations

import csv
import io

import jax
import numpy as np
import pytest
from raytrace import Staircase, total_reflectance, trace

from stairfit import cli, model

DEG = np.pi / 180


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(["predict", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def _rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def _column(rows: list[dict[str, str]], name: str) -> np.ndarray:
    return np.array([float(r[name]) for r in rows])


def test_density_csv_matches_the_model(capsys):
    code, out, err = _run(
        capsys,
        *("--wedge-deg", "30,60", "--wavelength-nm", "450,600", "--material", "pla-bodurov2016"),
        *("--theta-i-deg", "-20,0,35", "--theta-o-deg", "-90:90:15"),
        *("--sigma-deg", "3", "--layer-um", "150", "--edge-radius-um", "40"),
    )
    assert code == 0, err
    rows = _rows(out)
    assert list(rows[0]) == [
        "wedge_deg",
        "wavelength_nm",
        "n",
        "theta_i_deg",
        "theta_o_deg",
        "sigma_deg",
        "edge_radius_um",
        "fillet_radius_um",  # issue 15: 0 here (tests/app/test_predict_fillet.py has fillets)
        "rho_per_rad",
    ]
    assert len(rows) == 2 * 2 * 3 * 13
    assert {r["edge_radius_um"] for r in rows} == {"40"}
    # every row against a direct call with that row's own (radian) arguments
    b2, ti, to, lam = (
        _column(rows, k) for k in ("wedge_deg", "theta_i_deg", "theta_o_deg", "wavelength_nm")
    )
    n = np.asarray(model.materials.PLA_BODUROV_2016(lam))
    expected = jax.jit(model.brdf_rounded)(ti * DEG, to * DEG, b2 * DEG, n, 3 * DEG, 150.0, 40.0)
    # the CSV keeps 10 significant digits
    np.testing.assert_allclose(_column(rows, "rho_per_rad"), expected, rtol=1e-9, atol=1e-15)


def test_density_integrates_to_the_ray_traced_total(capsys):
    """Units end to end: with rho in 1/rad on a degree grid, sum(rho) * step * pi / 180 is the
    total reflectance, which the brute-force tracer measures independently."""
    code, out, err = _run(
        capsys,
        *("--wedge-deg", "60", "--theta-i-deg", "10", "--theta-o-deg", "-90:90:0.25"),
        *("--sigma-deg", "2", "--n", "1.46", "--edge-radius-um", "50"),
    )
    assert code == 0, err
    rho = _column(_rows(out), "rho_per_rad")
    integral = float(np.sum(0.5 * (rho[1:] + rho[:-1])) * 0.25 * DEG)
    ref = total_reflectance(trace(Staircase(60, 150.0, 50.0), 10.0, 1.46, n_rays=20_000))
    # 1%: the tolerance for the total (measured agreement is ~1e-4)
    assert abs(integral / ref - 1.0) <= 0.01, (integral, ref)


def test_zero_radius_is_the_sharp_model(capsys):
    args = ("--wedge-deg", "30,60", "--theta-i-deg", "0,40", "--theta-o-deg", "-90:90:10")
    code, out, err = _run(capsys, *args, "--edge-radius-um", "0")
    assert code == 0, err
    rows = _rows(out)
    b2, ti, to = (_column(rows, k) for k in ("wedge_deg", "theta_i_deg", "theta_o_deg"))
    sharp = jax.jit(model.brdf)(ti * DEG, to * DEG, b2 * DEG, 1.46, 5 * DEG)  # eager: op by op
    np.testing.assert_allclose(_column(rows, "rho_per_rad"), sharp, rtol=1e-9, atol=1e-15)
    # and a radius changes it (the option is not ignored)
    code, out_r, err = _run(capsys, *args, "--edge-radius-um", "30")
    assert code == 0, err
    rounded = _column(_rows(out_r), "rho_per_rad")
    assert np.max(np.abs(rounded - _column(rows, "rho_per_rad"))) > 1e-3


def test_lobes_list_the_ten_paths(capsys):
    code, out, err = _run(
        capsys, "--lobes", "--wedge-deg", "45", "--theta-i-deg", "-30,0", "--edge-radius-um", "60"
    )
    assert code == 0, err
    rows = _rows(out)
    assert len(rows) == 2 * 10
    assert [r["lobe"] for r in rows[:10]] == list(model.PATH_NAMES)
    for k in range(2):
        block = rows[10 * k : 10 * (k + 1)]
        weights = np.array([float(r["weight"]) for r in block])
        np.testing.assert_allclose(weights.sum(), 1.0, atol=1e-9)  # the paths partition a period
        # the delta lobes keep the sharp directions; the continuous ones have none
        ti = float(block[0]["theta_i_deg"])
        assert [float(r["theta_o_deg"]) for r in block[:3]] == pytest.approx(
            [ti + 90.0, ti - 90.0, -ti]
        )
        assert all(r["theta_o_deg"] == "" for r in block[3:])
        for r in block:  # ratio = weight x mean Fresnel factor
            if float(r["weight"]) > 0:
                assert float(r["ratio"]) == pytest.approx(
                    float(r["weight"]) * float(r["fresnel"]), rel=1e-8
                )


@pytest.mark.parametrize(
    ("radius", "range_text"),
    [("100", "[0, 86.6025] um"), ("-5", "[0, 86.6025] um"), ("nan", "[0, 86.6025] um")],
)
def test_radius_outside_the_cell_is_a_one_line_error(capsys, tmp_path, radius, range_text):
    """100 um fits the 30-degree cell (r_max = l1 = 150 um) but not the 60-degree one
    (r_max = l2 = 150 / sqrt(3) = 86.6 um): the valid range for the request is the latter."""
    target = tmp_path / "out.csv"
    code, out, err = _run(
        capsys, "--wedge-deg", "30,60", "--edge-radius-um", radius, "-o", str(target)
    )
    assert code == 2
    assert out == ""
    assert not target.exists()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith("stairfit predict: error: --edge-radius-um")
    assert range_text in lines[0]
    if radius == "100":
        assert "--wedge-deg 60" in lines[0]


def test_largest_radius_is_accepted(capsys):
    r_max = float(model.max_edge_radius(60 * DEG, 150.0))
    code, out, err = _run(
        capsys, "--wedge-deg", "60", "--theta-o-deg", "-60,0", "--edge-radius-um", repr(r_max)
    )
    assert code == 0, err
    rho = _column(_rows(out), "rho_per_rad")
    assert np.all(np.isfinite(rho)) and np.all(rho > 0)


def test_diffuse_with_a_radius_is_refused(capsys):
    code, out, err = _run(capsys, "--diffuse", "--edge-radius-um", "10")
    assert code == 2 and out == ""
    assert err.startswith("stairfit predict: error: --edge-radius-um with --diffuse")
