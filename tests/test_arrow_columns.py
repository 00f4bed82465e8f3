"""numpy <-> Arrow without pyarrow's pandas check (prism_stream/formats/arrow.py).

``from_numpy`` and ``to_numpy`` must give exactly what ``pa.array`` and
``to_numpy(zero_copy_only=False)`` give, for every column type a run
converts (and slices, chunks, empty columns); and a run must not import
pandas, which pyarrow's own conversions do whenever it is installed (0.15 s
of every run's start-up: bench/RESULTS_STARTUP.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from prism_stream.formats.arrow import from_numpy, indices, rows_of, string_scalar, to_numpy

REAL = Path(__file__).parent / "data" / "real"
DTYPES = [np.bool_, np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32, np.uint64, np.int64,
          np.float16, np.float32, np.float64]


def _reference(column) -> np.ndarray:
    return column.to_numpy() if isinstance(column, pa.ChunkedArray) else column.to_numpy(zero_copy_only=False)


@settings(max_examples=120, deadline=None)
@given(data=st.data(), dtype=st.sampled_from(DTYPES))
def test_the_same_arrays_as_pyarrows_own_conversions(data, dtype):
    values = data.draw(hnp.arrays(dtype, st.integers(0, 70)))
    got = from_numpy(values)
    ref = pa.array(values)
    # the input's own bits (a NaN's payload too: Arrow's equals() never holds a NaN equal, and pa.array's float16
    # path gave a NaN of other bits in some test orders)
    assert got.type == ref.type and got.null_count == 0, (values, got)
    assert got.to_numpy(zero_copy_only=False).tobytes() == np.ascontiguousarray(values).tobytes(), (values, got)
    start = data.draw(st.integers(0, len(values)))
    stop = data.draw(st.integers(start, len(values)))
    cut = data.draw(st.integers(start, stop))
    for column in (got, got.slice(start, stop - start),
                   pa.chunked_array([got.slice(start, cut - start), got.slice(cut, stop - cut)], type=got.type),
                   pa.chunked_array([], type=got.type)):
        back, want = to_numpy(column), _reference(column)
        assert back.dtype == want.dtype
        np.testing.assert_array_equal(back, want)


def test_nulls_strings_and_lists_take_pyarrows_path():
    for column in (pa.array([1.5, None, 3.0]), pa.array([1, None], type=pa.int32()), pa.array(["a", "bc"]),
                   pa.chunked_array([pa.array([1, 2]), pa.array([None], type=pa.int64())])):
        back, want = to_numpy(column), _reference(column)
        assert back.dtype == want.dtype and len(back) == len(want)
        assert [str(v) for v in back] == [str(v) for v in want]
    assert to_numpy(pa.array([[1, 2], [3, 4]], type=pa.list_(pa.int64(), 2)).flatten()).tolist() == [1, 2, 3, 4]


def test_other_byte_orders_and_two_dimensional_columns():
    big = np.arange(5, dtype=">u4")
    assert from_numpy(big).equals(pa.array(big.astype("<u4")))
    with pytest.raises(ValueError):
        from_numpy(np.zeros((2, 3)))
    assert indices([3, 1]).type == pa.int64() and indices([3, 1]).to_pylist() == [3, 1]
    assert string_scalar(" ").equals(pa.scalar(" ")) and string_scalar("é").as_py() == "é"


OTHERS = [None, "nulls", "strings", "large", "wkb", "lists", "points", "null points"]


def _other_column(cols: dict, other, n: int) -> None:
    """Adds a column of the kind ``other`` names (none for None) of ``n`` rows."""
    if other == "nulls":
        cols["o"] = pa.array([None if i % 3 else float(i) for i in range(n)])
    elif other == "strings":
        cols["o"] = pa.array([str(i) * (i % 4) for i in range(n)])  # empty strings among them
    elif other == "large":
        cols["o"] = pa.array([str(i) * (i % 3) for i in range(n)], type=pa.large_string())
    elif other == "wkb":  # GeoParquet's WKB points, 21 bytes each
        cols["o"] = pa.array([bytes([1, 1, 0, 0, 0]) + np.array([i, -i], dtype="<f8").tobytes()
                              for i in range(n)], type=pa.binary())
    elif other == "lists":
        cols["o"] = pa.array([[i, i, i] for i in range(n)], type=pa.list_(pa.int32()))
    elif other == "points":  # GeoArrow's points: three doubles a point, the child field not nullable
        child = pa.field("xyz", pa.float64(), nullable=False)
        cols["o"] = pa.array([[i, -i, 0.5] for i in range(n)], type=pa.list_(child, 3))
    elif other == "null points":
        cols["o"] = pa.array([[i, None] for i in range(n)], type=pa.list_(pa.float32(), 2))


@settings(max_examples=150, deadline=None)
@given(data=st.data(), dtypes=st.lists(st.sampled_from(DTYPES), min_size=1, max_size=4),
       other=st.sampled_from(OTHERS))
def test_rows_of_is_filter_and_take(data, dtypes, other):
    """rows_of: the batch ``filter`` (a mask) or ``take`` (positions, repeated, any order) gives, schema and
    its metadata included, for batches sliced at any offset; numbers through numpy, any other column (nulls,
    strings, lists) through pyarrow."""
    n = data.draw(st.integers(0, 40))
    off = data.draw(st.integers(0, 5))
    cols = {f"c{i}": from_numpy(data.draw(hnp.arrays(d, n + off))) for i, d in enumerate(dtypes)}
    _other_column(cols, other, n + off)
    batch = pa.RecordBatch.from_pydict(cols, metadata={b"k": b"v"}).slice(off, n)
    mask = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype=np.bool_)
    _same_batches(rows_of(batch, mask), batch.filter(pa.array(mask)))
    at = np.array(data.draw(st.lists(st.integers(0, max(n - 1, 0)), max_size=30 if n else 0)), dtype=np.int64)
    _same_batches(rows_of(batch, at), batch.take(pa.array(at, type=pa.int64())))


@pytest.mark.parametrize("other", OTHERS)
def test_rows_of_each_kind_of_column(other):
    """Each kind of column at a fixed size and offset, with masks and positions from three seeds: what the
    property test's fixed (derandomized) examples may not reach for every kind."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        cols = {"x": from_numpy(rng.random(13)), "c": from_numpy(rng.integers(0, 255, 13).astype(np.uint8))}
        _other_column(cols, other, 13)
        batch = pa.RecordBatch.from_pydict(cols, metadata={b"k": b"v"}).slice(2, 11)
        mask = rng.random(11) < 0.6
        _same_batches(rows_of(batch, mask), batch.filter(pa.array(mask)))
        at = rng.integers(0, 11, 9)
        _same_batches(rows_of(batch, at), batch.take(pa.array(at, type=pa.int64())))


