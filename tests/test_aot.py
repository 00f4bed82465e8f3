"""The kernels compiled ahead of time (core/aot.py): called only with the exact argument types they were
compiled for (any other goes to numba's JIT), the same rows and the same spill as the JIT, and numba never
imported by the runs they cover."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prism_stream.core import aot
from prism_stream.run import aot as run_aot

from conftest import real_file, write_las

DTYPES = ["u1", "u2", "u4", "u8", "i1", "i2", "i4", "i8", "f4", "f8", "?", ">u2", ">i8", "<f4"]


def _array(draw_dtype, shape, order, step, writeable, offset):
    base = np.zeros(tuple(s * step for s in shape[:1]) + tuple(shape[1:]) if shape else (), dtype=draw_dtype,
                    order=order)
    a = base[::step] if shape else base
    if offset:  # a view one byte into a buffer: unaligned for any itemsize above 1
        raw = np.zeros(a.nbytes + a.itemsize + 1, np.uint8)
        a = np.frombuffer(raw[1:1 + a.nbytes].data, dtype=a.dtype).reshape(a.shape) if a.size else a
    if not writeable:
        a = a.view()
        a.flags.writeable = False
    return a


@st.composite
def values(draw, depth=0):
    kind = draw(st.sampled_from(["array", "int", "bool", "float", "npscalar", "none"]
                                + (["tuple"] if depth < 2 else [])))
    if kind == "array":
        ndim = draw(st.integers(0, 2))
        shape = tuple(draw(st.integers(0, 3)) for _ in range(ndim))
        return _array(np.dtype(draw(st.sampled_from(DTYPES))), shape, draw(st.sampled_from("CF")),
                      draw(st.sampled_from([1, 2])), draw(st.booleans()), draw(st.booleans()))
    if kind == "int":
        return draw(st.sampled_from([0, 1, -1, 2**63 - 1, 2**63, 2**64 - 1, -(2**63), 255, 2**32]))
    if kind == "bool":
        return draw(st.sampled_from([True, False, np.bool_(True)]))
    if kind == "float":
        return draw(st.sampled_from([0.0, 1.5, -2.0]))
    if kind == "npscalar":
        return np.dtype(draw(st.sampled_from(["u1", "u2", "u4", "u8", "i4", "i8", "f4", "f8"]))).type(3)
    if kind == "none":
        return None
    return tuple(draw(st.lists(values(depth + 1), min_size=0, max_size=3)))


@settings(max_examples=400, deadline=None)
@given(values())
def test_a_values_key_is_the_key_of_the_type_numba_infers(v):
    """The compiled functions read their arguments without checking them: a key that matched a value numba
    would type otherwise (another dtype, layout, writability or alignment; an int past int64) would read the
    wrong memory. Where the front door gives a key, it is the key of numba's own type for the value."""
    import numba  # here, not at the top: a cluster worker imports this module to run _worker_state

    key = aot.value_key(v)
    try:
        t = numba.typeof(v)
    except Exception:  # noqa: BLE001 - a value numba cannot type (a big-endian array, an int past uint64)
        assert key is None
        return
    if key is not None:
        assert key == aot.type_key(t), (v, t)


def test_the_keys_tell_apart_what_numba_tells_apart():
    a = np.zeros(4, np.uint8)
    ro = a.view()
    ro.flags.writeable = False
    strided = np.zeros(8, np.uint8)[::2]
    keys = {aot.value_key(x) for x in (a, ro, strided, a.astype(np.uint16), a.astype(">u2"), np.zeros((2, 2), "u1"),
                                       np.zeros((2, 2), "u1", order="F"))}
    assert len(keys) == 7
    assert aot.value_key(2**63) != aot.value_key(2**63 - 1)
    assert aot.value_key(True) != aot.value_key(1)
    assert aot.value_key(2**64) is None and aot.value_key(np.zeros(2, "u1,u2")) is None
    assert aot.value_key("text") is None and aot.value_key([1, 2]) is None
    # subclasses are numba's to judge (it refuses a masked array, types an IntEnum as itself): never a match
    import collections
    import enum

    class Level(enum.IntEnum):
        ONE = 1

    pair = collections.namedtuple("pair", "a b")
    for v in (np.ma.masked_array(a), Level.ONE, pair(1, 2), np.asmatrix(np.zeros((2, 2)))):
        assert aot.value_key(v) is None, v


