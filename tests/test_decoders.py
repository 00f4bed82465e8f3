"""LAZ read from its chunk table (prism_stream.run.decoders), in-process and in worker processes.

The reader's promise: the same reads (first record, length) and the same record bytes as laspy's own
read of the same range, whatever the read size, the first and last record, the decompression selection
and the number of worker processes; so outputs are byte-identical whatever ``--threads``. A failing
chunk, a dead worker, Ctrl-C: one line, nothing left (no worker, no shared memory).
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism_stream.errors import CorruptInput, UsageError
from prism_stream.formats.las import LasSource
from prism_stream.run import decoders

from conftest import cli, edge_file, prism_stream_command, random_colors, real_file, user_env, write_las

N = 130_000  # three LAZ chunks of laspy's 50,000: 50,000, 50,000, 30,000


@pytest.fixture(scope="module")
def laz3(tmp_path_factory) -> Path:
    return write_las(tmp_path_factory.mktemp("laz") / "three.laz", random_colors(N, seed=5, palette=900), 3)


@pytest.fixture(scope="module")
def laz7(tmp_path_factory) -> Path:
    return write_las(tmp_path_factory.mktemp("laz") / "seven.laz", random_colors(N, seed=6, palette=900), 7,
                     version="1.4")


@pytest.fixture
def processes(monkeypatch):
    """Worker processes for reads of any size."""
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "0")


# the three ways a read is decoded: (threads, PRISM_STREAM_PROCESS_POINTS)
WAYS = {"one thread": (1, "0"), "in-process, lazrs's threads": (2, "-1"), "worker processes": (2, "0")}


@pytest.fixture(params=list(WAYS))
def way(request, monkeypatch) -> int:
    """Each way a read is decoded; the threads to ask for."""
    threads, least = WAYS[request.param]
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", least)
    return threads


def laspy_reads(path, chunk_size: int, start: int, stop: int, selection=None) -> list[tuple[int, bytes]]:
    kw = {"laz_backend": laspy.LazBackend.Lazrs}
    if selection is not None:
        kw["decompression_selection"] = selection
    out = []
    with laspy.open(str(path), **kw) as r:
        if start:
            r.seek(start)
        pos = start
        while pos < stop:
            pts = r.read_points(min(chunk_size, stop - pos))
            out.append((pos, pts.array.tobytes()))
            pos += len(pts)
    return out


def our_reads(path, chunk_size: int, start: int, stop: int, threads: int, selection=None) -> list[tuple[int, bytes]]:
    src = LasSource(str(path), 0, threads=threads)
    assert src._chunk_table() is not None, "this file should be read through its chunk table"
    return [(pos, pts.array.tobytes()) for pos, pts in src._records(chunk_size, start, stop, selection)]


@pytest.mark.parametrize("chunk_size,start,stop", [
    (1 << 20, 0, N), (65_536, 0, N), (50_000, 0, N), (100_000, 0, N), (7_001, 0, N), (1, 49_998, 50_003),
    (40_000, 49_999, 100_001), (30_000, 12_345, 128_000), (N, N - 1, N), (3, 0, 7), (50_000, 50_000, N),
])
def test_reads_equal_laspys(laz3, way, chunk_size, start, stop):
    assert our_reads(laz3, chunk_size, start, stop, way) == laspy_reads(laz3, chunk_size, start, stop)


def test_reads_held_together_keep_their_bytes(laz3, way):
    """Every read kept until the end is still its own bytes: a read's memory is used again only once nothing
    holds it (decoders.Buffers)."""
    src = LasSource(str(laz3), 0, threads=way)
    held = [(pos, pts) for pos, pts in src._records(20_000, 0, N, None)]  # the records themselves, not copies
    assert [(pos, pts.array.tobytes()) for pos, pts in held] == laspy_reads(laz3, 20_000, 0, N)


def test_a_buffer_is_handed_out_again_only_once_nothing_holds_it():
    pool = decoders.Buffers()
    first = pool.take(1000)
    address = first.__array_interface__["data"][0]
    kept = first.view(np.uint32)[10:20]  # a view of a view: it holds the buffer through its base
    del first
    second = pool.take(1000)
    assert second.__array_interface__["data"][0] != address
    del kept
    third = pool.take(800)  # smaller: the first buffer again, as a view of its start
    assert third.__array_interface__["data"][0] == address and third.nbytes == 800
    assert pool.take(5000).nbytes == 5000  # larger than any held: memory of its own
    del second, third
    took = [pool.take(100) for _ in range(pool.most + 2)]  # all held in use: the pool keeps at most ``most``
    assert len(pool.held) == pool.most and len({t.__array_interface__["data"][0] for t in took}) == len(took)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(chunk_size=st.integers(1, 140_000), start=st.integers(0, N - 1), length=st.integers(1, N))
def test_any_read_equals_laspys(laz3, way, chunk_size, start, length):
    stop = min(N, start + length)
    chunk_size = max(chunk_size, (stop - start) // 40)  # at most 40 reads an example: seconds, not minutes
    assert our_reads(laz3, chunk_size, start, stop, way) == laspy_reads(laz3, chunk_size, start, stop)


def test_selection_reads_equal_laspys(laz7, way):
    """``--reads two``'s first pass decodes the RGB layer only (LAS 1.4, point formats 6-10)."""
    sel = laspy.DecompressionSelection.base().decompress_rgb()
    ours = our_reads(laz7, 40_000, 0, N, way, sel)
    theirs = laspy_reads(laz7, 40_000, 0, N, sel)
    dtype = laspy.PointFormat(7).dtype()
    assert [p for p, _ in ours] == [p for p, _ in theirs]
    for (_, a), (_, b) in zip(ours, theirs):
        a, b = np.frombuffer(a, dtype), np.frombuffer(b, dtype)
        for name in ("X", "Y", "red", "green", "blue"):  # what the selection promises (the rest is undefined)
            assert np.array_equal(a[name], b[name]), name


