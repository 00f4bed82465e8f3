"""Turning whatever a third-party reader raises into one-line input errors."""

from __future__ import annotations

import contextlib

from ..errors import CorruptInput, PrismError


def describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = text[0] if text else ""
    name = type(exc).__name__
    return f"{name}: {first}" if first else name


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
        raise CorruptInput(f"{what}: {describe(exc)}", path) from None
