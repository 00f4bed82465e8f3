"""Turning whatever a third-party reader raises into one-line input errors (a remote file's store failures
into :mod:`..run.remote`'s)."""

from __future__ import annotations

import contextlib

from ..errors import CorruptInput, PrismError


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message, or its type name when it has none."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def describe(exc: BaseException) -> str:
    """``Type: first line`` of an exception (or just its type name)."""
    text = str(exc).strip().splitlines()
    name = type(exc).__name__
    return f"{name}: {text[0]}" if text else name


@contextlib.contextmanager
def reading(path: str, what: str = "cannot read the file"):
    """Re-raise reader failures as :class:`CorruptInput` naming the file.

    Rust decoders surface panics as ``PanicException``, a ``BaseException``
    that ``except Exception`` lets through; it is caught here too. Ctrl-C and
    interpreter exit pass untouched.
    """
    try:
        yield
    except PrismError:
        raise
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except MemoryError:
        raise CorruptInput(f"{what}: the reader ran out of memory (corrupt size fields?)", path) from None
    except BaseException as exc:  # noqa: BLE001 - see docstring
        from ..run import remote

        if remote.is_remote(path):  # the store's failures (network, credentials) are not the file's
            mapped = remote.failure(exc, path)
            if mapped is not None:
                raise mapped from None
        raise CorruptInput(f"{what}: {describe(exc)}", path) from None
