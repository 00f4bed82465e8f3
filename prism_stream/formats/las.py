"""LAS and LAZ (1.0 to 1.4, COPC read as LAZ), through laspy and lazrs.

Pass one reads only what binning needs: uncompressed LAS through a memory
map of the point records, LAZ 1.4 point formats 6 to 10 with selective
decompression of the RGB layer. Older LAZ formats compress whole records,
so pass one decodes them in full.
"""

from __future__ import annotations

import copy
import json
import math
import os
import struct
from typing import Iterator

import laspy
from laspy.vlrs.vlrlist import VLRList
import numpy as np
import pyarrow as pa

from ..errors import CorruptInput, NoColorError, OutputError, UnsupportedFormat, UsageError
from ..run import decoders, remote
from . import extrabytes
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit, WriteOptions, arrow_array, rows
from .columns import select_columns
from .guard import reading
from .lasbuild import ConvertedLasSink
from .lasheader import PROVENANCE_RECORD_ID, PROVENANCE_USER_ID, provenance_vlr, stamp

_VLR_HEADER = 54


def check_header(path: str, storage: dict | None = None) -> dict:
    """Validate the header's size fields against the file before laspy trusts them.

    A bogus VLR count or point count must be a one-line refusal, not an
    allocation of gigabytes or a silently short read. ``storage``: the
    store's options for a remote file (:mod:`..run.remote`).
    """
    with remote.failures(path):
        size = remote.size(path, storage)
        with remote.open_input(path, storage, block_size=remote.PROBE_BLOCK) as f:
            return _check_header(path, f, size)


def _check_header(path: str, f, size: int) -> dict:
    raw = f.read(375)
    if raw[:4] != b"LASF":
        raise UnsupportedFormat("not a LAS/LAZ file (no LASF signature)", path)
    if len(raw) < 227:
        raise CorruptInput(f"truncated: the file ends at byte {len(raw)}, inside the 227-byte LAS header", path)
    major, minor = raw[24], raw[25]
    header_size, offset, nvlr = struct.unpack_from("<HII", raw, 94)
    fmt_byte, record_len, legacy_count = struct.unpack_from("<BHI", raw, 104)
    count = legacy_count
    if (major, minor) >= (1, 4) and len(raw) >= 255:
        count = struct.unpack_from("<Q", raw, 247)[0] or legacy_count
    compressed = bool(fmt_byte & 0xC0)
    fmt = fmt_byte & 0x3F
    if header_size < 227 or header_size > size:
        raise CorruptInput(f"header size {header_size} is impossible for a {size}-byte file", path)
    if offset > size or offset < header_size:
        raise CorruptInput(f"point data offset {offset} lies outside the {size}-byte file", path)
    if nvlr * _VLR_HEADER > offset - header_size:
        room = (offset - header_size) // _VLR_HEADER
        raise CorruptInput(f"header declares {nvlr} VLRs but there is room for at most {room}", path)
    if not compressed and count:
        held = (size - offset) // record_len if record_len else 0
        if held < count:
            raise CorruptInput(f"header declares {count} points but the file holds {held}", path)
    tails = _tail_starts(raw, major, minor)
    if not compressed:
        _check_records_fill(path, size, offset, count, record_len, tails)
    elif nvlr:
        compressor = _laszip_compressor(f, header_size, offset, nvlr)
        if compressor == _POINTWISE:
            # lazrs 0.8 panics on these (a Rust panic prints its own lines to stderr before Python sees it)
            raise UnsupportedFormat("a LAZ encoding the lazrs decoder does not read: compressor 1 (point-wise, no "
                                    f"chunks; LASzip 1.x); {_UNLAZ}", path)
        newer = _newer_items(_laszip_vlr(f, header_size, offset, nvlr))
        if newer:
            raise UnsupportedFormat(f"a LAZ encoding the lazrs decoder does not read: {newer}; {_UNLAZ}", path)
        if compressor is not None:
            _check_chunk_table(path, f, size, offset, count, tails,
                               _laszip_chunk_size(f, header_size, offset, nvlr))
    return {"version": f"{major}.{minor}", "point_format": fmt, "record_length": record_len,
            "offset": offset, "count": count, "compressed": compressed}


