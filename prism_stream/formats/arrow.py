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


def _plain(type: pa.DataType) -> bool:
    return pa.types.is_integer(type) or pa.types.is_floating(type) or pa.types.is_boolean(type)