def _same_batches(got: pa.RecordBatch, want: pa.RecordBatch) -> None:
    """Equal schemas (metadata too) and columns, a float's NaN equal to the same NaN (its bits)."""
    assert got.schema.equals(want.schema, check_metadata=True) and got.num_rows == want.num_rows
    for a, b in zip(got.columns, want.columns):
        assert a.null_count == b.null_count and a.is_null().to_pylist() == b.is_null().to_pylist()
        if pa.types.is_floating(a.type) and not a.null_count:
            x, y = a.to_numpy(zero_copy_only=False), b.to_numpy(zero_copy_only=False)
            assert x.view(f"u{x.itemsize}").tolist() == y.view(f"u{y.itemsize}").tolist()
        else:
            assert a.equals(b)


def test_rows_of_dense_selections_through_pyarrow(monkeypatch):
    """Past DENSE_ROWS rows and half the batch, pyarrow's kernels (faster there): the same batch; every row in
    order: the batch itself."""
    from prism_stream.formats import arrow

    monkeypatch.setattr(arrow, "DENSE_ROWS", 2)
    batch = pa.RecordBatch.from_pydict({"x": np.arange(8.0), "w": [b"ab", b"", b"c", b"d", b"e", b"f", b"g", b"h"]})
    for rows in (np.arange(8) % 4 != 0, np.array([7, 0, 0, 3, 5])):
        want = batch.filter(pa.array(rows)) if rows.dtype == np.bool_ else batch.take(pa.array(rows))
        _same_batches(rows_of(batch, rows), want)
    for rows in (np.ones(8, dtype=np.bool_), np.arange(8)):
        assert rows_of(batch, rows) is batch
    assert rows_of(batch, np.array([0, 1, 2, 3, 4, 5, 7, 6])).equals(batch.take(pa.array([0, 1, 2, 3, 4, 5, 7, 6])))