@pytest.mark.parametrize("name", [
    "edge:pdal__1.2-with-color.copc.laz",      # COPC: chunks of varying size
    "edge:loadersgl__pdrf8-1.4.laz",
    "real:potree__lion_takanawa.copc.laz",
    "real:pdal__las_with_several_extra_byte_bloc.laz",  # extra bytes
])
def test_real_files_read_as_laspy_reads_them(name, way):
    kind, file = name.split(":")
    path = edge_file(file) if kind == "edge" else real_file(file)
    with laspy.open(str(path)) as r:
        n = r.header.point_count
    for chunk_size in (1 << 20, 4_099):
        assert our_reads(path, chunk_size, 0, n, way) == laspy_reads(path, chunk_size, 0, n), chunk_size


def test_a_table_lazrs_cannot_use_leaves_the_file_to_laspy(laz3, monkeypatch):
    """No chunk table (a streaming writer's file), or items lazrs decodes only point after point: laspy's
    sequential reader, the same records."""
    def refuse(*a, **k):
        raise ValueError("no table")

    monkeypatch.setattr(decoders, "ChunkTable", refuse)
    src = LasSource(str(laz3), 0, threads=2)
    assert src._chunk_table() is None
    got = [(pos, pts.array.tobytes()) for pos, pts in src._records(65_536, 0, N)]
    assert got == laspy_reads(laz3, 65_536, 0, N)


def test_items_of_version_4_are_not_read_through_the_table(edge_dir):
    vlr = bytearray(34 + 6)
    struct.pack_into("<H", vlr, 32, 1)
    struct.pack_into("<HHH", vlr, 34, 10, 30, 4)
    with pytest.raises(ValueError, match="item versions"):
        decoders.ChunkTable(str(edge_file("loadersgl__pdrf7-v4-1.4.laz")), 0, bytes(vlr), 1)


@pytest.mark.parametrize("threads", ["1", "2"])
@pytest.mark.parametrize("extra", [[], ["--reads", "two"]])
def test_outputs_do_not_depend_on_processes(tmp_path, capsys, monkeypatch, laz7, threads, extra):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "-1")
    code, _, err = cli(capsys, str(laz7), str(tmp_path / "base.laz"), "--ratio", "0.05", "--threads", "1",
                       "--chunk-size", "20000", *extra)
    assert code == 0, err
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "0")
    code, _, err = cli(capsys, str(laz7), str(tmp_path / "proc.laz"), "--ratio", "0.05", "--threads", threads,
                       "--chunk-size", "20000", *extra)
    assert code == 0, err
    a, b = laspy.read(str(tmp_path / "base.laz")), laspy.read(str(tmp_path / "proc.laz"))
    assert a.header.point_count == b.header.point_count == round(0.05 * N)
    assert a.points.array.tobytes() == b.points.array.tobytes()