def _compiler() -> str | None:
    import shlex
    import shutil
    import sysconfig

    cc = shlex.split(sysconfig.get_config_var("CC") or "cc")
    return shutil.which(cc[0]) if cc else None


def _built() -> dict:
    """The build of these sources, which `make test` makes wherever Python's C compiler is; on a machine
    without one, {} (every kernel then runs on numba's JIT, which the tests below still hold to)."""
    if not aot.kernels() and _compiler():
        pytest.fail("no ahead-of-time build of these sources, yet a C compiler is here: `make aot` (make test "
                    "runs it) builds one")
    return aot.kernels()


def test_the_build_covers_what_every_streamed_run_calls():
    built = _built()
    if not built:
        return  # no compiler here: nothing compiled ahead of time
    for name in ("candidate_scan", "bin_keys_counted", "channel_range", "splitmix64_array", "priorities_of",
                 "push_bottom_range", "keep_mask_ids", "keep_mask", "offer_all"):
        assert name in built, name


def test_another_type_goes_to_the_jit_and_gives_its_answer():
    from prism_stream.core import kernels

    built = _built() or {n: getattr(kernels, n) for n in ("channel_range", "splitmix64_array")}
    rng = np.random.default_rng(3)
    for dtype in (np.uint8, np.uint16, np.int32, np.float64):
        r, g, b = (rng.integers(0, 200, 50).astype(dtype) for _ in range(3))
        got = built["channel_range"](r, g, b)  # writable arrays: no compiled match, the JIT answers
        assert tuple(int(x) for x in got) == (int(min(r.min(), g.min(), b.min())), int(max(r.max(), g.max(),
                                                                                            b.max())))
    x = rng.integers(0, 2**63, 100, dtype=np.uint64)
    strided = np.repeat(x, 2)[::2]
    assert np.array_equal(built["splitmix64_array"](strided), built["splitmix64_array"](x.copy()))


def test_arguments_by_keyword_and_defaults_are_bound_in_order():
    calls = []
    d = aot.Dispatch("f", {}, ["a", "b", "c"], {"c": None})
    d._jit = lambda *a, **k: calls.append((a, k))
    d(1, 2)
    d(1, b=2)
    d(1, 2, c=None)
    assert d._bound((1, 2), {}) == (1, 2, None) and d._bound((1,), {"b": 2}) == (1, 2, None)
    assert d._bound((1,), {}) is None and d._bound((1, 2, 3, 4), {}) is None
    assert d._bound((1, 2), {"a": 5}) is None and d._bound((1, 2), {"z": 1}) is None
    assert len(calls) == 3  # no compiled entry: every call went to the JIT, as given


def test_a_build_of_other_sources_is_not_used(monkeypatch):
    assert run_aot.load() or not _built()
    monkeypatch.setattr(run_aot, "digest", lambda: "another build")
    assert run_aot.load() == {}
    monkeypatch.undo()
    monkeypatch.setattr(run_aot, "cpu", lambda: "another processor")  # its machine code may not run here
    assert run_aot.load() == {}
    monkeypatch.undo()
    for name in ("PRISM_STREAM_AOT", "NUMBA_BOUNDSCHECK", "NUMBA_DISABLE_JIT"):
        monkeypatch.setenv(name, "0" if name == "PRISM_STREAM_AOT" else "1")
        assert run_aot.load() == {}, name
        monkeypatch.undo()


def test_a_manifest_of_another_build_than_the_module_is_not_used(monkeypatch, tmp_path):
    """A rebuild between a process's read of the manifest and its import of the module: the symbols are named
    by position, so the module must be the manifest's own build (it exports build_<id>)."""
    import json as json_

    if not _built():
        return
    manifest = json_.loads(run_aot.MANIFEST.read_text())
    other = tmp_path / "m.json"
    other.write_text(json_.dumps({**manifest, "build": "0" * 16}))
    monkeypatch.setattr(run_aot, "MANIFEST", other)
    assert run_aot.load() == {}


