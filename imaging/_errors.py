"""The one exception type of `stairfit.imaging`."""

from __future__ import annotations


class ImagingError(Exception):
    """A photograph, ROI or marker layout that cannot give an honest measurement.

    The message names the photo (file name) and, where one is involved, the wedge, says what is
    wrong and what to do about it; the command line prints it as one line, never as a traceback.
    """


class ImagingWarning(UserWarning):
    """Something about a photo or the measurement cache worth knowing that does not stop a run.

    The message names the photo or file; the command line prints it as one line.
    """