def test_the_engine_uses_worker_processes(laz3, processes):
    """The path the tests above compare is the one a run takes at two threads."""
    assert decoders.processes_for(N, 2) == 2
    assert decoders.processes_for(N, 1) == 0
    src = LasSource(str(laz3), 0, threads=2)
    seen = []
    original = decoders._Processes

    class Spy(original):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            seen.append([s.name for s in self.slots])

    decoders._Processes = Spy
    try:
        reads = src._records(20_000, 0, N)
        next(reads)
        reads.close()  # abandoned after one read: its slots go at once
    finally:
        decoders._Processes = original
    assert seen and seen[0]
    for name in seen[0]:
        assert not os.path.exists(f"/dev/shm/{name.lstrip('/')}"), "a shared-memory slot was left behind"


def test_threshold_and_daemonic_processes(monkeypatch):
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "1000")
    assert decoders.processes_for(999, 4) == 0 and decoders.processes_for(1000, 4) == 4
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "-1")
    assert decoders.processes_for(10**9, 4) == 0
    monkeypatch.delenv("PRISM_STREAM_PROCESS_POINTS")
    assert decoders.processes_for(decoders.MIN_POINTS - 1, 2) == 0 and decoders.processes_for(decoders.MIN_POINTS, 2)
    import multiprocessing

    class Daemon:
        daemon = True

    monkeypatch.setattr(multiprocessing, "current_process", lambda: Daemon())
    assert decoders.processes_for(10**9, 4) == 0  # a Dask worker may start no process


def test_a_bad_setting_is_a_usage_error(monkeypatch, tmp_path, capsys, laz3):
    monkeypatch.setenv("PRISM_STREAM_PROCESS_POINTS", "lots")
    with pytest.raises(UsageError, match="PRISM_STREAM_PROCESS_POINTS"):
        decoders.min_points()
    code, _, err = cli(capsys, str(laz3), str(tmp_path / "o.parquet"), "--ratio", "0.1", "--threads", "2")
    assert code == 2 and "PRISM_STREAM_PROCESS_POINTS" in err and "Traceback" not in err


def test_a_chunk_past_the_end_of_the_file_names_the_file(laz3, way):
    """A chunk table whose last chunk runs past the end of the file (a truncated copy): one line naming it."""
    src = LasSource(str(laz3), 0, threads=way)
    table = src._chunk_table()
    points, size = table.entries[-1]
    table.entries[-1] = (points, size + 10**6)
    table.byte[-1] += 10**6
    with pytest.raises(CorruptInput, match="ends inside") as e:
        list(decoders.records(table, src.header, None, 65_536, 0, N, way))
    assert str(laz3) in str(e.value) and "\n" not in str(e.value)



def test_stop_unlinks_the_slots_of_a_read_never_closed(laz3, processes):
    """Found by CI: Ctrl-C at the moment the workers existed left the resource tracker reporting 3 leaked
    segments after the run's one line; the run ends by ``os._exit`` after its clean-up, so a read suspended in
    the unwound frames never ran its ``finally``. The clean-up's ``stop()`` unlinks what no read closed."""
    src = LasSource(str(laz3), 0, threads=2)
    reads = src._records(20_000, 0, N)
    next(reads)  # suspended with its slots mapped, never closed
    names = list(decoders._segments)
    assert names, "the read should hold shared-memory slots"
    decoders.stop()
    assert not decoders._segments
    for name in names:
        assert not os.path.exists(f"/dev/shm/{name.lstrip('/')}"), "a shared-memory slot outlived stop()"
    reads.close()  # what closing it later does to slots already gone: nothing
    assert our_reads(laz3, 65_536, 0, N, 2) == laspy_reads(laz3, 65_536, 0, N)  # a new pool after the stop



def test_no_pool_starts_after_the_final_stop(laz3, processes, monkeypatch):
    """Found while mending the above: Ctrl-C with the read-ahead thread inside a read let that thread start a
    new pool while the run's last step stopped the old one; its workers outlived the run (holding its stderr
    open, so a caller reading it to the end hung: 1 run in 10 of the test above at three threads). After the
    final stop a read fails instead, and starts nothing."""
    monkeypatch.setattr(decoders, "_final", False)  # put back after the test: this process goes on
    decoders.stop(final=True)
    src = LasSource(str(laz3), 0, threads=2)
    with pytest.raises(RuntimeError, match="run is ending"):
        next(src._records(20_000, 0, N))
    assert decoders._pool is None and not decoders._segments



LEFT = """
import os, sys
from multiprocessing.shared_memory import SharedMemory
from prism_stream.run import decoders
decoders._executor(1).submit(decoders._ready).result()  # the pool, and with it the resource tracker
shm = SharedMemory(create=True, size=4096)
print(shm.name, flush=True)
decoders.stop()  # the workers go (they hold the tracker's pipe too); the slot stays
os._exit(0)  # as a run ended without unlinking it: nothing of this process unlinks it
"""