_LASZIP_VLR = (b"laszip encoded", 22204)
_POINTWISE = 1
_VARIABLE_CHUNKS = 0xFFFFFFFF


def _tail_starts(raw: bytes, major: int, minor: int) -> list[int]:
    """Where the data after the point records may begin: LAS 1.3+ waveform packets, LAS 1.4 EVLRs."""
    starts = []
    if (major, minor) >= (1, 3) and len(raw) >= 235:
        starts.append(struct.unpack_from("<Q", raw, 227)[0])
    if (major, minor) >= (1, 4) and len(raw) >= 247:
        evlr_start, nevlr = struct.unpack_from("<QI", raw, 235)
        if nevlr:
            starts.append(evlr_start)
    return [s for s in starts if s]


def _check_records_fill(path: str, size: int, offset: int, count: int, record_len: int, tails: list) -> None:
    """Uncompressed records must end where the file (or its waveform/EVLR area) begins.

    Bytes left over mean the records are not where the header says (a header
    written twice, a wrong offset or record length): every point would be read
    from the wrong bytes, so the file is refused rather than read as garbage.
    """
    end = offset + count * record_len
    if end == size or end in tails:
        return
    what = f"the waveform/EVLR data starts at byte {min(tails)}" if tails else f"the file ends at byte {size}"
    over = (min(tails) if tails else size) - end
    raise CorruptInput(f"header declares {count} records of {record_len} bytes from byte {offset} (ending at byte "
                       f"{end}), but {what}: {abs(over)} bytes {'left over' if over > 0 else 'missing'} "
                       "(records misaligned: a duplicated header or a wrong offset?)", path)


