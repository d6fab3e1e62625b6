"""Start-up of the command line (issue 14): `stairfit predict` imports only what it needs and
compiles one program per model evaluation instead of one per JAX operation."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from stairfit import model

HEAVY = (
    "colour",
    "matplotlib",
    "scipy",
    "optimistix",
    "emcee",
    "cv2",
    "rawpy",
    "tqdm",
    "stairfit.commands.fit",
    "stairfit.commands.simulate",
    "stairfit.commands.demo",
    "stairfit.pipeline",
    "stairfit.simulation",
    "stairfit.fitting",
    "stairfit.imaging",
)
"""Modules a one-case `predict` has no use for (each costs import time)."""


def _predict_in_fresh_process(out: Path) -> subprocess.CompletedProcess[str]:
    code = (
        "import sys\n"
        "from stairfit import cli\n"
        "rc = cli.main(['predict', '--lobes', '--wedge-deg', '30', '--theta-i-deg', '0', "
        f"'-o', {str(out)!r}])\n"
        f"print(rc, sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    env = dict(os.environ, JAX_LOG_COMPILES="1", STAIRFIT_JAX_CACHE="off")
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    )


def test_predict_of_one_case_imports_little_and_compiles_two_programs(tmp_path):
    run = _predict_in_fresh_process(tmp_path / "lobes.csv")
    assert run.stdout.strip().split(maxsplit=1) == ["0", "[]"], run.stdout
    compiled = [line for line in run.stderr.splitlines() if "Finished XLA compilation" in line]
    # the index and the lobes; evaluated eagerly they were 40 programs (0.6-3 s of start-up)
    assert len(compiled) == 2, "\n".join(compiled)
    with open(tmp_path / "lobes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["lobe"] for r in rows] == list(model.LOBE_NAMES)
    # the lobes of the 30 deg wedge at normal incidence, worked out from conventions §3:
    # tread at theta_i + 2 beta2 = 60 deg, riser at theta_i - 2 beta1 = -120 deg, retro at 0
    np.testing.assert_allclose([float(r["theta_o_deg"]) for r in rows], [60.0, -120.0, 0.0])
    ref = model.sharp_lobes(0.0, np.deg2rad(30.0), 1.46)
    np.testing.assert_allclose([float(r["ratio"]) for r in rows], ref.ratio, rtol=1e-9)


def test_fitting_without_a_posterior_does_not_import_emcee():
    """emcee (and the SciPy it imports, about 1 s) is loaded only when a posterior is asked for
    (`stairfit.fitting.posterior`): `stairfit fit --no-posterior` and the report's module do not
    need it (issue 14)."""
    code = (
        "import sys\n"
        "from stairfit import fitting, report\n"
        "before = sorted(m for m in ('emcee', 'scipy') if m in sys.modules)\n"
        "from stairfit.fitting import posterior\n"
        "posterior.sample_posterior, posterior.load_chain, posterior.PosteriorOptions\n"
        "from stairfit.fitting.posterior import ChainBackend\n"
        "print(before, 'emcee' in sys.modules, ChainBackend.__module__)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["[]", "True", "stairfit.fitting._chain"], run.stdout


def test_the_console_script_is_the_entry_that_freezes_the_heap_and_keeps_the_status(tmp_path):
    """`stairfit` runs `cli.entry` (main, then `gc.freeze()` before the interpreter's shutdown,
    app/cli.py); the exit status of a success (0) and of a user error (2) pass through."""
    from importlib import metadata

    (script,) = [e for e in metadata.entry_points(group="console_scripts") if e.name == "stairfit"]
    assert script.value == "stairfit.cli:entry"
    ok = subprocess.run(
        [sys.executable, "-m", "stairfit.cli", "predict", "--lobes", "--wedge-deg", "30",
         "--theta-i-deg", "0", "-o", str(tmp_path / "lobes.csv")],
        capture_output=True, text=True, timeout=300,
        env=dict(os.environ, STAIRFIT_JAX_CACHE="off"),
    )  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert "lobe" in (tmp_path / "lobes.csv").read_text().splitlines()[0].split(",")
    bad = subprocess.run(
        [sys.executable, "-m", "stairfit.cli", "fit", str(tmp_path / "no-such-folder")],
        capture_output=True, text=True, timeout=300,
        env=dict(os.environ, STAIRFIT_JAX_CACHE="off"),
    )  # fmt: skip
    assert bad.returncode == 2, bad.stderr
    assert "Traceback" not in bad.stderr


def test_only_the_console_script_freezes_what_it_imported():
    """`cli.main(freeze_imports=True)` (what `entry` runs) freezes the start-up's imports once
    jax is set up, so that full collections do not walk them again; `main()` as tests and
    notebooks call it freezes nothing (what is frozen is never collected)."""
    code = (
        "import gc, sys\n"
        "from stairfit import cli\n"
        "counts = []\n"
        "for freeze in (False, True):\n"
        "    gc.unfreeze()\n"
        "    status = cli.main(['fit', '/no/such/folder/of/stairfit'], freeze_imports=freeze)\n"
        "    counts.append((status, gc.get_freeze_count() > 0))\n"
        "print(counts)\n"
    )
    env = dict(os.environ, STAIRFIT_JAX_CACHE="off")
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[(2, False), (2, True)]", run.stdout


def test_the_fit_pipeline_freezes_its_late_imports_only_when_asked():
    """`pipeline` freezes what the fit's late imports made (emcee, the report) only with
    `FitOptions.freeze_imports` (the console script); a fit called from a test or a notebook
    freezes nothing."""
    code = (
        "import gc\n"
        "from stairfit import pipeline\n"
        "from stairfit.outcome import FitOptions\n"
        "from stairfit.presets import PRESETS\n"
        "counts = []\n"
        "for freeze in (False, True):\n"
        "    gc.unfreeze()\n"
        "    options = FitOptions(PRESETS['balanced'], False, None, True, 0, 1, True, False,\n"
        "                         freeze_imports=freeze)\n"
        "    pipeline._freeze_imports(options)\n"
        "    counts.append(gc.get_freeze_count() > 0)\n"
        "print(counts)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[False, True]", run.stdout
