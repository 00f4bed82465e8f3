"""``validate(path)``: what in a LAS/LAZ/COPC, PLY or Parquet file a reader would refuse, misread or report
wrongly, whatever wrote the file (`prism-stream check`, issue 31).

A :class:`Report` holds two lists of one-line causes: *errors*, where a reader refuses the file or reads
something else than the data (a name lost, statistics that clip the values, a CRS that does not parse), and
*warnings*, where the file reads right but says something untrue or that some readers complain about (bounds
looser than the data, trailing spaces in a PLY header). A file that cannot be read at all raises the
project's error for it (:class:`.InputNotFound`, :class:`.UnsupportedFormat`, :class:`.CorruptInput`) instead.

Points are read in chunks (``CHUNK_POINTS`` LAS records, ``BATCH_ROWS`` Parquet rows), never the whole file:
memory stays bounded whatever its size. The checks, per format:

LAS, LAZ, COPC (the header, VLRs and EVLRs parsed from the bytes, the points through laspy):

- extra-bytes descriptors (every ``LASF_Spec``/4 record): a min or max flagged valid (options bits 1, 2;
  stored raw, before the descriptor's scale and offset) must hold every point's raw value (those equal to a
  valid no_data excluded); min above max, or an integer min/max beyond +-2^53, is an error too; a valid
  range looser than the data is a warning;
- names: a second ``LASF_Spec``/4 record (readers read the first: its dimensions come out unnamed), extra
  bytes no descriptor covers, descriptors covering more than the records hold: errors; a descriptor named
  ``ExtraBytes`` (laspy's name for bytes it found no descriptor for): a warning, the real name was lost;
- point formats 6 to 10 without the WKT bit of the global encoding: error;
- a WKT record (``LASF_Projection``/2112) pyproj cannot parse: error; in a COPC, a WKT VLR (copclib 2.6 reads
  a WKT record as if it were an EVLR, 6 bytes past its start): error;
- header against the points: point count, bounds (within half a scale step), points by return: errors;
  bounds looser than the data by more than a scale step: warning;
- prism-stream provenance (the ``prism-stream``/1 VLR) with a generating software that is not prism-stream:
  warning; a provenance that is not JSON: warning;
- COPC: the ``copc``/1 info VLR first, at byte 375, version 1.4 with point format 6 to 8, a ``copc``/1000
  hierarchy EVLR whose point counts sum to the header's: errors otherwise.

PLY: trailing whitespace on a header line (PCL warns "trailing whitespaces in the header"): warning; in a
binary file, the elements' fixed-size records must fill the bytes after the header exactly (or fit, when an
element with lists follows): error.

Parquet with a ``geo`` key (GeoParquet): valid JSON, a primary column that exists, WKB encoding, a CRS
(PROJJSON) pyproj parses, a bbox that holds the data, WKB points equal to the x/y(/z) columns: errors.
"""

from __future__ import annotations

import json
import math
import os
import struct
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import CorruptInput, InputNotFound, UnsupportedFormat
from . import extension
from .guard import first_line, reading
from .arrow import to_numpy

CHUNK_POINTS = 1 << 18  # LAS records read at a time (at most 67 bytes each: 17 MiB)
BATCH_ROWS = 1 << 16  # Parquet rows read at a time
MAX_SAFE_INTEGER = (1 << 53) - 1  # JavaScript's Number.MAX_SAFE_INTEGER
FORMATS = {".las": "las", ".laz": "laz", ".copc.laz": "copc", ".ply": "ply", ".parquet": "parquet",
           ".pq": "parquet", ".xyz": "xyz"}


@dataclass
class Report:
    """What :func:`validate` found in one file: ``errors`` (a reader refuses or misreads it) and
    ``warnings`` (it reads right, but something in it is untrue or draws complaints)."""

    path: str
    format: str
    errors: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors

    def error(self, cause: str) -> None:
        self.errors.append(cause)

    def warn(self, cause: str) -> None:
        self.warnings.append(cause)

    def lines(self) -> list[str]:
        """``PATH: error: cause`` and ``PATH: warning: cause``, errors first."""
        from ..errors import printable

        path = printable(self.path)
        return ([f"{path}: error: {c}" for c in self.errors]
                + [f"{path}: warning: {c}" for c in self.warnings])

    def as_dict(self) -> dict:
        return {"path": self.path, "format": self.format, "errors": list(self.errors),
                "warnings": list(self.warnings)}


