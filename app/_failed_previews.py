"""Previews of the photos a failed run could not use, kept where its error message names them.

A failed `fit` leaves no output folder (README "Commands"), and the measurement cache keeps
previews of successful photos only, under hash names. So that the user has something to look
at (the markers found, the pixel ROIs given, a pixel grid to draw `roi_px` on: docs/imaging.md
§Previews), the previews of the photos that failed, or of every photo when none gave a usable
measurement, are copied to `DIR/.stairfit-cache/failed-previews/` (replacing those of an
earlier failure) and the error names that folder. A run whose photos all measure removes it.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from stairfit.imaging import PhotoSpec

FAILED_PREVIEWS = "failed-previews"
"""The folder, inside the photo folder's cache folder, of the failed photos' previews."""


FAILED_CONTENTS = "markers found, ROIs given, pixel grid in raw coordinates for drawing roi_px"
"""What the preview of a photo that could not be measured shows."""


def keep_previews(
    folder: Path,
    preview_dir: Path,
    specs: Sequence[PhotoSpec],
    names: Iterable[str],
    contents: str = FAILED_CONTENTS,
) -> str:
    """Copy the previews of photos `names` from `preview_dir` into `folder`.

    Returns the sentence to append to the error message, naming `folder` and what the previews
    show (`contents`); "" when no preview exists (e.g. every photo failed to decode).
    """
    from stairfit import imaging

    from .outputs import in_staging

    if in_staging(folder):  # e.g. the demo's photos: the folder goes with the failed run
        return ""
    wanted = set(names)
    sources = [imaging.preview_path(preview_dir, s) for s in specs if s.name in wanted]
    sources = [p for p in sources if p.is_file()]
    if not sources:
        return ""
    try:
        forget_previews(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for path in sources:
            shutil.copyfile(path, folder / path.name)
    except OSError as e:
        return f"; the previews could not be kept in {folder} ({e.strerror or e})"
    what = "its preview" if len(sources) == 1 else f"the previews of {len(sources)} photos"
    return f"; {what} ({contents}): {folder}"


def forget_previews(folder: Path) -> None:
    """Remove the failed previews of an earlier run (best effort)."""
    shutil.rmtree(folder, ignore_errors=True)
