"""PCD in (PCL's Point Cloud Data): ascii, binary and binary_compressed.

Color is one 32-bit word per point, ``rgb`` (0x00RRGGBB) or ``rgba``
(0xAARRGGBB), declared ``F`` (a float whose *bits* are the word: they are
reinterpreted, never converted) or ``U``/``I``. In ASCII files PCL writes
the word as an integer; a value that is not a whole number in 0..2^32-1
(an old writer's float print) is read as the float's bits instead.

Written out, the word becomes uint8 ``red``, ``green`` and ``blue`` columns
(with ``alpha`` for ``rgba``), the color columns of every other format's
output, so a Parquet output can be sampled again or queried by name.

Organized clouds (RGB-D frames) mark missing depth with NaN coordinates.
Those points are skipped and counted (``nan_points_skipped`` in
``describe()``). A point's record index, the second half of its id (SPEC
3), is its index among the *kept* points, in file order: both passes and
every engine see the same cloud, the one the file describes, with its
holes removed. Finding ``count`` therefore takes a pre-scan of x/y/z at
open (a memory map for binary, a parse for ascii).

Streaming: binary and ascii are read a block at a time. binary_compressed
is one LZF block for the whole cloud, stored field by field, so it cannot
be read in parts: it is decompressed once, in memory (its decompressed size
is what it costs), like PDAL's readers.pcd.
"""

from __future__ import annotations

import functools
import os
from typing import Iterator

import numpy as np
import pyarrow as pa

from ..errors import CorruptInput, NoColorError, UnsupportedFormat
from .base import ColorChunk, PointChunk, Source, columns_to_arrow, rows
from .guard import reading

KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
DATA_KINDS = ("ascii", "binary", "binary_compressed")
MAX_HEADER = 1 << 16
BLOCK = 1 << 16  # raw records per block, the unit of the pre-scan's checkpoints
LZF_MAX_RATIO = 100  # an LZF back-reference of 3 bytes expands to at most 264


def lzf_decompress(src, out) -> int:
    """Decode LZF ``src`` into ``out``; the bytes written, or -1 on a malformed stream."""
    return _lzf_compiled()(src, out)


@functools.cache
def _lzf_compiled():
    """The LZF loop compiled by numba, on first use (importing numba costs most of a second)."""
    from numba import njit

    return njit(cache=True)(_lzf)


def _lzf(src, out):
    ip = 0
    op = 0
    n = src.shape[0]
    m = out.shape[0]
    while ip < n:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n or op + length > m:
                return -1
            for k in range(length):
                out[op + k] = src[ip + k]
            ip += length
            op += length
        else:
            length = ctrl >> 5
            ref = op - ((ctrl & 0x1F) << 8) - 1
            if ip >= n:
                return -1
            if length == 7:
                length += np.int64(src[ip])
                ip += 1
                if ip >= n:
                    return -1
            ref -= np.int64(src[ip])
            ip += 1
            length += 2
            if ref < 0 or op + length > m:
                return -1
            for k in range(length):
                out[op + k] = out[ref + k]
            op += length
    return op


MAX_COUNT = 1 << 16


