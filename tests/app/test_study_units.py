"""`stairfit study` without a cluster: finding folders, result names, the resume rule, the table.

The cluster runs are in tests/app/test_study.py; these check the rules they rely on, each against
values worked out here (hashes by hashlib, intervals by hand).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import pytest
import tomli_w
from test_scene import GOOD

from stairfit import __version__
from stairfit.errors import UserError
from stairfit.outcome import FitOptions
from stairfit.presets import get_preset
from stairfit.scene import load_scene
from stairfit.study import find_folders, output_name, output_names, prepare_output
from stairfit.study_report import Z95, csv_text, parameter_cells, study_row
from stairfit.study_task import (
    FolderTask,
    input_fingerprint,
    replaced_note,
    up_to_date,
    write_ledger,
)

OPTIONS = FitOptions(get_preset("balanced"), False, "sharp", True, 0, 1, True, False)


def _photo_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "scene.toml").write_text(tomli_w.dumps(GOOD))
    for name in ("a.dng", "b.dng"):
        (path / name).write_bytes(name.encode() * 100)
    return path


def test_roots_are_searched_and_photo_folders_taken_as_they_are(tmp_path: Path) -> None:
    a = _photo_folder(tmp_path / "root" / "a")
    c = _photo_folder(tmp_path / "root" / "b" / "c")
    _photo_folder(tmp_path / "root" / "a" / "inner")  # below a photo folder: not a specimen
    _photo_folder(tmp_path / "root" / ".hidden" / "d")
    _photo_folder(tmp_path / "root" / "out" / "e")  # the study folder itself is never searched
    lone = _photo_folder(tmp_path / "lone")
    found = find_folders(
        [tmp_path / "root", a, lone / "scene.toml"], exclude=(tmp_path / "root" / "out")
    )
    assert found == tuple(sorted(p.resolve() for p in (a, c, lone)))


def test_a_missing_path_or_an_empty_root_is_a_one_line_user_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="no such folder"):
        find_folders([tmp_path / "nope"])
    (tmp_path / "empty" / "x").mkdir(parents=True)
    with pytest.raises(UserError, match=r"no scene\.toml in it or below it"):
        find_folders([tmp_path / "empty"])


def test_result_names_are_unique_for_folders_of_the_same_name_and_stable(tmp_path: Path) -> None:
    one, two = tmp_path / "lab1" / "photos", tmp_path / "lab2" / "photos"
    names = output_names([one, two])
    assert names[one] != names[two]
    assert names[one].startswith("photos-") and names[two].startswith("photos-")
    digest = hashlib.sha256(str(one).encode()).hexdigest()[:8]
    assert output_name(one) == f"photos-{digest}"
    assert (
        output_name(tmp_path / "my scan #3")
        == f"my_scan_3-{output_name(tmp_path / 'my scan #3')[-8:]}"
    )


def test_an_existing_folder_that_is_not_a_study_is_refused(tmp_path: Path) -> None:
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(UserError, match="not a stairfit study folder"):
        prepare_output(tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    prepare_output(tmp_path / "new")
    prepare_output(tmp_path / "new")  # a study folder is taken again


def _fitted(tmp_path: Path) -> tuple[FolderTask, Path, Path, dict]:
    """A photo folder, a result folder whose results.json records its scene's hash, a ledger."""
    folder = _photo_folder(tmp_path / "photos")
    out = tmp_path / "study"
    task = FolderTask(folder, out, "photos-x", OPTIONS, False, None, __version__)
    dest = out / task.name
    dest.mkdir(parents=True)
    sha = hashlib.sha256((folder / "scene.toml").read_bytes()).hexdigest()
    (dest / "results.json").write_text(json.dumps({"inputs": {"scene": {"sha256": sha}}}))
    ledger = out / ".stairfit-study" / "photos-x.json"
    fingerprint = input_fingerprint(load_scene(folder), OPTIONS)
    write_ledger(ledger, task, fingerprint)
    return task, dest, ledger, fingerprint


def test_fingerprint_holds_the_hash_of_the_scene_and_of_every_photo(tmp_path: Path) -> None:
    task, _, _, fingerprint = _fitted(tmp_path)
    photo = hashlib.sha256(b"a.dng" * 100).hexdigest()
    assert fingerprint["input_files_sha256"]["a.dng"] == photo
    scene = hashlib.sha256((task.folder / "scene.toml").read_bytes()).hexdigest()
    assert fingerprint["scene_sha256"] == scene
    assert fingerprint["stairfit_version"] == __version__
    assert fingerprint["options"]["seed"] == 0 and fingerprint["options"]["model"] == "sharp"


def test_a_result_is_up_to_date_only_for_the_same_inputs_and_options(tmp_path: Path) -> None:
    task, dest, ledger, fingerprint = _fitted(tmp_path)
    assert up_to_date(dest, ledger, fingerprint)
    (task.folder / "b.dng").write_bytes(b"changed")
    now = input_fingerprint(load_scene(task.folder), OPTIONS)
    assert not up_to_date(dest, ledger, now)
    assert replaced_note(dest, ledger, now, False) == (
        "replaced an out-of-date result (input_files_sha256 changed)"
    )
    other_seed = input_fingerprint(load_scene(task.folder), dataclasses.replace(OPTIONS, seed=1))
    assert not up_to_date(dest, ledger, other_seed)
    progress_only = dataclasses.replace(OPTIONS, progress=True, workers=2, cache=False)
    assert input_fingerprint(load_scene(task.folder), progress_only) == now


def test_an_incomplete_or_foreign_result_is_not_up_to_date(tmp_path: Path) -> None:
    _, dest, ledger, fingerprint = _fitted(tmp_path)
    (dest / "results.json").write_text(json.dumps({"inputs": {"scene": {"sha256": "0" * 64}}}))
    assert not up_to_date(dest, ledger, fingerprint)  # the folder is not the ledger's
    (dest / "results.json").unlink()
    assert not up_to_date(dest, ledger, fingerprint)  # no results.json: not complete
    ledger.unlink()
    assert "without a study ledger" in replaced_note(dest, ledger, fingerprint, False)


RESULTS = {
    "model_selection": {"chosen": "sharp+floor"},
    "settings": {"posterior": True},
    "diagnostics": {
        "least_squares": {"chi2": 50.0, "dof": 45, "reduced_chi2": 50 / 45, "n_used": 48},
        "timings_s": {"measure_s": 1.0, "fit_s": 2.0, "posterior_s": 3.0},
    },
    "parameters": [
        {
            "name": "sigma_deg",
            "least_squares": {"value": 5.0, "stderr": 0.2},
            "posterior": {"median": 5.1, "p2_5": 4.7, "p97_5": 5.5},
        },
        {"name": "floor", "least_squares": {"value": 0.01, "stderr": 0.005}},
    ],
    "fixed_parameters": {"delta_n": 0.0, "edge_radius_um": 0.0},
}


def test_the_table_gives_every_parameter_with_its_interval(tmp_path: Path) -> None:
    cells = parameter_cells(RESULTS)
    assert cells["sigma_deg"] == {
        "value": 5.1, "lo95": 4.7, "hi95": 5.5, "from": "posterior", "stderr": 0.2
    }  # fmt: skip
    assert cells["floor"]["lo95"] == pytest.approx(0.01 - 1.959964 * 0.005)
    assert cells["floor"]["from"] == "least_squares" and pytest.approx(1.959964) == Z95
    assert cells["edge_radius_um"] == {
        "value": 0.0, "lo95": None, "hi95": None, "stderr": None, "from": "fixed"
    }  # fmt: skip
    report = {
        "folder": "/data/a",
        "output": "a-1234abcd",
        "status": "fitted",
        "error": None,
        "note": None,
        "scene": {"layer_um": 100.0, "material": "pla", "wedges_deg": [10, 45], "n_photos": 3,
                  "metadata": {"printer": "MK4", "nozzle_c": 215}},
        "results": RESULTS,
        "run": {"elapsed_s": 9.0, "host": "h", "pid": 1, "peak_rss_mb": 500.0},
    }  # fmt: skip
    row = study_row(report)
    assert row["meta.printer"] == "MK4" and row["meta.nozzle_c"] == 215
    assert row["chosen_model"] == "sharp+floor" and row["wedges_deg"] == "10;45"
    failed = {**report, "status": "failed", "error": "x: y: z", "results": None, "scene": None}
    text = csv_text([row, study_row(failed)]).splitlines()
    header = text[0].split(",")
    assert header[:4] == ["folder", "output", "status", "error"]
    assert {"sigma_deg", "sigma_deg_lo95", "sigma_deg_hi95", "meta.printer"} <= set(header)
    assert text[2].startswith("/data/a,,failed,x: y: z,")


