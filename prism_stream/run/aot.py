"""The ahead-of-time kernels (:mod:`..core.aot`) on disk: built by ``python -m prism_stream.engines.warm
--aot`` (``make setup-test`` and ``make aot`` run it; it needs the C compiler CPython's extensions are
built with), found and checked here.

The build runs the warm-up, which calls every kernel with the argument types runs give it, and compiles
each of those specializations with ``numba.pycc`` into ``prism_stream/core/_kernels_aot`` (an extension
module), with a manifest of the argument types of each. A run uses it only if the manifest's digest is that
of the sources now (:mod:`..core.jit`, :mod:`..core.constants`, the keys of :mod:`..core.aot`), numpy's
version and Python's: an edited loop or an upgraded numpy goes back to numba's JIT, never to stale machine
code. ``PRISM_STREAM_AOT=0`` turns it off.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..core import aot as core_aot
from ..core.aot import Dispatch, _frozen, type_key

MODULE = "_kernels_aot"
CORE = Path(core_aot.__file__).resolve().parent
MANIFEST = CORE / f"{MODULE}.json"
PACKAGE = CORE.parent
# the loops, their constants, the keys of the manifest; the warm-up that chose the specializations, and the build
SOURCES = ("core/jit.py", "core/constants.py", "core/aot.py", "engines/warm.py", "run/aot.py")


def cpu() -> str:
    """The processor the build's machine code is for: it is compiled for the host (as numba's JIT compiles),
    so a checkout shared with another machine (a network home, an image built elsewhere, a cluster's other
    nodes) must not run it there (an instruction that machine lacks is SIGILL). Linux: the CPU model and its
    feature flags."""
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            lines = f.read().splitlines()
        wanted = [ln.split(":", 1)[1].strip() for ln in lines if ln.startswith(("flags", "model name", "Features"))]
        if wanted:
            return "|".join(dict.fromkeys(wanted))  # each distinct line once (every core repeats them)
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()}"


def digest() -> str:
    """What a build must match: the sources above, numpy's version (the extension's array ABI), Python's, and
    the processor (:func:`cpu`)."""
    import hashlib

    import numpy as np

    h = hashlib.sha256()
    for name in SOURCES:
        h.update((PACKAGE / name).read_bytes())
    h.update(f"numpy {np.__version__} python {sys.version_info[:2]} cpu {cpu()}".encode())
    return h.hexdigest()


def install() -> None:
    """Let the core's front door find the build (nothing is read until a kernel is first called)."""
    core_aot.provide(load)


def load() -> dict:
    """{name: Dispatch} of a usable build; {} for none, another build of the sources, ``PRISM_STREAM_AOT=0``,
    or numba's debugging switches (NUMBA_DISABLE_JIT, NUMBA_BOUNDSCHECK), which only the JIT honours."""
    if os.environ.get("PRISM_STREAM_AOT", "1") == "0":
        return {}
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0") or os.environ.get("NUMBA_BOUNDSCHECK", "") \
            not in ("", "0"):
        return {}
    return _load()


def _load() -> dict:
    import importlib
    import json

    if not MANIFEST.exists():
        return {}
    manifest = json.loads(MANIFEST.read_text())
    if manifest.get("digest") != digest():
        return {}
    module = importlib.import_module(f"{core_aot.__package__}.{MODULE}")
    if not hasattr(module, f"build_{manifest.get('build', '')}"):
        return {}  # a module of another build than this manifest's (a rebuild between the two reads)
    out = {}
    for name, spec in manifest["kernels"].items():
        entries = {_frozen(key): getattr(module, symbol) for key, symbol in spec["entries"]}
        out[name] = Dispatch(name, entries, spec["params"], spec["defaults"])
    return out


def build(warm_up, verbose: bool = True) -> dict:
    """Run ``warm_up()`` (every kernel called with the types runs give it) on numba's JIT, then compile every
    specialization it compiled into ``_kernels_aot`` and write its manifest; returns the manifest. Needs
    numba's ``pycc`` and a C compiler."""
    import inspect
    import json
    import time

    t0 = time.perf_counter()
    os.environ["PRISM_STREAM_AOT"] = "0"  # the warm-up must reach numba's dispatchers, not a build being replaced
    core_aot.provide(load)
    warm_up()
    from numba.core import types
    from numba.core.registry import CPUDispatcher
    from numba.core.typing import signature
    from numba.pycc import CC
    from numba.pycc import compiler as pycc_compiler

    from ..core import jit

    class _NoGil(pycc_compiler.Flags):
        """pycc's flags, with the GIL released around each call as ``nogil=True`` releases it under the JIT
        (a thread decoding the next chunk runs beside the loop)."""

        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.release_gil = True

    cc = CC(MODULE, source_module=jit)
    cc.output_dir = str(CORE)
    cc.target_cpu = "host"  # built on the machine that runs it, as numba's JIT compiles
    build_id = os.urandom(8).hex()
    manifest = {"digest": digest(), "build": build_id, "kernels": {}}
    cc.export(f"build_{build_id}", "int64()")(_build_mark)  # the module says which manifest it belongs to
    exported = 0
    for name in sorted(vars(jit)):
        d = getattr(jit, name)
        if not isinstance(d, CPUDispatcher) or d.py_func.__module__ != jit.__name__ or not d.overloads:
            continue
        if name.startswith("_"):
            continue  # a helper the kernels call (compiled into them), never the front door
        if not d.targetoptions.get("nogil"):
            continue  # compiled here only what releases the GIL under the JIT too
        params = list(inspect.signature(d.py_func).parameters.values())
        defaults = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
        if any(v is not None for v in defaults.values()):
            continue
        entries = []
        for i, (argtys, cres) in enumerate(sorted(d.overloads.items(), key=lambda kv: str(kv[0]))):
            argtys = tuple(types.none if isinstance(t, types.Omitted) else t for t in argtys)
            key = type_key(types.Tuple(argtys)) if argtys else ("t", ())
            if key is None or len(argtys) != len(params):
                continue
            symbol = f"{name}__{i}"
            cc.export(symbol, signature(cres.signature.return_type, *argtys))(d.py_func)
            entries.append([key, symbol])
            exported += 1
        if entries:
            manifest["kernels"][name] = {"entries": entries, "params": [p.name for p in params],
                                         "defaults": defaults}
    MANIFEST.unlink(missing_ok=True)  # no manifest beside a half-written module
    saved = pycc_compiler.Flags
    pycc_compiler.Flags = _NoGil
    try:
        cc.compile()
    finally:
        pycc_compiler.Flags = saved
    MANIFEST.write_text(json.dumps(manifest))
    if verbose:
        sys.stderr.write(f"prism-stream: {exported} kernel specializations of {len(manifest['kernels'])} "
                         f"kernels compiled ahead of time in {time.perf_counter() - t0:.1f} s\n")
    return manifest


def _build_mark():
    return 0
