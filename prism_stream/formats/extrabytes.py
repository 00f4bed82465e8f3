"""LAS extra-bytes descriptors as readers need them: every name kept, statistics true or unset.

Two things laspy leaves to its callers (issue 31):

- A file may describe its extra bytes in several ``LASF_Spec``/4 records (IGN's LiDAR HD tiles
  do: one descriptor each). laspy reads only the first, so the later dimensions come out as one
  unnamed ``ExtraBytes`` field. :func:`merge_records` folds them into one record and names every
  dimension, as PDAL does, before a point is decoded; the point records keep their layout.
- A descriptor's min/max ("valid" bits 1 and 2 of its options) must be the values written. laspy's
  writer claims them for every descriptor but computes them from one element per chunk, and a
  header rebuilt from a point format resets them to the type's extremes (UINT64_MAX, 0), which
  web readers refuse. :class:`ExtraStats` counts them from the records written (points equal to
  the descriptor's no-data value, and NaN, left out) and :meth:`ExtraStats.apply` writes them into
  the header, or clears the bits when nothing was counted; the input's no-data value is kept.
"""

from __future__ import annotations

import contextlib

import numpy as np

MIN_MAX = 0b110  # options bits 1 and 2: min and max are valid
NO_DATA = 0b001


def _records(header):
    """The ExtraBytesVlr records of a laspy header (VLRs, then EVLRs)."""
    found = list(header.vlrs.get("ExtraBytesVlr"))
    if header.evlrs is not None:
        found += list(header.evlrs.get("ExtraBytesVlr"))
    return found


def descriptors(header) -> list:
    """Every extra-bytes descriptor of the header, in record order."""
    return [s for r in _records(header) for s in r.extra_bytes_structs]


def merge_records(header) -> bool:
    """Fold several extra-bytes records into one and name every dimension from them; True if changed.

    Only when the descriptors together cover exactly the bytes laspy left unnamed: otherwise the
    header is left as laspy read it (its unnamed bytes stay ``ExtraBytes``)."""
    import laspy
    from laspy.vlrs.known import ExtraBytesVlr

    records = list(header.vlrs.get("ExtraBytesVlr"))
    if len(records) < 2:
        return False
    fmt = header.point_format
    fmt_new = laspy.PointFormat(fmt.id)
    structs = [s for r in records for s in r.extra_bytes_structs]
    try:
        for r in records:
            for params in r.type_of_extra_dims():
                fmt_new.add_extra_dimension(params)
    except Exception:  # noqa: BLE001 - a descriptor laspy cannot type: keep what it read
        return False
    if fmt_new.size != fmt.size:
        return False
    merged = ExtraBytesVlr()
    merged.extra_bytes_structs = structs
    taken = {id(r) for r in records}
    at = next(i for i, v in enumerate(header.vlrs) if v is records[0])
    kept = [v for v in header.vlrs if id(v) not in taken]
    header.vlrs[:] = [*kept[:at], merged, *kept[at:]]
    header._point_format = fmt_new  # same record layout, every dimension named
    return True


def _long(struct) -> type:
    base = ((struct.data_type - 1) % 10) + 1
    if base in (9, 10):
        return np.float64
    return np.int64 if base in (2, 4, 6, 8) else np.uint64


