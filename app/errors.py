"""The exception type for mistakes a user can fix; the warning type for what to know; messages
shortened to the one line the command line prints (`one_line`)."""

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


MAX_WORD = 200
"""A longer run of characters without a space in a message (a value echoed back, e.g. a 5 MB
illuminant name) is shortened to its start and end."""
MAX_MESSAGE = 2000
"""A longer message keeps its start (file, field) and end (the fix), with the middle cut."""


def _short_word(word: str) -> str:
    if len(word) <= MAX_WORD:
        return word
    return f"{word[:120]}...{word[-40:]} ({len(word)} characters)"


def one_line(message: str) -> str:
    """A message on one line: line breaks and runs of spaces become single spaces; echoed
    values longer than `MAX_WORD` and messages longer than `MAX_MESSAGE` are shortened."""
    text = " ".join(_short_word(w) for w in str(message).split())
    if len(text) <= MAX_MESSAGE:
        return text
    cut = len(text) - MAX_MESSAGE
    return f"{text[:1200]} [... {cut} characters left out ...] {text[-(MAX_MESSAGE - 1200) :]}"
