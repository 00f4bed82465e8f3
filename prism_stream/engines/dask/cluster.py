"""The cluster's plumbing: connecting, holding values, reducing in a tree, gathering without hanging."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import warnings

from ...errors import PrismError, UsageError
from ...run.memory import release_memory
from ...run.progress import say
from ...run.request import cores

FAN_IN = 4
IN_FLIGHT = 4  # tasks a worker thread has submitted and not finished in a windowed step (windowed)
SETTLE_SECONDS = 120.0  # the longest a failed step waits for its running tasks to end (settle)


class ClusterError(PrismError):
    """The cluster could not run the job (unreachable scheduler, workers dying over and over)."""

    exit_code = 9


def _release_memory() -> None:
    """Hand freed memory back to the OS after a task.

    Dask pauses a worker whose process memory passes 80% of its limit, and
    memory that glibc or Arrow's allocator keep after a task looks exactly
    like a leak to it: a small worker would pause for good.
    """
    release_memory()


def task(fn):
    """Worker-side task wrapper: release the task's memory (:func:`_release_memory`) after it. A PrismError
    goes back to the driver as it is, its path a part of it (``PrismError.__reduce__``)."""

    def run(*args, **kw):
        try:
            return fn(*args, **kw)
        except PrismError as exc:
            raise exc from None
        finally:
            _release_memory()

    run.__name__ = fn.__name__
    run.__qualname__ = fn.__qualname__
    run.__doc__ = fn.__doc__
    return run


def _same(value):
    return value


def held(client, value, key: str):
    """``value`` on the cluster, sent to every worker, as a task rather than scattered data.

    Scattered data dies with the last worker holding it; a task that returns
    the value is rerun on another worker, so a killed worker never loses it.
    """
    with large_graphs():
        future = client.submit(_same, value, key=key, pure=False)
    client.replicate([future])
    return future


@contextlib.contextmanager
def large_graphs():
    """Submit a task that carries a large value in its graph on purpose (:func:`held`, the plan's rules' parts:
    the scheduler can then rerun it when its workers die) without Dask's advice to scatter it instead, which a
    user of the command line can do nothing about (over 2^24 bins the plan is 127 MiB, the cutoffs 57 MiB)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
        yield


STALL_SECONDS = 120.0


def gather(client, futures, stall_seconds: float | None = None):
    """client.gather, but a cluster whose every worker stays paused fails instead of hanging.

    A Dask worker pauses at 80% of its memory limit and waits for memory to
    be freed; when every worker is paused, nothing ever runs again.
    """
    from distributed import Future, KilledWorker

    flat = [futures] if isinstance(futures, Future) else list(futures)
    try:
        wait_unstalled(client, flat, "ALL_COMPLETED", stall_seconds)
        return client.gather(futures)
    except KilledWorker as exc:
        raise ClusterError(f"a worker died running the same task too many times ({exc}); out of memory?") from None


def wait_unstalled(client, futures: list, return_when: str = "ALL_COMPLETED", stall_seconds: float | None = None):
    """distributed.wait (all, or ``FIRST_COMPLETED``), failing with ClusterError when every worker stays
    paused at its memory limit for ``stall_seconds``. Returns wait's (done, not_done)."""
    from distributed import wait

    stall = STALL_SECONDS if stall_seconds is None else stall_seconds
    paused_since = None
    while True:
        try:
            return wait(futures, timeout=2.0, return_when=return_when)
        except TimeoutError:
            pass
        workers = client.scheduler_info().get("workers", {})
        statuses = [str(w.get("status", "")).lower() for w in workers.values()]
        if statuses and all("paused" in st for st in statuses):
            paused_since = paused_since or time.monotonic()
            if time.monotonic() - paused_since > stall:
                client.cancel(futures)
                limits = sorted({int(w.get("memory_limit") or 0) >> 20 for w in workers.values()})
                raise ClusterError(
                    f"every worker has been paused at its memory limit ({', '.join(map(str, limits))} MiB) "
                    f"for {stall:.0f} s; give workers at least 1 GB or use --quant-bits 1 or more")
        else:
            paused_since = None


def window(client) -> int:
    """Tasks a windowed step keeps submitted and not finished: :data:`IN_FLIGHT` a worker thread of the cluster
    now (queued work for every worker, and a bounded number of results waiting in their memory)."""
    return IN_FLIGHT * max(1, sum(client.nthreads().values()))


def windowed(client, count: int, submit, finished) -> None:
    """Run ``count`` tasks (``submit(i)``: the i-th one's future), at most :data:`IN_FLIGHT` a worker thread
    submitted and not yet finished, handing each to ``finished(i, future)`` as it completes (in that order):
    queued work for every worker, and a bounded number of results waiting in their memory."""
    flying: dict = {}  # key -> (i, future)
    fed = 0

    def feed():
        nonlocal fed
        while fed < count and len(flying) < window(client):
            f = submit(fed)
            flying[f.key] = (fed, f)
            fed += 1

    with settled(client, lambda: [f for _, f in flying.values()]):
        feed()
        while flying:
            done, _ = wait_unstalled(client, [f for _, f in flying.values()], "FIRST_COMPLETED")
            for f in done:
                finished(*flying.pop(f.key))
            done = f = None
            feed()