# --- issue 42: a study's cluster options and a cluster that lost its workers ------------------


def _study(capsys: pytest.CaptureFixture[str], tmp_path: Path, *options: str) -> tuple[int, str]:
    import time

    from stairfit.cli import main

    folder = tmp_path / "a"
    if not folder.exists():
        _photo_folder(folder)
    t0 = time.monotonic()
    status = main(["study", str(folder), "-o", str(tmp_path / "out"), "--quiet", *options])
    assert time.monotonic() - t0 < 10  # refused at once, not after a connection timeout
    return status, capsys.readouterr().err.strip()


@pytest.mark.parametrize(
    ("options", "fragments"),
    [
        (["--scheduler", ""], ["--scheduler: '' is empty", "leave --scheduler out"]),
        (["--scheduler", "tcp://127.0.0.1:99999"], ["--scheduler:", "port '99999'", "65535"]),
        (["--scheduler", "tcp://host:http"], ["port 'http'"]),
        (["--local-workers", "100000000"], ["--local-workers: 100000000 is outside 1 to"]),
        (["--local-workers", "0"], ["--local-workers: 0 is outside 1 to"]),
    ],
    ids=["empty-address", "port-99999", "port-not-a-number", "workers-huge", "workers-0"],
)
def test_cluster_options_are_checked_before_any_wait(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str], fragments: list[str]
) -> None:
    status, err = _study(capsys, tmp_path, *options)
    assert status == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("stairfit study: error: "), err
    for fragment in fragments:
        assert fragment in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        ('{"address": "tcp://127.0.0.1:87', "is not valid JSON"),  # truncated
        ('{"type": "Scheduler"}', "names no scheduler 'address'"),
        ('{"address": "tcp://127.0.0.1:0"}', "port '0'"),
        ("[" * 100_000, "is not valid JSON"),
    ],
    ids=["truncated", "no-address", "port-0", "deep"],
)
def test_a_broken_scheduler_file_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, fragment: str
) -> None:
    path = tmp_path / "scheduler.json"
    path.write_text(content)
    status, err = _study(capsys, tmp_path, "--scheduler-file", str(path))
    assert status == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("stairfit study: error: --scheduler-file: ") and fragment in err, err


def test_a_cluster_that_lost_its_last_worker_ends_the_wait() -> None:
    # issue 42 case 8: a study on a cluster whose only worker (no nanny) died waited forever
    import logging
    import time

    from distributed import Client, LocalCluster

    from stairfit import study

    with (
        LocalCluster(n_workers=1, processes=False, threads_per_worker=1, dashboard_address=None,
                     silence_logs=logging.CRITICAL) as cluster,
        Client(cluster) as client,
    ):  # fmt: skip
        future = client.submit(time.sleep, 2, pure=False)
        time.sleep(0.3)
        cluster.scale(0)  # the only worker is gone, the task is not finished
        t0 = time.monotonic()
        with pytest.raises(study.WorkersLostError, match="no worker for 1 s with 1 folder"):
            for _ in study.completed(client, {future: None}, "the cluster", worker_loss_s=1.0):
                pass
        assert time.monotonic() - t0 < 30


def test_an_internal_error_keeps_its_traceback_in_a_file(tmp_path: Path) -> None:
    # issue 42: `study --quiet` printed thousands of lines of worker tracebacks
    from stairfit.study_task import LEDGER_DIR, describe_error

    task = FolderTask(tmp_path / "a", tmp_path / "out", "a-12345678", OPTIONS, False, None, "0")
    (tmp_path / "out" / LEDGER_DIR).mkdir(parents=True)
    try:
        raise RuntimeError("something broke\nacross lines")
    except RuntimeError as err:
        line = describe_error(err, task)
    trace = tmp_path / "out" / LEDGER_DIR / "a-12345678.error.txt"
    assert "\n" not in line and str(trace) in line and "please report it" in line
    assert "Traceback (most recent call last)" in trace.read_text()
