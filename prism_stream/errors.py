"""The exceptions prism-stream raises, each with the exit code the CLI returns.

Every error carries the file it concerns (when there is one) so that the
message printed to the user is one line: ``path: cause``.
"""

from __future__ import annotations


class PrismError(Exception):
    """Base class: a failure that is reported as one line and an exit code."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None):
        super().__init__(message)
        self.message = message
        self.path = path

    def __reduce__(self):  # from a Dask task to the driver with its path, so the driver can name it anew
        return type(self), (self.message, self.path)

    def __str__(self) -> str:
        message = " ".join(str(self.message).splitlines())
        if self.path:
            return f"{printable(self.path)}: {message}"
        return message


def printable(path) -> str:
    """A path as it can be shown on one line: as is, or with its control characters escaped."""
    path = str(path)
    return path if path.isprintable() else repr(path)[1:-1]


class UsageError(PrismError):
    """The options do not make sense (ratio outside (0, 1], count above N...)."""

    exit_code = 2


class InputNotFound(PrismError):
    """An input path or glob matches no file."""

    exit_code = 3


class UnsupportedFormat(PrismError):
    """The file extension or the file's content is not a format we read or write."""

    exit_code = 4


class NoColorError(PrismError):
    """The cloud has no color fields, so its points cannot be binned."""

    exit_code = 5


class CorruptInput(PrismError):
    """The file claims to be a supported format but its content is invalid."""

    exit_code = 6


class OutputExists(PrismError):
    """The output exists and ``overwrite`` was not given."""

    exit_code = 7

    @classmethod
    def at_start(cls, path) -> "OutputExists":
        return cls("already exists (use --overwrite to replace it)", path)

    @classmethod
    def meanwhile(cls, path) -> "OutputExists":
        """Another run wrote ``path`` after this one checked it."""
        return cls("was written by another run meanwhile (use --overwrite to replace it)", path)


class OutputError(PrismError):
    """Writing the output failed (disk full, permissions...); nothing was left behind."""

    exit_code = 8


class StorageError(PrismError):
    """The object store holding an input refused the request or could not be reached (no credentials,
    network); a missing object or bucket is :class:`InputNotFound`."""

    exit_code = 10


class TempDataChanged(PrismError):
    """Another process changed or removed the run's temporary files (the spill, the key cache) while it ran:
    the run stops rather than read them; nothing was written."""

    exit_code = 11

    def __reduce__(self):  # from a Dask task to the driver, path and all
        return type(self), (self.what, self.path)

    def __init__(self, what: str, folder: str | None = None):
        self.what = what
        super().__init__(f"temporary data was changed or removed during the run ({what}); nothing was written",
                         folder)


class Interrupted(PrismError):
    """The run was interrupted (Ctrl-C); nothing was left behind."""

    exit_code = 130


class PrismWarning(UserWarning):
    """Something the user should know that does not stop the run (one bin, no points)."""