class PcdHeader:
    def __init__(self, path: str):
        self.path = path
        with reading(path, "cannot read the PCD header"):
            with open(path, "rb") as f:
                raw = f.read(MAX_HEADER)
        values, pos = {}, 0
        while "DATA" not in values:
            nxt = raw.find(b"\n", pos)
            if nxt < 0:
                if not values:
                    raise UnsupportedFormat("no PCD header (no FIELDS/POINTS/DATA lines)", path)
                raise CorruptInput("PCD header has no DATA line", path)
            line = raw[pos:nxt].strip()
            pos = nxt + 1
            if not line or line.startswith(b"#"):
                continue
            try:
                words = line.decode("ascii").split()
            except UnicodeDecodeError:
                words = [""]
            if words[0] not in KEYS:
                if not values:
                    raise UnsupportedFormat("no PCD header (no FIELDS/POINTS/DATA lines)", path)
                raise CorruptInput(f"unknown PCD header line {line[:40].decode('ascii', 'replace')!r}", path)
            values[words[0]] = words[1:]
        self.data_offset = pos
        for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "DATA"):
            if key not in values:
                raise CorruptInput(f"PCD header has no {key} line", path)
        self.fields = values["FIELDS"]
        n = len(self.fields)
        self.sizes = self._ints(values["SIZE"], "SIZE")
        self.types = values["TYPE"]
        self.counts = self._ints(values.get("COUNT", ["1"] * n), "COUNT")
        if not n or not (len(self.sizes) == len(self.types) == len(self.counts) == n):
            raise CorruptInput("FIELDS, SIZE, TYPE and COUNT disagree on the number of fields", path)
        self.width = self._one(values["WIDTH"], "WIDTH")
        self.height = self._one(values.get("HEIGHT", ["1"]), "HEIGHT")
        self.points = self._one(values["POINTS"], "POINTS") if "POINTS" in values else self.width * self.height
        if values["DATA"] == [] or values["DATA"][0] not in DATA_KINDS:
            raise UnsupportedFormat(f"PCD DATA {' '.join(values['DATA'])!r} (reads {', '.join(DATA_KINDS)})", path)
        self.data = values["DATA"][0]
        formats, names, pad = [], [], 0
        for name, size, typ, count in zip(self.fields, self.sizes, self.types, self.counts):
            code = {"F": "f", "U": "u", "I": "i"}.get(typ)
            # COUNT is an array length (PCL descriptors use up to a few hundred); a huge one is corruption
            if code is None or size not in ((4, 8) if code == "f" else (1, 2, 4, 8)) or not 1 <= count <= MAX_COUNT:
                raise CorruptInput(f"field {name!r} has unsupported TYPE {typ} SIZE {size} COUNT {count}", path)
            if name == "_":  # PCL's padding: not data, and there may be several
                name, pad = f"_pad{pad}", pad + 1
            if name in names:
                raise CorruptInput(f"field {name!r} declared twice", path)
            names.append(name)
            formats.append((f"<{code}{size}", (count,)) if count > 1 else f"<{code}{size}")
        try:
            self.dtype = np.dtype({"names": names, "formats": formats})
        except ValueError as exc:
            raise CorruptInput(f"PCD fields do not make a record layout ({exc})", path) from None

    def _ints(self, words, key):
        try:
            out = [int(w) for w in words]
        except ValueError:
            raise CorruptInput(f"PCD {key} holds a non-integer", self.path) from None
        if any(v < 0 for v in out):
            raise CorruptInput(f"PCD {key} holds a negative value", self.path)
        return out

    def _one(self, words, key) -> int:
        vals = self._ints(words, key)
        if len(vals) != 1:
            raise CorruptInput(f"PCD {key} should hold one integer", self.path)
        return vals[0]


UNPACKED = ("red", "green", "blue", "alpha")


class PcdPointChunk(PointChunk):
    def __init__(self, ordinal: int, start: int, records: np.ndarray, color_field: str):
        self.ordinal = ordinal
        self.start = start
        self.records = records
        self.color_field = color_field
        self.rgb = unpack(records[color_field])

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        """The fields as columns, the packed color word as uint8 ``red``, ``green``, ``blue`` in its place (and
        ``alpha``, an ``rgba`` word's top byte): the color columns of every other format's output, which
        prism-stream, DuckDB and GeoPandas read as colors. A file that has fields of those names already
        keeps its word packed."""
        rec = self.records if mask is None else rows(self.records, mask)
        names = [n for n in rec.dtype.names if not n.startswith("_pad")]
        if set(UNPACKED) & set(names):
            return columns_to_arrow({n: rec[n] for n in names})
        columns = {}
        for n in names:
            if n != self.color_field:
                columns[n] = rec[n]
                continue
            columns["red"], columns["green"], columns["blue"] = unpack(rec[n])
            if n == "rgba":
                columns["alpha"] = (np.ascontiguousarray(rec[n]).view(np.uint32) >> 24).astype(np.uint8)
        return columns_to_arrow(columns)


def unpack(word: np.ndarray) -> tuple:
    """The 8-bit channels of packed 0x??RRGGBB words (float words by their bits)."""
    w = np.ascontiguousarray(word).view(np.uint32)
    return (((w >> 16) & 0xFF).astype(np.uint8), ((w >> 8) & 0xFF).astype(np.uint8), (w & 0xFF).astype(np.uint8))