class _Point(pa.ExtensionType):
    """A Python extension type as geoarrow-pyarrow registers (no ``__hash__``: its instances do not hash)."""

    def __init__(self):
        super().__init__(pa.list_(pa.field("xyz", pa.float64(), nullable=False), 3), "test.point")

    def __arrow_ext_serialize__(self):
        return b""

    @classmethod
    def __arrow_ext_deserialize__(cls, storage_type, serialized):
        return cls()


def test_rows_of_other_columns_through_pyarrow():
    """Extension types (a Python one does not hash), lists of no values, and strings whose repeated rows would
    pass 32-bit offsets go to pyarrow's kernels, which give what they always gave."""
    storage = pa.array([[i, i, i] for i in range(5)], type=pa.list_(pa.field("xyz", pa.float64(), nullable=False), 3))
    empty = pa.array([[] for _ in range(5)], type=pa.list_(pa.int8(), 0))
    batch = pa.RecordBatch.from_arrays([pa.ExtensionArray.from_storage(_Point(), storage), empty,
                                        pa.array(np.arange(5.0))], names=["p", "e", "x"])
    for rows in (np.array([True, False, True, True, False]), np.array([4, 0, 0])):
        want = batch.filter(pa.array(rows)) if rows.dtype == np.bool_ else batch.take(pa.array(rows))
        got = rows_of(batch, rows)
        assert got.equals(want) and got.schema.equals(want.schema, check_metadata=True)
    from prism_stream.formats.arrow import _taken

    wide = pa.array(["x" * (1 << 20)])  # a 1 MiB string taken 2,049 times: past 2^31 bytes of offsets
    assert _taken(wide, np.zeros(2_049, dtype=np.int64)) is None
    assert _taken(wide, np.zeros(3, dtype=np.int64)).equals(pa.array(["x" * (1 << 20)] * 3))


def test_rows_of_refuses_what_filter_and_take_refuse():
    batch = pa.RecordBatch.from_pydict({"x": np.arange(4.0)})
    with pytest.raises(ValueError):
        rows_of(batch, np.ones(3, dtype=np.bool_))
    with pytest.raises(IndexError):
        rows_of(batch, np.array([4]))
    with pytest.raises(IndexError):
        rows_of(batch, np.array([-1]))


RUNS = """
import json, os, sys
import prism_stream
src, folder = sys.argv[1], sys.argv[2]
for memory in ("", "0"):  # held in memory, then streamed (the kernels' path)
    os.environ["PRISM_STREAM_MEMORY_POINTS"] = memory
    for ext in ("parquet", "laz", "ply", "xyz", "copc.laz"):
        prism_stream.sample(src, os.path.join(folder, f"m{memory}.{ext}"), ratio=0.05, overwrite=True)
    prism_stream.sample(src, os.path.join(folder, f"m{memory}-flag.parquet"), ratio=0.05, flag="keep")
    prism_stream.sample(os.path.join(folder, f"m{memory}.parquet"), os.path.join(folder, f"m{memory}-2.laz"),
                        ratio=0.5)
    prism_stream.rank(src, os.path.join(folder, f"m{memory}-ranked.parquet"))
print(json.dumps(sorted(m for m in sys.modules if m == "pandas" or m.startswith("pandas."))))
"""


def test_a_run_never_imports_pandas(tmp_path):
    """Every writer, from LAS and from Parquet, held and streamed: pandas (installed here, for GeoPandas) is
    never imported."""
    pytest.importorskip("pandas")
    done = subprocess.run([sys.executable, "-c", RUNS, str(REAL / "pdal__warsaw_small.las"), str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []
