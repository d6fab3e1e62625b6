"""Output files and folders (app/outputs.py): where an output may go, results staged and
replaced only when the same command made them, leftovers of killed runs cleaned, a full disk
naming the real file, a filesystem without locks. The same faults through the command line are
in tests/app/test_cli_hostile.py (issue 18 and 42).
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from test_cli_errors import _folder_snapshot

from stairfit import fileio, outputs
from stairfit.errors import UserError

POSIX = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals, locks and modes")


def _entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_check_output_refuses_home_and_root(tmp_path: Path) -> None:
    for unsafe in (Path.home(), Path("/")):
        with pytest.raises(UserError, match=r"home folder|current folder|root"):
            outputs.check_output(unsafe)
    inside = tmp_path / "photos"
    inside.mkdir()
    assert outputs.check_output(tmp_path / "results", inputs=[inside]) == tmp_path / "results"
    with pytest.raises(UserError, match="contains"):
        outputs.check_output(tmp_path, inputs=[inside])


def test_stale_leftovers_of_killed_runs_are_removed(tmp_path: Path) -> None:
    out = tmp_path / "results"
    with outputs.staged_folder(out, force=False, command="fit") as tmp:  # an earlier result
        (tmp / "a.txt").write_text("old")
    young_other = tmp_path / ".other.0123abcd.partial"
    old_other = tmp_path / ".older.89abcdef.partial"
    own = [
        tmp_path / ".results.deadbeef.partial",  # incomplete: no marker
        tmp_path / ".results.old-4242",  # an older result that `results` replaced
        tmp_path / ".results.AbC_12x9.tmp",
    ]
    for p in [young_other, old_other, *own[:2]]:
        p.mkdir()
        (p / "x.png").write_bytes(b"x" * 1000)
    own[2].write_text("half a file")
    long_ago = time.time() - 2 * outputs.STALE_AGE_S
    os.utime(old_other, (long_ago, long_ago))
    keep = [tmp_path / "results.partial", tmp_path / ".results.txt", tmp_path / "mine"]
    for p in keep:
        p.write_text("not stairfit's")
    with outputs.staged_folder(out, force=True, command="fit") as tmp:
        (tmp / "a.txt").write_text("new")
    assert _entries(tmp_path) == sorted(p.name for p in [out, young_other, *keep])
    assert (out / "a.txt").read_text() == "new"


def _result(folder: Path, command: str | None, text: str = "old") -> Path:
    """A folder holding a.txt, marked as made by `stairfit COMMAND` (None: not marked)."""
    folder.mkdir()
    (folder / "a.txt").write_text(text)
    if command is not None:
        fileio.mark_complete(folder, command, "0")
    return folder


def test_force_replaces_only_a_folder_the_same_command_made(tmp_path: Path) -> None:
    (tmp_path / "target").mkdir()
    (tmp_path / "target" / "kept.txt").write_text("the link's target is not deleted")
    refused = {
        "file": lambda p: p.write_text("the user's"),
        "link": lambda p: p.symlink_to(tmp_path / "target"),
        "unmarked-folder": lambda p: _result(p, None),
        "another-command's": lambda p: _result(p, "simulate"),
    }
    for name, make in refused.items():
        out = tmp_path / name
        make(out)
        before = _folder_snapshot(tmp_path)
        refused = pytest.raises(UserError, match="--force replaces only a result 'stairfit fit'")
        with refused, outputs.staged_folder(out, force=True, command="fit") as tmp:
            (tmp / "new.txt").write_text("new")
        assert _folder_snapshot(tmp_path) == before, name
    out = _result(tmp_path / "ours", "fit")
    with outputs.staged_folder(out, force=True, command="fit") as tmp:
        (tmp / "new.txt").write_text("new")
    assert _entries(out) == [fileio.MARKER, "new.txt"]
    assert fileio.made_by(out) == "fit"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], _entries(tmp_path)


def test_a_kill_between_the_two_renames_loses_nothing(tmp_path: Path) -> None:
    # issue 42 case 2: a replacement killed between `out -> .out.old-PID` and `partial -> out`
    # (SIGKILL cannot be held back) leaves the old result aside and the new one complete in its
    # staging folder; the next run puts the newer one back before anything else
    out = tmp_path / "results"
    backup = _result(tmp_path / ".results.old-4242", "fit", "old")
    partial = _result(tmp_path / ".results.0123abcd.partial", "fit", "new")
    incomplete = _result(tmp_path / ".results.89abcdef.partial", None, "half")
    exists = pytest.raises(UserError, match="already exists")  # without --force: not replaced
    with exists, outputs.staged_folder(out, force=False, command="fit"):
        pass
    assert (out / "a.txt").read_text() == "new"  # the newer complete result, in place
    assert not backup.exists() and not partial.exists() and not incomplete.exists()
    # killed again before the new run has its own result: the result in place survives
    with pytest.raises(KeyboardInterrupt), outputs.staged_folder(out, True, command="fit") as tmp:
        (tmp / "a.txt").write_text("newest")
        raise KeyboardInterrupt
    assert (out / "a.txt").read_text() == "new"
    assert _entries(tmp_path) == ["results"]


def test_only_an_old_copy_left_is_put_back(tmp_path: Path) -> None:
    out = tmp_path / "results"
    _result(tmp_path / ".results.old-77", "fit", "old")
    _result(tmp_path / ".results.00000000.partial", None, "half")  # incomplete: not a result
    assert outputs.remove_stale_leftovers(out) == [tmp_path / ".results.00000000.partial"]
    assert (out / "a.txt").read_text() == "old"
    assert _entries(tmp_path) == ["results"]


def test_failed_staging_removes_its_folder_and_names_the_real_target(tmp_path: Path) -> None:
    out = tmp_path / "results"
    with pytest.raises(OSError) as err, outputs.staged_folder(out, False, command="fit") as tmp:
        raise OSError(28, "No space left on device", str(tmp / "figures" / "corner.png"))
    assert err.value.filename == str(out / "figures" / "corner.png")
    with pytest.raises(OSError) as err, outputs.staged_folder(out, False, command="fit"):
        raise OSError(28, "No space left on device")  # a write through a file object: no name
    assert err.value.filename == str(out)
    assert _entries(tmp_path) == []


@contextmanager
def _file_size_limit(n_bytes: int) -> Iterator[None]:
    """Writes past `n_bytes` fail with EFBIG, as writes to a full disk fail (RLIMIT_FSIZE)."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (n_bytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


@POSIX
def test_full_disk_names_the_output_file(tmp_path: Path) -> None:
    # the temporary file's writes fail as on a full disk; the error names the real target
    target = tmp_path / "out.csv"
    with pytest.raises(OSError) as err, _file_size_limit(1000), outputs.atomic_text(target) as fh:
        fh.write("x" * 100_000)
    assert err.value.filename == str(target)
    assert _entries(tmp_path) == []


@POSIX
def test_a_filesystem_without_locks_warns_and_still_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno

    def no_locks(fd: int, how: int) -> None:
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(outputs.fcntl, "flock", no_locks)
    warns = pytest.warns(UserWarning, match="does not support file locks")
    with warns, outputs.staged_folder(tmp_path / "out", force=False, command="fit") as tmp:
        (tmp / "a.txt").write_text("done")
    assert _entries(tmp_path) == ["out"]


def test_no_failed_previews_are_promised_inside_a_staging_folder(tmp_path: Path) -> None:
    # the demo fits photos inside its own staging folder, which a failed run removes
    from stairfit._failed_previews import keep_previews

    with outputs.staged_folder(tmp_path / "demo", force=False, command="demo") as tmp:
        assert outputs.in_staging(tmp / "photos" / ".stairfit-cache" / "failed-previews")
        (tmp / "pv").mkdir()
        (tmp / "pv" / "a.dng.png").write_bytes(b"png")
        spec = type("Spec", (), {"name": "a.dng"})()
        assert keep_previews(tmp / "photos" / "kept", tmp / "pv", [spec], ["a.dng"]) == ""
        assert keep_previews(tmp_path / "kept", tmp / "pv", [spec], ["a.dng"]).endswith(
            str(tmp_path / "kept")
        )
    assert not outputs.in_staging(tmp_path / "demo" / "photos")
