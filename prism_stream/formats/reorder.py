"""A ranked output put in rank order: a progressive file, whose first T points are the exact sample for T.

Pass two writes the kept points in input order, each with its rank; this
rewrites that staged file with its points sorted by the rank column and
everything else unchanged (Parquet schema and metadata, LAS header, VLRs and
EVLRs, PLY header). Memory stays bounded: the ranks are a permutation of
0..n-1, so the file is rewritten one window of ranks at a time, each window
a read of the staged file that keeps the points whose rank falls in it.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import OutputError
from ..run import staging

WINDOW_BYTES = 256 << 20  # points held at a time: about this many bytes of records


def _windows(count: int, row_bytes: int):
    rows = max(1, WINDOW_BYTES // max(1, row_bytes))
    for lo in range(0, count, rows):
        yield lo, min(count, lo + rows)


def reorder_by(path: str, column: str, count: int, progress=None) -> None:
    """Rewrite ``path`` (a staged Parquet, LAS/LAZ or PLY output of ``count`` points) in order of ``column``.

    ``progress(n)`` is told of every n points written in order.
    """
    tmp = staging.new_file(path)
    progress = progress or (lambda n: None)
    try:
        ext = os.path.splitext(path.lower())[1]
        if ext in (".parquet", ".pq"):
            _parquet(path, tmp, column, count, progress)
        elif ext in (".las", ".laz"):
            _las(path, tmp, column, count, progress)
        elif ext == ".ply":
            _ply(path, tmp, column, count, progress)
        else:
            raise ValueError(f"no rank reordering for {ext} files")
        os.replace(tmp, path)
    except OSError as exc:
        raise OutputError(f"cannot write the output in rank order: {exc.strerror or exc}", path) from None
    finally:
        staging.remove(tmp)


def _placed(ranks: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows of this read whose rank is in [lo, hi), their places in the window)."""
    at = np.flatnonzero((ranks >= lo) & (ranks < hi))
    return at, ranks[at] - lo


def _parquet(path: str, tmp: str, column: str, count: int, progress) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    source = pq.ParquetFile(path)
    schema = source.schema_arrow
    row_bytes = max(1, source.metadata.serialized_size // max(1, count)) + 8 * len(schema.names)
    with pq.ParquetWriter(tmp, schema, compression="zstd") as writer:
        for lo, hi in _windows(count, row_bytes):
            parts, places = [], []
            for batch in source.iter_batches(batch_size=1 << 18):
                at, place = _placed(batch.column(column).to_numpy(), lo, hi)
                if len(at):
                    parts.append(batch.take(pa.array(at)))
                    places.append(place)
            table = pa.Table.from_batches(parts, schema=schema)
            order = np.empty(hi - lo, dtype=np.int64)
            order[np.concatenate(places)] = np.arange(hi - lo)
            writer.write_table(table.take(pa.array(order)))
            progress(hi - lo)


def _las(path: str, tmp: str, column: str, count: int, progress) -> None:
    import laspy

    with laspy.open(path) as reader:
        header = reader.header
        evlrs = reader.evlrs
        record = header.point_format.size
    with laspy.open(tmp, mode="w", header=header, do_compress=path.lower().endswith(".laz")) as writer:
        for lo, hi in _windows(count, record):
            window = np.zeros(hi - lo, dtype=header.point_format.dtype())
            with laspy.open(path) as reader:
                for points in reader.chunk_iterator(1 << 20):
                    at, place = _placed(np.asarray(points[column]), lo, hi)
                    window[place] = points.array[at]
            writer.write_points(laspy.PackedPointRecord(window, header.point_format))
            progress(hi - lo)
        if evlrs and header.version.minor >= 4:
            writer.write_evlrs(evlrs)


def _ply(path: str, tmp: str, column: str, count: int, progress) -> None:
    from .ply import read_header

    header = read_header(path)
    vertex = header.elements[0]
    dtype = np.dtype([(p.name, "<" + p.type) for p in vertex.properties])
    records = np.memmap(path, dtype=dtype, mode="r", offset=header.data_offset, shape=(vertex.count,))
    with open(path, "rb") as f:
        head = f.read(header.data_offset)
    step = 1 << 20
    with open(tmp, "wb") as out:
        out.write(head)
        for lo, hi in _windows(count, dtype.itemsize):
            window = np.empty(hi - lo, dtype=dtype)
            for a in range(0, vertex.count, step):
                part = records[a:a + step]
                at, place = _placed(part[column].astype(np.int64), lo, hi)
                window[place] = part[at]
            out.write(window.tobytes())
            progress(hi - lo)
    del records