class ExtraStats:
    """The raw (unscaled) min and max of every typed extra-bytes dimension over the records written."""

    def __init__(self, header):
        self.specs = {}  # name -> (long type, no-data values or None, elements)
        for s in descriptors(header):
            if s.data_type == 0 or s.data_type > 30:
                continue
            no_data = s.no_data if s.options & NO_DATA else None
            self.specs[s.format_name()] = (_long(s), None if no_data is None else np.asarray(no_data),
                                           s.num_elements())
        # name -> each element's min and max so far (None: no value counted yet)
        self.lo = {name: [None] * n for name, (_, _, n) in self.specs.items()}
        self.hi = {name: [None] * n for name, (_, _, n) in self.specs.items()}

    def grow(self, points) -> None:
        """Count the records of ``points`` (a laspy point record or a structured array)."""
        array = getattr(points, "array", points)
        if not len(array):
            return
        for name, (long, no_data, n) in self.specs.items():
            if name not in array.dtype.names:
                continue
            values = np.asarray(array[name]).reshape(len(array), -1)
            lo, hi = self.lo[name], self.hi[name]
            for i in range(min(n, values.shape[1])):
                col = values[:, i]
                if no_data is not None:
                    col = col[col != no_data[i]]
                if col.dtype.kind == "f":
                    col = col[~np.isnan(col)]
                if len(col):
                    a, b = long(col.min()), long(col.max())
                    lo[i] = a if lo[i] is None else min(lo[i], a)
                    hi[i] = b if hi[i] is None else max(hi[i], b)

    def apply(self, header) -> None:
        """Write the counted statistics into ``header``'s descriptors; clear the bits of the others."""
        for s in descriptors(header):
            if not 0 < s.data_type <= 30:
                continue  # undocumented bytes: their options byte is their length, not flags
            name = s.format_name()
            n = s.num_elements()
            lo, hi = self.lo.get(name, [None])[:n], self.hi.get(name, [None])[:n]
            if None in lo or None in hi:
                s.options &= ~MIN_MAX
                np.frombuffer(s._min, dtype=np.uint8)[:] = 0
                np.frombuffer(s._max, dtype=np.uint8)[:] = 0
                continue
            long = _long(s)
            np.frombuffer(s._min, dtype=long)[:n] = np.array(lo, dtype=long)
            np.frombuffer(s._max, dtype=long)[:n] = np.array(hi, dtype=long)
            s.options |= MIN_MAX


class RecordedFile:
    """A file that remembers the first OSError its writes raised: lazrs turns one (a full disk) into
    'LazrsError: IoError: Failed to call write', which :meth:`told` turns back into the OSError it was."""

    def __init__(self, f):
        self._f = f
        self.error: OSError | None = None

    def _noted(self, call, *args):
        try:
            return call(*args)
        except OSError as exc:
            self.error = self.error or exc
            raise

    def write(self, data):
        return self._noted(self._f.write, data)

    def flush(self):
        return self._noted(self._f.flush)

    def __getattr__(self, name):
        return getattr(self._f, name)

    @contextlib.contextmanager
    def told(self):
        try:
            yield
        except OSError:
            raise
        except Exception:
            if self.error is not None:
                raise self.error from None
            raise


class Writer:
    """laspy's LAS/LAZ writer, with the extra-bytes statistics of the records it wrote (:class:`ExtraStats`)
    set in the header it rewrites when it closes: every LAS writer of the project writes through it."""

    def __init__(self, dest, header, compress: bool):
        import laspy

        self.file = RecordedFile(open(dest, "wb"))
        try:
            self.writer = laspy.open(self.file, mode="w", header=header, do_compress=compress, closefd=True)
        except BaseException:
            self.file.close()
            raise
        self.stats = ExtraStats(header)

    def write_points(self, points) -> None:
        with self.file.told():
            self.writer.write_points(points)
        self.stats.grow(points)

    def write_evlrs(self, evlrs) -> None:
        with self.file.told():
            self.writer.write_evlrs(evlrs)

    def close(self) -> None:
        self.stats.apply(self.writer.header)
        with self.file.told():
            self.writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def keep_no_data(header, source_header) -> None:
    """Give ``header``'s descriptors the no-data values the source's descriptors of the same name and type
    declare (laspy drops them when it rebuilds the record from a point format)."""
    given = {s.format_name(): s for s in descriptors(source_header)}
    for s in descriptors(header):
        src = given.get(s.format_name())
        if src is None or not 0 < s.data_type <= 30 or src.data_type != s.data_type or not src.options & NO_DATA:
            continue
        np.frombuffer(s._no_data, dtype=np.uint8)[:] = np.frombuffer(src._no_data, dtype=np.uint8)
        s.options |= NO_DATA
