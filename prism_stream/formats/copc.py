"""COPC output (``.copc.laz``): the sample as a Cloud Optimized Point Cloud.

A COPC file is a LAZ 1.4 file (point format 6, 7 or 8) whose points are
grouped by the nodes of an octree, one LAZ chunk per node, with an index
(the hierarchy EVLR) that tells a reader where each node's chunk starts.
Viewers (QGIS, Potree) and PDAL stream the coarse levels first.

The sink writes the sample as an uncompressed LAS file in its staging
folder (the ordinary LAS/LAZ writers, so header, VLRs, CRS and extra bytes
are what a ``.las`` output would hold), then :func:`build` turns that file
into COPC in a few passes over it, holding at most ``GROUP_POINTS`` points:

- the cube: the bounding box's center, half its largest side;
- the octree: a node holds about ``MAX_NODE_POINTS`` points at most.
  Counting passes (one per level) find the nodes with more points than
  that below them; those are split. Each point draws a uniform number u
  from a hash of its position in the file; a split node X whose parent took
  the points with u < T_parent takes those with T_parent <= u < T_X,
  T_X = T_parent + MAX_NODE_POINTS / n_X, about MAX_NODE_POINTS of them, a
  uniform thinning of its region: the level of detail. A node that is not
  split takes every point left in it;
- the nodes are written in breadth-first order, each as one LAZ chunk
  compressed by lazrs, then the hierarchy (one page), then the input's
  EVLRs.

Point formats 2, 3 and 5 become 7 (8 when the input has NIR), 10 becomes 8:
COPC allows 6 to 8 only. A CRS held in GeoTIFF keys is stored as WKT (COPC,
as LAS 1.4 for these formats, requires WKT). Each change is noted.
"""

from __future__ import annotations

import copy
import os
import struct

import laspy
import numpy as np

from ..core.kernels import splitmix64_np
from ..errors import OutputError, PrismError, UsageError
from ..run import staging
from . import extrabytes
from .base import AtomicFile, Sink, Source, WriteOptions
from .guard import describe
from .las import COPC_INPUT_NOTE, LasSink, _is_copc, all_las, left_out

MAX_NODE_POINTS = 100_000
MAX_DEPTH = 19  # (d, x, y, z) packed in one int64: 3 * 19 bits of cell, the depth above them
READ_POINTS = 1 << 20
GROUP_POINTS = 4 << 20  # points held while a run of nodes is compressed
ROOT_CELLS = 128  # COPC's spacing: the root node's side over this

_INFO = struct.Struct("<5d2Q2d11Q")  # the COPC info VLR, 160 bytes
_ENTRY = struct.Struct("<4iQ2i")  # a hierarchy entry: key (d, x, y, z), offset, byte size, point count


def copc_point_format(pf: laspy.PointFormat) -> int:
    """COPC's point format for a LAS point format: 8 with NIR, 7 with RGB, 6 otherwise."""
    names = set(pf.standard_dimension_names)
    if "nir" in names:
        return 8
    if "red" in names:
        return 7
    return 6


