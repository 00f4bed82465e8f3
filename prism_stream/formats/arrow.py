"""numpy columns as Arrow arrays without pyarrow's pandas check.

``pa.array`` asks, for every argument, whether it is a pandas object, and
the first time it asks it imports pandas if pandas is installed: 0.15-0.2 s
of a run that never uses pandas (bench/RESULTS_STARTUP.md), paid by every
user who has it (GeoPandas brings it). A numeric or boolean numpy column is
one Arrow buffer as it is (bits, for booleans), so :func:`from_numpy` builds
the array from its buffer instead: the same array, no copy of numbers, no
pandas.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa


def from_numpy(values: np.ndarray) -> pa.Array:
    """A 1-D numpy column as an Arrow array of its own type (``pa.array(values)``, without pandas)."""
    values = np.ascontiguousarray(values)
    if values.ndim != 1:
        raise ValueError(f"a column is one-dimensional, not {values.ndim}-dimensional")
    if values.dtype == np.bool_:
        bits = np.packbits(values.view(np.uint8), bitorder="little")
        return pa.Array.from_buffers(pa.bool_(), len(values), [None, pa.py_buffer(bits)])
    if values.dtype.kind in "iuf":
        if not values.dtype.isnative:  # Arrow holds numbers in the machine's byte order
            values = values.astype(values.dtype.newbyteorder("="))
        return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), len(values),
                                     [None, pa.py_buffer(values)])
    return pa.array(values)  # strings, objects: pyarrow's own conversion


def string_scalar(text: str) -> pa.Scalar:
    """An Arrow string scalar (``pa.scalar(text)``, without pandas), for compute functions' arguments."""
    data = text.encode("utf-8")
    offsets = np.array([0, len(data)], dtype=np.int32)
    return pa.Array.from_buffers(pa.string(), 1, [None, pa.py_buffer(offsets), pa.py_buffer(data)])[0]


def indices(at: np.ndarray) -> pa.Array:
    """Positions for ``take``, as Arrow int64."""
    return from_numpy(np.asarray(at, dtype=np.int64))


def to_numpy(column: pa.Array | pa.ChunkedArray) -> np.ndarray:
    """An Arrow column as numpy (``column.to_numpy(zero_copy_only=False)``, without pandas): a numeric
    column without nulls is a view of its buffer (a copy when chunked), booleans are unpacked; anything
    else (nulls, strings, lists) goes through pyarrow's own conversion."""
    if isinstance(column, pa.ChunkedArray):
        if column.num_chunks == 1:
            return to_numpy(column.chunk(0))
        if column.num_chunks == 0 or column.null_count or not _plain(column.type):
            return column.to_numpy()
        return np.concatenate([to_numpy(c) for c in column.chunks])
    if column.null_count or not _plain(column.type):
        return column.to_numpy(zero_copy_only=False)
    data = column.buffers()[1]
    n, at = len(column), column.offset
    if pa.types.is_boolean(column.type):
        if data is None:
            return np.zeros(0, dtype=np.bool_)
        bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")
        return bits[at:at + n].astype(np.bool_)
    dtype = np.dtype(column.type.to_pandas_dtype())
    if data is None:
        return np.zeros(0, dtype=dtype)
    return np.frombuffer(data, dtype=dtype, count=n, offset=at * dtype.itemsize)


