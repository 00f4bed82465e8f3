"""Entry point: one line on stderr for every failure, and signals handled from the first instant.

This module imports nothing heavy at the top: :func:`run` installs the
SIGINT and SIGTERM handlers first, then loads the commands, so a signal
during start-up is the same one line as a signal during a run.
"""

from __future__ import annotations

import os  # os, sys and warnings are loaded before the first line runs: no search, no window for a signal
import sys
import warnings

import _thread  # built in, as _signal
import _signal as signal  # built in: no file search, so the window before run() installs its handlers is tiny

_SIGNALS = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated (SIGTERM)"}
_received: list[int] = []
_process = [False]  # run() is the process's command line (not a call from Python with its own argv)
_main_thread = [_thread.get_ident()]
_in_hook = [False]
_redelivery = [False]  # a signal is on its way again (see _unraisable): raise it, though one was received


def _on_signal(signum, frame):
    """The first SIGINT or SIGTERM unwinds the run (every cleanup runs); later ones are noted, not raised."""
    if _in_hook[0]:  # raised here it would be ignored too: once the hook has returned
        _deliver_later(signum)
        return
    _received.append(signum)
    if len(_received) == 1 or _redelivery[0]:
        _redelivery[0] = False
        raise KeyboardInterrupt


def _deliver_later(signum: int) -> None:
    """The signal again, to the main thread, from a thread of its own: the handler runs once the code that
    cannot raise has returned (a real signal, so a blocking call is interrupted as by the first)."""
    _thread.start_new_thread(signal.pthread_kill, (_main_thread[0], signum))


def _unraisable(unraisable) -> None:
    """An interrupt that landed where Python cannot raise it (a weakref callback of the import system's module
    locks, a ``__del__``) is ignored with a traceback on stderr and the run goes on as if never signalled;
    deliver it again instead, so that it unwinds the run at the next line that can raise."""
    if issubclass(unraisable.exc_type, KeyboardInterrupt) and _received \
            and signal.getsignal(_received[0]) is _on_signal:
        _in_hook[0] = True
        try:
            _redelivery[0] = True  # the signal stays received (an error unwinding meanwhile still sees it)
            _deliver_later(_received[0])
        finally:
            _in_hook[0] = False
        return
    sys.__unraisablehook__(unraisable)


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(f"prism-stream: warning: {message}\n")


def _cleanup() -> None:
    """Remove every temporary the run created and did not publish, and stop the decoder processes (signals
    are ignored meanwhile)."""
    if _process[0]:
        for s in _SIGNALS:
            signal.signal(s, signal.SIG_IGN)
    decoders = sys.modules.get("prism_stream.run.decoders")
    if decoders is not None:
        decoders.stop(final=_process[0])  # a process ends next (not a run in a caller's): no pool starts behind it
    staging = sys.modules.get("prism_stream.run.staging")
    if staging is not None:
        staging.discard_all()


def _fail(message: str, code: int):
    _cleanup()
    message = " ".join(str(message).splitlines())
    sys.stderr.write(f"prism-stream: error: {message}\n")
    sys.stderr.flush()
    if _process[0]:
        _quiet_exit()
        _hard_exit(code)
    sys.exit(code)


def _hard_exit(code: int) -> None:
    """End a failed or interrupted run without the interpreter's teardown, once its temporaries are gone and
    its line is said: a run stopped mid-computation (a k-d tree's query threads, Arrow's and BLAS's pools
    between tasks) could crash in the native libraries' exit handlers, ending 139 (SIGSEGV) instead of the
    table's code (5 of 24 SIGTERMs during `--denoise`). What the teardown would still do is done already: the
    outputs' temporaries discarded, the decoder processes stopped, a Dask cluster closed by its context."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _quiet_exit() -> None:
    """The error line is the last thing on stderr: what libraries print while the process exits (a Dask
    cluster interrupted half-way up complains from an atexit hook) goes to /dev/null."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
    except OSError:
        pass


def _interrupted(path: str | None = None):
    signum = _received[0] if _received else signal.SIGINT
    staging = sys.modules.get("prism_stream.run.staging")
    done = staging.published() if staging is not None else []
    if done:  # the signal came once the output was in place (its last moments, the summary): it stays
        _fail(f"{done[-1]}: {_SIGNALS.get(signum, 'interrupted')} after the output was written (it is complete)",
              128 + signum)
    where = f"{path}: " if path else ""
    _fail(f"{where}{_SIGNALS.get(signum, 'interrupted')}; no output was written", 128 + signum)


COMPLETE_VAR = "_PRISM_STREAM_COMPLETE"


def run(argv=None) -> None:
    """Console-script entry: one line on stderr for every failure, never a traceback for an expected one.

    Always ends in SystemExit, with the exit code of the README's table
    (130 after SIGINT, 143 after SIGTERM).
    """
    _process[0] = argv is None
    staging = sys.modules.get("prism_stream.run.staging")
    if staging is not None:
        staging.forget_published()
    try:
        if _process[0]:  # the process's own handlers; a call from Python keeps its caller's
            _main_thread[0] = _thread.get_ident()
            sys.unraisablehook = _unraisable
            for s in _SIGNALS:
                # a signal the parent ignores stays ignored (POSIX's convention, and Python's own for SIGINT):
                # sh starts a script's `cmd &` with SIGINT ignored, so that the terminal's Ctrl-C spares it
                if signal.getsignal(s) != signal.SIG_IGN:
                    signal.signal(s, _on_signal)
            # a signal mask is inherited through exec: a parent that started this process while blocking
            # SIGINT/SIGTERM (a thread pool's start-up, a supervisor's critical section) would leave them
            # pending for the whole run, which then ends 0 as if never interrupted
            signal.pthread_sigmask(signal.SIG_UNBLOCK, tuple(_SIGNALS))
            # no command's work goes through BLAS (3x3 products at most: an E57 pose, eval's NSS normals), whose
            # thread pool (numpy's OpenBLAS, one thread a core) spins when numpy loads: 0.1 s of CPU on two
            # cores, taken from the decode (bench/PROFILE.md). A value set is kept
            if "numpy" not in sys.modules:
                os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        import click

        from prism_stream.errors import Interrupted, PrismError

        from .app import app
        from .options import COMMAND
    except KeyboardInterrupt:
        _interrupted()
    warnings.showwarning = _one_line_warning
    instruction = os.environ.get(COMPLETE_VAR)
    if instruction:  # shell completion (README): what click's own main() would do
        from click.shell_completion import shell_complete

        sys.exit(shell_complete(app, {}, "prism-stream", COMPLETE_VAR, instruction))
    try:
        # click's own main() would print a blank line on an interrupt: make the context and invoke it here
        args = list(sys.argv[1:] if argv is None else argv)
        with app.make_context("prism-stream", args) as ctx:
            ctx.meta[COMMAND] = ("prism-stream", *args)  # for the outputs' provenance (options.request_of)
            app.invoke(ctx)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.UsageError as exc:  # a bad option value, a missing argument: one line, exit 2
        hint = f" (see {exc.ctx.command_path} --help)" if exc.ctx is not None else ""
        if isinstance(exc, click.NoSuchOption) and not exc.option_name.startswith("--"):
            hint += "; a path that starts with '-' goes after '--' or as ./NAME"
        _fail(exc.format_message().replace("\n", " ") + hint, 2)
    except click.ClickException as exc:
        _fail(exc.format_message().replace("\n", " "), exc.exit_code)
    except Interrupted as exc:
        _interrupted(exc.path)
    except PrismError as exc:
        if _received:  # a signal's KeyboardInterrupt, turned into another error by the library it crossed
            _interrupted()
        _fail(str(exc), exc.exit_code)
    except (KeyboardInterrupt, click.exceptions.Abort):
        _interrupted()
    except Exception as exc:  # noqa: BLE001 - a bug of ours: one line, and the traceback on request
        if _received:  # as above: lazrs reports an interrupt in its seek callback as "Failed to call seek"
            _interrupted()
        if os.environ.get("PRISM_STREAM_DEBUG"):
            raise
        _fail(f"internal error: {type(exc).__name__}: {exc} (set PRISM_STREAM_DEBUG=1 for the traceback, "
              "and please report it)", 70)
    if _process[0]:  # done, the output whole and said: a signal from here on would only kill the exit itself
        for s in _SIGNALS:
            signal.signal(s, signal.SIG_IGN)
    sys.exit(0)


if __name__ == "__main__":
    run()