def _uniform(first: int, n: int) -> np.ndarray:
    """u in [0, 1) for the points first .. first + n - 1 of the file (splitmix64 of the position)."""
    z = splitmix64_np(np.arange(first, first + n, dtype=np.uint64))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _bounds(lo: np.ndarray, hi: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> tuple:
    """The (mins, maxs) of points whose integer coordinates span lo..hi (a scale may be negative)."""
    a, b = lo * scales + offsets, hi * scales + offsets
    return np.minimum(a, b), np.maximum(a, b)


class _Cube:
    """The octree's cube over the points, and the cells of a point at any depth.

    The cube starts at the points' minimum corner and its side is their largest extent (as PDAL and
    untwine build it, and as copclib assumes when it derives a node's box from the LAS header).
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, scales: np.ndarray, offsets: np.ndarray):
        self.scales = scales
        self.offsets = offsets
        self.low, maxs = _bounds(lo, hi, scales, offsets)
        side = float(np.max(maxs - self.low))
        self.halfsize = side / 2 if side > 0 else float(np.max(np.abs(scales)))  # one point: any cube holds it
        self.center = self.low + self.halfsize
        # below this depth a cell is narrower than the coordinate grid: splitting cannot separate points
        step = float(np.min(np.abs(scales)))
        self.max_depth = int(np.clip(np.ceil(np.log2(max(side / step, 1.0))), 0, MAX_DEPTH))

    def cells(self, XYZ: np.ndarray) -> np.ndarray:
        """The (n, 3) cell indices of the points at MAX_DEPTH (clamped into the cube)."""
        size = 1 << MAX_DEPTH
        xyz = XYZ * self.scales + self.offsets
        idx = np.floor((xyz - self.low) / (2 * self.halfsize) * size)
        return np.clip(idx, 0, size - 1).astype(np.int64)

    @staticmethod
    def key(cells: np.ndarray, depth: int) -> np.ndarray:
        """One int64 per point naming its node at ``depth`` (sorted by depth, then x, y, z)."""
        c = cells >> (MAX_DEPTH - depth)
        return (np.int64(depth) << 58) | (c[:, 0] << (2 * depth)) | (c[:, 1] << depth) | c[:, 2]


def _unkey(key: int) -> tuple[int, int, int, int]:
    d = key >> 58
    mask = (1 << d) - 1 if d else 0
    return d, (key >> (2 * d)) & mask, (key >> d) & mask, key & mask


def _parent(key: int) -> int:
    """The key of a node's parent (the root's own for the root)."""
    d, x, y, z = _unkey(key)
    if d == 0:
        return key
    d, x, y, z = d - 1, x >> 1, y >> 1, z >> 1
    return (d << 58) | (x << (2 * d)) | (y << d) | z


def _chunks(path: str):
    """(first point, XYZ as an (n, 3) int64 array, the records) of each chunk of the staged LAS."""
    with laspy.open(path) as reader:
        first = 0
        for points in reader.chunk_iterator(READ_POINTS):
            XYZ = np.stack([np.asarray(points.X), np.asarray(points.Y), np.asarray(points.Z)], axis=1).astype(np.int64)
            yield first, XYZ, points
            first += len(points)


class _Octree:
    """The split nodes of each depth and their thresholds; which node each point goes to."""

    def __init__(self, path: str, n: int, cube: _Cube, max_points: int):
        self.cube = cube
        self.split: list[np.ndarray] = []  # per depth: the sorted keys of the nodes split there
        self.threshold: list[np.ndarray] = []  # per depth: T of each of them
        if n <= max_points or cube.max_depth == 0:
            return
        self.split.append(np.array([0], dtype=np.int64))
        self.threshold.append(np.array([max_points / n]))
        for depth in range(1, cube.max_depth):  # a node at max_depth takes all it holds: never split
            parents, parent_t = self.split[-1], self.threshold[-1]
            counts: dict[int, int] = {}
            for _, XYZ, _ in _chunks(path):
                cells = cube.cells(XYZ)
                parent = _Cube.key(cells, depth - 1)
                inside = _member(parents, parent)
                keys, k = np.unique(_Cube.key(cells[inside], depth), return_counts=True)
                for key, c in zip(keys.tolist(), k.tolist()):
                    counts[key] = counts.get(key, 0) + c
            keys = np.array(sorted(k for k, c in counts.items() if c > max_points), dtype=np.int64)
            if not len(keys):
                break
            n_x = np.array([counts[k] for k in keys.tolist()], dtype=np.float64)
            t_parent = parent_t[np.searchsorted(parents, np.array([_parent(k) for k in keys.tolist()]))]
            self.split.append(keys)
            self.threshold.append(np.minimum(1.0, t_parent + max_points / n_x))

    def nodes_of(self, first: int, XYZ: np.ndarray) -> np.ndarray:
        """The key of the node each point goes to."""
        n = len(XYZ)
        out = np.empty(n, dtype=np.int64)
        cells = self.cube.cells(XYZ)
        u = _uniform(first, n)
        open_ = np.arange(n)
        for depth in range(len(self.split) + 1):
            key = _Cube.key(cells[open_], depth)
            if depth == len(self.split):  # below the last split level every node takes all it holds
                out[open_] = key
                break
            split, t = self.split[depth], self.threshold[depth]
            pos = np.minimum(np.searchsorted(split, key), len(split) - 1)
            is_split = split[pos] == key
            take = ~is_split | (u[open_] < np.where(is_split, t[pos], 1.0))
            out[open_[take]] = key[take]
            open_ = open_[~take]
            if not len(open_):
                break
        return out


def _member(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[pos] == keys


def _is_waveform_descriptor(vlr) -> bool:
    """A waveform packet descriptor record (LAS 1.3+: LASF_Spec, record ids 100 to 354)."""
    return getattr(vlr, "user_id", "") == "LASF_Spec" and 99 < getattr(vlr, "record_id", 0) < 355


def _convert(points, fmt: laspy.PointFormat) -> np.ndarray:
    """The records in the output's point format (legacy fields carried to their LAS 1.4 places)."""
    if points.point_format.id == fmt.id:
        return points.array
    out = laspy.PackedPointRecord.from_point_record(points, fmt)
    names = set(points.point_format.dimension_names)
    if "scan_angle_rank" in names:  # degrees as int8; LAS 1.4 stores 0.006 degree steps
        out["scan_angle"] = np.round(np.asarray(points["scan_angle_rank"], dtype=np.float64) / 0.006).astype(np.int16)
    return out.array


def build(src: str, dest, work: str, max_points: int | None = None, note=None) -> dict:
    """Write the points of the LAS file ``src`` as COPC to the open binary file ``dest``, with temporary
    files in the folder ``work``; return facts (nodes, depth). ``note(text)`` is told of each change COPC
    forces."""
    import lazrs

    note = note or (lambda text: None)
    max_points = max_points or MAX_NODE_POINTS
    with laspy.open(src) as reader:
        source_header = reader.header
        header = copy.deepcopy(reader.header)
        evlrs = [v for v in (reader.header.evlrs or []) if not _is_copc(v)]
    if header.extra_header_bytes or header.extra_vlr_bytes:
        # COPC puts its info VLR right after a 375-byte header: bytes a writer left there cannot stay
        note(f"{len(header.extra_header_bytes) + len(header.extra_vlr_bytes)} undocumented bytes after the "
             "input's header or VLRs not written (COPC fixes the header's size)")
        header.extra_header_bytes = b""
        header.extra_vlr_bytes = b""
    n = header.point_count
    pf_in = header.point_format
    fmt = laspy.PointFormat(copc_point_format(pf_in))
    for dim in pf_in.dimensions:
        if not dim.is_standard:
            fmt.dimensions.append(dim)
    if fmt.id != pf_in.id:
        lost = sorted(set(pf_in.standard_dimension_names) - set(fmt.standard_dimension_names)
                      - {"scan_angle_rank"})
        if "wavepacket_index" in lost:  # no waveform left to point to
            header.global_encoding.waveform_data_packets_internal = False
            header.global_encoding.waveform_data_packets_external = False
            header.start_of_waveform_data_packet_record = 0
        note(f"point format {pf_in.id} written as {fmt.id} (COPC holds formats 6 to 8)"
             + (f"; {', '.join(lost)} not written" if lost else "")
             + ("; the waveform packet descriptors go with them"
                if lost and any(_is_waveform_descriptor(v) for v in [*header.vlrs, *evlrs]) else ""))
    crs = None
    try:
        crs = header.parse_crs()
    except Exception:  # noqa: BLE001 - an unreadable CRS is dropped below, and said
        crs = None
    records = [*header.vlrs, *evlrs]  # a CRS may sit in either
    had_wkt = any(type(v).__name__ == "WktCoordinateSystemVlr" for v in records)
    had_crs_records = crs is None and any(getattr(v, "user_id", "") == "LASF_Projection" for v in records)

    def kept(v) -> bool:
        """A record the COPC file keeps: not COPC's or LAZ's own, not a CRS record replaced by the WKT
        written below, not the descriptor of a waveform the format no longer has."""
        user = getattr(v, "user_id", "")
        if _is_copc(v) or user == "laszip encoded" or (user == "LASF_Projection" and crs is not None):
            return False
        if type(v).__name__ == "WktCoordinateSystemVlr":  # not a CRS pyproj reads (crs is None): dropped
            return False
        return not (_is_waveform_descriptor(v) and fmt.id != pf_in.id)

    header.vlrs = laspy.vlrs.vlrlist.VLRList([v for v in header.vlrs if kept(v)])
    evlrs = [v for v in evlrs if kept(v)]
    header.set_version_and_point_format(laspy.header.Version(1, 4), fmt)
    if crs is not None:
        if not had_wkt:
            note("CRS stored as WKT, converted from the input's GeoTIFF keys (COPC requires WKT)")
        header.add_crs(crs, keep_compatibility=False)
        if not any(type(v).__name__ == "WktCoordinateSystemVlr" for v in header.vlrs):
            raise OutputError("the CRS could not be written as WKT", "COPC")
    elif had_wkt:
        note("the input's WKT record is not a CRS pyproj can read, so it is not written; the output has no CRS")
    elif had_crs_records:
        note("the input's CRS records could not be read as a CRS, so they are kept as they are; COPC readers "
             "expect WKT")
    # the WKT goes in an EVLR, as copc-lib writes it: copclib (2.6) reads a WKT VLR 6 bytes past its start
    # (it skips an EVLR's 60-byte header for every WKT record) and refuses the file; laspy, PDAL and copc.js
    # read it in either place
    wkt = [v for v in header.vlrs if type(v).__name__ == "WktCoordinateSystemVlr"]
    if wkt:
        header.vlrs = laspy.vlrs.vlrlist.VLRList([v for v in header.vlrs if not any(v is w for w in wkt)])
        evlrs = [*evlrs, *wkt]
    header.global_encoding.wkt = True  # required for formats 6 to 10, with a CRS or without
    extrabytes.keep_no_data(header, source_header)  # the point format's rebuilt record lost them
    stats = extrabytes.ExtraStats(header)
    header.are_points_compressed = True
    laz = lazrs.LazVlr.new_for_compression(fmt.id, fmt.num_extra_bytes, True)
    info = laspy.VLR("copc", 1, "copc info", bytes(_INFO.size))
    header.vlrs.insert(0, info)
    header.vlrs.insert(1, laspy.VLR("laszip encoded", 22204, "lazrs variable chunks", laz.record_data()))

    # pass: bounds, returns, GPS time
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    returns = np.zeros(15, dtype=np.uint64)
    gps = [np.inf, -np.inf]
    for _, XYZ, points in _chunks(src):
        stats.grow(points)
        if len(XYZ):
            lo = np.minimum(lo, XYZ.min(axis=0))
            hi = np.maximum(hi, XYZ.max(axis=0))
            r = np.asarray(points.return_number).astype(np.int64)
            r = r[(r >= 1) & (r <= 15)]  # as LAS writers count: return 0 is no return number
            returns += np.bincount(r - 1, minlength=15)[:15].astype(np.uint64)
            if "gps_time" in set(pf_in.standard_dimension_names):
                t = np.asarray(points.gps_time)
                t = t[np.isfinite(t)]
                if len(t):
                    gps = [min(gps[0], float(t.min())), max(gps[1], float(t.max()))]
    if n == 0:
        lo = hi = np.zeros(3, dtype=np.int64)
    if not np.isfinite(gps[0]):
        gps = [0.0, 0.0]
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    cube = _Cube(lo.astype(np.float64), hi.astype(np.float64), scales, offsets)
    tree = _Octree(src, n, cube, max_points)

    # pass: every point's node, kept in a temporary file; the count of each node
    nodes_file = staging.ArrayFile(work, "nodes.i64", np.int64)
    try:
        counts: dict[int, int] = {}
        for first, XYZ, _ in _chunks(src):
            keys = tree.nodes_of(first, XYZ)
            nodes_file.append(keys)
            k, c = np.unique(keys, return_counts=True)
            for key, m in zip(k.tolist(), c.tolist()):
                counts[key] = counts.get(key, 0) + m
        # every ancestor of a node is in the hierarchy, empty if it took no point
        keys = set(counts)
        for key in list(counts):
            while key >> 58:
                key = _parent(key)
                if key in keys:
                    break
                keys.add(key)
        if not keys:
            keys.add(0)
        order = sorted(keys)
        filled = [k for k in order if counts.get(k, 0)]

        header.point_count = n
        header.number_of_points_by_return = returns
        header.mins, header.maxs = _bounds(lo, hi, scales, offsets)
        header.start_of_first_evlr = 0
        header.number_of_evlrs = 1 + len(evlrs)
        stats.apply(header)
        dest.seek(0)
        header.write_to(dest)
        point_start = dest.tell()
        compressor = lazrs.LasZipCompressor(dest, laz)
        started = False  # done() ends the last chunk; finish_current_chunk() ends each one before it
        for group in _groups(filled, counts):
            if started:
                compressor.finish_current_chunk()
            started = True
            if len(group) == 1:  # one node (perhaps more points than a run holds): streamed in file order
                held = 0
                for first, XYZ, points in _chunks(src):
                    mine = np.flatnonzero(nodes_file.read(first, len(XYZ)) == group[0])
                    if len(mine):
                        compressor.compress_many(np.frombuffer(_convert(points[mine], fmt).tobytes(), np.uint8))
                        held += len(mine)
                if held != counts[group[0]]:
                    raise OutputError("COPC build: the points found for a node differ from its count", "COPC")
                continue
            members = np.array(group, dtype=np.int64)
            starts = np.concatenate([[0], np.cumsum([counts[k] for k in group])]).astype(np.int64)
            cursor = starts[:-1].copy()  # where the next point of each node goes
            records = np.empty(int(starts[-1]), dtype=fmt.dtype())  # the run's points, placed node by node
            for first, XYZ, points in _chunks(src):
                keys_i = nodes_file.read(first, len(XYZ))
                mine = np.flatnonzero((keys_i >= members[0]) & (keys_i <= members[-1]))
                if not len(mine):
                    continue
                node = np.searchsorted(members, keys_i[mine])
                by_node = np.argsort(node, kind="stable")  # file order within each node
                node = node[by_node]
                within = np.arange(len(node)) - np.searchsorted(node, node)
                records[cursor[node] + within] = _convert(points[mine[by_node]], fmt)
                cursor += np.bincount(node, minlength=len(members))
            if not np.array_equal(cursor, starts[1:]):
                raise OutputError("COPC build: the points found for a run of nodes differ from their count", "COPC")
            for j, (a, b) in enumerate(zip(starts[:-1], starts[1:])):
                if j:
                    compressor.finish_current_chunk()
                compressor.compress_many(np.frombuffer(records[a:b].tobytes(), np.uint8))
            del records
        compressor.done()
    finally:
        nodes_file.discard()
    evlr_start = dest.tell()

    # the chunk table lazrs wrote gives each chunk's size, in the order of ``filled``
    dest.flush()
    dest.seek(point_start)
    sizes = [b for _, b in lazrs.read_chunk_table(dest, laz)] if filled else []
    if len(sizes) != len(filled):
        raise OutputError(f"COPC chunk table holds {len(sizes)} chunks for {len(filled)} nodes", "COPC")
    where = {}
    at = point_start + 8
    for key, size in zip(filled, sizes):
        where[key] = (at, size)
        at += size
    entries = bytearray()
    for key in order:
        off, size = where.get(key, (0, 0))
        entries += _ENTRY.pack(*_unkey(key), off, size, counts.get(key, 0))
    hierarchy = laspy.VLR("copc", 1000, "EPT hierarchy", bytes(entries))
    dest.seek(evlr_start)
    laspy.vlrs.vlrlist.VLRList([hierarchy, *evlrs]).write_to(dest, as_extended=True)
    end = dest.tell()

    info.record_data = _INFO.pack(*cube.center, cube.halfsize, 2 * cube.halfsize / ROOT_CELLS,
                                  evlr_start + 60, len(entries), gps[0], gps[1], *([0] * 11))
    header.start_of_first_evlr = evlr_start
    dest.seek(0)
    header.write_to(dest, ensure_same_size=True)
    dest.seek(end)
    dest.truncate()
    depth = max((_unkey(k)[0] for k in order), default=0)
    return {"nodes": len(order), "depth": depth, "max_node_points": max_points,
            "point_format": fmt.id}


def _groups(keys: list[int], counts: dict[int, int]):
    """Runs of consecutive nodes holding at most GROUP_POINTS points together (a bigger node alone)."""
    run, held = [], 0
    for key in keys:
        if run and held + counts[key] > GROUP_POINTS:
            yield run
            run, held = [], 0
        run.append(key)
        held += counts[key]
    if run:
        yield run


def refuse_clashes(sources: list[Source], selection: tuple | None = None) -> None:
    """Refuse LAS inputs whose extra-bytes dimensions are named as standard fields of the COPC point format
    (7 or 8) they would be written in: checked from the headers, before anything is read. The ones
    --keep/--drop leave out (``selection``) are not written, so they cannot clash."""
    if sources and all_las(sources):
        pf = sources[0].point_format
        taken = set(laspy.PointFormat(copc_point_format(pf)).standard_dimension_names)
        clash = sorted((set(pf.extra_dimension_names) & taken) - set(left_out(sources[0], selection)[0]))
        if clash:
            raise UsageError(f"extra-bytes dimension(s) {', '.join(clash)} would clash with the standard "
                             f"field(s) of that name of LAS 1.4 point format {copc_point_format(pf)}, which "
                             f"COPC needs; write .laz instead, or leave them out (--drop {','.join(clash)})",
                             sources[0].path)


class CopcSink(Sink):
    """``.copc.laz`` out: the LAS/LAZ writer's output, staged uncompressed, rebuilt as COPC on commit."""

    takes_grid = LasSink.takes_grid

    @classmethod
    def open(cls, path: str, sources: list[Source], provenance: dict, options: WriteOptions) -> "CopcSink":
        return cls(path, sources, provenance, options)

    @classmethod
    def refuse_selection(cls, path: str, sources: list, options: WriteOptions) -> None:
        LasSink.refuse_selection(path, sources, options)

    @classmethod
    def refuse_own(cls, path: str, sources: list, options: WriteOptions) -> None:
        LasSink.refuse_own(path, sources, options)
        refuse_clashes(sources, options.selection)

    def __init__(self, path: str, sources: list[Source], provenance: dict, options: WriteOptions):
        super().__init__(path, sources, provenance)
        selection = options.selection

        refuse_clashes(sources, selection)
        if "rank" in provenance:  # ranks are written, but the points are in octree order
            provenance = {**provenance, "rank": {**provenance["rank"], "order": "octree"}}

        self.folder = staging.temp_folder(path)
        self.facts: dict = {}
        stem = os.path.basename(path)[: -len(".copc.laz")] or "sample"
        try:
            self.inner = LasSink.open(os.path.join(self.folder, stem + ".las"), sources, provenance, options)
            self.file = AtomicFile(path)
        except BaseException:
            staging.remove(self.folder)
            raise

    def write(self, chunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        if ranks is None:
            self.inner.write(chunk, mask)
        else:
            self.inner.write(chunk, mask, ranks=ranks)
        self.written = self.inner.written

    def _commit(self) -> None:
        try:
            self.inner._commit()  # the staged LAS; its notes are this output's
            for text in self.inner.own_notes():
                if not text.startswith(COPC_INPUT_NOTE):  # an octree is written: this output's own
                    self.note(text)
            with open(self.file.tmp, "r+b") as raw:
                dest = extrabytes.RecordedFile(raw)  # lazrs says only that a write failed: the file knows why
                with dest.told():
                    self.facts = build(self.inner.path, dest, self.folder, note=self.note)
        except (PrismError, KeyboardInterrupt, SystemExit):
            self.abort()
            raise
        except BaseException as exc:  # noqa: BLE001 - disk full, a library's refusal: one line, nothing left
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else describe(exc)
            self.abort()
            raise OutputError(f"cannot write the COPC output: {why}", self.path) from None
        staging.remove(self.folder)
        self.file.commit()

    def _name_the_output(self, error: PrismError) -> None:
        """An error about the staged LAS or the octree's work files (a full disk in pass two) names the
        output, not the staging folder a user never asked for."""
        if error.path is not None and os.fspath(error.path).startswith(os.path.join(self.folder, "")):
            error.path = self.path
        super()._name_the_output(error)

    def abort(self) -> None:
        try:
            self.inner.abort()
        finally:
            staging.remove(self.folder)
            self.file.discard()