def _check_chunk_table(path: str, f, size: int, offset: int, count: int, tails: list,
                       chunk_size: int | None) -> None:
    """A LAZ file's chunk table must lie after the point data and cover exactly the declared points."""
    f.seek(offset)
    head = f.read(8)
    if len(head) < 8:
        raise CorruptInput(f"LAZ data at byte {offset} is shorter than its chunk table offset "
                           f"(file of {size} bytes)", path)
    table = struct.unpack("<q", head)[0]
    if table == -1:  # written by a streaming writer: no table to check
        return
    limit = min([size] + [t for t in tails if t > offset])
    if table > limit - 8 and limit == size and table < size * 4 + (1 << 20):
        # past the end, by no more than a cut file leaves out: the commonest way to get here is a file copied
        # or downloaded only in part
        raise CorruptInput(f"the file ends at byte {size}, before its LAZ chunk table (at byte {table}): it is cut "
                           "short (an incomplete copy or download?)", path)
    if not offset + 8 <= table <= limit - 8:
        raise CorruptInput(f"LAZ chunk table offset {table} lies outside the point data (bytes {offset + 8} to "
                           f"{limit}; a duplicated header or a wrong offset?)", path)
    f.seek(table)
    version, chunks = struct.unpack("<II", f.read(8))
    if version != 0:
        raise CorruptInput(f"LAZ chunk table at byte {table} has version {version}, not 0", path)
    if chunk_size and chunk_size != _VARIABLE_CHUNKS:
        need = -(-count // chunk_size)
        if chunks != need:
            raise CorruptInput(f"header declares {count} points, {need} chunks of {chunk_size}, but the LAZ "
                               f"chunk table lists {chunks} chunks", path)


def _laszip_vlr(f, header_size: int, offset: int, nvlr: int) -> bytes | None:
    """The LASzip VLR's payload (walked within the VLR area check_header validated), if any."""
    pos = header_size
    for _ in range(nvlr):
        f.seek(pos)
        head = f.read(_VLR_HEADER)
        if len(head) < _VLR_HEADER or pos + _VLR_HEADER > offset:
            return None
        user_id = head[2:18].rstrip(b"\0")
        record_id, length = struct.unpack_from("<HH", head, 18)
        if (user_id, record_id) == _LASZIP_VLR:
            return f.read(min(length, offset - pos - _VLR_HEADER))
        pos += _VLR_HEADER + length
    return None


_UNLAZ = "decompress it with LASzip first (laszip -i IN.laz -o OUT.las)"
_ITEM_NAMES = {0: "Byte", 6: "Point10", 7: "GpsTime11", 8: "RGB12", 9: "Wavepacket13", 10: "Point14", 11: "RGB14",
               12: "RGBNIR14", 13: "Wavepacket14", 14: "Byte14"}  # LASzip's item types
_LAST_ITEM_VERSION = 3  # lazrs 0.8 decodes LASzip items up to version 3 ("compression version: 4 is not supported")


def _newer_items(data: bytes | None) -> str | None:
    """The LASzip VLR's items of a compression version past what lazrs decodes, said (None: none)."""
    if data is None or len(data) < 34:
        return None
    count = struct.unpack_from("<H", data, 32)[0]
    newer = []
    for i in range(count):
        if 34 + 6 * (i + 1) > len(data):
            break
        kind, _, version = struct.unpack_from("<HHH", data, 34 + 6 * i)
        if version > _LAST_ITEM_VERSION:
            newer.append(f"{_ITEM_NAMES.get(kind, f'item type {kind}')} of compression version {version}")
    return ", ".join(newer) or None


def _laszip_compressor(f, header_size: int, offset: int, nvlr: int) -> int | None:
    """The compressor id of the LASzip VLR, if any."""
    data = _laszip_vlr(f, header_size, offset, nvlr)
    return struct.unpack_from("<H", data)[0] if data is not None and len(data) >= 2 else None


def _laszip_chunk_size(f, header_size: int, offset: int, nvlr: int) -> int | None:
    """Points per chunk from the LASzip VLR (0xFFFFFFFF: variable-size chunks), if it says."""
    data = _laszip_vlr(f, header_size, offset, nvlr)
    return struct.unpack_from("<I", data, 12)[0] if data is not None and len(data) >= 16 else None


def grid_fault(scales, offsets) -> str | None:
    """What makes a LAS header's coordinate grid unusable (a scale of 0 decodes every point to the offset; a
    scale or offset that is not a finite number, every point to NaN or infinity), or None."""
    for axis, s, o in zip("xyz", scales, offsets):
        if not math.isfinite(float(s)) or not math.isfinite(float(o)):
            return f"{axis} scale {float(s)!r} / offset {float(o)!r} is not a finite number"
        if float(s) == 0:
            return f"{axis} scale is 0 (every {axis} would be the offset)"
    return None


def open_reader(path: str, storage: dict | None = None, **kw) -> laspy.LasReader:
    """laspy's reader of a local path, or of a remote file through the file object fsspec opens."""
    with reading(path):
        if not remote.is_remote(path):
            reader = laspy.open(path, **kw)
        else:
            f = remote.open_input(path, storage)
            try:
                reader = laspy.open(f, closefd=True, **kw)
            except BaseException:
                f.close()
                raise
    if kw.get("mode", "r") == "r":
        extrabytes.merge_records(reader.header)  # every extra-bytes dimension named, as PDAL reads them
    return reader


class LasPointChunk(PointChunk):
    def __init__(self, start: int, points, header):
        self.start = start
        self.points = points
        self.header = header
        self.rgb = (np.asarray(points["red"]), np.asarray(points["green"]), np.asarray(points["blue"]))

    def las_points(self, mask: np.ndarray):
        """The masked points as laspy records (their array taken, see :func:`.base.rows`)."""
        p = self.points
        return type(p)(rows(p.array, mask), p.point_format, p.scales, p.offsets)

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        pts = self.points if mask is None else self.las_points(mask)
        arrays, names = [], []
        for name in pts.point_format.dimension_names:
            if name in ("X", "Y", "Z"):
                values = np.asarray(getattr(pts, name.lower()), dtype=np.float64)
                name = name.lower()
            else:
                values = np.asarray(pts[name])
            arrays.append(arrow_array(values))
            names.append(name)
        return pa.RecordBatch.from_arrays(arrays, names=names)


class LasSource(Source):
    format = "las"

    reads_remote = True

    def __init__(self, path: str, ordinal: int, threads: int = 1, storage_options: dict | None = None, **_):
        self.path = path
        self.ordinal = ordinal
        self.threads = threads
        self.storage = storage_options
        self.raw = check_header(path, storage_options)
        with open_reader(path, storage_options) as r:
            self.header = r.header
            with reading(path):
                if self.header.version.minor >= 4 and self.header.number_of_evlrs and self.header.evlrs is None:
                    r.read_evlrs()
                self.evlrs = r.header.evlrs
        self.point_format = self.header.point_format
        dims = set(self.point_format.dimension_names)
        if not {"red", "green", "blue"} <= dims:
            raise NoColorError(f"point format {self.point_format.id} has no RGB, so points cannot be binned by color", path)
        self.count = int(self.header.point_count)
        self.compressed = self.raw["compressed"]
        why = grid_fault(self.header.scales, self.header.offsets)
        if why:
            raise CorruptInput(f"header {why}: its coordinates cannot be decoded", path)

    def laz_chunk_size(self) -> int | None:
        """Points per LAZ chunk from the laszip VLR (None: not LAZ, or variable-size chunks as in COPC)."""
        if not self.compressed:
            return None
        for vlr in self.header.vlrs:
            if getattr(vlr, "user_id", "") == "laszip encoded" and getattr(vlr, "record_id", 0) == 22204:
                data = bytes(vlr.record_data_bytes())
                if len(data) >= 16:
                    size = struct.unpack_from("<I", data, 12)[0]
                    return None if size in (0, 0xFFFFFFFF) else int(size)
        return None

    def units(self, unit_size: int) -> list[Unit]:
        """Record ranges of about ``unit_size`` points; LAZ ranges are whole chunks, so no chunk is decoded twice."""
        laz = self.laz_chunk_size()
        if laz:
            unit_size = max(laz, (unit_size // laz) * laz)
        return super().units(unit_size)

    def prestart(self) -> None:
        """A local LAZ file: start the decoder processes its reads will use, while the run sets up."""
        if self.compressed and not remote.is_remote(self.path):
            decoders.prestart(self.count, self.threads)

    _table = False

    def _chunk_table(self) -> decoders.ChunkTable | None:
        """A local LAZ file's chunk table, read once, for :mod:`..run.decoders` (None: not LAZ, remote, or no
        table lazrs reads, as a file written without one: laspy's reader then)."""
        if self._table is False:
            self._table = None
            if self.compressed and not remote.is_remote(self.path):
                with reading(self.path), open(self.path, "rb") as f:
                    header_size, offset, nvlr = struct.unpack_from("<HII", f.read(104), 94)
                    vlr = _laszip_vlr(f, header_size, offset, nvlr)
                if vlr is not None and self.header.point_format.dtype().itemsize == self.raw["record_length"]:
                    try:
                        self._table = decoders.ChunkTable(self.path, self.raw["offset"], vlr, self.count)
                    except Exception:  # noqa: BLE001 - no usable table: laspy's reader, which says why
                        self._table = None
        return self._table

    def _backend(self):
        if self.threads > 1:
            return (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs)
        return (laspy.LazBackend.Lazrs,)

    def _records(self, chunk_size: int, start: int, stop: int | None, selection=None):
        stop = self.count if stop is None else stop
        table = self._chunk_table() if stop > start else None
        if table is not None:
            bits = None if selection is None else decoders.lazrs_selection(selection)
            yield from decoders.records(table, self.header, bits, chunk_size, start, stop, self.threads)
            return
        kw = {"laz_backend": self._backend()} if self.compressed else {}
        if selection is not None:
            kw["decompression_selection"] = selection
        with open_reader(self.path, self.storage, read_evlrs=False, **kw) as r, reading(self.path):
            if start:
                r.seek(start)
            pos = start
            while pos < stop:
                pts = r.read_points(min(chunk_size, stop - pos))
                if len(pts) == 0:
                    raise CorruptInput(f"file ends after {pos} of the {self.count} points its header declares", self.path)
                yield pos, pts
                pos += len(pts)

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        stop = self.count if stop is None else stop
        if not self.compressed:
            yield from self._mapped_colors(chunk_size, start, stop)
            return
        selection = None
        if self.point_format.id >= 6:
            selection = laspy.DecompressionSelection.base().decompress_rgb()
        for pos, pts in self._records(chunk_size, start, stop, selection):
            yield ColorChunk(pos, (np.asarray(pts["red"]), np.asarray(pts["green"]), np.asarray(pts["blue"])))

    def _mapped_colors(self, chunk_size: int, start: int, stop: int) -> Iterator[ColorChunk]:
        full = self.point_format.dtype()
        fields = {n: full.fields[n] for n in ("red", "green", "blue")}
        dtype = np.dtype({"names": list(fields), "formats": [f[0] for f in fields.values()],
                          "offsets": [f[1] for f in fields.values()], "itemsize": self.raw["record_length"]})
        if stop <= start:
            return
        if remote.is_remote(self.path):
            yield from self._ranged_colors(dtype, chunk_size, start, stop)
            return
        with reading(self.path):
            mm = np.memmap(self.path, dtype=dtype, mode="r", offset=self.raw["offset"], shape=(self.count,))
        try:
            for a in range(start, stop, chunk_size):
                rec = mm[a:min(stop, a + chunk_size)]
                yield ColorChunk(a, (np.array(rec["red"]), np.array(rec["green"]), np.array(rec["blue"])))
        finally:
            del mm

    def _ranged_colors(self, dtype: np.dtype, chunk_size: int, start: int, stop: int) -> Iterator[ColorChunk]:
        """A remote file's colors, read as whole records in byte ranges (what the memory map does locally)."""
        size = dtype.itemsize
        with reading(self.path), remote.open_input(self.path, self.storage) as f:
            f.seek(self.raw["offset"] + start * size)
            for a in range(start, stop, chunk_size):
                n = min(stop, a + chunk_size) - a
                data = f.read(n * size)
                if len(data) < n * size:
                    raise CorruptInput(f"file ends after {a + len(data) // size} of the {self.count} points its "
                                       "header declares", self.path)
                rec = np.frombuffer(data, dtype=dtype, count=n)
                yield ColorChunk(a, (np.array(rec["red"]), np.array(rec["green"]), np.array(rec["blue"])))

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[LasPointChunk]:
        for pos, pts in self._records(chunk_size, start, stop):
            yield LasPointChunk(pos, pts, self.header)

    spills = True

    def spill_state(self, chunk: LasPointChunk, at: np.ndarray):
        # laspy records do not pickle, their numpy records do; and only they are kept (masking the chunk's
        # color views too, as ``take`` does, cost a twentieth of pass one's own time on PF3)
        return rows(chunk.points.array, at)

    def restore(self, state) -> LasPointChunk:
        h = self.header
        chunk = LasPointChunk(0, laspy.ScaleAwarePointRecord(state, h.point_format, h.scales, h.offsets), h)
        chunk.ordinal = self.ordinal
        return chunk

    def arrow_schema(self) -> pa.Schema:
        empty = laspy.ScaleAwarePointRecord.zeros(0, header=self.header)
        return LasPointChunk(0, empty, self.header).to_arrow().schema

    def crs(self):
        """The header's CRS (WKT or GeoTIFF keys) as a pyproj CRS, or None."""
        if not hasattr(self, "_crs"):
            try:
                self._crs = self.header.parse_crs()
            except Exception:  # noqa: BLE001 - unparsable keys: no CRS to report
                self._crs = None
        return self._crs

    def crs_wkt(self) -> str | None:
        crs = self.crs()
        return crs.to_wkt() if crs is not None else None

    def describe(self) -> dict:
        h = self.header
        return {
            "format": "laz" if self.compressed else "las",
            "version": str(h.version),
            "point_format": int(h.point_format.id),
            "scales": [float(v) for v in h.scales],
            "offsets": [float(v) for v in h.offsets],
            "system_identifier": _text(h.system_identifier),
            "generating_software": _text(h.generating_software),
        }


def _text(value) -> str:
    """A header string field; laspy hands back bytes when they are not valid text."""
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).rstrip(b"\0").decode("ascii", "replace")
    return value


COPC_INPUT_NOTE = "COPC VLRs (octree index) of the input not written"


def _is_copc(vlr) -> bool:
    return getattr(vlr, "user_id", "") == "copc"


def _is_provenance(vlr) -> bool:
    return getattr(vlr, "user_id", "") == PROVENANCE_USER_ID and getattr(vlr, "record_id", None) == PROVENANCE_RECORD_ID


def all_las(sources) -> bool:
    """Whether every input is LAS/LAZ (their output keeps their own header)."""
    return all(isinstance(s, LasSource) for s in sources)


class LasSink(Sink):
    """LAS/LAZ out, from LAS inputs: the first input's header, VLRs and EVLRs.

    :meth:`open` picks this or, for inputs of other formats (Parquet,
    PLY...), :class:`.lasbuild.ConvertedLasSink`, which builds a header.
    """

    takes_grid = True  # for inputs of other formats (LAS inputs keep their own grid)

    @classmethod
    def open(cls, path: str, sources: list[Source], provenance: dict, options: WriteOptions) -> Sink:
        """The LAS/LAZ writer for these inputs: their own header when all are LAS, a built one otherwise (on the
        grid of --scale/--offset, when given). What it cannot write, :meth:`refuse_own` refused before."""
        if sources and not all_las(sources):
            return ConvertedLasSink(path, sources, provenance, rank=options.rank, grid=options.grid,
                                    selection=options.selection)
        return cls(path, sources, provenance, flag=options.flag, rank=options.rank, selection=options.selection)

    @classmethod
    def refuse_selection(cls, path: str, sources: list, options: WriteOptions) -> None:
        if options.selection is not None and sources and isinstance(sources[0], LasSource):
            left_out(sources[0], options.selection, options.flag)  # what a LAS record keeps whatever --drop says

    @classmethod
    def refuse_own(cls, path: str, sources: list, options: WriteOptions) -> None:
        if options.flag is not None and sources and not all_las(sources):
            raise UsageError("--flag with LAS output needs LAS/LAZ inputs; write Parquet for a flag column", path)
        if options.grid is not None and sources and all_las(sources):
            raise UsageError(GRID_OF_LAS_INPUTS, path)
        if sources and not all_las(sources):  # converted: the points' coordinates must be there to write
            from .parquet import point_xyz

            point_xyz(sources[0].arrow_schema(), sources[0].path, "LAS output", sources[0])

    def __init__(self, path: str, sources: list[Source], provenance: dict, flag: str | None = None,
                 rank: str | None = None, selection: tuple | None = None):
        """``flag``: write every point, marking the kept ones in an extra-bytes
        dimension of that name (uint8, 1 = kept), or with ``"withheld"``
        setting the withheld bit of every dropped point; ``rank``: add an
        int64 extra-bytes dimension of that name, each point's rank;
        ``selection``: --keep/--drop (:func:`left_out`)."""
        super().__init__(path, sources, provenance)
        self.flag = flag
        if not sources or not all_las(sources):
            raise UsageError("LAS/LAZ output needs LAS/LAZ inputs; write Parquet instead", path)
        first = sources[0]
        for s in sources[1:]:
            if s.point_format != first.point_format:
                raise UsageError(
                    f"inputs mix point formats {first.point_format.id} and {s.point_format.id}; "
                    "one LAS output needs one point format", s.path)
            self._check_grid(first, s)
        header = copy.deepcopy(first.header)
        # an input written by prism-stream carries its own run's provenance: this run's replaces it (one record,
        # as in Parquet's one key), so a reader never finds the older one first
        header.vlrs = VLRList([v for v in header.vlrs if not _is_copc(v) and not _is_provenance(v)])
        self.evlrs = VLRList([v for v in (first.evlrs or []) if not _is_copc(v)])
        self._drop_unreadable_wkt(header, first.path)
        stamp(header)
        self.note_depths(sources, provenance)  # records copied as they are: 8-bit and 16-bit colors side by side
        provenance = {**provenance, "input_software": input_software(sources)}
        header.vlrs.append(provenance_vlr(provenance))
        if any(_is_copc(v) for v in [*first.header.vlrs, *(first.evlrs or [])]):
            self.note(COPC_INPUT_NOTE + ": a sample is not the input's octree, so the output is a plain LAZ/LAS")
        dropped, self.zeroed = left_out(first, selection, flag)
        if dropped:
            header.remove_extra_dims(dropped)
        if self.zeroed:
            self.note(f"--{selection[0]}: {', '.join(self.zeroed)} written as 0 in every record (LAS point format "
                      f"{header.point_format.id} holds them; extra-bytes dimensions are left out)")
        self.reshaped = bool(dropped or self.zeroed)
        if flag is not None and flag != "withheld":
            if flag in set(header.point_format.dimension_names):
                raise UsageError(f"--flag {flag!r}: the input already has a dimension of that name", first.path)
            if len(flag.encode()) > 32:
                raise UsageError(f"--flag {flag!r}: LAS extra-bytes names hold at most 32 bytes", path)
            header.add_extra_dim(laspy.ExtraBytesParams(name=flag, type=np.uint8,
                                                        description="PRISM keep flag (1 = kept)"))
        self.rank = rank
        if rank is not None:
            self.check_rank_name(rank, header.point_format.dimension_names, 32)
            header.add_extra_dim(laspy.ExtraBytesParams(name=rank, type=np.int64,
                                                        description="PRISM rank: < T is sample T"))
        extrabytes.keep_no_data(header, first.header)
        self.header = header
        self.file = AtomicFile(path)
        with reading(path, "cannot write the output"):
            self.writer = extrabytes.Writer(self.file.tmp, header, path.lower().endswith(".laz"))

    def _drop_unreadable_wkt(self, header, path: str) -> None:
        """A WKT record that pyproj cannot read is not copied: readers that trust it would fail or misplace
        the points. Said once."""
        bad = [v for v in [*header.vlrs, *self.evlrs] if _unreadable_wkt(v)]
        if not bad:
            return
        header.vlrs = VLRList([v for v in header.vlrs if not any(v is b for b in bad)])
        self.evlrs = VLRList([v for v in self.evlrs if not any(v is b for b in bad)])
        self.note(f"{os.path.basename(path)}: its WKT record is not a CRS pyproj can read, so it is not "
                  "written; the output has no CRS (give the points a CRS with another tool)")

    def _check_grid(self, first: LasSource, other: LasSource) -> None:
        """``other``'s points are written on ``first``'s grid (its scales and offsets): refuse, before reading,
        a file whose extent does not fit that grid's 32-bit integers; say so when the grid is coarser."""
        fh, oh = first.header, other.header
        if np.array_equal(fh.scales, oh.scales) and np.array_equal(fh.offsets, oh.offsets):
            return
        if other.count:
            ends = np.stack([np.asarray(oh.mins), np.asarray(oh.maxs)])
            ints = np.round((ends - np.asarray(fh.offsets)) / np.asarray(fh.scales))
            if np.any(ints < -(2 ** 31)) or np.any(ints > 2 ** 31 - 1):
                raise UsageError(f"its coordinates do not fit the LAS grid of {os.path.basename(first.path)} "
                                 f"(scales {list(map(float, fh.scales))}, offsets {list(map(float, fh.offsets))}), "
                                 "which one LAS output uses for every input; write Parquet, or one output per "
                                 "input (an output folder)", other.path)
        coarser = np.abs(np.asarray(fh.scales)) > np.abs(np.asarray(oh.scales))
        if coarser.any():
            self.note(f"points of {os.path.basename(other.path)} written on the grid of "
                      f"{os.path.basename(first.path)} (scales {list(map(float, fh.scales))}), coarser than "
                      f"their own ({list(map(float, oh.scales))}): coordinates rounded to it")

    def write(self, chunk: LasPointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        if self.flag is None:
            if not mask.any():
                return
            points = chunk.las_points(mask)
            if self.rank is not None or self.reshaped:
                points = self._with(points, self.rank, ranks)
        else:
            points = self._flagged(chunk.points, mask)
        try:
            self.writer.write_points(points)
        except OSError as exc:
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", self.path) from None
        self.written += len(points)

    def _flagged(self, points, mask: np.ndarray):
        """Every point, with the keep decision recorded (flag mode)."""
        if self.flag == "withheld":
            points = points.copy()
            points.withheld = np.where(mask, np.asarray(points.withheld), 1).astype(np.uint8)
            return self._with(points) if self.reshaped else points
        return self._with(points, self.flag, mask)

    def _with(self, points, name: str | None = None, values: np.ndarray | None = None):
        """The points in the output's point format (a copy): its added dimension ``name`` set to ``values``,
        the extra-bytes dimensions --keep/--drop leave out left out, the standard ones it drops set to 0."""
        fmt = self.header.point_format
        array = np.zeros(len(points), dtype=fmt.dtype())
        for field in array.dtype.names:
            if field in points.array.dtype.names:
                array[field] = points.array[field]
        if name is not None:
            array[name] = values
        out = laspy.PackedPointRecord(array, fmt)
        for dim in self.zeroed:
            out[dim] = np.zeros(len(out), dtype=np.uint8)  # a bit field or a whole field alike
        return out

    def _commit(self) -> None:
        try:
            if len(self.evlrs) and self.header.version.minor >= 4:
                self.writer.write_evlrs(self.evlrs)
            self.writer.close()
        except OSError as exc:
            self.abort()
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", self.path) from None
        self.file.commit()

    def abort(self) -> None:
        try:
            self.writer.close()
        except BaseException:  # noqa: BLE001 - closing a half-written file may fail; it is deleted next
            pass
        self.file.discard()


def input_software(sources) -> list[dict]:
    """The inputs' own generating software and system identifier, each pair once with its count of files (a
    thousand tiles of one scanner are one entry, so the provenance stays small)."""
    seen: dict[tuple, int] = {}
    for s in sources:
        key = (_text(s.header.generating_software), _text(s.header.system_identifier))
        seen[key] = seen.get(key, 0) + 1
    return [{"generating_software": g, "system_identifier": i, "files": n} for (g, i), n in seen.items()]


def _unreadable_wkt(vlr) -> bool:
    if type(vlr).__name__ != "WktCoordinateSystemVlr":
        return False
    try:
        import pyproj

        pyproj.CRS.from_wkt(vlr.string.strip("\x00 \n"))
    except Exception:  # noqa: BLE001 - pyproj's CRSError, or text that is not a string
        return True
    return False


def read_provenance(path: str) -> dict | None:
    """The provenance JSON a prism-stream LAS/LAZ output carries, if any."""
    with laspy.open(path) as r:
        for v in r.header.vlrs:
            if _is_provenance(v):
                return json.loads(bytes(v.record_data))
    return None


# what a LAS record cannot do without: return numbers start at 1 (the per-return counts of the header follow them)
LAS_KEPT = ("return_number", "number_of_returns")


def left_out(source: LasSource, selection: tuple | None, flag: str | None = None) -> tuple[list[str], list[str]]:
    """What --keep/--drop (``selection``) leaves out of a LAS output from this input: (its extra-bytes
    dimensions, which are not written; its point format's standard dimensions, which every record holds and
    are written as 0). Coordinates, colors, the return numbers and the withheld bit of ``--flag withheld``
    stay: a --keep keeps them, a --drop of one is refused, as a name the input lacks is
    (:func:`.columns.select_columns`)."""
    if selection is None:
        return [], []
    schema = source.arrow_schema()
    kept = set(select_columns(schema, [source], selection, source.path).names)
    extra = set(source.point_format.extra_dimension_names)
    stay = LAS_KEPT + (("withheld",) if flag == "withheld" else ())
    if selection[0] == "drop":
        named = {n.lower() for n in selection[1]}
        refused = [n for n in stay if n in named]
        if refused:
            why = "--flag withheld writes it" if refused[0] == "withheld" else "LAS return numbers start at 1"
            raise UsageError(f"--drop {refused[0]!r}: a LAS output keeps it ({why})", source.path)
    gone = [n for n in schema.names if n not in kept and n not in stay]
    return [n for n in gone if n in extra], [n for n in gone if n not in extra]


GRID_OF_LAS_INPUTS = ("--scale and --offset apply to LAS output converted from other formats; LAS inputs keep "
                      "their own scale and offset, on which every point is exact")
