"""Temporary names for what a run writes before it is complete: one naming, one place.

Every output is first written under a hidden name beside its destination,
``.<name>.<random>.prism-tmp`` (a file, or a folder for a Dask dataset or a
directory-mode run), and renamed onto the destination only when complete.
:func:`leftovers` finds what a killed run left behind for a destination.
"""

from __future__ import annotations

import glob
import os
import shutil
import tempfile

from ..errors import OutputError

SUFFIX = ".prism-tmp"


def public_mode(mode: int) -> int:
    """``mode`` under the process umask: what a plain open() or mkdir() would give (mkstemp gives 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


def _prefix(dest: str) -> str:
    return "." + os.path.basename(os.path.abspath(dest).rstrip(os.sep)) + "."


def _folder(dest: str) -> str:
    folder = os.path.dirname(os.path.abspath(dest).rstrip(os.sep)) or "."
    if not os.path.isdir(folder):
        raise OutputError("output folder does not exist", dest)
    return folder


def temp_folder(dest: str) -> str:
    """A hidden folder beside ``dest`` (readable like a plain mkdir), to be renamed onto it."""
    path = tempfile.mkdtemp(prefix=_prefix(dest), suffix=SUFFIX, dir=_folder(dest))
    os.chmod(path, public_mode(0o777))
    return path


def leftovers(dest: str) -> list[str]:
    """The temporaries of ``dest`` that a run left behind (killed before it could clean up)."""
    folder = os.path.dirname(os.path.abspath(dest).rstrip(os.sep)) or "."
    pattern = os.path.join(glob.escape(folder), glob.escape(_prefix(dest)) + "*" + SUFFIX)
    return sorted(glob.glob(pattern))


def remove(path: str) -> None:
    """Remove a temporary file or folder; nothing if it is gone already."""
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


class AtomicFile:
    """A temporary path beside the destination, renamed over it on commit."""

    def __init__(self, dest: str):
        self.dest = os.path.abspath(dest)
        fd, self.tmp = tempfile.mkstemp(prefix=_prefix(dest), suffix=SUFFIX, dir=_folder(dest))
        os.close(fd)

    def commit(self) -> None:
        os.chmod(self.tmp, public_mode(0o666))
        os.replace(self.tmp, self.dest)

    def discard(self) -> None:
        remove(self.tmp)