def test_the_first_callers_all_get_the_build(monkeypatch):
    """The warm-up thread and the run ask for the kernels at once: each gets the build (one that got an empty
    table would go to numba's JIT for good, the 0.6 s the build is there to save)."""
    import threading
    import time

    built = _built()

    def slowly():
        time.sleep(0.2)
        return run_aot.load()

    monkeypatch.setattr(aot, "_provider", slowly)
    monkeypatch.setattr(aot, "_loaded", None)
    got = []
    threads = [threading.Thread(target=lambda: got.append(aot.kernels())) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == 4 and all(g is got[0] for g in got) and (got[0] or not built)


RUN = """
import json, sys
import prism_stream
from prism_stream.core import kernels
out = []
for i, (src, options) in enumerate(json.loads(sys.argv[2])):
    s = prism_stream.sample(src, f"{sys.argv[1]}/{i}.parquet", overwrite=True, **options)
    out.append({"kept": s.kept, "plan": s.plan})
compiled = sorted(n for n, v in vars(kernels).items() if type(v).__name__ == "Dispatch")
print(json.dumps({"numba": "numba" in sys.modules, "runs": out, "compiled": compiled}))
"""

CASES = [
    ("pdal__autzen_trim.las", dict(ratio=0.02)),  # 16-bit colors, one read
    ("pdal__autzen_trim.las", dict(ratio=0.02, reads="two")),
    ("laspy__fullwave.laz", dict(ratio=0.05, seed=7)),  # 8-bit colors in 16-bit fields
    ("pdal__autzen_trim.las", dict(ratio=0.3, chunk_size=2_000)),  # a spill compacted at the mark
    ("pcl__office1.pcd", dict(k=3)),  # float colors: last, as a kernel the build may not hold could load numba
]


def _runs(folder, cases, aot_on: bool) -> dict:
    """Every case in one process (a process's start is most of a small run)."""
    folder.mkdir()
    env = dict(os.environ, PRISM_STREAM_AOT="1" if aot_on else "0", PRISM_STREAM_MEMORY_POINTS="0")
    given = json.dumps([(name if os.path.isabs(name) else str(real_file(name)), options) for name, options in cases])
    done = subprocess.run([sys.executable, "-c", RUN, str(folder), given], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_compiled_and_jit_runs_keep_the_same_rows_and_spill(tmp_path):
    built = _built()
    import pyarrow.parquet as pq

    las = [c for c in CASES if not c[0].endswith(".pcd")]
    jit_run = _runs(tmp_path / "jit", CASES, aot_on=False)
    aot_run = _runs(tmp_path / "aot", CASES, aot_on=True)
    for i, (name, options) in enumerate(CASES):
        got, want = (pq.read_table(tmp_path / side / f"{i}.parquet") for side in ("aot", "jit"))
        assert got.equals(want), (name, options)
        a, j = aot_run["runs"][i]["plan"], jit_run["runs"][i]["plan"]
        for plan in (a, j):
            plan.get("temp", {}).pop("free_bytes", None)  # the disk's, which other jobs change
        assert a == j, (name, options)  # the spill's candidates, written, peak and compactions included
        assert "spill_candidates" in json.dumps(a) or options.get("reads") == "two"
    assert not jit_run["compiled"] and jit_run["numba"]
    if not built:
        return  # no compiler here: both ran on the JIT
    assert aot_run["compiled"]
    only = _runs(tmp_path / "las", las, aot_on=True) if aot_run["numba"] else aot_run
    assert not only["numba"], "a streamed run of LAS files imported numba beside the compiled kernels"


def test_16_bit_colors_read_in_place_or_contiguous_both_run_compiled(tmp_path):
    """A LAS record's 16-bit fields reach the loops strided (read where they lie), a Parquet file's 16-bit
    columns contiguous: two types, and the build holds both (else a run would load numba, or compile)."""
    if not _built():
        return  # no compiler here: the JIT serves both
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(3)
    c = rng.integers(0, 65536, (20_000, 3)).astype(np.uint16)
    src = tmp_path / "u16.parquet"
    pq.write_table(pa.table({"x": rng.random(len(c)), "red": c[:, 0], "green": c[:, 1], "blue": c[:, 2]}), src)
    laz = write_las(tmp_path / "u16.laz", c)
    cases = [(str(src), dict(ratio=0.02)), (str(src), dict(ratio=0.02, quant_step=300.0)),
             ("pdal__autzen_trim.las", dict(ratio=0.02)), ("pdal__autzen_trim.las", dict(ratio=0.02, quant_step=2.5)),
             (str(laz), dict(ratio=0.02, reads="two")),  # a LAZ file's color reads: strided too
             (str(laz), dict(ratio=0.02, flag="keep"))]
    run = _runs(tmp_path / "runs", cases, aot_on=True)
    assert not run["numba"], "a streamed run of 16-bit colors imported numba beside the compiled kernels"


def test_the_channels_are_all_read_in_place_or_all_copied():
    """Three strided 16-bit fields are read where they lie; any mix (a field beside a contiguous or an 8-bit
    column) is copied whole, so that the loops meet one of the types the build holds, never a mixed one."""
    from prism_stream.core import kernels

    rec = np.zeros(50, dtype=[("x", "<i4"), ("red", "<u2"), ("green", "<u2"), ("blue", "<u2")])
    rec["red"], rec["green"], rec["blue"] = np.arange(50), np.arange(50) * 2, np.arange(50) * 3
    fields = kernels.loop_channels(rec["red"], rec["green"], rec["blue"])
    assert all(not c.flags.c_contiguous and not c.flags.writeable and c.base is not None for c in fields)
    for mix in ((rec["red"], rec["green"], np.arange(50, dtype=np.uint16) * 3),
                (rec["red"], rec["green"], (np.arange(50) * 3).astype(np.uint8))):
        got = kernels.loop_channels(*mix)
        assert all(c.flags.c_contiguous and c.dtype == np.uint16 and not c.flags.writeable for c in got)
        assert all(np.array_equal(a, b) for a, b in zip(got, fields))


def _worker_state():
    kernels = sys.modules.get("prism_stream.core.kernels")
    jitted = sorted(n for n, v in vars(kernels).items() if type(v).__name__ == "Dispatch" and v._jit is not None)
    return "numba" in sys.modules, jitted


def test_a_cluster_worker_runs_every_step_without_numba(tmp_path):
    """A Dask worker calls the kernels through other paths than a local run (a unit's evidence, its bottom set,
    keys without counts): with the build, none of them loads numba (about 100 MiB of a worker's 1 GiB)."""
    if not _built():
        return  # no compiler here: the workers use the JIT
    distributed = pytest.importorskip("distributed")
    from prism_stream.engines import dask as dask_engine

    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None)
    with distributed.Client(cluster) as client:
        for options in (dict(ratio=0.05, reads="two"), dict(ratio=0.05, reads="one", space="0.5")):
            dask_engine.sample(client, [str(real_file("pdal__autzen_trim.las"))], str(tmp_path / "out"),
                               unit_size=20_000, overwrite=True, **options)
        assert list(client.run(_worker_state).values()) == [(False, [])]
    cluster.close()


def test_help_and_version_load_no_numpy():
    """`prism-stream --version` and `--help` start in a twentieth of a second: pointing the front door at the
    build (run/__init__.py) imports neither numpy nor the manifest's readers (it once doubled their time)."""
    script = ("import sys; sys.argv = ['prism-stream', sys.argv[1]]\n"
              "from prism_stream_cli.main import run\n"
              "try:\n    run()\nexcept SystemExit:\n    pass\n"
              "print(sorted(m for m in ('numpy', 'numba', 'hashlib', 'json', 'pyarrow') if m in sys.modules))")
    for flag in ("--version", "--help"):
        done = subprocess.run([sys.executable, "-c", script, flag], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        loaded = json.loads(done.stdout.strip().splitlines()[-1].replace("'", '"'))
        assert "numpy" not in loaded and "numba" not in loaded and "pyarrow" not in loaded, (flag, loaded)
