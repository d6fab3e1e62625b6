"""Signals, pipes and closed streams at every stage (issue 42 cases 9 and 11, and its unclear
messages): one line, the documented exit status, nothing left behind, no traceback and no
arrays; after SIGKILL no process of the run is left running.

The slow cases run whole fits (a posterior) in a subprocess.
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import emcee
import numpy as np
import pytest

POSIX = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
ENV = {**os.environ, "STAIRFIT_JAX_CACHE": "off"}


def _stairfit(*argv: str) -> list[str]:
    return [sys.executable, "-c", "from stairfit.cli import entry; entry()", *argv]


# --- the posterior's likelihood ------------------------------------------------------------


def test_an_interrupt_inside_the_likelihood_is_raised_without_emcee_printing(capsys) -> None:
    # issue 42 case 9: emcee printed "Exception while calling your likelihood function", the
    # walkers' parameters and a traceback before the one-line message
    from stairfit.fitting._posterior import _Guarded

    calls = 0

    def log_prob(theta: np.ndarray) -> np.ndarray:
        nonlocal calls
        calls += 1
        if calls == 5:
            raise KeyboardInterrupt
        return -0.5 * np.sum(theta**2, axis=1)

    guarded = _Guarded(log_prob)
    sampler = emcee.EnsembleSampler(8, 2, guarded, vectorize=True)
    start = np.random.default_rng(0).normal(size=(8, 2))
    with pytest.raises(KeyboardInterrupt):
        try:
            sampler.run_mcmc(start, 50, progress=False)
        finally:
            guarded.reraise()
    printed = capsys.readouterr()
    assert printed.out == "" and printed.err == "", printed
    assert calls == 5  # nothing evaluated after the interrupt
    guarded.reraise()  # raised once only


# --- the command line ------------------------------------------------------------------------


@POSIX
def test_sigterm_during_the_imports_is_one_line() -> None:
    # issue 42: "a SIGTERM during imports exits 143 silently"
    proc = subprocess.Popen(_stairfit("predict", "--theta-o-deg", "0"), env=ENV, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    time.sleep(0.8)  # inside main, importing jax (seconds), before any table is written
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.strip() == "stairfit predict: terminated by SIGTERM", err
    # a signal held back until an import ends is sent again a moment later, by when a loaded
    # machine may have written the table's header: never a partial line
    assert out == "" or (out.endswith("\n") and out.count("\n") == 1), out


@POSIX
def test_a_reader_that_leaves_the_pipe_ends_the_run_quietly() -> None:
    # issue 42: `predict | head -1` said "Broken pipe"
    for grid in ("0", "-90:90:0.01"):  # the pipe closes at the last flush, or while writing
        command = shlex.join(_stairfit("predict", "--theta-o-deg", grid))
        done = subprocess.run(
            f'{command} | head -1; echo "status ${{PIPESTATUS[0]}}"',
            shell=True, executable="/bin/bash", env=ENV, text=True, capture_output=True,
            timeout=300,
        )  # fmt: skip
        lines = done.stdout.splitlines()
        assert lines[0].startswith("wedge_deg,wavelength_nm,n,") and lines[-1] == "status 0"
        assert done.stderr == "", done.stderr


@POSIX
def test_closed_standard_streams(tmp_path: Path) -> None:
    # issue 42: "with stderr closed a fit exits 1 with nothing"; `predict >&-` a traceback
    out = tmp_path / "photos"
    simulate = _stairfit("simulate", str(out), "--megapixels", "0.3", "--views", "3")
    done = subprocess.run(simulate, env=ENV, stdout=subprocess.PIPE, timeout=300,
                          preexec_fn=lambda: os.close(2))  # fmt: skip
    assert done.returncode == 0 and (out / "scene.toml").is_file()
    done = subprocess.run(_stairfit("predict", "--theta-o-deg", "0"), env=ENV, text=True,
                          stderr=subprocess.PIPE, timeout=300,
                          preexec_fn=lambda: os.close(1))  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == (
        "stairfit predict: error: standard output is closed (>&-), so the table has nowhere "
        "to go; give -o FILE"
    )


# --- whole fits --------------------------------------------------------------------------------


def _simulated(folder: Path) -> Path:
    argv = ["simulate", str(folder), "--megapixels", "0.5", "--views", "5", "--seed", "1"]
    subprocess.run(_stairfit(*argv, "--quiet"), env=ENV, check=True, timeout=600)
    return folder


def _start_fit(photos: Path, out: Path, log: Path) -> subprocess.Popen:
    """A default fit (with a posterior) in its own process group, its stderr (progress bars)
    into `log` (a pipe nobody reads while it waits would fill and stop it)."""
    argv = _stairfit("fit", str(photos), "-o", str(out), "--model", "sharp+floor")
    with open(log, "w") as err:
        return subprocess.Popen(argv, env=ENV, text=True, stdout=subprocess.PIPE, stderr=err,
                                start_new_session=True)  # fmt: skip


def _wait_for_posterior(proc: subprocess.Popen, out: Path) -> None:
    """Until the fit's posterior has saved its first chunk (the chain in the staging folder)."""
    deadline = time.monotonic() + 900
    while not list(out.parent.glob(f".{out.name}.*.partial/chain.npz")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no posterior chunk in 900 s"
        time.sleep(0.05)


def _group_alive(pgid: int) -> list[int]:
    """Processes of process group `pgid` still running (Linux /proc)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if os.getpgid(int(entry.name)) == pgid:
                state = (entry / "stat").read_text().split(")")[-1].split()[0]
                alive += [int(entry.name)] if state != "Z" else []
        except (OSError, IndexError):
            continue
    return alive


@pytest.mark.slow
@POSIX
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_during_the_posterior_is_one_line(tmp_path: Path, sig: int) -> None:
    work, log = tmp_path / "work", tmp_path / "stderr.txt"
    photos, out = _simulated(work / "photos"), work / "out"
    proc = _start_fit(photos, out, log)
    _wait_for_posterior(proc, out)
    proc.send_signal(sig)
    stdout, _ = proc.communicate(timeout=300)
    err = log.read_text()
    expected = {signal.SIGTERM: "terminated by SIGTERM", signal.SIGINT: "interrupted"}[sig]
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130), err
    assert err.count("stairfit fit:") == 1 and err.splitlines()[-1] == f"stairfit fit: {expected}"
    assert "Traceback" not in err and "emcee" not in err + stdout and "params" not in stdout
    assert sorted(p.name for p in work.iterdir()) == ["photos"]


@pytest.mark.slow
@POSIX
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_sigkill_of_a_fit_leaves_no_process_running(tmp_path: Path) -> None:
    # issue 42 case 11: the figure-drawing process and its resource tracker outlived the fit
    photos, out = _simulated(tmp_path / "photos"), tmp_path / "out"
    proc = _start_fit(photos, out, tmp_path / "stderr.txt")
    _wait_for_posterior(proc, out)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    time.sleep(2.0)
    assert _group_alive(proc.pid) == []
