"""Read ahead on a background thread, so decoding overlaps with our kernels.

Decoders that release the GIL (pyarrow, numba kernels with nogil) then run
beside the main thread; those that do not lose nothing but a queue hop.
"""

from __future__ import annotations

import queue
import threading

_DONE = object()


class _Failure:
    def __init__(self, exc: BaseException):
        self.exc = exc


def prefetched(iterable, depth: int = 1):
    """Yield the items of ``iterable``, produced up to ``depth`` ahead on a thread (one chunk ahead is enough
    to overlap decoding with the kernels on two cores; a second held another decoded chunk, about 30 MB at a
    million points, at the peak of a run over millions of bins, and measured no faster)."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce():
        try:
            for item in iterable:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            item = _DONE
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            item = _Failure(exc)
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    worker = threading.Thread(target=produce, name="prism-stream-reader", daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, _Failure):
                raise item.exc
            yield item
    finally:
        stop.set()
        worker.join(timeout=5)
        close = getattr(iterable, "close", None)
        if close is not None and not worker.is_alive():
            close()
