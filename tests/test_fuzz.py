"""Mutated LAS, PLY and PCD files: the right output or the right one-line refusal, never anything else.

Hypothesis starts from small valid files (generated here) and changes their
header words, flips and inserts bytes, or cuts them short. Where the mutation
decides the outcome, that outcome is required: a file cut short once its
format is recognizable is ``CorruptInput`` (exit 6); bytes replaced inside
fixed-size point records must sample. Otherwise ``prism_stream.sample`` may
refuse, with an input error (exit 4, 5 or 6) naming the file and leaving no
output and no temporary file, or succeed. Whenever it succeeds, the output
must hold, column for column and in order, the records an independent reader
(laspy, plyfile, the oracle's PCD reader) finds in the mutant, at the indices
the oracle (tests/oracle.py) keeps. Any other exception is a bug. A few
mutants also go through the command, in a child process, so that a crash of
the interpreter (a panic, a segfault) would show as a signal.

Budget: a few hundred examples in all, well under two minutes.
"""

from __future__ import annotations

import functools
import json
import os
import resource
import struct
import subprocess
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import laspy
import numpy as np
import plyfile
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import prism_stream
from prism_stream.errors import CorruptInput, NoColorError, PrismError, UnsupportedFormat

import oracle
from conftest import lzf_literals, prism_stream_command, user_env, write_las

N = 40
RATIO = 0.5
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                         HealthCheck.too_slow])


def _colors(n=N, seed=1):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(n, 3)).astype(np.uint8)


def ply_bytes(encoding: str) -> bytes:
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-5, 5, size=(N, 3)).astype(np.float32)
    rgb = _colors()
    head = [b"ply", f"format {encoding} 1.0".encode(), b"comment fuzz", b"element face 2",
            b"property list uchar int vertex_indices", f"element vertex {N}".encode(), b"property float x",
            b"property float y", b"property float z", b"property uchar red", b"property uchar green",
            b"property uchar blue", b"end_header"]
    out = b"\n".join(head) + b"\n"
    if encoding == "ascii":
        out += b"3 0 1 2\n4 0 1 2 3\n"
        out += b"".join(b"%r %r %r %d %d %d\n" % (float(a), float(b), float(c), r, g, bl)
                        for (a, b, c), (r, g, bl) in zip(xyz.tolist(), rgb.tolist()))
    else:
        e = "<" if encoding == "binary_little_endian" else ">"
        faces = np.array([3], "u1").tobytes() + np.arange(3, dtype=e + "i4").tobytes()
        faces += np.array([4], "u1").tobytes() + np.arange(4, dtype=e + "i4").tobytes()
        rec = np.zeros(N, dtype=[("x", e + "f4"), ("y", e + "f4"), ("z", e + "f4"), ("red", "u1"), ("green", "u1"),
                                 ("blue", "u1")])
        rec["x"], rec["y"], rec["z"] = xyz.T
        rec["red"], rec["green"], rec["blue"] = rgb.T
        out += faces + rec.tobytes()
    return out


def pcd_bytes(data: str) -> bytes:
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-5, 5, size=(N, 3)).astype(np.float32)
    xyz[::7] = np.nan
    rgb = _colors().astype(np.uint32)
    word = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
            f"WIDTH {N}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {N}\nDATA {data}\n").encode()
    if data == "ascii":
        body = b"".join(b"%r %r %r %d\n" % (float(a), float(b), float(c), w) for (a, b, c), w in
                        zip(xyz.tolist(), word.tolist()))
    else:
        rec = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
        rec["x"], rec["y"], rec["z"] = xyz.T
        rec["rgb"] = word
        if data == "binary":
            body = rec.tobytes()
        else:
            raw = b"".join(np.ascontiguousarray(rec[n]).tobytes() for n in rec.dtype.names)
            packed = lzf_literals(raw)
            body = np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    return head + body


@functools.lru_cache(maxsize=None)
def _seeds() -> dict:
    with tempfile.TemporaryDirectory() as folder:
        las = write_las(Path(folder) / "seed.las", _colors().astype(np.uint16) << 8, point_format=3)
        files = {"seed.las": las.read_bytes()}
    for enc in ("ascii", "binary_little_endian", "binary_big_endian"):
        files[f"seed_{enc}.ply"] = ply_bytes(enc)
    for data in ("ascii", "binary", "binary_compressed"):
        files[f"seed_{data}.pcd"] = pcd_bytes(data)
    return files


@pytest.fixture
def seeds() -> dict:
    """Small valid files, generated once (a plain function, so a failure does not print them)."""
    return _seeds()


def test_seeds_are_valid(tmp_path, seeds):
    """The unmutated files all sample cleanly (else the fuzzing below proves little)."""
    for name, data in seeds.items():
        path = tmp_path / name
        path.write_bytes(data)
        s = prism_stream.sample(str(path), str(tmp_path / (name + ".parquet")), ratio=0.5)
        expected = N - len(range(0, N, 7)) if name.endswith(".pcd") else N
        assert s.points == expected, name
        assert pq.read_metadata(tmp_path / (name + ".parquet")).num_rows == s.kept


@dataclass(frozen=True)
class Mutation:
    """A mutant and how it was made: ``at`` holds the bytes replaced (flip), the insertion point
    (insert) or the new length (truncate); a header word (word) leaves it empty."""

    kind: str
    at: tuple
    data: bytes


def mutate(data: bytes, draw) -> Mutation:
    """One mutation: a header word replaced, bytes flipped or inserted, or the file cut short."""
    kind = draw(st.sampled_from(["word", "flip", "insert", "truncate"]))
    end = data.find(b"end_header")
    end = data.find(b"DATA") if end < 0 else end
    end = 375 if end < 0 else end  # LAS: the header block
    if kind == "word":
        header = data[:end]
        words = [i for i, w in enumerate(header.split(b" ")) if w]
        if not words:
            return Mutation(kind, (), data)
        parts = header.split(b" ")
        i = draw(st.sampled_from(words))
        parts[i] = draw(st.sampled_from([b"0", b"-1", b"1", b"4294967295", b"99999999999", b"nan", b"x", b"",
                                         b"list", b"double", b"binary", b"ascii", b"1e9", b"\xff"]))
        return Mutation(kind, (), b" ".join(parts) + data[end:])
    if kind == "flip":
        out = bytearray(data)
        changed = []
        for _ in range(draw(st.integers(1, 8))):
            at = draw(st.integers(0, len(out) - 1))
            out[at] = draw(st.integers(0, 255))
            changed.append(at)
        return Mutation(kind, tuple(changed), bytes(out))
    if kind == "insert":
        at = draw(st.integers(0, len(data)))
        return Mutation(kind, (at,), data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:])
    cut = draw(st.integers(0, len(data) - 1))
    return Mutation(kind, (cut,), data[:cut])


# -- what a mutation determines --------------------------------------------------------------

PLY_FACE_BYTES = (1 + 3 * 4) + (1 + 4 * 4)  # the two faces ply_bytes writes before the vertices (binary)
PLY_VERTEX_BYTES = 3 * 4 + 3
PCD_RECORD_BYTES = 4 * 4


@dataclass(frozen=True)
class Layout:
    """Where the parts of a seed file are.

    ``truncated_from``: from this length on, a prefix of the file is recognizably of its format
    and incomplete. ``records``/``records_end``: the bytes that hold the points (to the end of the
    file for ascii and LZF-compressed data). ``record_size``: the size of a fixed-size point record
    (binary LAS, binary PLY vertices, binary PCD), 0 where the points are not fixed-size bytes.
    ``last_line``: in an ascii file, where the last point's line starts. ``text_header``: a PLY or
    PCD header; where the reference reader refuses such a header and the engine reads on, the
    points must be those the seed's layout gives (see ``stricter_reading``). A LAS header is
    binary and holds the coordinates' scales and offsets: no such fallback.
    """

    binary: bool
    truncated_from: int
    records: int
    records_end: int
    record_size: int = 0
    last_line: int = 0
    text_header: bool = True


