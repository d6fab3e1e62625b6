"""Hostile and careless input (issue 18): the catalogue of faults, one table or test per fault.

Each case gives: no traceback, no silent wrong result, no deleted input, no leftover file, and
one clear line (exit status 2 for a mistake in the input, 1 for a system error, 128 + N for a
signal). The photo folders are copies of the small simulated folder of tests/app/test_cli_errors.py
(3 photos of 0.5 MP); almost every case stops before any model is fitted, so no JAX
compilation is needed.
"""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import textwrap
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
import test_cli_errors as cli_errors
from test_cli_errors import _folder_snapshot, assert_one_line_user_error, run

from stairfit import fileio, outputs

simulated = cli_errors.simulated  # the session's small simulated photo folder (a fixture)
photos = cli_errors.photos  # a private copy of it, to break (a fixture)
POSIX = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals, locks and modes")


def _entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# --- 1. data loss: an output that is, or contains, an input ---------------------------------

# (id, the -o given relative to the test's tmp_path (the photos are tmp_path/photos), --force)
UNSAFE_OUTPUTS = [
    ("photo-folder", "photos", False),
    ("photo-folder-force", "photos", True),
    ("parent-of-photos-force", ".", True),
    ("scene-file-force", "photos/scene.toml", True),
    ("a-photo-force", "photos/IMG_0002.dng", True),
    ("cache-folder-force", "photos/.stairfit-cache", True),
    ("link-to-photos-force", "link", True),
]


@pytest.mark.parametrize(
    ("output", "force"), [c[1:] for c in UNSAFE_OUTPUTS], ids=[c[0] for c in UNSAFE_OUTPUTS]
)
def test_output_holding_an_input_is_refused_and_nothing_is_deleted(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], output: str, force: bool
) -> None:
    (tmp_path / "link").symlink_to(photos, target_is_directory=True)
    (photos / ".stairfit-cache").mkdir()
    before = _folder_snapshot(photos)
    top = _entries(tmp_path)
    extra = ["--force"] if force else []
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / output), "--quiet", *extra)
    fragment = "stairfit keeps" if "cache" in output else "which this run reads"
    assert_one_line_user_error(status, err, "fit", fragment, "choose")
    assert _folder_snapshot(photos) == before
    assert _entries(tmp_path) == top


@pytest.mark.parametrize("command", ["fit", "simulate", "demo"])
def test_dot_output_with_force_is_refused_without_traceback(
    photos: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    command: str,
) -> None:
    # `-o .` (fit) or `OUT = .` (simulate, demo): the current folder, here the photo folder
    # itself for fit and an unrelated working folder for the others.
    cwd = photos if command == "fit" else tmp_path / "work"
    cwd.mkdir(exist_ok=True)
    (cwd / "mine.txt").write_text("keep me")
    before = _folder_snapshot(cwd)
    monkeypatch.chdir(cwd)
    argv = ["fit", str(photos), "-o", "."] if command == "fit" else [command, "."]
    status, err = run(capsys, *argv, "--force", "--quiet")
    fragment = "which this run reads" if command == "fit" else "the current folder"
    assert_one_line_user_error(status, err, command, fragment)
    assert _folder_snapshot(cwd) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# --- 8. leftovers (app/outputs.py's own cases: tests/app/test_outputs.py) ------------------


