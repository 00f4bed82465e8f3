"""Temporary names for what a run writes before it is complete: one naming, one place.

Every output is first written under a hidden name beside its destination,
``.<name>.<owner>-<random>.prism-tmp`` (a file, or a folder for a staged
output or a Dask dataset), and published onto the destination only when
complete. The key cache and DuckDB's spill live in a work folder
``prism-stream-<owner>-<random>`` in the temporary folder.

``<owner>`` is ``<host>-<pid>``: a short hash of the host name and the id of
the process that created the temporary. That makes two promises cheap:

- nothing a run creates is out of its cleanup's reach: a name is registered
  *before* the file or folder is created, and :func:`discard_all` removes
  every registered temporary still there (the command line calls it on any
  failure, an interrupt or SIGTERM included);
- a run killed before it could clean up (SIGKILL, power loss) is cleaned up
  by the next one: :func:`sweep` removes the temporaries of a folder whose
  owner is a process of this host that no longer exists.

:func:`publish_new` puts a finished file at a destination only if nothing is
there (``link()``, which fails if the name exists): two runs writing the
same output cannot both succeed.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import os
import re
import secrets
import shutil
import socket
import stat
import tempfile

import numpy as np

from ..errors import Interrupted, OutputError, TempDataChanged

RESERVE = 256 << 20  # free space a run leaves on the disk it writes temporaries to


def free_bytes(folder: str) -> int:
    return int(shutil.disk_usage(folder).free)


def gib(n: float) -> str:
    """Bytes as a person reads them."""
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"

SUFFIX = ".prism-tmp"
WORK_PREFIX = "prism-stream-"
HOST = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]
_TEMP = re.compile(r"^\..*\.([0-9a-f]{6})-(\d+)-[0-9a-f]{8}" + re.escape(SUFFIX) + "$", re.S)
_WORK = re.compile("^" + re.escape(WORK_PREFIX) + r"([0-9a-f]{6})-(\d+)-[0-9a-f]{8}$")
_LIVE: set[str] = set()  # every temporary this process created (or is about to) and has not published or removed
_UPLOADED_TO: dict[str, str] = {}  # a local staging folder -> the remote folder its files are uploaded to
_PUBLISHED: list[str] = []  # the outputs this process published whole (as the user named them)


def note_published(output: str) -> None:
    """``output`` is in place, whole: an interrupt from now on says so instead of "no output was written"."""
    _PUBLISHED.append(output)


def published() -> list[str]:
    """The outputs this process published whole, in order."""
    return list(_PUBLISHED)


def forget_published(after: int = 0) -> None:
    """A new run in this process (the command line called from Python): nothing of its own published yet;
    ``after``: all but the first ``after`` (what a part of a run published inside its staging folder, which
    the user never sees unless the whole run is)."""
    del _PUBLISHED[after:]


def public_mode(mode: int) -> int:
    """``mode`` under the process umask: what a plain open() or mkdir() would give (mkstemp gives 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


def owner() -> str:
    """This process as the owner of a temporary: host hash and pid."""
    return f"{HOST}-{os.getpid()}"


def _prefix(dest: str) -> str:
    return "." + os.path.basename(os.path.abspath(dest).rstrip(os.sep)) + "."


def _folder(dest: str) -> str:
    folder = os.path.dirname(os.path.abspath(dest).rstrip(os.sep)) or "."
    if not os.path.isdir(folder):
        if os.path.exists(folder):  # d.laz/x.parquet where d.laz is a file
            raise OutputError(f"{os.path.basename(folder)} is not a folder", dest)
        raise OutputError("output folder does not exist", dest)
    return folder


def _create(path_of, make) -> str:
    """Register a fresh name, then create it (so an interrupt in between leaves nothing out of reach)."""
    for _ in range(100):
        path = path_of(f"{owner()}-{secrets.token_hex(4)}")
        _LIVE.add(path)
        try:
            make(path)
            return path
        except FileExistsError:
            _LIVE.discard(path)
        except OSError as exc:
            _LIVE.discard(path)
            reason = exc.strerror or str(exc)
            if exc.errno == errno.ENOENT and os.path.isdir(os.path.dirname(path)):
                reason = f"the folder takes no new files ({reason})"  # /proc and its kind: there, yet no file made
            raise OutputError(f"cannot write here: {reason}", os.path.dirname(path)) from None
        # an interrupt leaves the name registered: the file may exist already, and discard_all removes it
    raise FileExistsError(errno.EEXIST, "no free temporary name", path)


def _new_file(path: str) -> None:
    os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))


def _new_folder(path: str) -> None:
    os.mkdir(path, 0o700)


