"""`--help` of every command, and `stairfit` without a command (issue 6, Checks)."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys

import pytest

from stairfit import __version__
from stairfit.cli import build_parser, main

# What each command must offer, written out from the README and issue 6 (not read from the
# parser), so that an option that disappears or is renamed fails here.
EXPECTED_OPTIONS = {
    "predict": [
        "--wedge-deg",
        "--layer-um",
        "--material",
        "--n",
        "--delta-n",
        "--sigma-deg",
        "--wavelength-nm",
        "--theta-i-deg",
        "--theta-o-deg",
        "--lobes",
        "--diffuse",
        "--cosine-weighted",
        "--output",
        "--force",
    ],
    "simulate": [
        "--sigma-deg",
        "--delta-n",
        "--edge-radius-um",
        "--floor",
        "--megapixels",
        "--views",
        "--seed",
        "--workers",
        "--exposure-tags",
        "--markers",
        "--force",
        "--quiet",
    ],
    "measure": ["--output", "--workers", "--no-cache", "--force", "--quiet"],
    "init": ["--light-deg", "--angles", "--layout", "--quiet"],
    "fit": [
        "--output",
        "--preset",
        "--no-posterior",
        "--model",
        "--no-model-error",
        "--seed",
        "--workers",
        "--no-cache",
        "--force",
        "--quiet",
    ],
    "demo": [
        "--sigma-deg",
        "--delta-n",
        "--edge-radius-um",
        "--megapixels",
        "--views",
        "--preset",
        "--no-posterior",
        "--seed",
        "--force",
        "--quiet",
    ],
    "study": [
        "--output",
        "--scheduler",
        "--scheduler-file",
        "--local-workers",
        "--jax-cache",
        "--preset",
        "--no-posterior",
        "--model",
        "--no-model-error",
        "--seed",
        "--no-cache",
        "--force",
        "--quiet",
    ],
}
POSITIONAL = {
    "predict": None,
    "simulate": "out",
    "fit": "DIR",
    "measure": "DIR",
    "init": "DIR",
    "demo": "out",
    "study": "ROOT_OR_FOLDER",
}


@pytest.fixture(autouse=True)
def _no_persistent_jax_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    # the CLI would point JAX's persistent compilation cache at ~/.cache for the session
    monkeypatch.setenv("STAIRFIT_JAX_CACHE", "off")


def _help(command: str, capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    return captured.out


def _registered_options(command: str) -> list[str]:
    """Every option string the parser of `command` accepts."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return [s for a in sub.choices[command]._actions for s in a.option_strings]


@pytest.mark.parametrize("command", sorted(EXPECTED_OPTIONS))
def test_help_of_every_command_exits_0_and_lists_its_options(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    text = _help(command, capsys)
    assert text.startswith(f"usage: stairfit {command}")
    for option in EXPECTED_OPTIONS[command]:
        # as a whole word: "--n" must not be satisfied by "--no-cache"
        assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text), option
    if POSITIONAL[command]:
        assert POSITIONAL[command] in text


@pytest.mark.parametrize("command", sorted(EXPECTED_OPTIONS))
def test_help_documents_every_registered_option(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # nothing the parser accepts is hidden from --help (argparse.SUPPRESS) or undocumented
    text = _help(command, capsys)
    options = _registered_options(command)
    assert set(EXPECTED_OPTIONS[command]) <= set(options)
    for option in options:
        assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text), option
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for action in sub.choices[command]._actions:
        assert action.help and action.help != argparse.SUPPRESS, action.option_strings


def test_top_level_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    for command in EXPECTED_OPTIONS:
        assert re.search(rf"^\s+{command}\s+\S", text, re.M), command  # name and a summary


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"stairfit {__version__}"


def test_no_command_prints_usage_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("usage: stairfit")
    for command in EXPECTED_OPTIONS:
        assert command in captured.err


def test_unknown_command_fails_with_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["fitt"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: stairfit")
    assert "invalid choice: 'fitt'" in err


def test_no_command_as_a_process() -> None:
    # the console entry point as a shell sees it: usage on stderr, non-zero status
    proc = subprocess.run(
        [sys.executable, "-m", "stairfit.cli"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.startswith("usage: stairfit")
    assert "Traceback" not in proc.stderr