@pytest.mark.parametrize("command", ["demo", "fit"])
def test_force_never_deletes_a_photo_folder(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    # issue 42 case 1: `demo DIR --force` and `fit PHOTOS -o OTHER_PHOTOS --force` deleted the
    # other folder's RAWs, scene.toml and notes; even a folder `stairfit simulate` made is kept
    other = tmp_path / "other"
    assert cli_errors.main(["simulate", str(other), "--megapixels", "0.3", "--views", "3",
                            "--quiet"]) == 0  # fmt: skip
    (other / "notes.txt").write_text("the user's notes")
    capsys.readouterr()
    before = _folder_snapshot(other)
    argv = ["demo", str(other)] if command == "demo" else ["fit", str(photos), "-o", str(other)]
    status, err = run(capsys, *argv, "--force", "--quiet")
    assert_one_line_user_error(status, err, command, str(other), "'stairfit simulate'",
                               "--force replaces only")  # fmt: skip
    assert _folder_snapshot(other) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other", "photos"]


_FULL_DISK = """
import resource, signal, sys
from stairfit.cli import main
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
sys.exit(main(sys.argv[2:]))
"""


@POSIX
@pytest.mark.parametrize("command", ["predict", "measure"])
def test_a_full_disk_is_one_line_naming_the_file(photos: Path, tmp_path: Path, command: str):
    # issue 42: "disk full names a folder or says Input/output error, not the file"
    out = tmp_path / ("p.csv" if command == "predict" else "m")
    argv = (["predict", "--theta-o-deg", "-90:90:0.01", "-o", str(out)] if command == "predict"
            else ["measure", str(photos), "-o", str(out), "--quiet", "--no-cache"])  # fmt: skip
    done = subprocess.run([sys.executable, "-c", _FULL_DISK, "20000", *argv], text=True,
                          capture_output=True, env={**os.environ, "STAIRFIT_JAX_CACHE": "off"},
                          timeout=600)  # fmt: skip
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert lines[0].startswith(f"stairfit {command}: error: {out}"), lines[0]
    named = lines[0].split(": error: ")[1].split(": ")[0]
    assert named != str(out) or command == "predict", lines[0]  # the file, not the folder
    assert "File too large" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


_SLOW_SIMULATE = """
import sys
from stairfit.cli import main
sys.exit(main(["simulate", sys.argv[1], "--megapixels", "4", "--views", "40"]))
"""


@POSIX
@pytest.mark.parametrize(
    "sig",
    [signal.SIGTERM, pytest.param(signal.SIGINT, marks=pytest.mark.slow)],  # SIGINT: as before
    ids=["SIGTERM", "SIGINT"],
)
def test_signal_during_a_run_cleans_up_with_one_line(tmp_path: Path, sig: int) -> None:
    out = tmp_path / "sim"
    env = {**os.environ, "STAIRFIT_JAX_CACHE": "off"}
    proc = subprocess.Popen(
        [sys.executable, "-c", _SLOW_SIMULATE, str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 240
    while not list(tmp_path.glob(".sim.*.partial/IMG_0001.dng")):  # rendering has begun
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no photo rendered in 240 s"
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    expected = 128 + sig if sig != signal.SIGINT else 130
    assert proc.returncode == expected, err
    lines = [ln for ln in err.splitlines() if ln.startswith("stairfit simulate")]
    assert len(lines) == 1 and ("terminated by SIGTERM" in lines[0] or "interrupted" in lines[0])
    assert "Traceback" not in err
    assert _entries(tmp_path) == []


# --- 10. two runs into one output ------------------------------------------------------------

_HOLD_LOCK = """
import sys, time
from pathlib import Path
from stairfit import fileio, outputs
with outputs.output_lock(Path(sys.argv[1]).resolve()):
    print("locked", flush=True)
    time.sleep(600)
"""


@POSIX
def test_second_run_into_a_locked_output_is_refused_and_a_dead_lock_is_not(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "results"
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD_LOCK, str(out)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        status, err = run(capsys, "fit", str(photos), "-o", str(out), "--quiet")
        assert_one_line_user_error(status, err, "fit", str(out), "another stairfit run", "wait")
        status, err = run(capsys, "predict", "--theta-o-deg", "0", "-o", str(out))
        assert_one_line_user_error(status, err, "predict", "another stairfit run")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.communicate()
    assert (tmp_path / ".results.lock").exists()  # left by the killed holder ...
    (photos / "IMG_0001.dng").write_text("garbage")  # ... does not block: the run gets further
    status, err = run(capsys, "fit", str(photos), "-o", str(out), "--quiet")
    assert_one_line_user_error(status, err, "fit", "IMG_0001.dng", "cannot decode")
    assert _entries(tmp_path) == ["photos"]  # and the stale lock file is gone


# --- 12. file modes --------------------------------------------------------------------------


@POSIX
def test_written_files_honour_the_umask(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    old = os.umask(0o027)
    try:
        status, err = run(capsys, "predict", "--theta-o-deg", "0", "-o", str(tmp_path / "a.csv"))
        assert status == 0, err
        outputs.atomic_bytes(tmp_path / "b.bin", b"x")
        fileio.atomic_bytes(tmp_path / "c.bin", b"x")
        sibling = fileio.temporary_sibling(tmp_path / "d.dng")
    finally:
        os.umask(old)
    for p in ("a.csv", "b.bin", "c.bin", sibling.name):
        assert stat.S_IMODE((tmp_path / p).stat().st_mode) == 0o640, p


@POSIX
def test_simulated_photos_and_chain_honour_the_umask(simulated: Path, tmp_path: Path) -> None:
    import numpy as np

    from stairfit.fitting._chain import save_npz

    umask = os.umask(0)
    os.umask(umask)
    save_npz(tmp_path / "chain.npz", {"x": np.zeros(3)})
    for p in [*simulated.iterdir(), tmp_path / "chain.npz"]:
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask, p.name


# --- 2. the measurement cache is verified, not trusted ---------------------------------------


def _specs(folder: Path) -> list:
    from stairfit.imaging_specs import photo_specs
    from stairfit.scene import load_scene

    return photo_specs(load_scene(folder))


def _tamper(cache: Path, how: str, column: str = "value") -> None:
    lines = cache.read_text().splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    col = header.index(column)
    if how == "scale-one-photo":  # every row of the first photo x 1.1
        photo = lines[1].split(",")[0]
        for k in range(1, len(lines)):
            fields = lines[k].split(",")
            if fields[0] == photo:
                fields[col] = repr(float(fields[col]) * 1.1)
                lines[k] = ",".join(fields)
    elif how == "one-digit":
        fields = lines[1].split(",")
        digit = next(i for i, ch in enumerate(fields[col]) if ch.isdigit() and ch != "0")
        fields[col] = fields[col][:digit] + "0" + fields[col][digit + 1 :]
        lines[1] = ",".join(fields)
    elif how == "truncated":
        lines = lines[: len(lines) // 2]
    cache.write_text("".join(lines))


@pytest.mark.parametrize("how", ["scale-one-photo", "one-digit", "truncated", "no-checksum"])
def test_tampered_cache_is_measured_again_with_a_warning(photos: Path, tmp_path: Path, how: str):
    from stairfit import imaging
    from stairfit.imaging._cache import checksum_path

    cache = tmp_path / "cache" / "measurements.csv"
    specs = _specs(photos)
    first = imaging.measure_photos(specs, cache=cache)
    if how == "no-checksum":
        checksum_path(cache).unlink()
    else:
        _tamper(cache, how)
    with pytest.warns(imaging.ImagingWarning, match="measuring every photo again") as record:
        again = imaging.measure_photos(specs, cache=cache)
    assert str(cache) in str(record[0].message)
    assert again.to_csv() == first.to_csv()  # measured again, not read from the cache
    if how != "scale-one-photo":
        return
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the rewritten cache is trusted again, silently
        assert imaging.measure_photos(specs, cache=cache).to_csv() == first.to_csv()


def test_cache_in_the_way_or_read_only_does_not_stop_the_measurement(
    photos: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from stairfit import imaging
    from stairfit.imaging import _cache

    specs = _specs(photos)
    reference = imaging.measure_photos(specs)
    folder_cache = tmp_path / "a" / "measurements.csv"
    folder_cache.mkdir(parents=True)  # a folder where the cache file should be
    with pytest.warns(imaging.ImagingWarning) as record:
        table = imaging.measure_photos(specs, cache=folder_cache, preview_dir=tmp_path / "pv")
    assert table.to_csv() == reference.to_csv()
    text = " ".join(str(w.message) for w in record)
    assert "cannot read it" in text and "cannot write it" in text
    # a read-only photo folder that already holds a cache (simulated: root ignores mode bits)
    cache = tmp_path / "b" / "measurements.csv"
    imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "pv1")

    def read_only(path: Path, data: bytes) -> Path:
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(_cache, "atomic_bytes", read_only)
    monkeypatch.setattr(Path, "unlink", lambda self, missing_ok=False: read_only(self, b""))
    with pytest.warns(imaging.ImagingWarning, match="cannot write it"):
        table = imaging.measure_photos(specs, cache=cache, preview_dir=tmp_path / "pv2")
    assert table.to_csv() == reference.to_csv()
    assert sorted(p.name for p in (tmp_path / "pv2").iterdir()) == sorted(
        p.name for p in (tmp_path / "pv1").iterdir()
    )


def test_fit_says_in_one_line_that_an_edited_cache_is_measured_again(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # overexposed photos: measuring succeeds (and fills the cache), the fit stops right after
    cli_errors.rewrite_photos(photos, overexpose=1000.0)
    argv = ["fit", str(photos), "-o", str(tmp_path / "out"), "--quiet"]
    status, err = run(capsys, *argv)
    assert_one_line_user_error(status, err, "fit", "no usable measurement")
    cache = photos / ".stairfit-cache" / "measurements.csv"
    _tamper(cache, "one-digit", column="black_level")  # values are NaN: all saturated
    status, err = run(capsys, *argv)
    lines = err.strip().splitlines()
    assert status == 2 and "Traceback" not in err and len(lines) == 2, err
    assert lines[0].startswith("stairfit fit: warning: measurement cache ")
    assert str(cache) in lines[0] and "does not match its checksum" in lines[0]
    assert lines[1].startswith("stairfit fit: error: ") and "no usable measurement" in lines[1]


# --- 3. non-physical refractive indices ------------------------------------------------------

# (id, [specimen] index table, fragments of the one-line error); each passed the old check of
# n(550 nm) alone
BAD_INDICES = [
    (
        "cauchy-below-1-at-380",
        {"model": "cauchy", "a": 1.05, "b_um2": -0.01},
        ("specimen.index", "n(380 nm) = 0.98", "Re n > 1", "fix the cauchy coefficients"),
    ),
    (
        "sellmeier-pole-in-band",
        {"model": "sellmeier", "b": [1.0], "c_um": [0.5]},
        ("specimen.index", "Sellmeier pole", "500 nm", "fix the sellmeier coefficients"),
    ),
    (
        "tabulated-unsorted",
        {"model": "tabulated", "wavelength_nm": [700, 400, 550], "n": [1.46, 1.48, 1.47]},
        ("specimen.index", "increase strictly", "sort the table"),
    ),
    (
        "negative-k",
        {"model": "constant", "n": 1.5, "k": -0.01},
        ("specimen.index", "k >= 0"),
    ),
]


@pytest.mark.parametrize(
    ("index", "fragments"), [c[1:] for c in BAD_INDICES], ids=[c[0] for c in BAD_INDICES]
)
def test_non_physical_index_is_refused(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], index: dict, fragments
) -> None:
    def change(scene: dict) -> None:
        scene["specimen"].pop("material", None)
        scene["specimen"]["index"] = index

    cli_errors.edit_scene(photos, change)
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", *fragments)
    assert _entries(tmp_path) == ["photos"]


def test_fit_outside_the_validity_range_warns_and_notes_it(photos: Path) -> None:
    from stairfit.pipeline import fit_setup, index_notes
    from stairfit.presets import get_preset
    from stairfit.scene import load_scene

    cli_errors.edit_scene(photos, lambda s: s["specimen"].update(material="pla-bodurov2016"))
    scene = load_scene(photos)
    setup = fit_setup(scene, get_preset("accurate"))  # 5 nm samples over 380-780 nm
    with pytest.warns(UserWarning, match="valid over 405-635 nm") as record:
        notes = index_notes(scene, setup)
    message = str(record[0].message)
    assert notes == [message]
    assert "380-400 nm and 640-780 nm" in message
    assert "% of the channels' spectral weight" in message
    cli_errors.edit_scene(photos, lambda s: s["specimen"].update(material="pla"))
    constant = load_scene(photos)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert index_notes(constant, fit_setup(constant, get_preset("accurate"))) == []


@pytest.mark.parametrize(
    ("options", "status", "fragments"),
    [
        (["--material", "pla-bodurov2016", "--wavelength-nm", "390"], 0,
         ("warning:", "valid over 405-635 nm", "390 nm", "extrapolated")),
        (["--material", "pla-bodurov2016", "--wavelength-nm", "450,600"], 0, ()),
        (["--delta-n", "-0.5"], 2, ("error:", "--delta-n", "Re n > 1")),
        (["--material", "pla-bodurov2016", "--delta-n", "-0.47"], 2, ("error:", "Re n > 1")),
    ],
    ids=["extrapolated", "inside", "delta-n-below-1", "material-delta-n-below-1"],
)  # fmt: skip
def test_predict_checks_the_index_at_every_wavelength(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options, status, fragments
) -> None:
    out = tmp_path / "p.csv"
    code, err = run(capsys, "predict", "--theta-o-deg", "0", "-o", str(out), *options)
    assert code == status, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == (1 if fragments else 0), err
    for fragment in fragments:
        assert fragment in err
    assert out.exists() == (status == 0)


# --- 4, 5, 11. photo files: duplicates, paths outside the folder, files that are not photos -----


def _set_file(k: int, name: str) -> object:
    return lambda scene: scene["photos"][k].update(file=name)


def _link(d: Path, name: str, target: Path | str) -> None:
    (d / name).symlink_to(target)


# (id, how the folder is broken, fragments of the one-line error)
PHOTO_FILE_CASES = [
    (
        "same-file-dot-slash",
        lambda d: cli_errors.edit_scene(d, _set_file(1, "./IMG_0001.dng")),
        ("photos[1].file", "'./IMG_0001.dng' is the same file as photos[0].file", "once"),
    ),
    (
        "same-file-via-link",
        lambda d: (
            _link(d, "alias.dng", "IMG_0001.dng"),
            cli_errors.edit_scene(d, _set_file(2, "alias.dng")),
        ),
        ("photos[2].file", "'alias.dng' is the same file as photos[0].file"),
    ),
    (
        "the-folder-itself",
        lambda d: cli_errors.edit_scene(d, _set_file(0, ".")),
        ("photos[0].file", "'.' names the photo folder, not a photo file"),
    ),
    (
        "spaces-around-the-name",
        lambda d: cli_errors.edit_scene(d, _set_file(1, " IMG_0002.dng")),
        ("photos[1].file", "is not in", "mind the spaces"),
    ),
    (
        "parent-path",
        lambda d: cli_errors.edit_scene(d, _set_file(0, "../elsewhere/IMG_0001.dng")),
        ("photos[0].file", "is outside the photo folder", "copy the file (or a link to it)"),
    ),
    (
        "absolute-path-outside",
        lambda d: cli_errors.edit_scene(d, _set_file(0, "/etc/hostname")),
        ("photos[0].file", "'/etc/hostname' is outside the photo folder"),
    ),
    (
        "link-to-dev-zero",
        lambda d: (
            _link(d, "zero.dng", "/dev/zero"),
            cli_errors.edit_scene(d, _set_file(0, "zero.dng")),
        ),
        ("photos[0].file", "'zero.dng' is a link to /dev/zero, a character device", "RAW file"),
    ),
    (
        "link-loop",  # issue 42 case 10: a traceback (RuntimeError: Symlink loop)
        lambda d: (
            _link(d, "loop.dng", "loop2.dng"),
            _link(d, "loop2.dng", "loop.dng"),
            cli_errors.edit_scene(d, _set_file(0, "loop.dng")),
        ),
        ("photos[0].file", "'loop.dng' is a loop of symbolic links", "fix the link"),
    ),
    (
        "named-pipe",  # issue 42 case 7: reading it would block forever
        lambda d: (os.mkfifo(d / "pipe.dng"), cli_errors.edit_scene(d, _set_file(0, "pipe.dng"))),
        ("photos[0].file", "'pipe.dng' is a named pipe (FIFO), not a RAW file"),
    ),
    (
        "folder-named-like-a-photo",
        lambda d: ((d / "IMG_0002.dng").unlink(), (d / "IMG_0002.dng").mkdir()),
        ("photos[1].file", "'IMG_0002.dng' is a folder, not a RAW file"),
    ),
    (
        "dangling-link",
        lambda d: ((d / "IMG_0003.dng").unlink(), _link(d, "IMG_0003.dng", "gone.dng")),
        ("photos[2].file", "is a link to gone.dng, which does not exist", "fix the link"),
    ),
]


@pytest.mark.parametrize(
    ("breaks", "fragments"),
    [c[1:] for c in PHOTO_FILE_CASES],
    ids=[c[0] for c in PHOTO_FILE_CASES],
)
def test_photo_file_mistakes_are_one_line_errors(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], breaks, fragments
) -> None:
    breaks(photos)
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", *fragments)
    assert _entries(tmp_path) == ["photos"]


def test_a_link_inside_the_folder_may_point_outside(photos: Path, tmp_path: Path) -> None:
    from stairfit.scene import load_scene

    store = tmp_path / "store"
    store.mkdir()
    (photos / "IMG_0001.dng").rename(store / "IMG_0001.dng")
    _link(photos, "IMG_0001.dng", store / "IMG_0001.dng")
    scene = load_scene(photos)
    assert store / "IMG_0001.dng" in scene.input_files()  # and so protected as an output


def test_same_bytes_under_two_names_warns(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    cli_errors.rewrite_photos(photos, overexpose=1000.0)  # stops after measuring (fast)
    shutil.copyfile(photos / "IMG_0001.dng", photos / "copy.dng")
    cli_errors.edit_scene(photos, _set_file(2, "copy.dng"))
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 2, err
    assert lines[0].startswith("stairfit fit: warning: photos 'IMG_0001.dng', 'copy.dng' are")
    assert "same file content" in lines[0]
    assert lines[1].startswith("stairfit fit: error: ")


def test_preview_names_never_leave_the_preview_folder_and_never_collide(tmp_path: Path) -> None:
    import re

    from stairfit import imaging

    names = {
        "IMG_0001.dng": "IMG_0001.dng.png",  # a plain file name keeps its name
        "a__IMG.dng": "a__IMG.dng.png",
        "a/IMG.dng": r"a__IMG\.dng-[0-9a-f]{8}\.png",  # flattened, with its name's hash
        "a\\IMG.dng": r"a__IMG\.dng-[0-9a-f]{8}\.png",
        "../../x/IMG.dng": r"x__IMG\.dng-[0-9a-f]{8}\.png",
        "/abs/IMG.dng": r"abs__IMG\.dng-[0-9a-f]{8}\.png",
        "..": r"photo-[0-9a-f]{8}\.png",
    }
    paths = []
    for name, expected in names.items():
        rois = {"w": [(0, 0), (9, 0), (9, 9)]}
        spec = imaging.PhotoSpec(tmp_path / "a.dng", name=name, rois=rois)
        path = imaging.preview_path(tmp_path / "pv", spec)
        assert path.parent == tmp_path / "pv" and re.fullmatch(expected, path.name), (name, path)
        paths.append(path)
    assert len(set(paths)) == len(paths)  # issue 42: a/IMG.dng and a__IMG.dng shared one file


@pytest.mark.parametrize(
    ("polygon", "fragments"),
    [
        ([[100, 100], [300, 300], [300, 100], [100, 300]], ("crosses itself", "in order")),
        ([[100, 100], ["nan", 100], [300, 300]], ("point 1 is [nan, 100.0]", "finite number")),
        ([[100, 100], [200, 100], [300, 100]], ("folds back",)),
    ],
    ids=["bow-tie", "nan", "collinear"],
)
@pytest.mark.parametrize("where", ["roi_px", "face_mm"])
def test_bad_polygons_are_named(
    photos: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    polygon: list,
    fragments: tuple,
    where: str,
) -> None:
    points = [[float(c) for c in p] for p in polygon]

    def change(scene: dict) -> None:
        if where == "roi_px":
            scene["photos"][0]["roi_px"]["w10"] = points
        else:
            scene["specimen"]["wedges"][0]["face_mm"] = points

    cli_errors.edit_scene(photos, change)
    field = "photos[0].roi_px.w10" if where == "roi_px" else "specimen.wedges[0].face_mm"
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", field, *fragments)


def test_scene_file_with_a_byte_order_mark_is_read(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = photos / "scene.toml"
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())  # as Windows Notepad saves UTF-8
    (photos / "IMG_0002.dng").write_text("not a raw file")  # stop right after the scene is read
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "IMG_0002.dng", "cannot decode")


# --- issue 12: a linear DNG below its black level; previews of photos that failed ------------


def test_linear_dng_below_black_names_the_flag_and_the_right_fix(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    _link(folder, "DSC8695.dng", shared_data / "raw" / "DSC8695.dng")
    (folder / "scene.toml").write_text(
        textwrap.dedent(
            """\
            [specimen]
            layer_um = 150
            [[specimen.wedges]]
            name = "w30"
            angle_deg = 30
            roi_px = [[100, 100], [300, 100], [300, 300], [100, 300]]
            [[photos]]
            file = "DSC8695.dng"
            light_deg = 0
            view_deg = 20
            """
        )
    )
    status, err = run(capsys, "fit", str(folder), "-o", str(tmp_path / "out"), "--quiet")
    lines = err.strip().splitlines()
    assert status == 2 and "Traceback" not in err and len(lines) == 2, err
    assert "warning: photo 'DSC8695.dng': every ROI is below the black level (51 DN" in lines[0]
    assert lines[1].startswith("stairfit fit: error: ")
    for fragment in ("no usable measurement", "3 below_black", "black level", "original RAW"):
        assert fragment in lines[1]
    assert "shorten the exposures" not in lines[1]
    table = (folder / ".stairfit-cache" / "measurements.csv").read_text().splitlines()
    rows = [dict(zip(table[0].split(","), ln.split(","), strict=True)) for ln in table[1:]]
    assert [r["value"] for r in rows] == ["nan"] * 3  # never a negative radiance
    assert all("below_black" in r["flag"] for r in rows)
    kept = folder / ".stairfit-cache" / "failed-previews"
    assert str(kept) in lines[1] and (kept / "DSC8695.dng.png").is_file()


def test_low_signal_photo_warns(tmp_path: Path) -> None:
    import numpy as np

    from stairfit import imaging
    from stairfit.imaging import synthetic

    # 40 DN above black of 14 bits, with shot noise: an ROI without any scatter is flagged
    # few_blocks (its standard error cannot be estimated, docs/imaging.md §Standard errors)
    rng = np.random.default_rng(0)
    mosaic = (1024 + rng.poisson(40, (120, 160))).astype(np.uint16)
    path = synthetic.write_dng(
        tmp_path / "dim.dng",
        mosaic,
        black_level=1024,
        white_level=16383,
        exposure=imaging.Exposure(0.01, 4.0, 100),
    )
    spec = imaging.PhotoSpec(path, rois={"w": [(20, 20), (140, 20), (140, 100), (20, 100)]})
    low = r"very low signal.*(39\.[5-9]|40|40\.[0-4]) DN above black, 0\.26%"
    with pytest.warns(imaging.ImagingWarning, match=low):
        table = imaging.measure_photos([spec])
    assert all(r.flag == "" for r in table)  # a warning, not a reason to drop the photo
    bright = (1024 + rng.poisson(4000, (120, 160))).astype(np.uint16)
    path = synthetic.write_dng(tmp_path / "ok.dng", bright, black_level=1024, white_level=16383,
                               exposure=imaging.Exposure(0.01, 4.0, 100))  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bright_table = imaging.measure_photos([imaging.PhotoSpec(path, rois=dict(spec.rois))])
    assert all(r.flag == "" for r in bright_table)  # usable rows, so the silence means something


def test_failed_photo_keeps_a_preview_with_markers_and_a_grid(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import cv2

    roi = tomllib.loads((photos / "scene.toml").read_text())["photos"][1]["roi_px"]["w10"]
    cli_errors.edit_scene(photos, lambda s: cli_errors._roi_out_of_image(s, photo=1))
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    kept = photos / ".stairfit-cache" / "failed-previews"
    assert_one_line_user_error(status, err, "fit", "IMG_0002.dng", "pixel grid", str(kept))
    assert _entries(kept) == ["IMG_0002.dng.png"]  # only the photo that failed
    failed = cv2.imread(str(kept / "IMG_0002.dng.png"))
    normal = cv2.imread(str(next((photos / ".stairfit-cache").glob("*.previews/*.png"))))
    grey = np.all(failed == (160, 160, 160), axis=2)  # the grid lines
    assert grey.mean() > 0.01 and np.all(normal != (160, 160, 160), axis=2).mean() > 0.99
    assert _entries(tmp_path) == ["photos"]
    # fixed, the next run removes the stale failed previews (it then fails later: saturated)
    cli_errors.rewrite_photos(photos, overexpose=1000.0)
    cli_errors.edit_scene(photos, lambda s: s["photos"][1]["roi_px"].update(w10=roi))
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "no usable measurement", str(kept))
    assert _entries(kept) == ["IMG_0001.dng.png", "IMG_0002.dng.png", "IMG_0003.dng.png"]


# --- 6, 7, 9. numeric options, huge requests, contradictions (all refused before any work) ----

PREDICT_CASES = [
    # 6. NaN in, NaN out: every numeric option finite and in range
    (["--n", "nan"], ("--n", "'nan' is not a finite number")),
    (["--n", "inf"], ("--n", "not a finite number")),
    (["--n", "1.5+nanj"], ("--n", "not a finite number")),
    (["--n", "1.5-0.1j"], ("--n", "0 <= Im(n)")),
    (["--delta-n", "nan"], ("--delta-n", "must be a finite number, not nan")),
    (["--layer-um", "nan"], ("--layer-um", "finite")),
    (["--layer-um", "inf"], ("--layer-um", "finite")),
    (["--sigma-deg", "nan"], ("--sigma-deg", "finite")),
    (["--edge-radius-um", "nan"], ("--edge-radius-um", "outside the valid range")),
    (["--theta-o-deg", "nan"], ("--theta-o-deg", "not a finite number")),
    (["--wavelength-nm", "inf"], ("--wavelength-nm", "not a finite number")),
    # 7. huge requests: refused up front, never a MemoryError, an OverflowError or a long run
    (["--theta-o-deg", "-90:90:1e-9"], ("--theta-o-deg", "gives 1.8e+11 values", "coarser")),
    (["--theta-o-deg", "0:inf:1"], ("--theta-o-deg", "not a finite number")),
    (["--theta-o-deg", "-90:90:0.000018"], ("--theta-o-deg", "gives 1e+07 values")),
    (["--wedge-deg", "10", "--theta-o-deg", "-90:90:0.0001"],
     ("the table would have 1,800,001 rows", "1 wedge x", "the limit is 1,000,000")),
    (["--lobes", "--wedge-deg", "10:80:1", "--theta-i-deg", "-90:90:0.01"],
     ("the table would have", "x 3 lobes", "limit")),
    # 9. silently accepted, no effect: contradictions refused
    (["--sigma-deg", "1e6"], ("--sigma-deg", "1e+06 deg is outside [0, 90] deg")),
    (["--n", "1.5", "--material", "pla"], ("--n with --material", "only one")),
    (["--lobes", "--diffuse"], ("--lobes with --diffuse",)),
    (["--cosine-weighted"], ("--cosine-weighted", "add --diffuse")),
    (["--lobes", "--sigma-deg", "3"], ("--sigma-deg with --lobes", "sharp")),
    (["--lobes", "--theta-o-deg", "0"], ("--theta-o-deg with --lobes",)),
    (["--diffuse", "--theta-i-deg", "10"], ("--theta-i-deg with --diffuse",)),
]  # fmt: skip


@pytest.mark.parametrize(
    ("options", "fragments"), PREDICT_CASES, ids=[" ".join(c[0]) for c in PREDICT_CASES]
)
def test_predict_refuses_bad_numbers_huge_grids_and_contradictions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options, fragments
) -> None:
    t0 = time.perf_counter()
    status, err = run(capsys, "predict", "-o", str(tmp_path / "out.csv"), *options)
    assert_one_line_user_error(status, err, "predict", *fragments)
    assert _entries(tmp_path) == []
    assert time.perf_counter() - t0 < 10  # refused up front (no model evaluation)


def test_predict_defaults_and_documented_combinations_still_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the README's examples: --sigma-deg 0 with --diffuse, --lobes with --theta-i-deg
    for k, options in enumerate(
        [
            ["--lobes", "--wedge-deg", "30", "--theta-i-deg", "-90:90:45"],
            ["--diffuse", "--sigma-deg", "0", "--wedge-deg", "10", "--theta-o-deg", "0,10"],
            ["--diffuse", "--cosine-weighted", "--wedge-deg", "10", "--theta-o-deg", "0"],
            ["--n", "1.5", "--lobes", "--sigma-deg", "0", "--wedge-deg", "20"],
        ]
    ):
        status, err = run(capsys, "predict", "-o", str(tmp_path / f"{k}.csv"), *options)
        assert status == 0 and err == "", (options, err)


@pytest.mark.parametrize("command", ["fit", "simulate", "measure"])
def test_too_many_workers_is_refused(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    target = (
        [str(photos), "-o", str(tmp_path / "out")] if command != "simulate"
        else [str(tmp_path / "s")]
    )  # fmt: skip
    status, err = run(capsys, command, *target, "--workers", "100000", "--quiet")
    assert_one_line_user_error(status, err, command, "--workers", "<= 32", "100000")
    assert _entries(tmp_path) == ["photos"]


def test_killed_predict_temp_file_is_removed_by_the_next_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "p.csv"
    (tmp_path / ".p.csv.k3x_9ab2.tmp").write_text("half a table")  # left by SIGKILL (mkstemp)
    (tmp_path / ".p.csv.0123abcd.tmp").write_text("half a table")  # (this version's names)
    status, err = run(capsys, "predict", "--theta-o-deg", "0", "-o", str(out))
    assert status == 0, err
    assert _entries(tmp_path) == ["p.csv"]


def test_huge_erosion_is_refused_up_front_and_a_large_one_adapts(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cli_errors.edit_scene(photos, lambda s: s.update(extraction={"erode_px": 1000}))
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "extraction.erode_px", "1000 is outside [0, 64]")
    assert _entries(tmp_path) == ["photos"]
    from stairfit import imaging

    # 64 px would empty every face of these 0.5 MP photos (once the whole fit stopped with
    # "empty after eroding it by 64 px"): the erosion adapts to each face's thickness
    # (docs/imaging.md §Pixels) and every face is measured, quickly (most are then too small
    # for their texture: few_blocks, not a failure)
    cli_errors.edit_scene(photos, lambda s: s.update(extraction={"erode_px": 64}))
    t0 = time.perf_counter()
    status, err = run(capsys, "measure", str(photos), "-o", str(tmp_path / "m"), "--quiet")
    assert status == 0, err
    assert time.perf_counter() - t0 < 30
    table = imaging.MeasurementTable.read_csv(tmp_path / "m" / "measurements.csv")
    assert len(table) == 54 and all(np.isfinite(r.value) and "thin" not in r.flag for r in table)
    assert all(3 <= r.erode_px <= r.thickness_px / 2 for r in table), [
        (r.erode_px, r.thickness_px) for r in table
    ]


def test_narrow_roi_shortcut_agrees_with_the_erosion() -> None:
    # whenever the up-front "too narrow" test refuses an ROI, the erosion leaves nothing of it
    import cv2

    from stairfit import imaging
    from stairfit.imaging import _roi

    rng = np.random.default_rng(7)
    narrow = 0
    for _ in range(400):
        r = int(rng.integers(1, 12))
        pts = rng.uniform(20.0, 60.0, size=(int(rng.integers(3, 6)), 2))  # away from the border
        pts = pts[np.argsort(np.arctan2(*(pts - pts.mean(0)).T[::-1]))]  # a star-shaped order
        filled = imaging.roi_mask(
            tuple(map(tuple, pts.tolist())), (80, 80), 0, photo="p", wedge="w"
        )
        mask = filled.mask.astype(np.uint8)
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        eroded = cv2.erode(np.pad(mask, r + 1), disk, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        if _roi._too_narrow(mask, r, (True, True), (True, True)):
            narrow += 1
            assert not eroded.any()
    assert narrow > 50  # the shortcut was exercised


def test_below_black_rows_are_nan_also_as_ratios_to_a_reference(tmp_path: Path) -> None:
    from stairfit import imaging
    from stairfit.imaging import synthetic

    rng = np.random.default_rng(3)
    mosaic = (1024 + rng.normal(0, 2, (120, 200))).astype(np.uint16)
    mosaic[:, :100] -= 30  # the face: 30 DN below the black level
    mosaic[:, 100:] += 2000  # the reference: well above it
    path = synthetic.write_dng(tmp_path / "a.dng", mosaic, black_level=1024, white_level=16383,
                               exposure=imaging.Exposure(0.01, 4.0, 100))  # fmt: skip
    rois = {"face": [(10, 10), (90, 10), (90, 110), (10, 110)],
            "ref": [(110, 10), (190, 10), (190, 110), (110, 110)]}  # fmt: skip
    spec = imaging.PhotoSpec(path, rois=rois, reference="ref")
    rows = imaging.measure_frame(imaging.decode_raw(path), spec, imaging.ExtractionSettings()).rows
    face = [r for r in rows if r.wedge == "face"]
    assert len(face) == 3 and all(r.normalised_by == "ref" for r in face)
    for row in face:  # never a negative ratio
        assert np.isnan(row.value) and np.isnan(row.stderr), row
        assert row.flag == "below_black"
    assert all(r.value > 0 for r in rows if r.wedge == "ref")


@POSIX
def test_a_device_or_pipe_is_never_replaced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for argv in (["predict", "--theta-o-deg", "0", "-o", str(fifo), "--force"],
                 ["simulate", str(fifo), "--force", "--quiet"]):  # fmt: skip
        status, err = run(capsys, *argv)
        assert_one_line_user_error(status, err, argv[0], "is a named pipe (FIFO)", "not a file")
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    assert _entries(tmp_path) == ["pipe"]


# --- issue 42: hostile scene files, outputs and polygons ------------------------------------


def _replace_scene(d: Path, make: object) -> None:
    (d / "scene.toml").unlink()
    make(d / "scene.toml")  # type: ignore[operator]


SCENE_FILE_CASES = [
    ("named-pipe", lambda p: os.mkfifo(p), "is a named pipe (FIFO), not a scene file"),
    ("folder", lambda p: p.mkdir(), "is a folder, not a scene file"),
    ("link-to-dev-zero", lambda p: p.symlink_to("/dev/zero"),
     "is a link to /dev/zero, a character device, not a scene file"),
    ("link-loop", lambda p: p.symlink_to(p.name), "is a loop of symbolic links"),
    ("deep-nesting", lambda p: p.write_text("a = " + "[" * 100_000 + "]" * 100_000),
     "nested too deeply"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("make", "fragment"), [c[1:] for c in SCENE_FILE_CASES], ids=[c[0] for c in SCENE_FILE_CASES]
)
def test_a_scene_file_that_is_not_a_text_file_is_one_line(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], make, fragment: str
) -> None:
    _replace_scene(photos, make)
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", fragment)
    assert _entries(tmp_path) == ["photos"]


def _markers(change) -> object:
    return lambda d: cli_errors.edit_scene(d, lambda s: change(s["markers"]))


def _first_wedge_name(name: str) -> object:
    return lambda d: cli_errors.edit_scene(
        d, lambda s: s["specimen"]["wedges"][0].update(name=name)
    )


SCENE_VALUE_CASES = [
    ("duplicate-marker-id", _markers(lambda m: m["marker"][1].update(id=m["marker"][0]["id"])),
     ("markers.marker[1].id", "is also markers.marker[0].id")),
    ("marker-id-outside-dictionary", _markers(lambda m: m["marker"][0].update(id=50)),
     ("markers.marker[0].id", "50 is outside [0, 49]")),
    ("unknown-dictionary", _markers(lambda m: m.update(dictionary="DICT_4X4_5O")),
     ("markers.dictionary", "not an OpenCV ArUco dictionary", "DICT_4X4_50")),
    ("min-markers-above-count", _markers(lambda m: m.update(min_markers=100)),
     ("markers.min_markers", "100 is more than the 4 markers listed")),
    ("absurd-corner", _markers(lambda m: m["marker"][0]["corners_mm"][0].__setitem__(0, 1e300)),
     ("markers.marker[0].corners_mm", "beyond +-1e+06")),
    ("absurd-roi-vertex", lambda d: cli_errors.edit_scene(
        d, lambda s: s["photos"][0].update(roi_px={"w10": [[0, 0], [1e300, 0], [0, 10]]})),
     ("photos[0].roi_px.w10", "beyond +-1e+06")),
    ("empty-wedge-name", _first_wedge_name(""), ("specimen.wedges[0].name", "'' is empty")),
    ("blank-wedge-name", _first_wedge_name("  "), ("specimen.wedges[0].name", "is empty")),
]  # fmt: skip


@pytest.mark.parametrize(
    ("breaks", "fragments"), [c[1:] for c in SCENE_VALUE_CASES],
    ids=[c[0] for c in SCENE_VALUE_CASES],
)  # fmt: skip
def test_impossible_scene_values_are_one_line(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], breaks, fragments
) -> None:
    breaks(photos)
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", *fragments)


def test_an_empty_patch_name_is_refused(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    patch = {"name": "", "roi_px": [[0, 0], [40, 0], [40, 40], [0, 40]]}
    cli_errors.edit_scene(photos, lambda s: s.update(patches=[patch]))
    status, err = run(capsys, "measure", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "measure", "patches[0].name", "is empty")


def test_a_huge_value_is_not_echoed_whole(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # issue 42: a 5 MB illuminant name came back as a 5 MB error line
    cli_errors.edit_scene(photos, lambda s: s["light"].update(illuminant="D" * 5_000_000))
    status, err = run(capsys, "fit", str(photos), "-o", str(tmp_path / "out"), "--quiet")
    assert_one_line_user_error(status, err, "fit", "scene.toml", "light.illuminant",
                               "(5000003 characters)")  # fmt: skip
    assert len(err) < 3000


@pytest.mark.parametrize("command", ["fit", "predict", "demo"])
def test_an_output_that_is_a_loop_of_links_is_one_line(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    loop = tmp_path / "loop"
    loop.symlink_to(loop.name)
    argv = {
        "fit": ["fit", str(photos), "-o", str(loop), "--quiet"],
        "predict": ["predict", "--theta-o-deg", "0", "-o", str(loop)],
        "demo": ["demo", str(loop), "--quiet"],
    }[command]
    status, err = run(capsys, *argv, "--force")
    assert_one_line_user_error(status, err, command, str(loop), "is a loop of symbolic links")
    assert _entries(tmp_path) == ["loop", "photos"]


def test_results_say_which_values_came_from_the_cache(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # issue 42 case 5: a cache edited with its checksum recomputed was trusted, and results.json
    # listed the photos' hashes as if measured from them (the issue's set-up: 5 views)
    import json

    from stairfit.imaging._cache import checksum_path, table_digest

    photos = tmp_path / "photos"
    simulate = ["simulate", str(photos), "--megapixels", "0.5", "--views", "5", "--seed", "1"]
    assert run(capsys, *simulate, "--quiet")[0] == 0

    assert run(capsys, "measure", str(photos), "-o", str(tmp_path / "m"), "--quiet")[0] == 0
    cache = photos / ".stairfit-cache" / "measurements.csv"
    _tamper(cache, "scale-one-photo")
    check = json.loads(checksum_path(cache).read_text())  # recomputed, as anyone could
    check.update(scheme="sha256", digest=table_digest(cache.read_bytes(), check["table_version"],
                                                      None, check["previews"]))  # fmt: skip
    checksum_path(cache).write_text(json.dumps(check))
    fit = ["fit", str(photos), "-o", str(tmp_path / "out"), "--no-posterior", "--model",
           "sharp+floor", "--quiet", "--force"]  # fmt: skip
    status, err = run(capsys, *fit)
    assert status == 0 and "written without this user's cache key" in err, err

    def results() -> dict:
        return json.loads((tmp_path / "out" / "results.json").read_text())

    assert {p["measured_from"] for p in results()["inputs"]["photos"]} == {"photo"}
    status = cli_errors.main(fit)
    printed = capsys.readouterr()
    assert status == 0, printed.err
    assert {p["measured_from"] for p in results()["inputs"]["photos"]} == {"cache"}
    assert "came from the measurement cache" in printed.out
    assert any("came from the measurement cache" in n for n in results()["diagnostics"]["notes"])


def test_no_user_cache_folder_without_a_home() -> None:
    # issue 42: `HOME=` made the caches at /.cache/stairfit
    from stairfit._jaxcache import cache_dir, user_cache_dir

    bad = ({"HOME": ""}, {"HOME": "/"}, {"HOME": "relative"}, {"HOME": "", "XDG_CACHE_HOME": "x"})
    for env in bad:
        assert user_cache_dir(env) is None and cache_dir(env) is None, env
    assert user_cache_dir({"HOME": "/h/u"}) == Path("/h/u/.cache/stairfit")  # any absolute home
    assert user_cache_dir({"HOME": "", "XDG_CACHE_HOME": "/c"}) == Path("/c/stairfit")


@POSIX
def test_a_folder_name_that_is_not_utf8_is_measured_and_printed(
    photos: Path, tmp_path: Path
) -> None:
    # issue 42: a non-UTF-8 folder name gave a UnicodeEncodeError after the whole fit
    base = os.fsencode(tmp_path)
    folder, out = base + b"/bad\xffname", base + b"/out\xff"
    os.rename(photos, folder)
    argv = [sys.executable, "-c", "from stairfit.cli import entry; entry()", "measure",
            os.fsdecode(folder), "-o", os.fsdecode(out), "--quiet"]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, timeout=600,
                          env={**os.environ, "STAIRFIT_JAX_CACHE": "off"})  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert b"Traceback" not in done.stderr
    assert b"bad\\udcffname" in done.stdout  # printed, its odd byte shown as an escape
    with open(out + b"/report.html", "rb") as fh:
        assert b"bad\xffname" in fh.read()  # the name's own bytes, as on disk


def test_a_huge_sparse_photo_is_refused_by_its_size(
    photos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # issue 42: a 3 GB sparse DNG was read whole; a 20 GB one ran out of memory and was told
    # about "the accurate preset's filleted rungs"
    target = photos / "IMG_0002.dng"
    target.unlink()
    with open(target, "wb") as fh:
        fh.truncate(20 * 2**30)  # sparse: no disk used
    t0 = time.monotonic()
    status, err = run(capsys, "measure", str(photos), "-o", str(tmp_path / "m"), "--quiet")
    assert time.monotonic() - t0 < 60
    assert status == 2 and "Traceback" not in err, err
    line = err.strip().splitlines()[-1]
    assert "IMG_0002.dng" in line and "is 20 GiB, more than the 2 GiB allowed" in line, line
    assert "filleted" not in err


@POSIX
def test_a_link_to_dev_zero_in_the_cache_is_skipped(photos: Path, tmp_path: Path) -> None:
    # issue 42 case 7: a link to /dev/zero in place of the cache read until memory ran out
    from stairfit import imaging

    cache = tmp_path / "cache" / "measurements.csv"
    cache.parent.mkdir()
    cache.symlink_to("/dev/zero")
    with pytest.warns(imaging.ImagingWarning, match="a link to /dev/zero, a character device"):
        table = imaging.measure_photos(_specs(photos), cache=cache)
    assert len(table) > 0