def gather_settled(client, futures: list):
    """:func:`gather` of one step's tasks, all submitted at once (it waits for every one of them before it
    says the first error); interrupted, the others are cancelled before the run goes."""
    with settled(client, lambda: futures):
        return gather(client, futures)


@contextlib.contextmanager
def settled(client, in_flight):
    """A step's loop over its tasks: on a failure, :func:`settle` the ones ``in_flight()`` gives before the
    error leaves (on Ctrl-C or a signal, cancelled only)."""
    try:
        yield
    except BaseException as exc:
        settle(client, in_flight(), interrupted=not isinstance(exc, Exception))
        raise


# a worker's task in one of these may yet run, or still runs (a cancelled or resumed one is running when freed;
# fetch and flight are a result's transfer, not a run)
_MAY_RUN = ("waiting", "ready", "constrained", "executing", "long-running", "cancelled", "resumed")


def _executing(client, keys: set) -> set | None:
    """Of ``keys``, those a worker is running or may yet start (None: the workers could not be asked)."""

    def running(dask_worker):
        return [key for key, ts in dask_worker.state.tasks.items() if ts.state in _MAY_RUN]

    try:
        return {k for listed in client.run(running).values() for k in listed} & keys
    except Exception:  # noqa: BLE001 - a cluster gone runs nothing more
        return None


def settle(client, futures: list, seconds: float | None = None, interrupted: bool = False) -> None:
    """A failed step's tasks still in flight: every one cancelled (a task queued on the scheduler or in a
    worker's ready queue never starts), then, unless ``interrupted`` (Ctrl-C: the run goes at once), the ones
    a worker is running waited for, up to ``seconds`` (:data:`SETTLE_SECONDS`). A cancel does not stop a task
    a worker is running: what it writes beside the output (a spill, a part, a routed file) would otherwise
    land after the driver removed the staging folder, and be left there."""
    if not futures:
        return
    keys = {f.key for f in futures}
    try:
        client.cancel(futures)
    except Exception:  # noqa: BLE001 - the step's own error is the one to report
        return
    if interrupted:
        return
    limit = SETTLE_SECONDS if seconds is None else seconds
    deadline = time.monotonic() + limit
    said, clear = False, 0
    while True:
        left = _executing(client, keys)
        # twice clear, 0.1 s apart: a task the scheduler sent before the cancel may reach a worker after the
        # first look (its messages and client.run's travel apart) and start there; the cancel follows it
        clear = clear + 1 if not left else 0
        if clear >= 2 or left is None:
            return
        if not left:
            time.sleep(0.1)
            continue
        if time.monotonic() >= deadline:
            say(f"{len(left)} task(s) still running after {limit:.0f} s; what they write beside the output may be "
                "left there")
            return
        if not said:
            say(f"a task failed: waiting for the {len(left)} still running to end before cleaning up")
            said = True
        time.sleep(0.1)


def connect(address: str):
    """A Client for ``tcp://host:port`` (an existing scheduler) or ``local:N`` (a LocalCluster of N processes).

    A context manager; a LocalCluster is shut down on exit.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UsageError("--dask needs Dask: pip install 'dask[distributed]', or pip install '.[dask]' in the clone") from None

    if address.startswith("local:") or address == "local":
        n = address.partition(":")[2] or str(cores())
        if not n.isdigit() or int(n) < 1:
            raise UsageError(f"--dask local:N needs a positive number of workers, not {n!r}")
        # the workers' own logs (warnings as they are interrupted, shut down...) stay quiet: what goes wrong
        # reaches the driver as a task's error and is reported there, on one line
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        # Ctrl-C reaches the whole process group, the workers too: they start with their stderr on /dev/null,
        # so what they print as they die is not mixed into ours (their failures reach the driver as task errors)
        sys.stderr.flush()
        saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
            cluster = LocalCluster(n_workers=int(n), threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.CRITICAL)
            client = Client(cluster)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            os.close(devnull)
        return _Owned(client, cluster)
    if any(c.isspace() for c in address) or not address.strip():
        raise UsageError("--dask takes a scheduler address (tcp://host:8786) or local:N", address)
    try:
        return _Owned(Client(address, timeout="20s"), None)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"cannot reach the Dask scheduler: {exc}", address) from None
    except (ValueError, TypeError) as exc:
        raise UsageError(f"--dask takes a scheduler address (tcp://host:8786) or local:N: {exc}", address) from None


class _Owned:
    def __init__(self, client, cluster):
        self.client, self.cluster = client, cluster

    def __enter__(self):
        return self.client

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


