"""A ranked output put in rank order: a progressive file, whose first T points are the exact sample for T.

Pass two writes the kept points in input order, each with its rank; this
rewrites that staged file with its points sorted by the rank column and
everything else unchanged (Parquet schema and metadata, LAS header, VLRs and
EVLRs, PLY header). The ranks are a permutation of 0..n-1, so one read of the
staged file deals its points into buckets of consecutive ranks (temporary
files, about 256 MiB of records each); then each bucket in turn is loaded,
its points put in place by rank, and appended to the output. Memory holds
one bucket; every point is read and written twice.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import OutputError
from ..run import staging
from .arrow import from_numpy, indices, to_numpy

WINDOW_BYTES = 256 << 20  # records of one bucket, about


def _rows(count: int, row_bytes: int) -> int:
    """Points in a bucket."""
    return max(1, min(count, WINDOW_BYTES // max(1, row_bytes)))


def reorder_by(path: str, column: str, count: int, progress=None) -> None:
    """Rewrite ``path`` (a staged Parquet, LAS/LAZ or PLY output of ``count`` points) in order of ``column``.

    ``progress(n)`` is told of every n points written in order.
    """
    tmp = staging.new_file(path)
    folder = staging.temp_folder(path)
    progress = progress or (lambda n: None)
    try:
        ext = os.path.splitext(path.lower())[1]
        if ext in (".parquet", ".pq"):
            _parquet(path, tmp, folder, column, count, progress)
        elif ext in (".las", ".laz"):
            _las(path, tmp, folder, column, count, progress)
        elif ext == ".ply":
            _ply(path, tmp, folder, column, count, progress)
        else:
            raise ValueError(f"no rank reordering for {ext} files")
        os.replace(tmp, path)
    except OSError as exc:
        raise OutputError(f"cannot write the output in rank order: {exc.strerror or exc}",
                          staging.public_name(path)) from None
    finally:
        staging.remove(tmp)
        staging.remove(folder)


class _Buckets:
    """Structured records dealt into files of consecutive ranks, then read back one bucket at a time in order."""

    def __init__(self, folder: str, count: int, dtype: np.dtype, column: str):
        self.folder = folder
        self.rows = _rows(count, dtype.itemsize)
        self.count = count
        self.dtype = dtype
        self.column = column

    def path(self, i: int) -> str:
        return os.path.join(self.folder, f"bucket-{i:06d}.rec")

    def deal(self, records: np.ndarray) -> None:
        which = records[self.column].astype(np.int64) // self.rows
        order = np.argsort(which, kind="stable")
        which = which[order]
        cuts = np.flatnonzero(np.diff(which)) + 1
        for part in np.split(order, cuts):
            if len(part):
                with open(self.path(int(records[self.column][part[0]]) // self.rows), "ab") as f:
                    records[part].tofile(f)

    def in_order(self):
        """Each bucket's records, placed by rank."""
        for i, lo in enumerate(range(0, self.count, self.rows)):
            hi = min(self.count, lo + self.rows)
            records = np.fromfile(self.path(i), dtype=self.dtype) if os.path.exists(self.path(i)) else \
                np.zeros(0, self.dtype)
            if len(records) != hi - lo:
                raise ValueError(f"bucket {i} holds {len(records)} points, not {hi - lo}: the ranks are not a "
                                 "permutation")
            window = np.empty(hi - lo, dtype=self.dtype)
            window[records[self.column].astype(np.int64) - lo] = records
            if os.path.exists(self.path(i)):
                os.unlink(self.path(i))
            yield window


def _parquet(path: str, tmp: str, folder: str, column: str, count: int, progress) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    source = pq.ParquetFile(path)
    schema = source.schema_arrow
    row_bytes = max(1, sum(source.metadata.row_group(g).total_byte_size for g in range(source.num_row_groups))
                    // max(1, count))
    rows = _rows(count, row_bytes * 2)  # decoded Arrow takes more room than Parquet's encoded columns
    writers: dict = {}
    try:
        for batch in source.iter_batches(batch_size=1 << 18):
            which = to_numpy(batch.column(column)) // rows
            for i in np.unique(which):
                if int(i) not in writers:
                    writers[int(i)] = pa.ipc.new_file(os.path.join(folder, f"bucket-{int(i):06d}.arrow"), schema)
                writers[int(i)].write_batch(batch.filter(from_numpy(which == i)))
    finally:
        for w in writers.values():
            w.close()
    with pq.ParquetWriter(tmp, schema, compression="zstd") as writer:
        for i, lo in enumerate(range(0, count, rows)):
            bucket = os.path.join(folder, f"bucket-{i:06d}.arrow")
            with pa.memory_map(bucket) as f:
                table = pa.ipc.open_file(f).read_all()
            place = to_numpy(table.column(column)) - lo
            order = np.empty(len(place), dtype=np.int64)
            order[place] = np.arange(len(place))
            writer.write_table(table.take(indices(order)))
            del table
            os.unlink(bucket)
            progress(len(place))


def _las(path: str, tmp: str, folder: str, column: str, count: int, progress) -> None:
    import laspy

    with laspy.open(path) as reader:
        header = reader.header
        evlrs = reader.evlrs
        buckets = _Buckets(folder, count, header.point_format.dtype(), column)
        for points in reader.chunk_iterator(1 << 20):
            buckets.deal(points.array)
    from .extrabytes import Writer

    with Writer(tmp, header, path.lower().endswith(".laz")) as writer:
        for window in buckets.in_order():
            writer.write_points(laspy.PackedPointRecord(window, header.point_format))
            progress(len(window))
        if evlrs and header.version.minor >= 4:
            writer.write_evlrs(evlrs)


def _ply(path: str, tmp: str, folder: str, column: str, count: int, progress) -> None:
    from .ply import read_header

    header = read_header(path)
    vertex = header.elements[0]
    dtype = np.dtype([(p.name, "<" + p.type) for p in vertex.properties])
    records = np.memmap(path, dtype=dtype, mode="r", offset=header.data_offset, shape=(vertex.count,))
    buckets = _Buckets(folder, count, dtype, column)
    for a in range(0, vertex.count, 1 << 20):
        buckets.deal(np.asarray(records[a:a + (1 << 20)]))
    del records
    with open(path, "rb") as f:
        head = f.read(header.data_offset)
    with open(tmp, "wb") as out:
        out.write(head)
        for window in buckets.in_order():
            out.write(window.tobytes())
            progress(len(window))
