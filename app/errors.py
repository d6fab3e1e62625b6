"""The exception type for mistakes a user can fix; the warning type for what to know."""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input: the message names the file, the field and the fix.

    The command line prints it as one line and exits with status 2; it is never shown as a
    traceback.
    """


class StairfitWarning(UserWarning):
    """Something the user should know that does not stop the run (e.g. an extrapolated index).

    The command line prints it as one line, `stairfit COMMAND: warning: ...`.
    """