def rows_of(batch: pa.RecordBatch, rows: np.ndarray) -> pa.RecordBatch:
    """The records of ``batch`` at ``rows`` (booleans, or positions in order): ``batch.filter`` or
    ``batch.take``, without ``pyarrow.compute`` (30-50 ms of a run's start, the first time a filter or take
    loads it) where every column is numbers, booleans, binary or strings, or fixed-size lists of numbers
    (GeoArrow points), without nulls: taken through numpy, as fast as pyarrow's take up to half the rows
    (2^20 rows of 11 columns: 1% in 1.3 against 1.5 ms, 25% in 4.4 against 4.9, 50% in 5.9 against 7.2) and
    slower past it (70%: 15.0 against 9.6 ms; 90%: 20.6 against 11.4), where pyarrow's kernels take them
    (:data:`DENSE_ROWS`). Every row in order is the batch itself."""
    rows = np.asarray(rows)
    if rows.dtype == np.bool_ and len(rows) != batch.num_rows:
        raise ValueError(f"a mask of {len(rows)} rows for a batch of {batch.num_rows}")
    at = np.flatnonzero(rows) if rows.dtype == np.bool_ else rows.astype(np.int64, copy=False)
    if len(at) and (at.min() < 0 or at.max() >= batch.num_rows):
        raise IndexError(f"rows past the batch's {batch.num_rows}")
    if len(at) == batch.num_rows and (len(at) == 0 or (at[0] == 0 and (np.diff(at) == 1).all())):
        return batch  # every row in order (pass one's first chunks are all candidates): the batch itself
    if len(at) > DENSE_ROWS and 2 * len(at) > batch.num_rows:
        return _arrow_rows(batch, rows, at)  # pyarrow's kernels gather more than half of a batch faster
    taken = []
    for column in batch.columns:
        got = _taken(column, at)
        if got is None:  # another kind of column: pyarrow's own kernels
            return _arrow_rows(batch, rows, at)
        taken.append(got)
    return pa.RecordBatch.from_arrays(taken, schema=batch.schema)


DENSE_ROWS = 1 << 16  # rows_of takes more rows than this, and more than half a batch, with pyarrow's kernels


def _arrow_rows(batch: pa.RecordBatch, rows: np.ndarray, at: np.ndarray) -> pa.RecordBatch:
    return batch.filter(from_numpy(rows)) if rows.dtype == np.bool_ else batch.take(indices(at))


def _taken(column: pa.Array, at: np.ndarray) -> pa.Array | None:
    if column.null_count:
        return None
    if _plain(column.type):
        return from_numpy(to_numpy(column)[at])
    if isinstance(column.type, pa.BaseExtensionType):  # its own storage rules (and a type may not hash)
        return None
    if pa.types.is_fixed_size_list(column.type) and column.type.list_size > 0 and _plain(column.type.value_type):
        size = column.type.list_size
        values = list_values(column)
        if values.null_count or pa.types.is_boolean(values.type):
            return None
        flat = to_numpy(values).reshape(-1, size)[at].reshape(-1)
        return pa.FixedSizeListArray.from_arrays(from_numpy(flat), type=column.type)
    offsets = _offsets(column.type)
    if offsets is not None:  # binary or strings (GeoParquet's WKB points): offsets and bytes
        _, off, data = column.buffers()
        off = np.frombuffer(off, dtype=offsets, count=len(column) + 1, offset=column.offset * offsets.itemsize)
        data = np.frombuffer(data, dtype=np.uint8) if data is not None else np.zeros(0, dtype=np.uint8)
        starts, lengths = off[at], off[at + 1] - off[at]
        new = np.zeros(len(at) + 1, dtype=np.int64)
        np.cumsum(lengths, out=new[1:])
        if new[-1] > np.iinfo(offsets).max:  # rows repeated past 32-bit offsets: pyarrow's take refuses it
            return None
        new = new.astype(offsets)
        where = np.arange(int(new[-1]), dtype=np.int64) + np.repeat(starts.astype(np.int64) - new[:-1], lengths)
        return pa.Array.from_buffers(column.type, len(at), [None, pa.py_buffer(new), pa.py_buffer(data[where])])
    return None


def list_values(column: pa.FixedSizeListArray) -> pa.Array:
    """A fixed-size list column's own values, its offset applied (``flatten()`` would load pyarrow.compute)."""
    size = column.type.list_size
    return column.values.slice(column.offset * size, len(column) * size)


def _offsets(type: pa.DataType) -> np.dtype | None:
    """The offsets' type of a binary or string column, None for any other."""
    if pa.types.is_binary(type) or pa.types.is_string(type):
        return np.dtype(np.int32)
    if pa.types.is_large_binary(type) or pa.types.is_large_string(type):
        return np.dtype(np.int64)
    return None


def _plain(type: pa.DataType) -> bool:
    return pa.types.is_integer(type) or pa.types.is_floating(type) or pa.types.is_boolean(type)
