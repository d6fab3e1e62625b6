"""The records of one `stairfit fit`: what it was asked to do (`FitOptions`), the fit's
observations with their labels (`Observations`, `RowLabel`) and everything it produced
(`FitOutcome`), shared by the pipeline (app/pipeline.py) and the outputs it writes
(app/report.py, app/_misfit_report.py), so that neither imports the other for them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .presets import Preset
from .scene import Scene

if TYPE_CHECKING:
    from stairfit import fitting, imaging
    from stairfit.fitting.posterior import PosteriorResult

    from .accuracy import AccuracyCheck
    from .fit_setup import FitSetup


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
    """Freeze what the late imports made out of the collector's way (`gc.freeze()` after the
    posterior's and the report's imports, `pipeline`): the console script only (`cli.entry`)."""
    kernel: str | None = None
    """The lab model's facet kernel, given (`--kernel`): no kernel probes. None: every kernel
    the model has is probed and the criterion chooses."""


@dataclass(frozen=True)
class RowLabel:
    """Where one observation row comes from, for the observation table and the figures: its
    photo, wedge and channel, the photo's light and view angles, the row's incidence and view
    angles on the face [conventions §1], and whether the fit uses it."""

    photo: str
    wedge: str
    channel: str
    light_deg: float
    view_deg: float
    theta_i_deg: float
    theta_o_deg: float
    use: bool


@dataclass(frozen=True)
class Observations:
    """The fit's observations of a scene (`data`, one row per photo x wedge x channel), each
    row's `labels` in the same order, and `notes` on the rows left out of the fit."""

    data: fitting.Observations
    labels: tuple[RowLabel, ...]
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class FitOutcome:
    """Everything a fit produced, for the report and the summary (built once, never changed:
    the report's figures are drawn from it in a second thread).

    `photo_specs`: what was measured of each photo (computed once per fit); `setup`: the
    index, spectral setup, aperture and effective wavelengths of the fit; `posterior`: None
    when not sampled; `accuracy`: the accuracy check (None when not made); `lab_reason`: why
    the scene was fitted with the lab model (`stairfit.lab.lab_choice`), None: in-plane.
    """

    scene: Scene
    options: FitOptions
    photo_specs: tuple[imaging.PhotoSpec, ...]
    table: imaging.MeasurementTable
    observations: Observations
    setup: FitSetup
    selection: fitting.Selection
    posterior: PosteriorResult | None
    timings: dict[str, float]
    notes: tuple[str, ...]
    accuracy: AccuracyCheck | None = None
    lab_reason: str | None = None


def sha256_of(path: Path) -> str:
    """SHA-256 of a file (for results.json)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
