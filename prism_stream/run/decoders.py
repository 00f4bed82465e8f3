"""LAZ decoded whole chunks at a time through the chunk table, in worker processes when threads allow.

laspy's LAZ read feeds lazrs through a Python file object; lazrs can instead decode a buffer of whole
chunks (``decompress_points_with_chunk_table``), which costs less CPU for the same records
(bench/RESULTS.md: the "whole-chunk decode" floor beside laspy's read). And lazrs decodes under the GIL
(bench/PROFILE.md): a thread decoding beside the main thread takes the interpreter from it, so with
threads the filter could not run while a read decoded. So a local LAZ file with a chunk table is read
here as *tasks*, runs of whole chunks of at least a read's size, each decoded into a buffer:

- at one thread, in the calling thread, a chunk a call (one core), each read's whole chunks straight
  into its records;
- at two or more threads and at least ``PRISM_STREAM_PROCESS_POINTS`` points (default
  :data:`MIN_POINTS`; 0: any; -1: never), by that many worker processes (spawned; they import lazrs and
  nothing of prism-stream's), each task into a shared-memory slot, one task more than the workers ahead
  of the main process;
- else (fewer points, or a daemonic process such as a Dask worker, which may start none) in the calling
  thread, a read's whole chunks a call, which lazrs spreads over its threads as laspy's parallel reader
  does.

From processes, the main process copies each read's records out of the tasks in order; in-process, a
chunk a read shares with its neighbour goes through a chunk-sized buffer. Each read is wrapped as
laspy's own read would be: the same record bytes in the same reads (tests/test_decoders.py), so every output is
byte-identical whatever the thread or process count. The pool is made on first use and kept for the
process's life (made anew if a worker dies), so a run over many tiles, or many runs in one process,
start it once. A file without a chunk table, or a remote one, is read by laspy (formats/las.py).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections import deque

from . import signals

MIN_POINTS = 1 << 21  # two default reads: below that there is little for a second process to decode ahead

_lock = threading.Lock()
_pool = None
_pool_size = 0
_final = False  # stop(final=True) ran: the process is ending, and no pool may start again


def min_points() -> int:
    """``PRISM_STREAM_PROCESS_POINTS`` (the smallest read given to worker processes; -1: none)."""
    from ..errors import UsageError

    value = os.environ.get("PRISM_STREAM_PROCESS_POINTS", "")
    try:
        return int(value) if value.strip() else MIN_POINTS
    except ValueError:
        raise UsageError(f"PRISM_STREAM_PROCESS_POINTS must be a number of points, not {value!r}") from None


def processes_for(points: int, threads: int) -> int:
    """How many worker processes decode a read of ``points`` records at ``threads`` threads (0: in-process)."""
    if threads < 2:
        return 0
    least = min_points()
    if least < 0 or points < max(least, 1):
        return 0
    import multiprocessing

    return 0 if multiprocessing.current_process().daemon else threads  # a daemonic process may start none


_segments: dict = {}  # name -> the shared-memory slot of a read in progress, in the main process


def _executor(workers: int):
    global _pool, _pool_size
    with _lock:
        if _final:  # a read on another thread (the read-ahead) after the run's last step: its error goes nowhere
            raise RuntimeError("the run is ending: no decoder processes start now")
        if _pool is None or _pool_size != workers or getattr(_pool, "_broken", False):  # a worker died: anew
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            _quiet_tracker()

            if _pool is not None:
                _pool.shutdown(wait=False, cancel_futures=True)
            # spawn, not fork: a fork copies the locks the main process's threads hold (the numba loading,
            # the read-ahead), and Python 3.12 warns of it
            class Pool(ProcessPoolExecutor):
                def _spawn_process(self):  # Python 3.9+: each worker is started here, on some submit
                    # with Ctrl-C held, so blocked in the worker for life: a worker interrupted while Python
                    # starts in it would print a traceback before its initializer could ignore the signal
                    with signals.held(signal.SIGINT), _main_hidden():
                        super()._spawn_process()

            _pool = Pool(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_start,
                         initargs=(os.getpid(),))
            _pool_size = workers
            for _ in range(workers):  # started now, their start-up beside the caller's
                _pool.submit(_ready)
        return _pool


_spawning = threading.local()  # on while this thread spawns a decoder worker (:func:`_main_hidden`)


@contextlib.contextmanager
def _main_hidden():
    """A worker spawned here does not run the caller's ``__main__`` again: the workers need nothing of it (their
    functions live here), and a script that calls the library without the ``if __name__ == "__main__":`` guard
    would otherwise start its whole run again in each worker, which breaks the pool (what a newcomer's script
    met). multiprocessing's preparation data for the new process is given without its ``init_main_from_*``
    entries, for a start on this thread only: ``__main__`` itself is not touched, and another pool's start,
    on another thread, keeps its own."""
    from multiprocessing import spawn

    if not getattr(spawn.get_preparation_data, "prism_stream_wrapped", False):
        spawn.get_preparation_data = _without_main(spawn.get_preparation_data)
    _spawning.on = True
    try:
        yield
    finally:
        _spawning.on = False


def _without_main(get_preparation_data):
    def wrapped(name):
        data = get_preparation_data(name)
        if getattr(_spawning, "on", False):
            data.pop("init_main_from_path", None)
            data.pop("init_main_from_name", None)
        return data

    wrapped.prism_stream_wrapped = True
    return wrapped


def _quiet_tracker() -> None:
    """Start multiprocessing's resource tracker (the first worker's start would) with its stderr on /dev/null.
    It unlinks the slots of a main process killed outright; but Ctrl-C at the wrong moment (1 run in 45 of
    tests/test_decoders.py's at three threads, and once in CI) left it a slot it reports as leaked and finds
    already unlinked: two warnings after the run's one line, of nothing a user could act on."""
    from multiprocessing import resource_tracker

    if getattr(resource_tracker._resource_tracker, "_fd", None) is not None:
        return  # running already (started by this process, or inherited)
    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        resource_tracker.ensure_running()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def stop(seconds: float = 5.0, final: bool = False) -> None:
    """Stop the worker processes and wait for them (at most ``seconds``, then they are killed): a failing run's
    last step. A worker still starting when its parent exits finds the parent's semaphores gone and prints a
    traceback after the run's one line. ``final``: the process is ending, and no pool starts after this one
    stopped: the read-ahead thread, still reading when Ctrl-C came, started a new pool while the last was
    shutting down, whose workers outlived the run (holding its stderr open: a caller waiting for the end of
    that output waited for ever)."""
    global _pool, _pool_size, _final
    with _lock:
        _final = _final or final
        pool, _pool, _pool_size = _pool, None, 0
    if pool is None:
        _unlink_segments()
        return
    processes = list(getattr(pool, "_processes", {}).values())
    # waited for with the pool held: a pool let go unlinks its queues' semaphores, which a worker still
    # starting has yet to open (FileNotFoundError, printed by the worker)
    closing = threading.Thread(target=pool.shutdown, kwargs={"wait": True, "cancel_futures": True}, daemon=True)
    closing.start()
    closing.join(seconds)
    for p in processes:
        if p.is_alive():  # a worker stuck in a task: it goes now
            p.kill()
    _unlink_segments()


def _unlink_segments() -> None:
    """Unlink the shared-memory slots of reads that never reached their ``close`` (a run interrupted, then
    ended by ``os._exit``, leaves a suspended read's ``finally`` unrun): else the resource tracker reports them
    leaked on stderr after the run's one line, and a segment held by no tracker would outlive the run in
    /dev/shm."""
    with signals.held(signal.SIGINT, signal.SIGTERM):
        while _segments:
            _, slot = _segments.popitem()
            try:
                slot.unlink()
            except OSError:
                pass
            try:
                slot.close()
            except BufferError:  # a view of it still referenced by the unwound frames: unlinked is what matters
                pass


def prestart(points: int, threads: int) -> None:
    """Start the worker processes a read of ``points`` at ``threads`` would use, without waiting for them:
    their start-up (a Python process, lazrs) then overlaps the run's own set-up (the local engine calls this
    once the run's refusals are behind it, before numba loads)."""
    workers = processes_for(points, threads)
    if workers:
        _executor(workers)


def _ready() -> None:
    import lazrs  # noqa: F401 - loaded ahead of the first task


class ChunkTable:
    """A local LAZ file's chunks: first record, records and first byte of each (from lazrs), for a file of
    ``points`` records."""

    def __init__(self, path: str, offset: int, vlr: bytes, points: int):
        import struct

        import lazrs
        import numpy as np

        items = struct.unpack_from("<H", vlr, 32)[0] if len(vlr) >= 34 else 0
        versions = {struct.unpack_from("<H", vlr, 38 + 6 * i)[0] for i in range(items) if 40 + 6 * i <= len(vlr)}
        if not items or not versions <= {1, 2, 3}:
            # lazrs 0.8 reads items of version 4 (LASzip 3.4 r3) one point after another, not from a chunk table
            raise ValueError(f"LAZ item versions {sorted(versions)}: read by laspy")
        with open(path, "rb") as f:
            f.seek(offset)
            entries = lazrs.read_chunk_table(f, lazrs.LazVlr(vlr))
        # a table of fixed-size chunks stores no point counts: lazrs lists the chunk size for each, the last
        # chunk's too, which holds what is left of the header's count
        listed = sum(c for c, _ in entries)
        if entries and listed > points and listed - entries[-1][0] < points:
            entries[-1] = (points - (listed - entries[-1][0]), entries[-1][1])
        counts = np.array([c for c, _ in entries], dtype=np.int64).reshape(-1)
        sizes = np.array([b for _, b in entries], dtype=np.int64).reshape(-1)
        self.path, self.vlr = path, vlr
        self.entries = entries
        self.first = np.concatenate([[0], np.cumsum(counts)])    # record index of each chunk's start
        self.byte = offset + 8 + np.concatenate([[0], np.cumsum(sizes)])  # after the table's 8-byte offset

    @property
    def points(self) -> int:
        return int(self.first[-1])

    def tasks(self, start: int, stop: int, size: int) -> list[tuple[int, int, int, int, list]]:
        """Runs of whole chunks covering records [start, stop), each of at least ``size`` records (but the
        last): (first record, records, first byte, bytes, the run's table entries)."""
        import numpy as np

        a = int(np.searchsorted(self.first, start, side="right")) - 1
        out = []
        while a < len(self.entries) and int(self.first[a]) < stop:
            b = int(np.searchsorted(self.first, int(self.first[a]) + max(1, size), side="left"))
            b = min(max(b, a + 1), len(self.entries))
            out.append((int(self.first[a]), int(self.first[b] - self.first[a]), int(self.byte[a]),
                        int(self.byte[b] - self.byte[a]), self.entries[a:b]))
            a = b
        return out


def lazrs_selection(selection) -> int:
    """laspy's ``DecompressionSelection`` as lazrs's bits (laspy numbers its layers otherwise)."""
    import laspy
    import lazrs

    bits = 0
    for flag in laspy.DecompressionSelection:
        if flag in selection and flag.name:
            bits |= getattr(lazrs, f"SELECTIVE_DECOMPRESS_{flag.name}")
    return bits


def records(table: ChunkTable, header, selection: int | None, chunk_size: int, start: int, stop: int,
            threads: int):
    """Yield (first record, laspy ``ScaleAwarePointRecord``) for records [start, stop), ``chunk_size`` a read
    as laspy's reads make them, decoded by worker processes when :func:`processes_for` says, else here.
    ``selection``: lazrs's layer bits (:func:`lazrs_selection`), or None for every layer."""
    import laspy

    from ..errors import CorruptInput

    dtype = header.point_format.dtype()
    width = dtype.itemsize
    if table.points < stop:
        raise CorruptInput(f"the chunk table holds {table.points} of the {stop} points the header declares",
                           table.path)
    workers = processes_for(stop - start, threads)
    if not workers:
        yield from _in_process(table, header, selection, chunk_size, (start, stop), threads > 1)
        return
    tasks = deque(table.tasks(start, stop, chunk_size))
    largest = max((t[1] for t in tasks), default=0)
    job = (os.urandom(8).hex(), table.path, table.vlr, selection, width)
    feed = _Processes(job, workers, largest)
    try:
        feed.fill(tasks)
        pos = start
        buffers = Buffers()
        while pos < stop:
            n = min(chunk_size, stop - pos)
            flat = buffers.take(n * width)
            out = flat.view(dtype)
            done = 0
            while done < n:
                first, count, view = feed.head()
                a = pos + done - first
                take = min(count - a, n - done)
                flat[done * width:(done + take) * width] = view[a * width:(a + take) * width]
                done += take
                if a + take == count:
                    feed.pop(tasks)
            yield pos, laspy.ScaleAwarePointRecord(out, header.point_format, header.scales, header.offsets)
            pos += n
    finally:
        feed.close()


class Buffers:
    """The memory of a read's records, used again once nothing holds it.

    A read's records are about 36 MB (a million PF7 points): past glibc's largest threshold for mapping
    an allocation on its own (32 MiB), so a fresh array a read was mapped anew and its pages faulted in one
    by one as the decoder wrote them (at 100M points 2 s of system time of a 35 s run, bench/PROFILE.md). A
    buffer is handed out again only when this pool holds the last reference to it: every array, laspy record
    or Arrow buffer made from a read holds one through its base, so a read still in use (the one the caller
    works on while the next is decoded, one waiting in the read-ahead's queue, anything kept of it) is never
    written over. At most ``most`` buffers are kept (two at one thread: the read worked on and the next; four
    with the read-ahead, which holds one more in its queue and decodes another); a read past them gets memory
    of its own.
    """

    def __init__(self, most: int = 4):
        import numpy as np

        self.most = most
        self.held: list = []
        # what the count says of a buffer only the list holds, measured the way _free measures (an interpreter
        # may count a call's argument or borrow it: Python 3.14 borrows some references on its stack)
        self._alone = _count([np.empty(0, np.uint8)], 0)

    def take(self, nbytes: int):
        """A uint8 array of ``nbytes`` that nothing else references."""
        import numpy as np

        for i in range(len(self.held)):
            if self.held[i].nbytes >= nbytes and self._free(i):
                return self.held[i][:nbytes]
        buf = np.empty(max(nbytes, 1), dtype=np.uint8)
        if len(self.held) < self.most:
            self.held.append(buf)
        return buf[:nbytes]

    def _free(self, i: int) -> bool:
        return _count(self.held, i) <= self._alone


def _count(items: list, i: int) -> int:
    return sys.getrefcount(items[i])


class _Failed(RuntimeError):
    """A decoding error, by its message (named as in-process reads name it)."""

    def __str__(self) -> str:
        return str(self.args[0])


def _raise_failure(path: str, failure: str):
    from ..formats.guard import reading

    with reading(path):
        raise _Failed(failure)


def _in_process(table: ChunkTable, header, selection: int | None, chunk_size: int, span: tuple, parallel: bool):
    """Records ``span`` = [start, stop) decoded in this thread, a read at a time: the chunks a read holds
    whole straight into its records (a run of them a call, which lazrs spreads over its threads when
    ``parallel``, else a chunk a call on this thread), a chunk it shares with the read before or after
    through a chunk-sized buffer, kept for that neighbour."""
    import laspy
    import lazrs
    import numpy as np

    from ..formats.guard import reading

    start, stop = span
    dtype = header.point_format.dtype()
    width = dtype.itemsize
    first, byte, entries = table.first, table.byte, table.entries
    sel = lazrs.DecompressionSelection(selection) if selection is not None else None
    scratch = np.empty(max((c for c, _ in entries), default=1) * width, dtype=np.uint8)
    held = -1  # the chunk whose records the buffer holds

    def decode(f, c: int, d: int, out) -> None:
        """Chunks [c, d) into ``out``."""
        data = _read_run(f, int(byte[c]), int(byte[d] - byte[c]))
        _chunks_into(data, table.vlr, sel, entries[c:d], width, out, parallel)

    buffers = Buffers(4 if parallel else 2)
    with reading(table.path), open(table.path, "rb") as f:
        pos = start
        while pos < stop:
            end = min(stop, pos + chunk_size)
            flat = buffers.take((end - pos) * width)
            out = flat.view(dtype)
            c = int(np.searchsorted(first, pos, side="right")) - 1
            while c < len(entries) and first[c] < end:
                lo, hi = max(pos, int(first[c])), min(end, int(first[c + 1]))
                if lo == first[c] and hi == first[c + 1]:  # whole chunks: straight into the read's records
                    d = c + 1
                    while d < len(entries) and first[d + 1] <= end:
                        d += 1
                    decode(f, c, d, flat[(lo - pos) * width:(int(first[d]) - pos) * width])
                    c = d
                    continue
                if held != c:
                    held = -1
                    decode(f, c, c + 1, scratch[:int(first[c + 1] - first[c]) * width])
                    held = c
                a = lo - int(first[c])
                flat[(lo - pos) * width:(hi - pos) * width] = scratch[a * width:(a + hi - lo) * width]
                c += 1
            yield pos, laspy.ScaleAwarePointRecord(out, header.point_format, header.scales, header.offsets)
            pos = end


def _read_run(f, byte: int, size: int) -> bytes:
    """The compressed bytes of a run of chunks (EOFError: the file is shorter than its chunk table says)."""
    f.seek(byte)
    data = f.read(size)
    if len(data) < size:
        raise EOFError(f"the file ends inside a LAZ chunk ({len(data)} of the {size} bytes from byte {byte})")
    return data


def _chunks_into(data, vlr: bytes, sel, entries: list, width: int, out, whole: bool) -> None:
    """Decode ``data``, the whole chunks ``entries`` (points, bytes), into ``out``: in one call when
    ``whole`` (lazrs spreads it over its threads), else a chunk a call."""
    import lazrs

    if whole:
        lazrs.decompress_points_with_chunk_table(data, vlr, out, entries, sel)
        return
    with memoryview(data) as src:
        at = put = 0
        for points, nbytes in entries:
            lazrs.decompress_points_with_chunk_table(src[at:at + nbytes], vlr, out[put:put + points * width],
                                                     [(points, nbytes)], sel)
            at += nbytes
            put += points * width


class _Processes:
    """Tasks decoded by worker processes into shared-memory slots, up to one more than the workers ahead."""

    def __init__(self, job: tuple, workers: int, largest: int):
        from multiprocessing.shared_memory import SharedMemory

        self.job = job
        self.pool = _executor(workers)
        self.slots = []
        for _ in range(workers + 1):  # each one known to stop() the moment it exists (an interrupt may come next)
            with signals.held(signal.SIGINT, signal.SIGTERM):  # made, registered with the tracker, and noted here
                slot = SharedMemory(create=True, size=max(1, largest * job[4]))
                _segments[slot.name] = slot
            self.slots.append(slot)
        self.free = list(self.slots)
        self.pending: deque = deque()

    def fill(self, tasks) -> None:
        while tasks and self.free:
            first, count, *task = tasks.popleft()
            slot = self.free.pop()
            try:
                fut = self.pool.submit(_decode, self.job, task, count, slot.name)
            except Exception as exc:  # noqa: BLE001 - the pool broke (a worker died) since the last task
                self.free.append(slot)
                self._died(exc)
            self.pending.append([fut, slot, first, count, False])  # False: its outcome not yet checked

    def _died(self, exc: BaseException):
        from ..errors import CorruptInput

        raise CorruptInput(f"a decoder process failed: {type(exc).__name__}: {exc}", self.job[1]) from None

    def head(self):
        item = self.pending[0]
        if not item[4]:
            try:
                failure = item[0].result()
            except Exception as exc:  # noqa: BLE001 - a worker that died (killed, out of memory)
                self._died(exc)
            if failure is not None:
                _raise_failure(self.job[1], failure)
            item[4] = True
        return item[2], item[3], item[1].buf

    def pop(self, tasks) -> None:
        fut, slot, *_ = self.pending.popleft()
        self.free.append(slot)
        self.fill(tasks)

    def close(self) -> None:
        for fut, *_ in self.pending:
            fut.cancel()
        for fut, *_ in self.pending:  # a slot is unlinked once no worker writes into it
            if not fut.cancelled():
                try:
                    fut.result()
                except Exception:  # noqa: BLE001, S110 - already failing or abandoned: its slot goes anyway
                    pass
        self.pending.clear()
        # an interrupt between a segment's unlink and its unregistering left the resource tracker a name to
        # unlink again at exit, and its warnings after the run's one line (CI, stop 53)
        with signals.held(signal.SIGINT, signal.SIGTERM):
            for slot in self.slots:
                if _segments.pop(slot.name, None) is not None:
                    slot.close()
                    slot.unlink()


# ---------------------------------------------------------------------------------------------------------
# The decoding, in a worker process (or in-process at one thread): module-level state of that process.

_open: dict = {}   # token -> the open file
_slots: dict = {}  # shared-memory name -> mapped segment


def _worker_start(parent: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to report, once
    os.environ.setdefault("RAYON_NUM_THREADS", "1")  # lazrs: one thread a worker, the pool is the parallelism
    # the main process's pid as it gave it: one killed while this worker started is already gone here
    threading.Thread(target=_orphan_watch, args=(parent,), name="prism-stream-orphan-watch", daemon=True).start()


ORPHAN_POLL = 0.5  # seconds between a worker's looks at whether its main process is still there


def _orphan_watch(parent: int) -> None:
    """A worker whose main process died without stopping it (``kill -9``) ends too: its task queue never
    closes (each worker holds both ends), so it would wait for work for ever, holding its memory, and
    multiprocessing's resource tracker, which unlinks the shared-memory slots once every process that could
    use them is gone, would wait with it."""
    while os.getppid() == parent:
        time.sleep(ORPHAN_POLL)
    os._exit(1)


def _forget(token: str) -> None:
    f = _open.pop(token, None)
    if f is not None:
        f.close()


def _decode_into(job: tuple, task: list, out) -> str | None:
    """A worker's task into ``out``: ``job`` = (token, path, LASzip VLR, lazrs selection bits or None, record
    width), ``task`` = (first byte, bytes, the table entries of its whole chunks), in one call (a worker's
    lazrs has one thread). None, or the failure's ``Type: first line``."""
    token, path, vlr, selection, width = job
    byte, size, entries = task
    try:
        import lazrs

        f = _open.get(token)
        if f is None:
            for old in list(_open):  # one open file at a time: a new read's token closes the last one's
                _forget(old)
            f = _open[token] = open(path, "rb")
        data = _read_run(f, byte, size)
        sel = lazrs.DecompressionSelection(selection) if selection is not None else None
        _chunks_into(data, vlr, sel, entries, width, out, whole=True)
        return None
    except BaseException as exc:  # noqa: BLE001 - a Rust panic (a BaseException) too; handed back by its message
        _forget(token)
        text = str(exc).strip().splitlines()
        return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _decode(job: tuple, task: list, count: int, slot: str) -> str | None:
    """A worker's task: decode into the main process's shared-memory slot ``slot`` (``count`` records)."""
    try:
        shm = _attach(slot)
    except BaseException as exc:  # noqa: BLE001 - the main process gave up on this read
        return f"{type(exc).__name__}: {exc}"
    with memoryview(shm.buf) as view:
        return _decode_into(job, task, view[:count * job[4]])


def _attach(name: str):
    """The main process's segment ``name``, mapped into this worker without registering it with the
    resource tracker (which would unlink it, or complain, when this worker exits: the main process owns it)."""
    shm = _slots.get(name)
    if shm is None:
        while len(_slots) >= 16:  # segments of finished reads (unlinked by the main process)
            _slots.pop(next(iter(_slots))).close()
        try:
            from multiprocessing.shared_memory import SharedMemory

            shm = SharedMemory(name=name, track=False)  # Python 3.13
        except TypeError:
            shm = _Mapped(name)
        _slots[name] = shm
    return shm


class _Mapped:
    """A POSIX shared-memory segment mapped by name, untracked (what ``SharedMemory(track=False)`` does)."""

    def __init__(self, name: str):
        import mmap

        import _posixshmem

        fd = _posixshmem.shm_open("/" + name.lstrip("/"), os.O_RDWR, mode=0o600)
        try:
            self.buf = memoryview(mmap.mmap(fd, os.fstat(fd).st_size))
        finally:
            os.close(fd)

    def close(self) -> None:
        mm = self.buf.obj
        self.buf.release()
        mm.close()
