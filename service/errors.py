"""What the job service refuses, and why: one exception per kind of refusal, each with a one-line
``detail``. They say nothing about HTTP: the app answers each kind with its status code
(:data:`service.app.JOB_ERROR_STATUS`), the command line prints the detail. A leaf module, so the
upload readers' processes raise them too (they pickle)."""

from __future__ import annotations

import re


class JobError(Exception):
    """A request the job service refuses, with one line saying why."""

    def __init__(self, detail: str):
        self.detail = " ".join(str(detail).split())
        super().__init__(self.detail)


class NotFound(JobError):
    """No such job, or one the caller may not see."""


class Forbidden(JobError):
    """The caller may not do this (a non-admin asking for another user's jobs)."""


class NotReady(JobError):
    """The job has no result (yet, or any more)."""


class Unprocessable(JobError):
    """A malformed request or option, or a file the readers refuse."""


class TooLarge(JobError):
    """Over this server's size limits (upload, frames, cameras)."""


class TooMany(JobError):
    """The caller already has the most active jobs allowed."""


class NoSpace(JobError):
    """The server's storage is full (its disk, or the total for all jobs)."""


def storage_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk is full: ENOSPC or EDQUOT from the OS, :class:`service.store.StoreFull`
    from the job table, or an error raised while handling one of those."""
    import errno

    from service.store.errors import StoreFull

    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:  # the error itself, or one it was raised from
        seen.add(id(e))
        if isinstance(e, StoreFull) or isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(e, OSError) and e.errno is None and "No space left on device" in str(e):
            return True  # HDF5's own writes: errno is in the text, not the exception
        e = e.__cause__ or e.__context__
    return False


DISK_FULL = "the server's disk is full; delete finished jobs to make room, or ask the admin"
# A job process's exit status when the disk was full and it could not record its own failure
# (ENOSPC's number): its scheduler fails the job with DISK_FULL once the table has room.
EXIT_DISK_FULL = 28


# An absolute path in a message (a server's file, say /srv/acinoset/jobs/<id>/input/keypoints/01/cam1.csv):
# a slash not after a word character, a dot, a colon or a slash (so not inside a URL), then directories.
_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/])/(?:[^\s/'\"()<>,;:]+/)+([^\s/'\"()<>,;:]+)")


def strip_paths(text: str) -> str:
    """``text`` with every absolute path cut to its file name (:func:`without_paths`)."""
    return _ABSOLUTE_PATH.sub(r"\1", text)


def without_paths(text: str | None) -> str | None:
    """``text`` with every absolute path cut to its file name: what the solver says of the server's
    files names them the way the user uploaded them, not where the server keeps them."""
    return None if text is None else strip_paths(text)