def new_file(dest: str) -> str:
    """An empty temporary file beside ``dest`` (mode 0600), registered for cleanup."""
    folder = _folder(dest)
    sweep(folder)
    return _create(lambda tag: os.path.join(folder, _prefix(dest) + tag + SUFFIX), _new_file)


def temp_folder(dest: str, uploaded_to: str | None = None) -> str:
    """A hidden folder beside ``dest`` (readable like a plain mkdir), to be renamed or published onto it.

    ``uploaded_to``: the remote folder (a URL) its files are uploaded to, what :func:`public_name` names them by.
    """
    folder = _folder(dest)
    sweep(folder)
    path = _create(lambda tag: os.path.join(folder, _prefix(dest) + tag + SUFFIX), _new_folder)
    os.chmod(path, public_mode(0o777))
    if uploaded_to is not None:
        _UPLOADED_TO[path] = uploaded_to.rstrip("/")
    return path


OUT_OF_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # a full disk, a quota, a file-size limit
NOT_ALLOWED = (errno.EACCES, errno.EPERM, errno.EROFS)  # a folder made read-only, a file system remounted so


def make_work_folder(parent: str) -> str:
    """A private work folder in ``parent``, registered for cleanup (:func:`remove` it when done)."""
    if not os.path.isdir(parent):
        raise OutputError("the temporary folder is a file, not a folder" if os.path.exists(parent)
                          else "the temporary folder does not exist", parent)
    sweep(parent)
    return _create(lambda tag: os.path.join(parent, WORK_PREFIX + tag), _new_folder)


@contextlib.contextmanager
def work_dir(parent: str | None = None):
    """A private work folder in ``parent`` (default: the system's temporary folder), removed on exit."""
    parent = parent or tempfile.gettempdir()
    path = make_work_folder(parent)
    try:
        yield path
    except Exception as exc:
        # another process truncated, replaced or removed the run's files: not a bug of ours (an interrupt may
        # have come between a write and its mark: it is told as the interrupt it is)
        if isinstance(exc, TempDataChanged):
            what = exc.what
        else:
            what = None if isinstance(exc, Interrupted) else changed(path)
        if what is not None:
            raise TempDataChanged(what, parent) from None
        if isinstance(exc, OSError) and exc.errno in OUT_OF_ROOM + NOT_ALLOWED and (
                exc.filename is None or str(exc.filename).startswith(path)):
            # the key cache or DuckDB's spill ran out of room, or its folder was made read-only meanwhile
            # (the sinks report their own)
            raise OutputError(f"cannot write the temporary files: {exc.strerror}", parent) from None
        raise
    finally:
        remove(path)


def leftovers(dest: str) -> list[str]:
    """The temporaries of ``dest`` that a run left behind (killed before it could clean up)."""
    folder = os.path.dirname(os.path.abspath(dest).rstrip(os.sep)) or "."
    pattern = os.path.join(glob.escape(folder), glob.escape(_prefix(dest)) + "*" + SUFFIX)
    return sorted(glob.glob(pattern))


def is_temporary(name: str) -> bool:
    """Whether a file name is one of our temporaries (beside an output, or a work folder)."""
    return bool(_TEMP.match(name) or _WORK.match(name))


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return not _zombie(pid)


def _zombie(pid: int) -> bool:
    """Whether ``pid`` has exited and only waits to be reaped (a killed batch's worker whose parent died too,
    where nothing reaps orphans at once: it answers a signal, yet writes nothing more). Linux's /proc only."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rindex(b")") + 2:][:1] in (b"Z", b"X")  # the state follows the command's name


def stale(folder: str) -> list[str]:
    """The temporaries in ``folder`` whose owner provably died: created on this host by a process that is gone."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    out = []
    for name in names:
        m = _TEMP.match(name) or _WORK.match(name)
        if m and m.group(1) == HOST and not _alive(int(m.group(2))):
            out.append(os.path.join(folder, name))
    return sorted(out)


def sweep(folder: str) -> list[str]:
    """Remove :func:`stale` temporaries of ``folder``; return what was removed."""
    gone = stale(folder)
    for path in gone:
        remove(path)
    return gone


def _writable_again(folder: str) -> None:
    """Give the owner back write permission on ``folder`` (a run's own temporary folder) and every folder in
    it, so that it can be removed."""
    def own(path: str) -> None:
        try:
            if stat.S_ISDIR(os.lstat(path).st_mode):  # never through a link to a folder elsewhere
                os.chmod(path, stat.S_IRWXU)
        except OSError:
            pass  # another user's folder: left as it is

    own(folder)
    for root, dirs, _ in os.walk(folder):
        for d in dirs:
            own(os.path.join(root, d))


