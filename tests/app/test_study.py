"""`stairfit study` on real Dask clusters (issue 16).

* A LocalCluster of 1 spawned worker over 3 tiny simulated folders (two of the same name, one
  broken): the broken one is recorded with its one-line error, the others fitted into
  distinct folders; a second run skips the finished ones. Two workers (each compiling the
  fit, about 20 s more here) are run by `benchmarks/bench_study.py`, which requires every
  folder fitted with 1 and with 2 workers, on an empty and on a filled cache. Slow twins: a
  second run refits only a folder whose scene changed; a study's folder holds what `stairfit
  fit` writes.
* `dask scheduler` and `dask worker` started as subprocesses on 127.0.0.1 (free ports: the
  scheduler picks one and writes it to its scheduler file), the study run through
  `--scheduler` and resumed through `--scheduler-file`.
* (slow) Ctrl-C in the middle of a study: finished folders intact, no partial folders.

Fast settings: 0.5 MP photos, 9 views, `--model sharp --no-posterior`; one JAX compilation
cache for the session, so that only the first study compiles.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from stairfit.cli import main

FAST = ("--model", "sharp", "--no-posterior", "--quiet")
FIT_FILES = {"results.json", "measurements.csv", "observations.csv", "report.html", "figures"}


@pytest.fixture(scope="session")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One tiny photo folder (9 photos of 0.5 MP), copied into every study."""
    folder = tmp_path_factory.mktemp("study-sim") / "photos"
    # 0.5 MP x 9 views as test_end_to_end: at 0.3-0.5 MP most faces are too small for their
    # texture (flagged few_blocks, docs/imaging.md §Standard errors), and 3 views then leave
    # too few rows to constrain sigma
    argv = ["simulate", str(folder), "--megapixels", "0.5", "--views", "9", "--quiet"]
    assert main(argv) == 0
    return folder


@pytest.fixture(scope="session")
def jax_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The JAX compilation cache every study of this session shares."""
    return tmp_path_factory.mktemp("study-jax-cache")


def specimen(simulated: Path, dest: Path, **metadata: object) -> Path:
    """A copy of the simulated folder with `[specimen.metadata]` appended to its scene."""
    shutil.copytree(simulated, dest, ignore=shutil.ignore_patterns(".stairfit-cache"))
    lines = "".join(f"{k} = {json.dumps(v)}\n" for k, v in metadata.items())
    with open(dest / "scene.toml", "a") as fh:
        fh.write(f"\n[specimen.metadata]\n{lines}")
    return dest


def read_table(out: Path) -> dict[str, dict[str, str]]:
    """study.csv by photo folder (resolved path)."""
    with open(out / "study.csv", newline="") as fh:
        return {row["folder"]: row for row in csv.DictReader(fh)}


def test_local_cluster_fits_records_failures_and_resumes(
    simulated: Path, jax_cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "root"
    one = specimen(simulated, root / "lab1" / "photos", printer="MK4", nozzle_c=210)
    two = specimen(simulated, root / "lab2" / "photos", printer="X1C", nozzle_c=220)
    broken = specimen(simulated, root / "broken", printer="X1C")
    text = (broken / "scene.toml").read_text().replace("layer_um =", "layr_um =")
    (broken / "scene.toml").write_text(text)
    out = tmp_path / "out"
    argv = ["study", str(root), "-o", str(out), "--local-workers", "1", "--jax-cache"]
    status = main([*argv, str(jax_cache), *FAST])
    assert status == 1  # one folder failed; the others are done
    table = read_table(out)
    assert set(table) == {str(p.resolve()) for p in (one, two, broken)}
    bad = table[str(broken.resolve())]
    assert bad["status"] == "failed" and bad["output"] == ""
    assert bad["error"] == (
        f"{broken.resolve() / 'scene.toml'}: specimen.layr_um: unknown field; did you mean "
        "'layer_um'?"
    )
    assert f"failed: {broken.resolve()}: " in capsys.readouterr().out
    outputs = []
    for folder in (one, two):
        row = table[str(folder.resolve())]
        assert row["status"] == "fitted" and row["chosen_model"] == "sharp", row
        dest = out / row["output"]
        assert {p.name for p in dest.iterdir()} >= FIT_FILES
        results = json.loads((dest / "results.json").read_text())
        scene_sha = hashlib.sha256((folder / "scene.toml").read_bytes()).hexdigest()
        assert results["inputs"]["scene"]["sha256"] == scene_sha
        assert float(row["sigma_deg"]) == results["parameters"][0]["least_squares"]["value"]
        assert row["jax_cache"] == str(jax_cache.resolve())
        outputs.append(row["output"])
    assert len(set(outputs)) == 2  # lab1/photos and lab2/photos do not collide
    assert table[str(two.resolve())]["meta.nozzle_c"] == "220"
    assert table[str(two.resolve())]["meta.printer"] == "X1C"
    page = (out / "study.html").read_text()
    assert all(f"href='{name}/report.html'" in page for name in outputs)
    assert (out / "study-figures" / "vs_meta_nozzle_c.png").is_file()
    assert (out / "study-figures" / "vs_meta_printer.png").is_file()
    assert any(jax_cache.iterdir())  # the workers wrote their compilations to the shared cache
    assert not list(out.glob(".*.partial"))

    # resume: the finished folders are skipped (not rewritten), the broken one tried again
    stamps = {name: (out / name / "results.json").stat().st_mtime_ns for name in outputs}
    assert main([*argv, str(jax_cache), *FAST]) == 1
    again = read_table(out)
    statuses = [again[str(p.resolve())]["status"] for p in (one, two, broken)]
    assert statuses == ["skipped", "skipped", "failed"]
    for name in outputs:
        assert (out / name / "results.json").stat().st_mtime_ns == stamps[name]
    assert again[str(one.resolve())]["sigma_deg"] == table[str(one.resolve())]["sigma_deg"]


@pytest.mark.slow  # two more studies with a fit each; the fast test above resumes by skipping
def test_resume_refits_only_the_folder_whose_scene_changed(
    simulated: Path, jax_cache: Path, tmp_path: Path
) -> None:
    one = specimen(simulated, tmp_path / "root" / "a", nozzle_c=210)
    two = specimen(simulated, tmp_path / "root" / "b", nozzle_c=220)
    out = tmp_path / "out"
    argv = ["study", str(tmp_path / "root"), "-o", str(out), "--local-workers", "1"]
    argv += ["--jax-cache", str(jax_cache), *FAST]
    assert main(argv) == 0
    table = read_table(out)
    stamps = {f: (out / table[f]["output"] / "results.json").stat().st_mtime_ns for f in table}
    text = (two / "scene.toml").read_text().replace("nozzle_c = 220", "nozzle_c = 225")
    (two / "scene.toml").write_text(text)
    assert main(argv) == 0
    again = read_table(out)
    a, b = str(one.resolve()), str(two.resolve())
    assert (again[a]["status"], again[b]["status"]) == ("skipped", "fitted")
    # the scene file is one of the folder's input files (Scene.input_files), so both changed
    assert again[b]["note"] == (
        "replaced an out-of-date result (scene_sha256, input_files_sha256 changed)"
    )
    assert again[b]["meta.nozzle_c"] == "225"
    assert (out / again[a]["output"] / "results.json").stat().st_mtime_ns == stamps[a]
    assert (out / again[b]["output"] / "results.json").stat().st_mtime_ns != stamps[b]


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """`dask scheduler` and one `dask worker` on 127.0.0.1; (address, scheduler file)."""
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD": "spawn"}
    scheduler_file = tmp_path / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [
        subprocess.Popen(
            [str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
             "--scheduler-file", str(scheduler_file), *common],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    ]  # fmt: skip
    try:
        address = _wait_for_address(scheduler_file, procs[0])
        procs.append(
            subprocess.Popen(
                [str(bin_dir / "dask"), "worker", address, "--host", "127.0.0.1",
                 "--nworkers", "1", "--nthreads", "1", *common],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
        )  # fmt: skip
        yield address, scheduler_file
    finally:
        # the worker first, then the scheduler: a worker whose scheduler is already gone
        # spends seconds trying to reach it before it exits
        for proc in reversed(procs):
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def _wait_for_address(scheduler_file: Path, proc: subprocess.Popen, timeout: float = 60) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, "dask scheduler exited"
        if scheduler_file.is_file():
            try:
                return json.loads(scheduler_file.read_text())["address"]
            except (ValueError, KeyError):
                pass  # being written
        time.sleep(0.2)
    raise TimeoutError("dask scheduler did not write its scheduler file")


def test_existing_scheduler_runs_the_study_and_resumes(
    simulated: Path, jax_cache: Path, tmp_path: Path, dask_cluster: tuple[str, Path]
) -> None:
    address, scheduler_file = dask_cluster
    assert address.startswith("tcp://127.0.0.1:")
    a = specimen(simulated, tmp_path / "a", layer="thin")
    b = specimen(simulated, tmp_path / "b", layer="thick")
    out = tmp_path / "out"
    cache = ("--jax-cache", str(jax_cache))
    common = [str(a), str(b), "-o", str(out), *cache, *FAST]
    assert main(["study", *common, "--scheduler", address]) == 0
    table = read_table(out)
    assert [table[str(p.resolve())]["status"] for p in (a, b)] == ["fitted", "fitted"]
    assert main(["study", *common, "--scheduler-file", str(scheduler_file)]) == 0
    table = read_table(out)
    assert [table[str(p.resolve())]["status"] for p in (a, b)] == ["skipped", "skipped"]


def test_unreachable_scheduler_is_a_one_line_user_error(
    tmp_path: Path, simulated: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = specimen(simulated, tmp_path / "a")
    argv = ["study", str(folder), "-o", str(tmp_path / "out"), "--scheduler-file"]
    status = main([*argv, str(tmp_path / "none.json"), *FAST])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("stairfit study: error: --scheduler-file: ") and "dask scheduler" in err


@pytest.mark.slow  # a fresh process, a cluster and a compilation: about a minute
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_keeps_finished_folders_and_leaves_no_partial_ones(
    simulated: Path, jax_cache: Path, tmp_path: Path, sig: int
) -> None:
    # SIGTERM (issue 42 case 11) left a .partial with chain.npz and a lock, and no study.csv
    folders = [specimen(simulated, tmp_path / "root" / f"s{k}") for k in range(4)]
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "stairfit.cli", "study", str(tmp_path / "root"), "-o"]
    argv += [str(out), "--local-workers", "1", "--jax-cache", str(jax_cache), *FAST]
    proc = subprocess.Popen(argv, start_new_session=True, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not list((out / ".stairfit-study").glob("*.json")):  # a first folder finished
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)  # what Ctrl-C in a terminal does: the whole group
        else:
            proc.send_signal(sig)  # what `kill PID`, `timeout` or a batch system does
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == (130 if sig == signal.SIGINT else 143), err
    expected = "interrupted" if sig == signal.SIGINT else "terminated by SIGTERM"
    assert f"stairfit study: {expected}" in err
    assert not list(out.glob(".*.partial")) and not list(out.glob(".*.lock"))
    assert not list(tmp_path.glob(".*.lock"))
    ledgers = list((out / ".stairfit-study").glob("*.json"))
    assert ledgers
    for ledger in ledgers:  # every folder the workers finished is complete
        json.loads((out / ledger.stem / "results.json").read_text())
        assert (out / ledger.stem / "report.html").is_file()
    table = read_table(out)
    assert len(table) == len(folders)
    assert {row["status"] for row in table.values()} <= {"fitted", "interrupted"}
    assert any(row["status"] == "interrupted" for row in table.values())


@pytest.mark.slow  # an extra fit in this process (its compilation is not cached here)
def test_a_study_folder_holds_what_stairfit_fit_writes(
    simulated: Path, jax_cache: Path, tmp_path: Path
) -> None:
    folder = specimen(simulated, tmp_path / "a", printer="MK4")
    out = tmp_path / "out"
    cache = ("--jax-cache", str(jax_cache))
    assert main(["study", str(folder), "-o", str(out), "--local-workers", "1", *cache, *FAST]) == 0
    direct = tmp_path / "direct"
    assert main(["fit", str(folder), "-o", str(direct), *FAST]) == 0
    (row,) = read_table(out).values()
    in_study = out / row["output"]
    files = {p.relative_to(in_study) for p in in_study.rglob("*")}
    assert files == {p.relative_to(direct) for p in direct.rglob("*")}
    a, b = (json.loads((d / "results.json").read_text()) for d in (in_study, direct))
    for r in (a, b):  # each variant's fitting time (`elapsed_s`) is the one thing that differs
        for row in r["model_selection"]["table"]:
            assert row.pop("elapsed_s") > 0
    for key in ("parameters", "fixed_parameters", "model_selection", "inputs", "settings"):
        assert a[key] == b[key], key


@pytest.mark.slow  # a cluster, a worker killed while it fits: about a minute
def test_a_study_ends_when_the_only_worker_of_its_cluster_dies(
    simulated: Path, jax_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    # issue 42 case 8: a worker started without a nanny died mid-task; the study waited forever
    import threading

    from stairfit import study

    monkeypatch.setattr(study, "WORKER_LOSS_S", 5.0)
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD": "spawn"}
    scheduler_file = tmp_path / "scheduler.json"
    scheduler = subprocess.Popen(
        [str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
         "--scheduler-file", str(scheduler_file), "--no-dashboard"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    worker = None
    try:
        address = _wait_for_address(scheduler_file, scheduler)
        worker = subprocess.Popen(
            [str(bin_dir / "dask"), "worker", address, "--host", "127.0.0.1", "--no-nanny",
             "--nthreads", "1", "--no-dashboard"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        folder = specimen(simulated, tmp_path / "a")
        out = tmp_path / "out"

        def kill_when_fitting() -> None:
            deadline = time.monotonic() + 300
            while not list(out.glob(".*.partial")) and time.monotonic() < deadline:
                time.sleep(0.1)
            worker.kill()

        killer = threading.Thread(target=kill_when_fitting, daemon=True)
        killer.start()
        argv = ["study", str(folder), "-o", str(out), "--scheduler", address]
        status = main([*argv, "--jax-cache", str(jax_cache), *FAST])
        killer.join(timeout=60)
    finally:
        for proc in (worker, scheduler):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(timeout=30)
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1, err
    assert err[-1].startswith("stairfit study: error: the scheduler tcp://127.0.0.1:"), err
    assert "has had no worker for 5 s with 1 folder(s) still to fit" in err[-1]
    assert read_table(out)[str(folder.resolve())]["status"] == "interrupted"
