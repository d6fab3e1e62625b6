"""stairfit.explore: reading fit folders back, chains, Fisher information, fronts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stairfit import explore


def _results(stderr=(0.1, 2.0), corr=((1.0, -0.8), (-0.8, 1.0))):
    return {
        "parameters": [
            {
                "name": "sigma_deg",
                "parameter": "sigma_rad",
                "wedge": None,
                "unit": "deg",
                "least_squares": {"value": 5.0, "stderr": stderr[0], "at_bound": False},
                "posterior": {"median": 5.1, "p16": 5.0, "p84": 5.2, "p2_5": 4.9, "p97_5": 5.3},
            },
            {
                "name": "scale",
                "parameter": "scale",
                "wedge": None,
                "unit": "radiance units x rad",
                "least_squares": {"value": 100.0, "stderr": stderr[1], "at_bound": False},
            },
        ],
        "fixed_parameters": {"delta_n": 0.02, "edge_radius_um": 0.0},
        "correlation": {"names": ["sigma_deg", "scale"], "matrix": [list(r) for r in corr]},
        "model_selection": {
            "chosen": "b",
            "table": [{"variant": "a", "bic": 3.0}, {"variant": "b", "bic": 1.0}],
        },
    }


def test_parameter_table_keeps_values_and_relative_error():
    rows = explore.parameter_table(_results())
    assert [r["name"] for r in rows] == ["sigma_deg", "scale"]
    assert rows[0]["relative"] == pytest.approx(0.1 / 5.0)
    assert rows[0]["median"] == 5.1 and rows[1]["median"] is None


def test_selection_table_marks_the_chosen_variant():
    rows = explore.selection_table(_results())
    assert [r["chosen"] for r in rows] == [False, True]


def test_covariance_from_results_is_corr_times_stderrs():
    cov = explore.covariance_from_results(_results())
    np.testing.assert_allclose(cov, [[0.01, -0.8 * 0.1 * 2.0], [-0.16, 4.0]])
    assert explore.covariance_from_results(_results(stderr=(None, 1.0))) is None


def test_strong_correlations_threshold_and_order():
    m = np.array([[1, 0.3, -0.9], [0.3, 1, 0.6], [-0.9, 0.6, 1]])
    pairs = explore.strong_correlations(["a", "b", "c"], m, threshold=0.5)
    assert pairs == [("a", "c", -0.9), ("b", "c", 0.6)]


def test_params_from_results_converts_sigma_to_radians():
    p = explore.params_from_results(_results())
    assert p.sigma_rad == pytest.approx(np.deg2rad(5.0))
    assert p.scale == 100.0 and p.delta_n == 0.02


def test_params_from_results_per_wedge_sigma():
    res = _results()
    res["parameters"][0] |= {"name": "sigma_deg[1: 20 deg]", "wedge": 1}
    res["parameters"].insert(
        0,
        {
            "name": "sigma_deg[0: 10 deg]",
            "parameter": "sigma_rad",
            "wedge": 0,
            "unit": "deg",
            "least_squares": {"value": 3.0, "stderr": 0.1, "at_bound": False},
        },
    )
    p = explore.params_from_results(res)
    np.testing.assert_allclose(p.sigma_rad, np.deg2rad([3.0, 5.0]))


def test_autocorrelation_of_ar1_chain():
    # AR(1) x_t = phi x_{t-1} + e_t has autocorrelation phi^k
    rng = np.random.default_rng(1)
    phi, n, walkers = 0.8, 20000, 4
    x = np.zeros((n, walkers, 1))
    e = rng.normal(size=(n, walkers))
    for t in range(1, n):
        x[t, :, 0] = phi * x[t - 1, :, 0] + e[t]
    acf = explore.autocorrelation(x, 5)
    # 80000 samples: the estimator's error is a few 0.01 at these lags
    np.testing.assert_allclose(acf[:, 0], phi ** np.arange(5), atol=0.03)


def test_pareto_front():
    t = [1.0, 2.0, 3.0, 0.5, 2.5, np.nan]
    e = [1.0, 0.5, 0.1, 2.0, 0.6, 0.0]
    # (2.5, 0.6) is beaten by (2.0, 0.5); nan is ignored
    assert list(explore.pareto_front(t, e)) == [3, 0, 1, 2]


def test_fisher_matrix_of_a_straight_line():
    # y = a + b x with sd s: F = sum [1, x; x, x^2] / s^2 (closed form)
    x = np.array([0.0, 1.0, 2.0, 3.0])
    J = np.stack([np.ones_like(x), x], axis=1)
    F = explore.fisher_matrix(J, np.full(4, 0.5), use=np.array([1, 1, 1, 0], bool))
    np.testing.assert_allclose(F, np.array([[3, 3], [3, 5]]) / 0.25)


def test_read_table_and_observations(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("group,config,time_s,err\npreset,fast,0.5,\nmodel,x,1e-2,3\n")
    rows = explore.read_table(path)
    assert rows[0] == {"group": "preset", "config": "fast", "time_s": 0.5, "err": None}
    assert rows[1]["time_s"] == 0.01
    obs = tmp_path / "o.csv"
    obs.write_text(
        ",".join(explore.OBSERVATION_COLUMNS)
        + "\nA.dng,w10,R,-10,-80,-20,-70,3.5,0.1,1,3.4,0.2,0.5\n"
        + "A.dng,w10,G,-10,-80,-20,-70,3.5,0.1,0,3.4,0.2,0.5\n"
    )
    o = explore.read_observations(obs)
    assert list(o["used"]) == [True, False]
    assert o["theta_o_deg"][0] == -70.0 and o["wedge"][1] == "w10"


def test_find_photo_folder_checks_the_scene_hash(tmp_path):
    import hashlib

    photos, fit = tmp_path / "photos", tmp_path / "fit"
    photos.mkdir()
    fit.mkdir()
    (photos / "scene.toml").write_text("version = 1\n")
    sha = hashlib.sha256(b"version = 1\n").hexdigest()
    res = {"inputs": {"scene": {"file": "scene.toml", "sha256": sha}}}
    assert explore.find_photo_folder(fit, res) == photos.resolve()
    res["inputs"]["scene"]["sha256"] = "0" * 64
    assert explore.find_photo_folder(fit, res) is None
    # DIR-fit next to DIR
    other = tmp_path / "shots"
    other.mkdir()
    (other / "scene.toml").write_text("x = 2\n")
    res = {
        "inputs": {
            "scene": {"file": "scene.toml", "sha256": hashlib.sha256(b"x = 2\n").hexdigest()}
        }
    }
    assert explore.find_photo_folder(tmp_path / "shots-fit", res) == other.resolve()


def test_open_fit_needs_results(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"results\.json"):
        explore.open_fit(tmp_path)
    (tmp_path / "results.json").write_text(json.dumps({"files": {"observations": "o.csv"}}))
    with pytest.raises(FileNotFoundError):
        explore.open_fit(tmp_path)


def test_results_without_parameter_records_are_refused(tmp_path):
    """A results.json from before the parameter records: one line naming the folder and the
    fix, not a guess at the identity from the display name `sigma_deg[1: 20 deg]`."""
    res = _results()
    for rec in res["parameters"]:
        del rec["parameter"], rec["wedge"]
    res["files"] = {"observations": "observations.csv"}
    (tmp_path / "results.json").write_text(json.dumps(res))
    row = {c: "1" for c in explore.OBSERVATION_COLUMNS}
    lines = [",".join(row), ",".join(row.values())]
    (tmp_path / "observations.csv").write_text("\n".join(lines) + "\n")
    expected = (
        f"results.json in {tmp_path} was written by an older stairfit (no parameter records): "
        "re-run `stairfit fit`"
    )
    with pytest.raises(explore.OlderResultsError) as err:
        explore.open_fit(tmp_path)
    assert str(err.value) == expected
    with pytest.raises(explore.OlderResultsError, match=r"older stairfit .*'sigma_deg'"):
        explore.params_from_results(res)
    res["parameters"][0]["parameter"] = "sigma_rad"  # `wedge` still missing
    with pytest.raises(explore.OlderResultsError):
        explore.parameter_key(res["parameters"][0])


def test_preset_table_lists_presets():
    names = [r["name"] for r in explore.preset_table()]
    assert {"fast", "balanced", "accurate"} <= set(names)