def remove(path: str) -> None:
    """Remove a temporary file or folder (nothing if it is gone already), and forget it."""
    try:
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
            if os.path.lexists(path):  # made read-only under the run (by another hand): ours, so writable again
                _writable_again(path)
                shutil.rmtree(path, ignore_errors=True)
        else:
            os.unlink(path)
    except FileNotFoundError:
        pass
    if not os.path.lexists(path):
        _LIVE.discard(path)
        _UPLOADED_TO.pop(path, None)
        for marked in [m for m in list(_MARKS) if m == path or m.startswith(os.path.join(path, ""))]:
            unmark(marked)


def forget(path: str) -> None:
    """``path`` is no longer a temporary (it was published)."""
    _LIVE.discard(path)


def discard_all() -> None:
    """Remove every temporary this process created and has not published: the last cleanup of a failed run."""
    for path in sorted(_LIVE, key=len, reverse=True):
        with contextlib.suppress(OSError):
            remove(path)


def publish_new(tmp: str, dest: str) -> None:
    """Give the finished file ``tmp`` the name ``dest`` only if no file has it (FileExistsError otherwise).

    ``link()`` fails if ``dest`` exists, so of two runs publishing the same
    destination exactly one wins; ``tmp`` keeps its name too (the caller
    removes it). A file system without hard links gets an ``O_EXCL`` claim
    on the name, then the rename.
    """
    try:
        os.link(tmp, dest)
        return
    except FileExistsError:
        raise
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS):
            raise
    os.close(os.open(dest, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
    os.replace(tmp, dest)


class AtomicFile:
    """A temporary path beside the destination, renamed over it on commit (or published only if new)."""

    def __init__(self, dest: str):
        self.dest = os.path.abspath(dest)
        self.tmp = new_file(dest)

    def commit(self, replace: bool = True) -> None:
        """Publish: replace whatever is at the destination, or (``replace=False``) fail if something is."""
        os.chmod(self.tmp, public_mode(0o666))
        if replace:
            os.replace(self.tmp, self.dest)
        else:
            publish_new(self.tmp, self.dest)
            remove(self.tmp)
        forget(self.tmp)

    def discard(self) -> None:
        remove(self.tmp)


def public_name(path: str) -> str:
    """The destination a staged path is published as: the path without its temporary folder (or, staged
    for an upload, the URL it is uploaded to)."""
    for folder, url in _UPLOADED_TO.items():
        if path.startswith(folder + os.sep):
            return url + "/" + path[len(folder) + 1:].replace(os.sep, "/")
    head, tail = os.path.split(path)
    if not head:
        return path
    kept = os.sep.join(p for p in head.split(os.sep) if not (p.startswith(".") and p.endswith(SUFFIX)))
    if not kept:
        return os.sep + tail if head.startswith(os.sep) else tail
    return os.path.join(kept, tail)


# -- temporary data changed under a run -------------------------------------------------------------------
# A run's temporary files (the spill, the key cache) are its own: another process (a cleaner of /tmp, a user)
# that truncates, replaces or deletes one would make the run read garbage or fail deep inside. Each file's
# state after this process's last write is noted; :func:`changed` compares the files with it, so that a failure
# is reported as what it is (:class:`TempDataChanged`), and a run checks before it publishes anything.
_MARKS: dict[str, tuple[int, int, int]] = {}  # path -> (inode, size, mtime ns) after this process's last write


def mark(path: str, fd: int) -> None:
    """Note ``path``'s state after a write of this process (its data flushed to ``fd``)."""
    st = os.fstat(fd)
    _MARKS[path] = (st.st_ino, st.st_size, st.st_mtime_ns)


def discard_file(path: str) -> None:
    """Delete a temporary file of this process, closed (nothing if it is gone), and forget its mark."""
    unmark(path)
    try:
        os.unlink(path)
    except OSError:
        pass


def unmark(path: str) -> None:
    _MARKS.pop(path, None)


def unmark_under(folder: str) -> None:
    """Stop watching this process's files under ``folder``: handed to another process, which removes them (a
    cluster task's), they are no longer this process's to find changed."""
    prefix = os.path.join(folder, "")
    for path in [p for p in list(_MARKS) if p.startswith(prefix)]:  # (a snapshot: other tasks' threads mark)
        _MARKS.pop(path, None)


def changed(folder: str | None = None) -> str | None:
    """How one of this process's temporary files (under ``folder``, if given) was changed by someone else since
    it last wrote it (``spill.keys was removed``...), or None when none was."""
    for path in list(_MARKS):
        if folder is not None and not path.startswith(os.path.join(folder, "")):
            continue
        what = _change(path)
        if what is not None:
            return what
    return None


def verify(path: str) -> None:
    """Before this process writes to ``path`` again: raise :class:`TempDataChanged` if someone else changed it
    (a write after a truncation would otherwise leave a hole of zeros that the next mark takes as ours)."""
    what = _change(path)
    if what is not None:
        raise TempDataChanged(what, os.path.dirname(path))


def _change(path: str) -> str | None:
    noted = _MARKS.get(path)
    if noted is None:
        return None
    ino, size, mtime = noted
    return change_of(path, size, mtime, ino)


def change_of(path: str, size: int, mtime: int, ino: int | None = None) -> str | None:
    """How the file ``path`` differs from what its writer left (its size and mtime in ns, and its inode where
    the writer is this process), said for :class:`TempDataChanged` (``spill.keys was truncated ...``); None
    when it does not."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        what = "was removed" if os.path.isdir(os.path.dirname(path)) else "was removed with its folder"
    except OSError as exc:
        what = f"cannot be read ({exc.strerror})"
    else:
        if ino is not None and st.st_ino != ino:
            what = "was replaced"
        elif st.st_size != size:
            what = f"was {'truncated' if st.st_size < size else 'extended'} ({size:,} to {st.st_size:,} bytes)"
        elif st.st_mtime_ns != mtime:
            what = "was written to"
        else:
            return None
    return f"{os.path.basename(path)} {what}"


def check_unchanged(folder: str | None = None) -> None:
    """Raise :class:`TempDataChanged` if a temporary file of this process was changed by someone else."""
    what = changed(folder)
    if what is not None:
        raise TempDataChanged(what, folder)


def pwrite_all(fd: int, data, offset: int, path: str) -> None:
    """Write all of ``data`` at ``offset`` (``os.pwrite`` may write part of it: a disk filling up writes what
    fits and fails the next call with ENOSPC, which the callers take as out of room). An error names ``path``."""
    view = memoryview(data).cast("B")
    try:
        while len(view):
            done = os.pwrite(fd, view, offset)
            if done <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view, offset = view[done:], offset + done
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror, path) from None
        raise


class ArrayFile:
    """An append-only array of one dtype in a temporary file: pass one's keys, the spill's index."""

    def __init__(self, folder: str, name: str, dtype=np.uint32, mode: str = "w+b"):
        self.dtype = np.dtype(dtype)
        self.path = os.path.join(folder, name)
        self.file = open(self.path, mode)
        self.size = os.fstat(self.file.fileno()).st_size // self.dtype.itemsize  # 0 unless reopened
        if "w" in mode:
            mark(self.path, self.file.fileno())

    def _written(self) -> None:
        try:
            self.file.flush()
        finally:  # what a failed write (a full disk) left is this process's own too
            mark(self.path, self.file.fileno())

    def append(self, values: np.ndarray) -> None:
        verify(self.path)
        try:
            self.file.write(np.ascontiguousarray(values, dtype=self.dtype).tobytes())
            self.size += len(values)
        finally:
            self._written()

    def read(self, offset: int, n: int) -> np.ndarray:
        self.file.flush()
        size = self.dtype.itemsize
        data = os.pread(self.file.fileno(), n * size, offset * size)
        if len(data) != n * size:  # the file is shorter than what was written to it
            check_unchanged(os.path.dirname(self.path))
            if self.path not in _MARKS:  # another process's file (a Dask unit's spill), cut since it was opened
                raise TempDataChanged(f"{os.path.basename(self.path)} was truncated while it was read",
                                      os.path.dirname(self.path))
        return np.frombuffer(data, dtype=self.dtype)

    def overwrite_zero(self, offset: int, n: int) -> None:
        verify(self.path)
        self.file.flush()
        try:
            os.pwrite(self.file.fileno(), bytes(n * self.dtype.itemsize), offset * self.dtype.itemsize)
        finally:
            mark(self.path, self.file.fileno())

    def write_at(self, offset: int, values: np.ndarray) -> None:
        """Write ``values`` over the entries from ``offset`` on (a compaction moving survivors down, in place)."""
        verify(self.path)
        self.file.flush()
        try:
            pwrite_all(self.file.fileno(), np.ascontiguousarray(values, dtype=self.dtype), offset * self.dtype.itemsize,
                       self.path)
        finally:
            mark(self.path, self.file.fileno())

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` entries; appends go on after them."""
        verify(self.path)
        self.file.flush()
        try:
            self.file.truncate(n * self.dtype.itemsize)
            self.file.seek(0, os.SEEK_END)
            self.size = n
        finally:
            mark(self.path, self.file.fileno())

    def clear(self) -> None:
        verify(self.path)
        try:
            self.file.seek(0)
            self.file.truncate()
            self.size = 0
        finally:
            self._written()

    def close(self) -> None:
        self.file.close()

    def discard(self) -> None:
        """Close and delete the file."""
        self.file.close()
        discard_file(self.path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
