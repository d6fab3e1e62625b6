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


class PhotosFailedError(ImagingError):
    """Some photos of a `measure_photos` call could not be measured; `failed_photos` names them.

    Its message is one line covering every failed photo (see `measure_photos`).
    """

    def __init__(self, message: str, failed_photos: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.failed_photos = tuple(failed_photos)