def layout_of(name: str, data: bytes) -> Layout:
    if name.endswith(".las"):
        # LAS 1.2 header (ASPRS spec): offset to point data at byte 96, record length at 105. The file is
        # recognizably LAS once its LASF signature is there: any cut after it is a truncated file (exit 6).
        offset, = struct.unpack_from("<I", data, 96)
        size, = struct.unpack_from("<H", data, 105)
        return Layout(True, len(b"LASF"), offset, offset + N * size, size, text_header=False)
    last_line = data.rindex(b"\n", 0, len(data) - 1) + 1
    if name.endswith(".ply"):
        magic = len(b"ply\n")
        body = data.index(b"end_header\n") + len(b"end_header\n")
        if "ascii" in name:
            vertices = data.index(b"\n", data.index(b"\n", body) + 1) + 1  # after the two face lines
            return Layout(False, magic, vertices, len(data), last_line=last_line)
        records = body + PLY_FACE_BYTES
        return Layout(True, magic, records, records + N * PLY_VERTEX_BYTES, PLY_VERTEX_BYTES)
    first_key = data.index(b"\n", data.index(b"\nVERSION ") + 1) + 1  # after "# .PCD v0.7" and "VERSION 0.7"
    body = data.index(b"\n", data.index(b"\nDATA ") + 1) + 1
    if "ascii" in name:
        return Layout(False, first_key, body, len(data), last_line=last_line)
    if "compressed" in name:
        return Layout(True, first_key, body, len(data))
    return Layout(True, first_key, body, body + N * PCD_RECORD_BYTES, PCD_RECORD_BYTES)


def determined(layout: Layout, m: Mutation):
    """``"ok"``, the error class a mutation must end in, or None where it does not decide.

    - A file cut short once its format is recognizable (PLY: after ``ply``; PCD: after its first
      keyword line; LAS: after the header) lacks part of its header or declared points:
      ``CorruptInput`` (exit 6). Ascii: only a cut before the last point's line is sure to lose
      a point (a cut inside that line can leave a shorter number that still parses).
    - Bytes replaced inside fixed-size point records change values, not the structure: the run
      succeeds, on the records as they now are.
    Everything else (header words, inserted bytes, flips in headers, faces or LZF streams) may
    go either way; the run is then checked against the reference reader if it succeeds.
    """
    if m.kind == "truncate":
        cut = m.at[0]
        if layout.binary and cut >= layout.truncated_from:
            return CorruptInput
        if not layout.binary and layout.truncated_from <= cut < layout.last_line:
            return CorruptInput
    if m.kind == "flip" and layout.record_size:
        if all(layout.records <= at < layout.records_end for at in m.at):
            return "ok"
    return None


def stricter_reading(layout: Layout, m: Mutation, seed: bytes) -> bytes | None:
    """What a successful run must have read when the reference reader refuses the mutant, or None.

    Readers differ in what they let pass outside the points: plyfile wants version 1.0 and
    ASCII face lines, say, where the engine reads on. Where a mutation cannot have changed how
    the points are laid out, the output must hold the points of this file instead: the seed with
    only the mutant's point bytes (bytes replaced in a PLY or PCD), or the seed itself (a PLY or
    PCD header word changed; bytes added after the points, or without a line break to an ascii
    face line). Otherwise None: the engine accepted what no reference reader reads.
    """
    if m.kind == "insert":
        at = m.at[0]
        added = m.data[at:at + len(m.data) - len(seed)]
        if at >= layout.records_end:
            return seed
        if layout.text_header and not layout.binary and at < layout.records and not any(c in added for c in b"\r\n"):
            return seed
    if m.kind == "word" and layout.text_header:
        return seed
    if m.kind == "flip" and layout.text_header:
        a, b = layout.records, layout.records_end
        header_end = seed.find(b"end_header")
        if any(at < header_end for at in m.at):
            # a flip in the header may change the layout (a count's digit, say): the mutant's header over the
            # seed's other elements and the mutant's point bytes, when the reference reader reads that header
            # (or, when those point bytes no longer parse where that header puts them, the seed's points)
            for instead in (m.data[:header_end] + seed[header_end:a] + m.data[a:b] + seed[b:],
                            m.data[:header_end] + seed[header_end:]):
                try:
                    reference_points_of(instead)
                    return instead
                except Exception:  # noqa: BLE001 - the reference reader refuses it: the next, or the seed's header
                    pass
        return seed[:a] + m.data[a:b] + seed[b:]
    return None


