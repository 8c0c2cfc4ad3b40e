"""Errors a user can act on.

:class:`InputError` carries one line naming the file and what is wrong with it. The CLI prints it
and exits with status 2; the service answers 422 with it as ``detail``. Never raise it with a
multi-line message or a traceback in the text.
"""

from __future__ import annotations

from pathlib import Path

# what a reader says of a file whose arrays or tables nest deeper than the parser can follow
NESTED_TOO_DEEPLY = "arrays or tables nested too deeply (hundreds of levels inside each other)"


class InputError(ValueError):
    """Bad user input: a file that cannot be read, or data that do not fit together."""

    def __init__(self, message: str, path: str | Path | None = None):
        text = " ".join(str(message).split())
        if path is not None:
            text = f"{Path(path).name}: {text}"
        super().__init__(text)
        self.path = None if path is None else str(path)


def unreadable(error: OSError, path: str | Path, what: str = "a file") -> InputError:
    """The one-line :class:`InputError` for a file the system would not open or read (``error``):
    ``no such file``, ``is a directory, not <what>``, or ``cannot read: <the system's reason>``
    (permission denied, an I/O error, ...). Raise it ``from None``: the reason is in its line."""
    if isinstance(error, FileNotFoundError):
        return InputError("no such file", path)
    if isinstance(error, IsADirectoryError):
        return InputError(f"is a directory, not {what}", path)
    return InputError(f"cannot read: {error.strerror or error}", path)


class TooLargeInput(InputError):
    """Input over a size limit the caller set, refused before it is read; ``limit`` names the limit
    (``"frames"``, ``"bodyparts"``)."""

    def __init__(self, message: str, path: str | Path | None = None, limit: str = ""):
        super().__init__(message, path)
        self.limit = limit


class WorkerLost(RuntimeError):
    """A worker process that solved part of a run died (killed, out of memory): one line saying so and
    what to do; the run's finished part stands (``acinoset solve --resume``)."""
