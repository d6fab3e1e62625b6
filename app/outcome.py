"""The records of one `stairfit fit`: what it was asked to do (`FitOptions`) and everything it
produced (`FitOutcome`), shared by the command (app/commands/fit.py) and the outputs it writes
(app/report.py, app/_misfit_report.py), so that neither imports the other for them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .presets import Preset
from .scene import Scene


@dataclass(frozen=True)
class FitOptions:
    """What `fit` was asked to do (recorded in results.json)."""

    preset: Preset
    posterior: bool
    model: str | None
    model_error: bool
    seed: int
    workers: int
    cache: bool
    progress: bool
    freeze_imports: bool = False
    """Freeze what the late imports made out of the collector's way (`_prefetch.prefetch`):
    the console script only (`cli.entry`)."""


@dataclass
class FitOutcome:
    """Everything a fit produced, for the report and the summary."""

    scene: Scene
    options: FitOptions
    table: Any  # imaging.MeasurementTable
    observations: Any  # fitting.Observations
    row_info: list[dict[str, Any]]
    spectral: Any
    selection: Any
    posterior: Any | None
    timings: dict[str, float]
    notes: list[str]
    accuracy: Any = None  # commands._accuracy_check.AccuracyCheck
    lab_reason: str | None = None
    """Why the scene was fitted with the lab model (`stairfit.lab.lab_reason`); None: in-plane."""


def sha256_of(path: Path) -> str:
    """SHA-256 of a file (for results.json)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