def validate(path) -> Report:
    """Check one file (LAS, LAZ, COPC, PLY, Parquet, XYZ); raise the project's error when it cannot be read."""
    from ..run.remote import is_remote

    path = os.fspath(path)
    if is_remote(path):
        raise UnsupportedFormat("check reads local files only: copy it here first", path)
    if not os.path.exists(path):
        raise InputNotFound("no such file", path)
    if not os.path.isfile(path):
        raise UnsupportedFormat("not a regular file", path)
    if not os.access(path, os.R_OK):
        raise InputNotFound("cannot be read (permission denied)", path)
    fmt = FORMATS.get(extension(path))
    if fmt is None:
        raise UnsupportedFormat(f"check reads LAS, LAZ, COPC, PLY, Parquet and XYZ files, not "
                                f"{extension(path) or 'files without an extension'!r}", path)
    report = Report(path, fmt)
    if fmt in ("las", "laz", "copc"):
        _check_las(path, report)
    elif fmt == "ply":
        _check_ply(path, report)
    elif fmt == "xyz":
        _check_xyz(path, report)
    else:
        _check_parquet(path, report)
    return report


# ---------------------------------------------------------------------------------------------------- LAS


@dataclass
class _Record:
    """A VLR or an EVLR: where it is and, for the kinds checked here, its payload."""

    kind: str  # "VLR" or "EVLR"
    index: int
    start: int  # where its header starts
    user_id: str
    record_id: int
    length: int
    data: bytes | None = None

    def is_(self, user_id: str, record_id: int) -> bool:
        return self.user_id == user_id and self.record_id == record_id

    @property
    def where(self) -> str:
        return f"{self.kind} {self.index + 1}"


_READ_PAYLOAD = {("LASF_Spec", 4), ("LASF_Projection", 2112), ("copc", 1), ("prism-stream", 1)}
_MAX_PAYLOAD = 16 << 20


def _records(f, end: int, start: int, count: int, kind: str, report: Report) -> list[_Record]:
    """The ``count`` VLRs or EVLRs from byte ``start``, each ending by byte ``end`` (the point data's start for
    VLRs, the file's end for EVLRs)."""
    from ..errors import printable

    head, fmt = (54, "<H16sHH") if kind == "VLR" else (60, "<H16sHQ")
    limit = "the start of the point data" if kind == "VLR" else "the end of the file"
    out, pos = [], start
    for i in range(count):
        f.seek(pos)
        raw = f.read(head)
        if len(raw) < head or pos + head > end:
            report.error(f"the header declares {count} {kind}s, but {kind} {i + 1} would start at byte {pos}, "
                         f"past {limit} (byte {end})")
            break
        _, uid, rid, length = struct.unpack_from(fmt, raw)
        rec = _Record(kind, i, pos, printable(uid.split(b"\0", 1)[0].decode("ascii", "replace")), rid, length)
        if pos + head + length > end:
            report.error(f"{rec.where} ({rec.user_id}/{rid}) of {length} bytes runs past {limit} (byte {end}): "
                         f"the header declares {count} {kind}s")
            break
        if (rec.user_id, rid) in _READ_PAYLOAD and length <= _MAX_PAYLOAD:
            rec.data = f.read(length)
        out.append(rec)
        pos += head + length
    return out


_TYPES = {1: "u1", 2: "i1", 3: "u2", 4: "i2", 5: "u4", 6: "i4", 7: "u8", 8: "i8", 9: "f4", 10: "f8"}


@dataclass
class _Descriptor:
    name: str
    data_type: int
    options: int
    raw: bytes
    record: _Record
    offset: int = 0  # within the point's extra bytes

    @property
    def dtype(self) -> str | None:
        return _TYPES.get((self.data_type - 1) % 10 + 1) if 1 <= self.data_type <= 30 else None

    @property
    def count(self) -> int:
        return 1 if self.data_type <= 10 else 2 if self.data_type <= 20 else 3

    @property
    def size(self) -> int | None:
        if self.data_type == 0:
            return self.options  # undocumented bytes: the options field holds their number
        return None if self.dtype is None else np.dtype(self.dtype).itemsize * self.count

    def stored(self, at: int) -> list:
        """The count values of the 24-byte field at ``at`` (no_data 40, min 64, max 88): each in 8 bytes, as
        an unsigned or signed 64-bit integer or a double, by the data type."""
        code = {"u": "<Q", "i": "<q", "f": "<d"}[self.dtype[0]]
        return [struct.unpack_from(code, self.raw, at + 8 * i)[0] for i in range(self.count)]