def test_a_slot_left_behind_is_unlinked_by_the_tracker_which_says_nothing():
    """The resource tracker (started with the first pool, its stderr on /dev/null) still unlinks a slot of a
    process that ended without unlinking it, and prints nothing where the run's one line goes."""
    done = subprocess.run([sys.executable, "-c", LEFT], capture_output=True, text=True, timeout=120)
    name = done.stdout.strip().lstrip("/")
    assert done.returncode == 0 and name, done.stderr
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and os.path.exists(f"/dev/shm/{name}"):
        time.sleep(0.05)
    assert not os.path.exists(f"/dev/shm/{name}"), "the tracker did not unlink the slot"
    assert done.stderr == "", done.stderr


def test_a_dead_worker_is_one_line_and_the_next_read_starts_anew(laz3, big_laz, processes):
    src = LasSource(str(big_laz), 0, threads=2)
    reads = src._records(50_000, 0, src.count)  # 60 tasks, at most 3 in flight
    next(reads)
    for proc in list(decoders._pool._processes.values()):
        os.kill(proc.pid, signal.SIGKILL)
    with pytest.raises(CorruptInput, match="decoder process failed") as e:
        for _ in reads:
            pass
    assert str(big_laz) in str(e.value) and "\n" not in str(e.value)
    assert our_reads(laz3, 65_536, 0, N, 2) == laspy_reads(laz3, 65_536, 0, N)  # a new pool


@pytest.fixture(scope="module")
def big_laz(tmp_path_factory) -> Path:
    return write_las(tmp_path_factory.mktemp("big") / "big.laz", random_colors(3_000_000, seed=9, palette=4000), 3)


def _started_with_workers(args, workers: int, **popen):
    """A prism-stream run started in a session of its own (LAZ decoder processes for any size), once it has
    ``workers`` of them or has ended: (the process, all its child processes then)."""
    import psutil

    proc = subprocess.Popen([*prism_stream_command(), *map(str, args)], start_new_session=True,
                            env=user_env(PRISM_STREAM_PROCESS_POINTS="0"), **popen)
    deadline = time.monotonic() + 60
    children = []
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            children = psutil.Process(proc.pid).children(recursive=True)
        except psutil.Error:
            children = []
        if sum("spawn_main" in " ".join(c.cmdline()) for c in children) >= workers:
            break
        time.sleep(0.01)
    return proc, children


@pytest.mark.parametrize("after,threads", [(0.0, 2), (0.3, 2), (0.0, 3)])
def test_ctrl_c_stops_the_workers_too(tmp_path, big_laz, after, threads):
    """Ctrl-C in a terminal reaches the whole process group: exit 130, one line (none from the workers),
    no output, and no worker process outlives the run; also the moment the workers exist, while Python
    starts in them (where a worker used to print a traceback)."""
    import psutil

    temp_dir = tmp_path / "tmp"
    temp_dir.mkdir()
    out = tmp_path / "out.parquet"
    proc, children = _started_with_workers([big_laz, out, "--ratio", "0.3", "--threads", threads, "--temp-dir",
                                            temp_dir, "--quiet"], threads, stdout=subprocess.PIPE,
                                           stderr=subprocess.PIPE, text=True)
    children = [c for c in children if "spawn_main" in " ".join(c.cmdline())]
    try:
        assert len(children) >= threads, "the run started fewer decoder processes than threads"
        time.sleep(after)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "interrupt" in lines[0], stderr
    assert not out.exists()
    gone = time.monotonic() + 10
    while time.monotonic() < gone and any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children):
        time.sleep(0.05)
    assert not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children), "a worker outlived the run"


def test_every_worker_starts_with_ctrl_c_held(monkeypatch):
    """Found by a review: a pool starts a worker on a submit, and none when a worker is idle; a parent slowed
    between two starts (a busy machine) let the first worker's finished warm-up stand for the next one, which a
    later decode task then started with Ctrl-C unblocked. Each start is now held, whoever submits."""
    import signal as sig
    from concurrent.futures import ProcessPoolExecutor

    from prism_stream.run import decoders

    log = []
    start = ProcessPoolExecutor._spawn_process

    def slow_start(self):
        log.append(sig.SIGINT in sig.pthread_sigmask(sig.SIG_BLOCK, []))
        start(self)
        time.sleep(0.3)  # the parent preempted after a start: the first worker may be idle by the next submit

    monkeypatch.setattr(ProcessPoolExecutor, "_spawn_process", slow_start)
    monkeypatch.setattr(decoders, "_pool", None)
    monkeypatch.setattr(decoders, "_pool_size", 0)
    pool = decoders._executor(3)
    try:
        # tasks that hold their worker until every submit is made: each warm-up submit that found a worker idle
        # started none and claimed one of the warm-up's three completions, so the completions left unclaimed are
        # as many as the workers started, at most three of the six submits find a worker idle, and the others
        # start the workers missing, as a run's decode tasks would. (With quick tasks a worker idle again by
        # every submit left the pool at two workers: 1 run in several hundred, once in the suite.)
        import multiprocessing

        with multiprocessing.get_context("spawn").Manager() as manager:
            go = manager.Event()
            waiting = [pool.submit(go.wait, 60) for _ in range(6)]
            go.set()
            for f in waiting:
                assert f.result(timeout=60) is True
        assert len(pool._processes) == 3 and log == [True, True, True], log
        assert sig.SIGINT not in sig.pthread_sigmask(sig.SIG_BLOCK, [])  # the caller's mask is back
    finally:
        pool.shutdown()


