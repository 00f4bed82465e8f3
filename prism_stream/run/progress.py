"""Progress bars and the notice of a first compile, on stderr, shown only when stderr is a terminal."""

from __future__ import annotations

import os
import sys


COMPILING = ("prism-stream: compiling the numba kernels for this machine, once (about 5 to 15 s); later runs load "
             "them from the cache\n")
_noticed = [False]


def notice_compiling(enabled: bool) -> None:
    """Say so on a terminal when this run is about to compile the kernels (once per process)."""
    if enabled and not _noticed[0] and sys.stderr.isatty():
        from ..core.warm import cached

        _noticed[0] = True
        if not cached():
            sys.stderr.write(COMPILING)
            sys.stderr.flush()


VERBOSE = [False]  # -v/--verbose: each step on stderr as it starts and ends, terminal or not


def set_verbose(on: bool) -> None:
    VERBOSE[0] = bool(on)


def say(message: str) -> None:
    """One line on stderr under --verbose."""
    if VERBOSE[0]:
        sys.stderr.write(f"prism-stream: {message}\n")
        sys.stderr.flush()


class Progress:
    """A tqdm bar over points, or nothing when disabled or not on a TTY; under --verbose, a line as the step
    starts and one as it ends (points and seconds)."""

    def __init__(self, label: str, total: int, enabled: bool):
        import time

        self.bar = None
        self.label = label
        self.done = 0
        self.t0 = time.perf_counter()
        if VERBOSE[0]:
            say(f"{label}: {total:,} points" if total is not None else f"{label}...")
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=label, unit="pt", unit_scale=True, file=sys.stderr, leave=False,
                            dynamic_ncols=True)

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)

    def at(self, path: str, sources: int) -> None:
        """Show which input the bar is on (when there are several)."""
        if self.bar is not None and sources > 1:
            self.bar.set_postfix_str(os.path.basename(path), refresh=False)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        import time

        if self.bar is not None:
            self.bar.close()
        if exc_type is None:
            say(f"{self.label}: done, {self.done:,} points in {time.perf_counter() - self.t0:.2f} s")
