"""The numba loops compiled ahead of time: the front door's match of a call to a compiled function.

Importing numba and loading the cached machine code of the first kernel takes about 0.6 s of every
streamed run (bench/PROFILE.md), a tenth of a 10M-point LAZ run and a quarter of a 10M-point Parquet one.
:mod:`..run.aot` builds, ahead of time, every specialization the warm-up of :mod:`..engines.warm` calls into
a C extension (``numba.pycc``) that loads in a millisecond without numba, and provides it here (the core
reads no file: the run layer finds and checks the build).

:mod:`.kernels` (the loops' front door) calls the compiled function when a call's arguments have exactly
the types one was compiled for, and numba's JIT otherwise (any other type, a kernel not compiled, no
build). The extension's functions do not check their arguments (a wrong type reads the wrong memory), so
the match is exact: array dtype, dimensions, layout and writability (aligned, native-order arrays only),
each scalar's type as numba would infer it, tuples element by element (:func:`value_key` mirrors
``numba.typeof``; ``tests/test_aot.py`` holds the two equal). Both run the same compiled code of the same
function, with the GIL released as ``nogil`` does, so the results are the same bytes (the tests compare
whole runs).
"""

from __future__ import annotations

import threading

_INT64 = 1 << 63  # numpy is imported where a key is made, not here: `prism-stream --version` loads this module


def _array_key(a):
    flags = a.flags
    if not flags.aligned:
        return None  # numba types it as aligned all the same: left to the JIT, as the build holds none
    layout = "C" if flags.c_contiguous else ("F" if flags.f_contiguous else "A")
    return ("a", a.dtype.str, a.ndim, layout, bool(flags.writeable))


def value_key(v):
    """The type numba infers for a call's argument, as a hashable key (None: a kind no compiled function
    takes, which goes to the JIT)."""
    import numpy as np

    kind = type(v)  # exact types only: a subclass (a masked array, an IntEnum, a namedtuple) is numba's to judge
    if kind is np.ndarray or kind is np.memmap:
        dtype = v.dtype
        return _array_key(v) if dtype.kind in "biuf" and dtype.isnative and dtype.fields is None else None
    if kind is tuple:
        keys = tuple(value_key(x) for x in v)
        return None if None in keys else ("t", keys)
    if v is None:
        return ("n",)
    if kind is bool or kind is np.bool_:
        return ("s", "|b1")
    if kind is int:
        if -_INT64 <= v < _INT64:
            return ("s", "<i8")
        return ("s", "<u8") if 0 <= v < 2 * _INT64 else None
    if kind is float:
        return ("s", "<f8")
    if isinstance(v, np.generic) and kind is v.dtype.type and v.dtype.kind in "iuf" and v.dtype.isnative:
        return ("s", v.dtype.str)
    return None


def type_key(t):
    """:func:`value_key` of a numba type (the build's side of the match); None for a type it does not
    cover."""
    import numpy as np
    from numba.core import types

    if type(t) is types.Array:
        if not isinstance(t.dtype, (types.Integer, types.Float, types.Boolean)) or not t.aligned:
            return None
        return ("a", np.dtype(str(t.dtype)).str, t.ndim, t.layout, bool(t.mutable))
    if type(t) in (types.Tuple, types.UniTuple):  # not a NamedTuple: its instances are no plain tuples
        keys = tuple(type_key(x) for x in t.types)
        return None if None in keys else ("t", keys)
    if isinstance(t, (types.NoneType, types.Omitted)):
        return ("n",) if not isinstance(t, types.Omitted) or t.value is None else None
    if isinstance(t, (types.Boolean, types.Integer, types.Float)):
        return ("s", np.dtype(str(t)).str)
    return None


def _frozen(key):
    """A key read back from JSON (lists) as the tuples :func:`value_key` makes."""
    return tuple(_frozen(x) for x in key) if isinstance(key, list) else key


class Dispatch:
    """One kernel's front door: the compiled function for the arguments' exact types, else numba's."""

    __slots__ = ("name", "entries", "params", "defaults", "_jit")

    def __init__(self, name: str, entries: dict, params: list, defaults: dict):
        self.name, self.entries, self.params, self.defaults = name, entries, params, defaults
        self._jit = None

    def _bound(self, args: tuple, kw: dict) -> tuple | None:
        """The call's arguments in parameter order, defaults filled in (None: a call numba's own dispatcher
        should judge: too many, one missing, an unknown keyword)."""
        if not kw and len(args) == len(self.params):
            return args
        if len(args) > len(self.params):
            return None
        rest = self.params[len(args):]
        if any(p not in rest for p in kw):
            return None
        full = list(args)
        for p in rest:
            if p in kw:
                full.append(kw[p])
            elif p in self.defaults:
                full.append(self.defaults[p])
            else:
                return None
        return tuple(full)

    def __call__(self, *args, **kw):
        full = self._bound(args, kw)
        fn = None if full is None else self.entries.get(value_key(full))
        if fn is None:
            if self._jit is None:
                from . import jit

                self._jit = getattr(jit, self.name)
            return self._jit(*args, **kw)
        return fn(*full)


_loaded: dict | None = None
_provider = None
_lock = threading.Lock()


def provide(loader) -> None:
    """Where the compiled kernels come from: ``loader()`` returns {name: :class:`Dispatch`} ({} for none),
    called once, on the first kernel a process calls (:func:`..run.aot.install`)."""
    global _provider, _loaded
    with _lock:
        _provider, _loaded = loader, None


def kernels() -> dict:
    """{name: :class:`Dispatch`} of the compiled kernels, once per process; {} when there is none (no
    provider, no usable build)."""
    global _loaded
    if _loaded is None:
        with _lock:  # the warm-up thread and the run ask at once: both get the build, neither an empty table
            if _loaded is None:
                table = {}
                if _provider is not None:
                    try:
                        table = _provider()
                    except Exception:  # noqa: BLE001 - the JIT is always there
                        table = {}
                _loaded = table
    return _loaded