class PcdSource(Source):
    format = "pcd"
    spills = True  # point chunks implement take; the default spill state (the chunk) pickles

    def __init__(self, path: str, ordinal: int, **_):
        self.path = path
        self.ordinal = ordinal
        self.header = h = PcdHeader(path)
        names = h.dtype.names
        color = [n for n in ("rgb", "rgba") if n in names]
        if not color:
            raise NoColorError(f"PCD has no rgb or rgba field (fields: {' '.join(h.fields)})", path)
        self.color_field = color[0]
        if h.dtype.fields[self.color_field][0].itemsize != 4:
            raise CorruptInput(f"field {self.color_field!r} is not one 32-bit word", path)
        # the columns of its colors in what to_arrow writes: the word unpacked, unless names clash
        self.color_fields = (self.color_field,) if set(UNPACKED) & set(names) else ("red", "green", "blue")
        # an unpacked rgba word's alpha: part of the color, so --keep keeps it (:func:`.columns.select_columns`)
        self.word_alpha = ("alpha",) if self.color_field == "rgba" and len(self.color_fields) == 3 else ()
        self.xyz = [n for n in ("x", "y", "z") if n in names and h.dtype.fields[n][0].kind == "f"]
        if h.points != h.width * h.height:
            raise CorruptInput(f"POINTS {h.points} is not WIDTH x HEIGHT = {h.width * h.height}", path)
        self.size = os.path.getsize(path)
        self.columns = None  # binary_compressed: every field, decompressed
        self.line_offsets = []  # ascii: byte offset of each block
        if h.data == "binary":
            need = h.data_offset + h.points * h.dtype.itemsize
            if need > self.size:
                held = (self.size - h.data_offset) // h.dtype.itemsize
                raise CorruptInput(f"header declares {h.points} points but the file holds {held}", path)
            if need < self.size:
                # PCL writes binary data to the byte; more means the records are not where the header
                # says (a header written twice...), and every point would be read from the wrong bytes
                raise CorruptInput(f"header declares {h.points} points of {h.dtype.itemsize} bytes from byte "
                                   f"{h.data_offset} (ending at byte {need}), but the file ends at byte "
                                   f"{self.size}: {self.size - need} bytes left over (a duplicated header?)", path)
        elif h.data == "binary_compressed":
            self._decompress()
        self.raw_count = h.points
        self.block_kept = self._prescan()  # kept points before each block
        self.count = int(self.block_kept[-1])
        self.nan_points = self.raw_count - self.count

    # -- raw records -----------------------------------------------------

    def _decompress(self) -> None:
        h = self.header
        with reading(self.path), open(self.path, "rb") as f:
            f.seek(h.data_offset)
            sizes = f.read(8)
            if len(sizes) < 8:
                raise CorruptInput("binary_compressed data has no size words", self.path)
            packed, unpacked = np.frombuffer(sizes, "<u4").tolist()
            expected = h.points * h.dtype.itemsize
            if unpacked != expected:
                raise CorruptInput(f"compressed data unpacks to {unpacked} bytes, {h.points} points need "
                                   f"{expected}", self.path)
            if packed > self.size - h.data_offset - 8:
                raise CorruptInput(f"compressed data of {packed} bytes runs past the end of the file", self.path)
            if expected > LZF_MAX_RATIO * packed + 1024:
                raise CorruptInput(f"{packed} compressed bytes cannot hold {expected}", self.path)
            src = np.frombuffer(f.read(packed), dtype=np.uint8)
        out = np.empty(expected, dtype=np.uint8)
        if expected and lzf_decompress(src, out) != expected:
            raise CorruptInput("binary_compressed data is not a valid LZF stream", self.path)
        # PCL stores the fields one after another: all x, then all y, ...
        self.columns, at = {}, 0
        for name in h.dtype.names:
            dt, _ = h.dtype.fields[name]
            nbytes = h.points * dt.itemsize
            col = out[at:at + nbytes].view(dt.base)
            self.columns[name] = col.reshape((h.points,) + dt.shape) if dt.shape else col
            at += nbytes

    def _raw_blocks(self, first_block: int, dtype=None) -> Iterator[tuple[int, np.ndarray]]:
        """Native records ``[b * BLOCK, ...)``, one block at a time, from block ``first_block``."""
        h = self.header
        start = first_block * BLOCK
        if h.data == "binary_compressed":
            names = h.dtype.names if dtype is None else dtype.names
            for a in range(start, h.points, BLOCK):
                b = min(h.points, a + BLOCK)
                rec = np.empty(b - a, dtype=h.dtype if dtype is None else dtype)
                for n in names:
                    rec[n] = self.columns[n][a:b]
                yield a, rec
        elif h.data == "binary":
            if h.points == 0:
                return
            view = h.dtype if dtype is None else dtype
            with reading(self.path):
                mm = np.memmap(self.path, dtype=view, mode="r", offset=h.data_offset, shape=(h.points,))
            try:
                for a in range(start, h.points, BLOCK):
                    yield a, np.array(mm[a:a + BLOCK])
            finally:
                del mm
        else:
            yield from self._ascii_blocks(first_block)

    def _ascii_blocks(self, first_block: int) -> Iterator[tuple[int, np.ndarray]]:
        h = self.header
        offset = self.line_offsets[first_block] if first_block < len(self.line_offsets) else h.data_offset
        with reading(self.path), open(self.path, "rb") as f:
            f.seek(offset)
            for a in range(first_block * BLOCK, h.points, BLOCK):
                if a // BLOCK >= len(self.line_offsets):
                    self.line_offsets.append(f.tell())
                n = min(BLOCK, h.points - a)
                lines = []
                while len(lines) < n:
                    line = f.readline()
                    if not line:
                        raise CorruptInput(f"file ends after {a + len(lines)} of the {h.points} points its "
                                           "header declares", self.path)
                    if line.strip():
                        lines.append(line)
                yield a, self._parse(lines, a)

    def _parse(self, lines, first: int) -> np.ndarray:
        h = self.header
        width = sum(h.counts)
        rows = [ln.split() for ln in lines]
        for i, row in enumerate(rows):
            if len(row) != width:
                raise CorruptInput(f"point {first + i} has {len(row)} values, the header declares {width}",
                                   self.path)
        try:
            values = np.array(rows, dtype=np.float64).reshape(len(rows), width)
        except ValueError:
            raise CorruptInput(f"a value near point {first} is not a number", self.path) from None
        out = np.empty(len(rows), dtype=h.dtype)
        col = 0
        for name, count in zip(h.dtype.names, h.counts):
            dt = h.dtype.fields[name][0].base
            v = values[:, col:col + count] if count > 1 else values[:, col]
            col += count
            if name == self.color_field:
                out[name] = ascii_color_word(v).view(dt)
            elif dt.kind == "f":
                out[name] = v.astype(dt)
            else:
                info = np.iinfo(dt)
                ok = np.isfinite(v) & (v == np.floor(v)) & (v >= info.min) & (v <= info.max)
                if not ok.all():
                    raise CorruptInput(f"field {name!r} near point {first} holds a value that is not a {dt}",
                                       self.path)
                out[name] = v.astype(dt)
        return out

    def _prescan(self) -> np.ndarray:
        """Kept (non-NaN) points before each block, and in all at the end."""
        kept = [0]
        if self.xyz and self.header.data == "binary":
            full = self.header.dtype
            dtype = np.dtype({"names": self.xyz, "formats": [full.fields[n][0] for n in self.xyz],
                              "offsets": [full.fields[n][1] for n in self.xyz], "itemsize": full.itemsize})
        else:
            dtype = None
        for _, rec in self._raw_blocks(0, dtype):
            kept.append(kept[-1] + int(self._keep(rec).sum()) if self.xyz else kept[-1] + len(rec))
        return np.asarray(kept, dtype=np.int64)

    def _keep(self, rec: np.ndarray) -> np.ndarray:
        bad = np.zeros(len(rec), dtype=bool)
        for n in self.xyz:
            bad |= np.isnan(rec[n])
        return ~bad

    def _kept_records(self, chunk_size: int, start: int, stop: int | None) -> Iterator[tuple[int, np.ndarray]]:
        stop = self.count if stop is None else min(stop, self.count)
        if stop <= start:
            return
        block = int(np.searchsorted(self.block_kept, start, side="right")) - 1
        pos = int(self.block_kept[block])
        for _, rec in self._raw_blocks(block):
            if self.xyz:
                rec = rec[self._keep(rec)]
            n = len(rec)
            a, b = max(start - pos, 0), min(stop - pos, n)
            for c in range(a, b, chunk_size):
                yield pos + c, rec[c:min(b, c + chunk_size)]
            pos += n
            if pos >= stop:
                return

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        for pos, rec in self._kept_records(chunk_size, start, stop):
            yield ColorChunk(pos, unpack(rec[self.color_field]))

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[PcdPointChunk]:
        for pos, rec in self._kept_records(chunk_size, start, stop):
            yield PcdPointChunk(self.ordinal, pos, rec, self.color_field)

    def arrow_schema(self) -> pa.Schema:
        return PcdPointChunk(self.ordinal, 0, np.zeros(0, self.header.dtype), self.color_field).to_arrow().schema

    def describe(self) -> dict:
        h = self.header
        return {
            "format": "pcd",
            "data": h.data,
            "fields": [f"{n}:{t}{s}" + (f"x{c}" if c > 1 else "") for n, t, s, c in
                       zip(h.fields, h.types, h.sizes, h.counts)],
            "width": h.width,
            "height": h.height,
            "points_declared": h.points,
            "nan_points_skipped": self.nan_points,
            "record_index": "index among the points kept (NaN points skipped)",
        }

    def close(self) -> None:
        self.columns = None


def ascii_color_word(v: np.ndarray) -> np.ndarray:
    """Packed color words from ASCII values: whole numbers are the word, anything else a float's bits."""
    v = np.asarray(v, dtype=np.float64)
    whole = np.isfinite(v) & (v == np.floor(v)) & (v >= 0) & (v < 2.0 ** 32)
    words = np.where(whole, np.where(whole, v, 0).astype(np.uint64), 0).astype(np.uint32)
    bits = v.astype(np.float32).view(np.uint32)
    return np.where(whole, words, bits).astype(np.uint32)
