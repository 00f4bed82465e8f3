"""Where the inputs come from: paths, globs and folders expanded in a fixed order, then opened.

The order fixes each source's ordinal, and with it every point's id (SPEC 3):
arguments in the order given, each glob or folder expanded in sorted path order.
Remote ones (``s3://bucket/tiles/*.laz``) are listed by :mod:`.remote` in the
same order.
"""

from __future__ import annotations

import fnmatch
import glob
import os
import warnings

from ..core.kernels import ID_SHIFT, MAX_RECORDS_PER_SOURCE
from ..errors import CorruptInput, InputNotFound, PrismWarning, UnsupportedFormat, UsageError
from ..formats import READERS, extension, open_source
from . import remote


def _readable(name: str) -> bool:
    base = os.path.basename(name)
    return extension(name) in READERS and not base.startswith((".", "_"))


def _walk(folder: str) -> list[tuple[str, str]]:
    if remote.is_remote(folder):
        found = [(f, rel) for f, rel in remote.walk(folder) if _readable(f)]
    else:
        found = []
        for root, dirs, files in os.walk(folder):
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            found += [os.path.join(root, f) for f in files if _readable(f)]
        found = [(f, os.path.relpath(f, folder)) for f in sorted(found)]
    if not found:
        raise UnsupportedFormat(f"folder holds no readable point cloud ({', '.join(sorted(READERS))})", folder)
    return found


def _expand_remote(item: str) -> list[tuple[str, str]]:
    if any(c in item.partition("://")[2] for c in "*?["):
        matches = remote.glob(item)
        if not matches:
            raise InputNotFound("the pattern matches no file", item)
        return [(m, m.rsplit("/", 1)[-1]) for m in matches]
    found = remote.kind(item)
    if found == "directory":
        return _walk(item)
    if found == "file":
        return [(item, item.rstrip("/").rsplit("/", 1)[-1])]
    raise InputNotFound("no such file in the store", item)


def expand(inputs) -> list[tuple[str, str]]:
    """(file, path relative to what was named) for paths, globs and folders.

    The order of the arguments is kept (it fixes each source's ordinal); a
    glob or a folder expands in sorted path order.
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    out: list[tuple[str, str]] = []
    for item in inputs:
        item = os.fspath(item)
        if remote.is_remote(item):
            out += _expand_remote(item)
        elif any(c in item for c in "*?[") and not os.path.exists(item):  # a file named w[1].las is that file
            matches = sorted(p for p in glob.glob(item, recursive=True) if os.path.isfile(p))
            if not matches:
                raise InputNotFound("the pattern matches no file", item)
            out += [(m, os.path.basename(m)) for m in matches]
        elif os.path.isdir(item):
            out += _walk(item)
        elif os.path.isfile(item):
            out.append((item, os.path.basename(item)))
        elif os.path.exists(item):
            raise UnsupportedFormat("not a regular file", item)
        else:
            raise InputNotFound("no such file", item)
    seen = set()
    for f, _ in out:
        key = remote.real(f)
        if key in seen:
            raise UsageError("given twice; each input file may appear once", f)
        seen.add(key)
    return out


def read_again_through(inputs, output) -> str | None:
    """The input (a folder, or a pattern) through which a later run over the same inputs would read this run's
    ``output`` as one more input (an output written inside its input folder), or None."""
    if output is None or remote.is_remote(os.fspath(output)):
        return None
    out = os.path.realpath(os.fspath(output))
    for item in [inputs] if isinstance(inputs, (str, os.PathLike)) else inputs:
        item = os.fspath(item)
        if remote.is_remote(item):
            continue
        if os.path.isdir(item):
            folder = os.path.realpath(item)
            inside = out[len(folder) + 1:].split(os.sep) if out.startswith(folder + os.sep) else []
            if inside and not any(part.startswith(".") for part in inside[:-1]):  # _walk skips hidden folders
                return item
        elif any(c in item for c in "*?[") and fnmatch.fnmatch(out, os.path.realpath(item)):
            return item
    return None


def warn_read_again(inputs, output) -> None:
    """An output written where a later run over the same inputs reads it (inside an input folder, or matching
    an input pattern): said before pass one, as that run would sample this run's sample too."""
    through = read_again_through(inputs, output)
    if through is not None:
        how = "is inside the input folder" if os.path.isdir(through) else "matches the input pattern"
        warnings.warn(f"{output}: {how} {through}: a later run over {through} reads it as one more input",
                      PrismWarning, stacklevel=3)


def expand_inputs(inputs) -> list[str]:
    """Paths, globs and folders to the list of input files, in source-ordinal order."""
    return [f for f, _ in expand(inputs)]


def open_sources(files: list[str], copies_to: str | None = None, refuse_copies: str | None = None,
                 **open_options) -> list:
    """Every input opened, in ordinal order; each small enough for its ids (2^40 records).

    ``copies_to``: where an http(s) file whose server answers no range requests is copied first (None: the
    system's temporary folder); ``refuse_copies``: why no such copy may be made (:func:`.remote.local_copy`)."""
    remote.copies_to(copies_to, refuse_copies)
    sources = []
    try:
        for i, f in enumerate(files):
            if not remote.is_remote(f) and not os.access(f, os.R_OK):
                raise InputNotFound("cannot be read (permission denied)", f)
            sources.append(open_source(f, i, **open_options))
            if sources[-1].count is not None and sources[-1].count >= MAX_RECORDS_PER_SOURCE:
                raise CorruptInput(f"{sources[-1].count} points is more than one source may hold (2^{ID_SHIFT})", f)
    except BaseException:
        for s in sources:
            s.close()
        raise
    finally:
        remote.copies_to(None)  # a copy is made while opening (later reads find it made)
    return sources
