"""Signals held while a child process is started.

A process started while SIGINT can reach it is exposed from its first instruction: Ctrl-C goes to the
whole process group, and a spawned Python interrupted while it unpickles its start-up message prints a
traceback (no handler of ours runs there yet). A signal blocked in the starting thread is blocked in the
child too (the mask is inherited through fork and exec), so the child never sees it, and the parent gets
it right after the start, as usual.
"""

from __future__ import annotations

import contextlib
import signal


@contextlib.contextmanager
def held(*signums: int):
    """``signums`` (default SIGINT and SIGTERM) wait until the block is over, then are delivered as usual;
    processes started inside the block keep them blocked for their life.

    Blocking them in this thread is not enough in the main thread: another thread of the process (DuckDB's,
    lazrs's) may take the signal, and Python then runs its handler in the main thread at the next bytecode,
    inside the block (a child half started). So there the handlers are swapped for ones that only note the
    signal, and the noted signals are raised again after the block.
    """
    signums = signums or (signal.SIGINT, signal.SIGTERM)
    noted: list[int] = []
    try:
        before = {s: signal.signal(s, lambda signum, frame: noted.append(signum)) for s in signums}
    except ValueError:  # not the main thread: handlers cannot be set here, and do not run here either
        before = None
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, signums) if hasattr(signal, "pthread_sigmask") else None
    try:
        yield
    finally:
        if mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if before is not None:
            for s, handler in before.items():
                signal.signal(s, handler)
            for s in dict.fromkeys(noted):
                signal.raise_signal(s)