def reference_points_of(data: bytes):
    """reference_points of a PLY or PCD file's bytes."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / ("f.ply" if data.startswith(b"ply") else "f.pcd")
        path.write_bytes(data)
        return reference_points(path)


# -- the rows a successful run must hold, read without the engine -------------------------------

def reference_points(path: Path) -> tuple[dict, tuple]:
    """The mutant's points read by an independent reader (laspy, plyfile, the oracle's PCD reader):
    every column by output name, and the three color channels the oracle bins."""
    if path.suffix == ".las":
        las = laspy.read(str(path))
        names = [n.lower() if n in ("X", "Y", "Z") else n for n in las.point_format.dimension_names]
        cols = {n: np.asarray(getattr(las, n) if n in ("x", "y", "z") else las[n]) for n in names}
        return cols, (cols["red"], cols["green"], cols["blue"])
    if path.suffix == ".ply":
        vertex = plyfile.PlyData.read(str(path))["vertex"].data
        cols = {n: np.asarray(vertex[n]) for n in vertex.dtype.names}
        return cols, (cols["red"], cols["green"], cols["blue"])
    cols = oracle.read_pcd(path)
    colors = oracle.pcd_colors(cols["rgb"])
    if {"red", "green", "blue", "alpha"} & set(cols):  # names taken: the output keeps the packed word
        return cols, colors
    # the output writes the packed word as uint8 red, green, blue in its place (issue 28, item 10)
    out = {}
    for name, values in cols.items():
        if name == "rgb":
            out.update(zip(("red", "green", "blue"), (c.astype(np.uint8) for c in colors)))
        else:
            out[name] = values
    return out, colors


def assert_oracle_rows(path: Path, output: Path, summary, fallback: bytes | None = None) -> None:
    """The output holds the reference reader's records at the oracle's indices, every column, in order.

    ``fallback``: the file to read instead if the reference reader refuses ``path`` (see
    ``stricter_reading``); without one, that refusal is the failure.
    """
    try:
        cols, colors = reference_points(path)
    except Exception as exc:  # noqa: BLE001 - any refusal of the reference reader counts
        if fallback is None:
            raise AssertionError(f"the engine sampled a file its reference reader refuses: {exc!r}") from exc
        instead = path.with_name("stricter" + path.suffix)
        instead.write_bytes(fallback)
        cols, colors = reference_points(instead)
    if not len(colors[0]):  # no points (a header flip made the count 0): nothing to sample, nothing written
        assert summary.points == summary.kept == pq.read_metadata(output).num_rows == 0
        return
    want = oracle.sample([colors], ratio=RATIO)
    rows = want.kept[0]
    assert summary.points == want.points and summary.kept == len(rows) == want.target
    table = pq.read_table(output)
    assert table.column_names == list(cols)
    for name in table.column_names:
        column = table.column(name).combine_chunks()
        if pa.types.is_fixed_size_list(column.type):  # LAS bytes no VLR describes: one list per point
            got = column.flatten().to_numpy().reshape(len(column), column.type.list_size)
        else:
            got = column.to_numpy()
        expected = np.asarray(cols[name])[rows]
        assert got.dtype == expected.dtype.newbyteorder("="), name
        assert got.tobytes() == expected.astype(got.dtype).tobytes(), name  # bits: NaN is a value here


INPUT_ERRORS = (UnsupportedFormat, NoColorError, CorruptInput)  # exit 4, 5, 6: what a bad file can be


def check_one(folder: Path, name: str, seed_bytes: bytes, mutation: Mutation) -> str:
    """Run the API on one mutant; assert the outcome the mutation determines, else one of the two
    allowed ones (rows checked against the oracle, or an input error naming the file)."""
    data = mutation.data
    path = folder / name
    path.write_bytes(data)
    output = folder / "out.parquet"
    if output.exists():
        output.unlink()
    temp = folder / "temp"
    temp.mkdir(exist_ok=True)
    layout = layout_of(name, seed_bytes)
    want = determined(layout, mutation)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            summary = prism_stream.sample(str(path), str(output), ratio=RATIO, chunk_size=16, temp_dir=str(temp))
    except PrismError as exc:
        assert type(exc) in INPUT_ERRORS, f"{type(exc).__name__} (exit {exc.exit_code}): {exc}"
        assert want in (None, type(exc)), f"{mutation.kind} at {mutation.at}: expected " \
            f"{getattr(want, '__name__', want)}, got {type(exc).__name__}: {exc}"
        assert "\n" not in str(exc), str(exc)
        assert exc.path in (str(path), str(output)), str(exc)
        assert not output.exists(), "a refused run left its output"
        outcome = "refused"
    else:
        assert want in (None, "ok"), f"{mutation.kind} at {mutation.at}: expected {want.__name__}, the run succeeded"
        assert_oracle_rows(path, output, summary, stricter_reading(layout, mutation, seed_bytes))
        outcome = "ok"
    assert path.read_bytes() == data, "the input was modified"
    assert [n for n in os.listdir(folder) if n.endswith((".prism-tmp", ".spool"))] == []
    assert os.listdir(temp) == []
    return outcome


@pytest.mark.parametrize("seed_name", ["seed.las", "seed_ascii.ply", "seed_binary_little_endian.ply",
                                       "seed_binary_big_endian.ply", "seed_ascii.pcd", "seed_binary.pcd",
                                       "seed_binary_compressed.pcd"])
@FUZZ
@given(data=st.data())
def test_mutants_sample_or_refuse(tmp_path, seed_name, data):
    seed = _seeds()[seed_name]
    mutation = mutate(seed, data.draw)
    check_one(tmp_path, seed_name.replace("seed", "mutant"), seed, mutation)


def _limit():
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


@pytest.mark.parametrize("seed_name", ["seed.las", "seed_binary_little_endian.ply", "seed_binary_compressed.pcd"])
def test_mutants_through_the_command(tmp_path, seeds, seed_name):
    """A handful of mutants in a child process: an interpreter crash would be a signal here.

    The exit code is the one the mutation determines (0 for bytes replaced inside the point
    records), else 0 or an input error (4, 5, 6); a successful run holds the oracle's rows. The command runs
    as a user's does (a small file held in memory); the streaming reader meets every mutant in this process,
    in the tests above."""
    rng = np.random.default_rng(7)
    base = bytearray(seeds[seed_name])
    layout = layout_of(seed_name, bytes(base))
    cmd = prism_stream_command()
    for i in range(4):
        data = bytearray(base)
        changed = []
        for at in rng.integers(0, len(data), size=6):
            data[at] = int(rng.integers(0, 256))
            changed.append(int(at))
        mutation = Mutation("flip", tuple(changed), bytes(data))
        want = determined(layout, mutation)
        path = tmp_path / f"m{i}{Path(seed_name).suffix}"
        path.write_bytes(bytes(data))
        output = tmp_path / f"m{i}.parquet"
        r = subprocess.run([*cmd, str(path), str(output), "--ratio", str(RATIO), "-q"], capture_output=True,
                           text=True, timeout=120, preexec_fn=_limit, env=user_env())
        assert r.returncode >= 0, f"killed by signal {-r.returncode}"
        assert "Traceback" not in r.stderr
        if r.returncode == 0:
            assert want in (None, "ok"), f"flips at {changed}: expected exit {want.exit_code}, got 0"
            assert output.is_file()
            provenance = json.loads(pq.read_schema(output).metadata[b"prism_stream"])
            summary = SimpleNamespace(points=provenance["points"], kept=provenance["kept"])
            assert_oracle_rows(path, output, summary, stricter_reading(layout, mutation, bytes(base)))
        else:
            codes = [want.exit_code] if isinstance(want, type) else [e.exit_code for e in INPUT_ERRORS]
            assert want != "ok" and r.returncode in codes, f"flips at {changed}: exit {r.returncode}: {r.stderr}"
            lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
            assert len(lines) == 1 and lines[0].startswith("prism-stream: error: "), r.stderr
            assert str(path) in lines[0], lines[0]
            assert not output.exists()