def _descriptors(records: list[_Record], report: Report) -> list[_Descriptor]:
    out = []
    for rec in records:
        data = rec.data or b""
        if len(data) % 192:
            report.error(f"extra-bytes record ({rec.where}, LASF_Spec/4) holds {len(data)} bytes, not a whole "
                         "number of 192-byte descriptors")
        for i in range(len(data) // 192):
            raw = data[192 * i:192 * (i + 1)]
            name = raw[4:36].split(b"\0", 1)[0].decode("ascii", "replace")
            out.append(_Descriptor(name, raw[2], raw[3], raw, rec))
    return out


def _num(v) -> str:
    if isinstance(v, float) and v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return str(v)


def _check_names(descriptors: list[_Descriptor], spec: list[_Record], extra: int, report: Report) -> bool:
    """Names and byte coverage; True when every descriptor's bytes are known (the statistics can be read)."""
    offset, known = 0, True
    for d in descriptors:
        d.offset = offset
        if d.size is None:
            report.error(f"descriptor {d.name!r} has data type {d.data_type}, not one of LAS 1.4's (0 to 30): "
                         "the bytes after it cannot be placed")
            known = False
            break
        offset += d.size
    if len(spec) > 1:
        later = [d for d in descriptors if d.record is not spec[0]]
        what = ", ".join(f"{d.name!r} (extra bytes {d.offset}..{d.offset + d.size - 1})" for d in later
                         if d.size is not None) or "none"
        report.error(f"{len(spec)} extra-bytes records (LASF_Spec/4: {', '.join(r.where for r in spec)}): laspy "
                     f"and most readers read the first only, so the dimensions of the others come out unnamed "
                     f"('ExtraBytes' in laspy): {what}")
    if known and offset < extra:
        report.error(f"extra bytes {offset}..{extra - 1} of each point ({extra - offset} of {extra}) have no "
                     "descriptor: readers name them 'ExtraBytes' or drop them")
    elif known and offset > extra:
        report.error(f"the extra-bytes descriptors describe {offset} bytes per point, the records hold {extra}")
        known = False
    for d in descriptors:
        if d.name == "ExtraBytes":
            report.warn("descriptor 'ExtraBytes' is the name laspy gives extra bytes it found no descriptor for: "
                        "the dimension's own name was lost on the way (written from a file whose name was in a "
                        "second LASF_Spec/4 record, or had none)")
    return known


class _Stats:
    """Running min/max of every descriptor's raw values (those equal to its valid no_data left out)."""

    def __init__(self, descriptors: list[_Descriptor], std: int):
        self.items = [d for d in descriptors if d.dtype is not None and d.options & 0b110]
        self.std = std
        self.lo = {id(d): [None] * d.count for d in self.items}
        self.hi = {id(d): [None] * d.count for d in self.items}

    def add(self, records: np.ndarray) -> None:
        if not self.items or not len(records):
            return
        raw = records.view(np.uint8).reshape(len(records), records.dtype.itemsize)
        for d in self.items:
            a = self.std + d.offset
            values = np.ascontiguousarray(raw[:, a:a + d.size]).view("<" + d.dtype).reshape(len(records), d.count)
            nodata = d.stored(40) if d.options & 1 else None
            for i in range(d.count):
                v = values[:, i]
                if nodata is not None:
                    v = v[v.astype(np.float64) != nodata[i]] if d.dtype[0] == "f" else v[v != nodata[i]]
                if d.dtype[0] == "f":
                    v = v[~np.isnan(v)]
                if not len(v):
                    continue
                lo, hi = v.min().item(), v.max().item()
                cur = self.lo[id(d)][i]
                self.lo[id(d)][i] = lo if cur is None else min(cur, lo)
                cur = self.hi[id(d)][i]
                self.hi[id(d)][i] = hi if cur is None else max(cur, hi)

    def report(self, report: Report, points: int) -> None:
        for d in self.items:
            has_min, has_max = bool(d.options & 2), bool(d.options & 4)
            mins, maxs = d.stored(64), d.stored(88)
            for i in range(d.count):
                name = d.name if d.count == 1 else f"{d.name}[{i}]"
                lo, hi = mins[i], maxs[i]
                if d.dtype[0] != "f":
                    big = [f"{w} {_num(v)}" for w, v, on in (("min", lo, has_min), ("max", hi, has_max))
                           if on and abs(v) > MAX_SAFE_INTEGER]
                    if big:
                        report.error(f"descriptor {name!r}: {', '.join(big)} flagged valid is beyond +-2^53: the "
                                     "npm copc reader (web viewers) throws 'Cannot convert bigint to number'")
                stated = (f"min = max = {_num(lo)}" if has_min and has_max and lo == hi else
                          ", ".join(f"{w} {_num(v)}" for w, v, on in (("min", lo, has_min), ("max", hi, has_max))
                                    if on))
                if has_min and has_max and lo > hi:
                    report.error(f"descriptor {name!r}: min {_num(lo)} > max {_num(hi)} flagged valid")
                    continue
                actual_lo, actual_hi = self.lo[id(d)][i], self.hi[id(d)][i]
                if not points or actual_lo is None:
                    continue  # no points (or every one no_data): nothing to hold
                values = (f"values run {_num(actual_lo)}..{_num(actual_hi)}" if actual_lo != actual_hi
                          else f"every value is {_num(actual_lo)}")
                if (has_min and lo > actual_lo) or (has_max and hi < actual_hi):
                    report.error(f"descriptor {name!r}: {stated} flagged valid, {values} (readers that trust "
                                 "the statistics clip or misscale them)")
                elif (has_min and lo < actual_lo) or (has_max and hi > actual_hi):
                    report.warn(f"descriptor {name!r}: {stated} flagged valid, looser than the data: {values}")


def _check_las(path: str, report: Report) -> None:
    import laspy

    from .las import check_header  # the structural checks every read makes first: a refusal raises

    check_header(path)
    size = os.path.getsize(path)
    with reading(path, "cannot read the LAS header"), open(path, "rb") as f:
        raw = f.read(375)
        major, minor = raw[24], raw[25]
        genc = struct.unpack_from("<H", raw, 6)[0]
        software = raw[58:90].split(b"\0", 1)[0].decode("ascii", "replace")
        header_size, offset, nvlr = struct.unpack_from("<HII", raw, 94)
        pf = raw[104] & 0x3F
        record_len, legacy_count = struct.unpack_from("<HI", raw, 105)
        legacy_returns = list(struct.unpack_from("<5I", raw, 111))
        scales = struct.unpack_from("<3d", raw, 131)
        offsets = struct.unpack_from("<3d", raw, 155)
        mx, mn_x, my, mn_y, mz, mn_z = struct.unpack_from("<6d", raw, 179)
        box_lo, box_hi = (mn_x, mn_y, mn_z), (mx, my, mz)
        v14 = (major, minor) >= (1, 4) and len(raw) >= 375
        count, returns = legacy_count, legacy_returns
        evlrs = []
        vlrs = _records(f, offset, header_size, nvlr, "VLR", report)
        if v14:
            evlr_start, nevlr, count64 = struct.unpack_from("<QIQ", raw, 235)
            count = count64 or legacy_count
            returns = list(struct.unpack_from("<15Q", raw, 255))
            if legacy_count and legacy_count != count:
                report.error(f"legacy point count {legacy_count} differs from the point count {count}")
            if nevlr:
                evlrs = _records(f, size, evlr_start, nevlr, "EVLR", report)
        records = vlrs + evlrs

        # copc: the info VLR, its place, the hierarchy
        copc_info = [r for r in records if r.is_("copc", 1)]
        copc = bool(copc_info) or report.format == "copc"
        if copc:
            report.format = "copc"
            _check_copc(f, size, (vlrs, evlrs), copc_info, ((major, minor), pf, count), report)

    # 3: the WKT bit
    if 6 <= pf <= 10 and not genc & 0x10:
        report.error(f"point format {pf} without the WKT bit (bit 4) of the global encoding: LAS 1.4 requires it "
                     "for formats 6 to 10, and readers that honour it look for GeoTIFF keys (or no CRS)")
    # 4: WKT records
    from pyproj import CRS

    for r in records:
        if not r.is_("LASF_Projection", 2112) or r.data is None:
            continue
        text = r.data.split(b"\0", 1)[0]
        if not text.strip():
            report.warn(f"WKT record ({r.where}, LASF_Projection/2112) is empty: readers find no CRS in it")
        else:
            try:
                CRS.from_wkt(text.decode("utf-8"))
            except Exception as exc:  # noqa: BLE001 - pyproj's CRSError, a decoding error: the record is unusable
                cause = first_line(exc)
                report.error(f"WKT record ({r.where}, LASF_Projection/2112) does not parse as a CRS: "
                             f"{cause[:100]}{'...' if len(cause) > 100 else ''}")
        if copc and r.kind == "VLR":
            report.error(f"WKT record as a VLR ({r.where}) in a COPC: copclib 2.6 reads a WKT VLR 6 bytes past its "
                         "start and fails; write it as an EVLR")
    # 6: provenance against the generating software
    for r in records:
        if r.is_("prism-stream", 1) and r.data is not None:
            try:
                json.loads(r.data)
            except ValueError:
                report.warn(f"prism-stream provenance ({r.where}) is not JSON")
            if not software.startswith("prism-stream"):
                report.warn(f"carries prism-stream provenance ({r.where}) but its generating software is "
                            f"{software!r} (copied from an input?): tools that show who wrote the file name "
                            "another program")

    # 2: names; 1, 5: the points
    try:
        std = laspy.PointFormat(pf).size
    except Exception:  # noqa: BLE001 - laspy refuses the format id: no reader will decode the points
        raise CorruptInput(f"point format {pf} is not a LAS point format (0 to 10)", path) from None
    extra = record_len - std
    if extra < 0:
        raise CorruptInput(f"records of {record_len} bytes are shorter than point format {pf}'s {std}", path)
    spec = [r for r in records if r.is_("LASF_Spec", 4)]
    descriptors = _descriptors(spec, report)
    known = _check_names(descriptors, spec, extra, report)
    stats = _Stats(descriptors if known else [], std)
    n = 0
    lo = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
    by_return = np.zeros(16, dtype=np.int64)
    with reading(path, "cannot read the points"), laspy.open(path) as reader:
        for chunk in reader.chunk_iterator(CHUNK_POINTS):
            records_ = chunk.array
            if records_.dtype.itemsize != record_len:
                raise CorruptInput(f"laspy reads {records_.dtype.itemsize}-byte records, the header says "
                                   f"{record_len}", path)
            n += len(records_)
            if not len(records_):
                continue
            for i, axis in enumerate("XYZ"):
                a = records_[axis]
                lo[i] = min(lo[i], int(a.min()))
                hi[i] = max(hi[i], int(a.max()))
            by_return += np.bincount(np.asarray(chunk.return_number, dtype=np.int64), minlength=16)[:16]
            stats.add(records_)
    if n != count:
        report.error(f"header declares {count} points, the data holds {n}")
    stats.report(report, n)
    from .las import grid_fault  # here: las imports laspy, which `check` loads only for LAS files

    fault = grid_fault(scales, offsets)
    if fault:
        report.error(f"header {fault}: no reader decodes its coordinates")
    elif n:
        _check_bounds(lo, hi, scales, offsets, box_lo, box_hi, report)
        data = [int(c) for c in by_return[1:1 + len(returns)]]
        if data != [int(c) for c in returns]:
            report.error(f"points by return in the header ({_counts(returns)}) differ from the data "
                         f"({_counts(data)})")


def _counts(values) -> str:
    """Counts by return, up to the last that is not zero."""
    last = max([i + 1 for i, c in enumerate(values) if c] or [1])
    return ", ".join(str(int(c)) for c in values[:last])


def _check_bounds(lo, hi, scales, offsets, box_lo, box_hi, report: Report) -> None:
    held, loose = [], []
    for i, axis in enumerate("xyz"):
        s, o = scales[i], offsets[i]
        if not s:
            continue
        # in steps of the grid: the header's bounds as raw integers
        hlo, hhi = (box_lo[i] - o) / s, (box_hi[i] - o) / s
        decimals = max(0, min(12, -math.floor(math.log10(abs(s))))) if s else 6
        text = (f"{axis} runs {lo[i] * s + o:.{decimals}f}..{hi[i] * s + o:.{decimals}f}, header says "
                f"{box_lo[i]:.{decimals}f}..{box_hi[i]:.{decimals}f}")
        if lo[i] < hlo - 0.5 - 1e-6 or hi[i] > hhi + 0.5 + 1e-6:
            held.append(text)
        elif lo[i] > hlo + 1 + 1e-6 or hi[i] < hhi - 1 - 1e-6:
            loose.append(text)
    if held:
        report.error("header bounds do not hold every point: " + "; ".join(held))
    if loose:
        report.warn("header bounds looser than the data by more than a scale step: " + "; ".join(loose))


_COPC_INFO = struct.Struct("<5d2Q2d11Q")
_COPC_ENTRY = struct.Struct("<4iQ2i")


def _check_copc(f, size: int, records: tuple, info, header: tuple, report: Report) -> None:
    """A COPC file's own promises; ``records``: (VLRs, EVLRs); ``header``: (version, point format, count)."""
    vlrs, evlrs = records
    version, pf, count = header
    if not info:
        report.error("named .copc.laz but holds no COPC info VLR (copc/1): a plain LAZ, no octree to stream")
        return
    first = vlrs[0] if vlrs else None
    if first is not info[0] or first.start != 375:
        report.error(f"the COPC info VLR (copc/1) is {info[0].where} at byte {info[0].start}: COPC requires it "
                     "first, at byte 375")
    if version != (1, 4) or pf not in (6, 7, 8):
        report.error(f"COPC requires LAS 1.4 with point format 6, 7 or 8, not {version[0]}.{version[1]} format {pf}")
    data = info[0].data or b""
    if len(data) < _COPC_INFO.size:
        report.error(f"the COPC info VLR holds {len(data)} bytes, not {_COPC_INFO.size}")
        return
    root_offset, root_size = _COPC_INFO.unpack_from(data)[5:7]
    hierarchy = [r for r in evlrs if r.is_("copc", 1000)]
    if not hierarchy:
        report.error("no COPC hierarchy EVLR (copc/1000): readers find no node")
        return
    h = hierarchy[0]
    if not (h.start + 60 <= root_offset and root_offset + root_size <= h.start + 60 + h.length):
        report.error(f"the COPC root hierarchy page (bytes {root_offset}..{root_offset + root_size}) lies outside "
                     f"the hierarchy EVLR")
        return
    total, pages, seen = 0, [(root_offset, root_size)], set()
    while pages:
        at, length = pages.pop()
        if (at, length) in seen or at + length > size or length % _COPC_ENTRY.size:
            report.error(f"COPC hierarchy page at byte {at} ({length} bytes) is out of the file, repeated or "
                         "not whole entries")
            return
        seen.add((at, length))
        f.seek(at)
        page = f.read(length)
        for entry in _COPC_ENTRY.iter_unpack(page):
            offset, byte_size, points = entry[4:]
            if points == -1:
                pages.append((offset, byte_size))
            elif points > 0:
                total += points
    if total != count:
        report.error(f"the COPC hierarchy's nodes hold {total} points, the header declares {count}")


# ---------------------------------------------------------------------------------------------------- PLY


def _check_ply(path: str, report: Report) -> None:
    from .ply import provenance_text, read_header

    header = read_header(path)  # raises for a header no reader takes
    with open(path, "rb") as f:
        raw = f.read(header.data_offset)
    lines = raw.split(b"\n")
    padded = [(i + 1, ln.rstrip(b"\r")) for i, ln in enumerate(lines) if ln.rstrip(b"\r") != ln.rstrip()]
    if padded:
        n, first = padded[0]
        shown = first.decode("ascii", "replace")
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        report.warn(f"{len(padded)} header line(s) end in whitespace (line {n}: {shown!r}): PCL warns "
                    "\"trailing whitespaces in the header\", stricter readers refuse the line")
    if header.format == "ascii":  # one record a line: the data lines against the declared counts
        declared = sum(el.count for el in header.elements)
        with open(path, "rb") as f:
            f.seek(header.data_offset)
            held = sum(1 for line in f if line.strip())
        if held != declared:
            counts = ", ".join(f"{el.name} {el.count}" for el in header.elements)
            report.error(f"the header declares {declared} records ({counts}), the file holds {held} lines of data "
                         "(cut short, or the counts are wrong)")
    else:
        from .ply import FORMATS, element_bytes

        size = os.path.getsize(path)
        follows = size - header.data_offset
        need, walked = 0, None
        for el in header.elements:  # the list elements walked (a mesh's faces), as a reader would read them
            if not el.has_lists:
                need += el.count * sum(np.dtype(p.type).itemsize for p in el.properties)
                continue
            try:
                need += element_bytes(path, el, FORMATS[header.format], header.data_offset + need, size)
            except CorruptInput as exc:
                walked = f"{exc.args[0]} (after {need} bytes of data)"
                break
        sizes = ", ".join(f"element {el.name} {el.count} x {sum(np.dtype(p.type).itemsize for p in el.properties)} "
                          "bytes" for el in header.elements if not el.has_lists)
        if walked is not None:
            report.error(f"{walked}: the element counts do not match the data, or the file is cut")
        elif need != follows:
            report.error(f"{sizes or 'the elements'} need {need} bytes, {follows} follow the header (the counts do "
                         "not match the data)")
    text = provenance_text(header.comments)
    if text is not None:
        try:
            json.loads(text)
        except ValueError:
            report.warn("prism-stream provenance comment is not JSON")
    for c in header.comments:
        if len(c) + len("comment \n") > 1023:
            report.warn(f"a comment line of {len(c) + 8} bytes: Open3D's PLY reader (rply) aborts on lines over "
                        "1,023")
            break


# ---------------------------------------------------------------------------------------------------- XYZ


def _check_xyz(path: str, report: Report) -> None:
    """What prism-stream's own reader refuses is raised (a line of another width, a value that is not a
    number, an integer color outside 0..65535: exit 6, as for any corrupt file); then the ``//`` header line's
    names against the columns (error: readers that take the names, CloudCompare's among them, misplace every
    column after a missing or extra one), colors past 8 bits (warning: text readers take 0..255), and the
    prism-stream provenance line as JSON (warning)."""
    from .xyz import XyzSource, _is_point
    from .xyzout import PROVENANCE_LINE, read_provenance

    source = XyzSource(path, 0)  # counts the points, one width, colors that are numbers
    brightest = 0.0
    for chunk in source.point_chunks(CHUNK_POINTS):
        if len(chunk.rgb[0]):
            brightest = max(brightest, *(float(np.max(c)) for c in chunk.rgb))
    names = None
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("utf-8", "replace").strip()
            if _is_point(raw) or (line.startswith("//") and not line.startswith(PROVENANCE_LINE.strip())):
                names = line[2:].replace(",", " ").split() if line.startswith("//") else None
                break
    if names is not None and len(names) != source.width:
        report.error(f"the header line names {len(names)} columns ({' '.join(names[:8])}"
                     f"{' ...' if len(names) > 8 else ''}), the points hold {source.width}: a reader that takes "
                     "the names puts the values after the first difference under the wrong ones")
    if source.color_kind == "int" and brightest > 255:
        report.warn(f"colors up to {brightest:g}: text readers (CloudCompare among them) take R G B as 0..255")
    try:
        read_provenance(path)
    except ValueError:
        report.warn("prism-stream provenance line is not JSON")


# ------------------------------------------------------------------------------------------------ Parquet


def _check_parquet(path: str, report: Report) -> None:
    import pyarrow.parquet as pq

    from .columns import numeric_axes, wkb_typed
    from .parquet import PROVENANCE_KEY

    with reading(path, "cannot read the Parquet file"):
        pf = pq.ParquetFile(path)
        meta = dict(pf.metadata.metadata or {})
        meta.update(pf.schema_arrow.metadata or {})
    if PROVENANCE_KEY in meta:
        try:
            json.loads(meta[PROVENANCE_KEY])
        except ValueError:
            report.warn("prism-stream provenance (key 'prism_stream') is not JSON")
    # every page decoded, a batch at a time (as check reads a LAS file's every point): a garbled page is what a
    # run would meet half-way, exit 6
    with reading(path, "cannot read the Parquet file"):
        for _ in pf.iter_batches(batch_size=1 << 16, use_threads=False):
            pass
    if b"geo" not in meta:
        return
    try:
        geo = json.loads(meta[b"geo"])
    except ValueError as exc:
        report.error(f"GeoParquet 'geo' metadata is not JSON ({exc})")
        return
    if not isinstance(geo, dict):
        report.error("GeoParquet 'geo' metadata is not a JSON object")
        return
    schema = pf.schema_arrow
    primary = geo.get("primary_column")
    columns = geo.get("columns") if isinstance(geo.get("columns"), dict) else {}
    if primary not in schema.names:
        report.error(f"GeoParquet primary column {primary!r} is not a column of the file")
        return
    col = columns.get(primary)
    if not isinstance(col, dict):
        report.error(f"GeoParquet 'columns' has no entry for the primary column {primary!r}")
        return
    if col.get("encoding") != "WKB":
        report.error(f"GeoParquet column {primary!r} has encoding {col.get('encoding')!r}, not 'WKB'")
        return
    kind = schema.field(primary).type
    if not wkb_typed(kind):
        report.error(f"GeoParquet primary column {primary!r} holds {kind}, not WKB (binary)")
        return
    if "crs" in col and col["crs"] is not None:
        from pyproj import CRS

        try:
            if not isinstance(col["crs"], dict):
                raise ValueError("not a PROJJSON object")
            CRS.from_json_dict(col["crs"])
        except Exception as exc:  # noqa: BLE001 - pyproj's CRSError and kin: no CRS a reader can use
            report.error(f"GeoParquet CRS of {primary!r} does not parse as PROJJSON ({first_line(exc)})")
    bbox = col.get("bbox")
    if bbox is not None and not (isinstance(bbox, list) and len(bbox) in (4, 6)
                                 and all(isinstance(v, (int, float)) for v in bbox)):
        report.error(f"GeoParquet bbox of {primary!r} is not 4 or 6 numbers: {bbox!r}")
        bbox = None
    # the x, y, z a run reads (numeric, the lower-case name first: formats.columns.kept_coordinates)
    xyz = numeric_axes(schema, leave=(primary,))
    xyz = xyz if xyz[0] and xyz[1] else [None, None, None]
    wanted = [primary] + [c for c in xyz if c]
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    differ, first_row, row, other = 0, None, 0, 0
    with reading(path, "cannot read the Parquet data"):
        for batch in pf.iter_batches(batch_size=BATCH_ROWS, columns=wanted):
            points, valid, has_z, others = _wkb_points(batch.column(0))
            other += others
            ok = valid & ~np.isnan(points[:, 0])
            if ok.any():
                with warnings.catch_warnings():  # 2D points alone: z is all NaN, as meant
                    warnings.simplefilter("ignore", RuntimeWarning)
                    lo = np.fmin(lo, np.nanmin(np.where(ok[:, None], points, np.nan), axis=0))
                    hi = np.fmax(hi, np.nanmax(np.where(ok[:, None], points, np.nan), axis=0))
            if xyz[0]:
                axes = 3 if (xyz[2] and has_z) else 2
                cols = np.column_stack([to_numpy(batch.column(c)).astype(np.float64)
                                        for c in xyz[:axes]])
                # (a 2D point beside points with Z has no z to differ: its NaN is left out)
                bad = valid & np.any((cols != points[:, :axes]) & ~np.isnan(points[:, :axes]), axis=1)
                if bad.any():
                    differ += int(bad.sum())
                    first_row = first_row if first_row is not None else row + int(np.flatnonzero(bad)[0])
            row += batch.num_rows
    if differ:
        report.error(f"the WKB points of {primary!r} differ from the columns {', '.join(c for c in xyz if c)} at "
                     f"{differ} of {row} rows (first: row {first_row})")
    if other:
        report.warn(f"{other} geometries of {primary!r} are not WKB points: the bbox and the x/y/z columns were "
                    "checked against the points only")
    if bbox is not None and np.isfinite(lo[0]):
        box_lo, box_hi = (bbox[:2], bbox[2:]) if len(bbox) == 4 else (bbox[:3], bbox[3:])
        k = len(box_lo)
        if np.isnan(lo[2]):
            k = 2
        if any(lo[i] < box_lo[i] or hi[i] > box_hi[i] for i in range(k)):
            runs = ", ".join(f"{'xyz'[i]} {_num(float(lo[i]))}..{_num(float(hi[i]))}" for i in range(k))
            report.error(f"GeoParquet bbox {bbox} of {primary!r} does not hold the data ({runs})")


def _wkb_points(array) -> tuple:
    """(n x 3 float64 coordinates, NaN where absent; mask of the rows that are points; any Z; rows that are
    other geometries) of a WKB column chunk, as a run reads them (:func:`.geo.wkb_rows`)."""
    from .geo import wkb_rows

    out, valid, has_z, _ = wkb_rows(array)
    out[valid & ~has_z, 2] = np.nan  # a 2D point has no z to compare
    return out, valid, bool(has_z.any()), int(len(array) - array.null_count - valid.sum())