def test_a_killed_run_leaves_no_worker_behind(tmp_path, big_laz):
    """``kill -9`` of the main process (no Ctrl-C, no cleanup of its own): the workers, whose task queue never
    closes, see their main process gone and end within a second, and multiprocessing's resource tracker, which
    unlinks the shared-memory slots once no process can use them, ends with them (a newcomer found both
    alive a minute later, holding three slots in /dev/shm)."""
    import psutil

    proc, children = _started_with_workers([big_laz, tmp_path / "out.parquet", "--ratio", "0.3", "--threads", 2,
                                            "--temp-dir", tmp_path, "--quiet"], 2, stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL)
    try:
        assert sum("spawn_main" in " ".join(c.cmdline()) for c in children) >= 2, "no decoder processes started"
        assert any("resource_tracker" in " ".join(c.cmdline()) for c in children), children
        time.sleep(0.3)  # the workers at their tasks
        proc.kill()
        proc.wait(timeout=30)
        gone = time.monotonic() + 10
        while time.monotonic() < gone and any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children):
            time.sleep(0.05)
        left = [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
        assert not left, f"alive 10 s after the main process was killed: {[' '.join(c.cmdline()) for c in left]}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_script_without_the_main_guard_runs(tmp_path, laz3):
    """The README's Python example saved as a script, without ``if __name__ == "__main__":``: the decoder
    processes do not run the script again (which started its run again in each and broke the pool, said as
    a corrupt input)."""
    script = tmp_path / "noguard.py"
    script.write_text("import prism_stream\n"
                      "print('started', flush=True)\n"
                      f"summary = prism_stream.sample({str(laz3)!r}, {str(tmp_path / 'out.parquet')!r}, ratio=0.1, "
                      "threads=2)\n"
                      "print('kept', summary.kept)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          env=user_env(PRISM_STREAM_PROCESS_POINTS="0"))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == "started" and done.stdout.count("started") == 1, done.stdout
    assert done.stdout.splitlines()[-1].startswith("kept "), done.stdout
    assert (tmp_path / "out.parquet").exists()


def test_a_worker_whose_main_process_is_gone_when_it_starts_ends():
    """The parent's pid comes from the main process (``initargs``): a worker that starts after a kill -9 of its
    main process (reparented already) ends too, where reading its own parent then would watch the reaper."""
    code = ("from prism_stream.run import decoders\n"
            "decoders.ORPHAN_POLL = 0.05\n"
            "decoders._worker_start(2 ** 22 + 12345)  # a parent that is not this process's\n"
            "import time\n"
            "time.sleep(20)\n"
            "print('still here')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "still here" not in done.stdout, (done.returncode, done.stdout, done.stderr)


def test_only_the_spawning_thread_leaves_main_out():
    """A worker's start drops ``init_main_from_*`` from its own preparation data; ``__main__`` is not touched,
    and a spawn on another thread meanwhile (a user's own pool) keeps them."""
    import threading
    from multiprocessing import spawn

    main = sys.modules["__main__"]
    before = dict(main.__dict__)
    seen = {}
    with decoders._main_hidden():
        seen["here"] = spawn.get_preparation_data("w")
        other = threading.Thread(target=lambda: seen.update(there=spawn.get_preparation_data("u")))
        other.start()
        other.join()
        assert main.__dict__.get("__file__") == before.get("__file__")
        assert main.__dict__.get("__spec__") is before.get("__spec__")
    after = spawn.get_preparation_data("v")
    mains = ("init_main_from_path", "init_main_from_name")
    assert not any(k in seen["here"] for k in mains)
    assert [k for k in mains if k in seen["there"]] == [k for k in mains if k in after]
