"""PCD in: ascii, binary and binary_compressed; packed colors by their bits; NaN points skipped.

Files are generated here (a literal-run LZF encoder stands in for PCL's
compressor). A point's record index is its index among the finite points,
so the oracle runs on the finite points' colors, in file order.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import CorruptInput, UnsupportedFormat
from prism_stream.formats.pcd import PcdSource, lzf_decompress

import oracle
from conftest import lzf_literals, real_file

RATIO = 0.3


def organized(width=30, height=20, seed=0, color_type="F", field="rgb"):
    """An organized cloud: x y z, a packed color word, a normal (COUNT 3); every 5th row is a NaN hole."""
    rng = np.random.default_rng(seed)
    n = width * height
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), (field, "<u4"), ("normal", "<f4", (3,)),
                             ("ring", "<u2")])
    rec["x"], rec["y"], rec["z"] = rng.normal(size=(3, n)).astype(np.float32)
    hole = (np.arange(n) // width) % 5 == 0
    hole |= rng.random(n) < 0.1
    rec["x"][hole] = rec["y"][hole] = rec["z"][hole] = np.nan
    palette = rng.integers(0, 256, size=(40, 3)).astype(np.uint32)
    pick = palette[rng.integers(0, 40, n)]
    alpha = np.uint32(255) if field == "rgba" else np.uint32(0)  # 0xFF alpha makes the float bits a NaN
    rec[field] = (alpha << 24) | (pick[:, 0] << 16) | (pick[:, 1] << 8) | pick[:, 2]
    rec["normal"] = rng.normal(size=(n, 3)).astype(np.float32)
    rec["ring"] = np.arange(n) % 16
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z {field} normal ring\nSIZE 4 4 4 4 4 2\n"
              f"TYPE F F F {color_type} F U\nCOUNT 1 1 1 1 3 1\nWIDTH {width}\nHEIGHT {height}\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n")
    return rec, header


def write_pcd(path, rec, header, data):
    if data == "ascii":
        lines = []
        for r in rec:
            word = int(r[3])
            lines.append(" ".join([repr(float(r[0])), repr(float(r[1])), repr(float(r[2])), str(word),
                                   *[repr(float(v)) for v in r[4]], str(int(r[5]))]))
        body = ("\n".join(lines) + "\n").encode()
    elif data == "binary":
        body = rec.tobytes()
    else:
        raw = b"".join(np.ascontiguousarray(rec[n]).tobytes() for n in rec.dtype.names)
        packed = lzf_literals(raw)
        body = np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    path.write_bytes((header + f"DATA {data}\n").encode() + body)
    return path


def finite(rec):
    return ~(np.isnan(rec["x"]) | np.isnan(rec["y"]) | np.isnan(rec["z"]))


def unpack(words):
    w = np.asarray(words, dtype=np.uint32)
    return ((w >> 16) & 255, (w >> 8) & 255, w & 255)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("color_type,field", [("F", "rgb"), ("U", "rgb"), ("F", "rgba")])
def test_pcd_to_parquet_keeps_the_oracles_finite_points(tmp_path, data, color_type, field):
    rec, header = organized(color_type=color_type, field=field)
    src = write_pcd(tmp_path / "in.pcd", rec, header, data)
    out = tmp_path / "out.parquet"
    summary = prism_stream.sample(str(src), str(out), ratio=RATIO, seed=9)
    kept_points = rec[finite(rec)]
    rows = oracle.sample([unpack(kept_points[field])], ratio=RATIO, seed=9).kept[0]
    assert summary.points == len(kept_points)
    table = pq.read_table(out)
    # the packed word is written as the color columns every other format's output has (issue 28, item 10)
    alpha = ["alpha"] if field == "rgba" else []
    assert table.column_names == ["x", "y", "z", "red", "green", "blue", *alpha, "normal", "ring"]
    assert table.num_rows == len(rows)
    want = kept_points[rows]
    for name in ("x", "y", "z", "ring"):
        assert table.column(name).to_numpy().tobytes() == np.ascontiguousarray(want[name]).tobytes(), name
    word = np.ascontiguousarray(want[field]).view(np.uint32)  # the bits, not a float conversion
    for name, channel in zip(("red", "green", "blue"), unpack(word)):
        column = table.column(name).to_numpy()
        assert column.dtype == np.uint8 and column.tolist() == channel.tolist(), name
    if field == "rgba":
        assert table.column("alpha").to_numpy().tolist() == (word >> 24).tolist()
    normal = table.column("normal").combine_chunks().flatten().to_numpy().reshape(-1, 3)
    assert normal.tobytes() == np.ascontiguousarray(want["normal"]).tobytes()
    facts = json.loads(pq.read_schema(out).metadata[b"prism_stream_source"])
    assert facts["nan_points_skipped"] == len(rec) - len(kept_points)


def test_ranges_inside_and_across_blocks_read_the_same_points(tmp_path):
    rec, header = organized(width=1000, height=70)
    src = write_pcd(tmp_path / "big.pcd", rec, header, "binary")
    with PcdSource(str(src), 0) as s:
        whole = np.concatenate([c.records for c in s.point_chunks(1 << 20)])
        assert len(whole) == s.count == finite(rec).sum()
        edge = int(s.block_kept[1])  # the first kept point of the second block
        assert 0 < edge < s.count
        for start, stop, chunk in ((0, 10, 3), (edge - 1000, edge + 1000, 777), (edge, edge + 5, 1),
                                   (s.count - 5, s.count, 2)):
            chunks = list(s.point_chunks(chunk, start, stop))
            # contiguous, at most ``chunk`` points each (a block edge may end a chunk early)
            assert [c.start for c in chunks] == list(np.cumsum([start] + [len(c) for c in chunks[:-1]]))
            assert all(0 < len(c) <= chunk for c in chunks)
            assert np.concatenate([c.records for c in chunks]).tobytes() == whole[start:stop].tobytes()


def test_lzf_back_references_decode():
    # "abcd" as literals, then a back-reference of 10 bytes at distance 4, then one of 20 (extended length)
    lit = bytes([3]) + b"abcd"
    ref10 = bytes([(7 << 5) | 0, 10 - 2 - 7, 3])  # length 10: 7 + extra 1, + 2; offset 3 means distance 4
    ref5 = bytes([(3 << 5) | 0, 3])  # length 3 + 2 = 5
    src = np.frombuffer(lit + ref10 + ref5, dtype=np.uint8)
    out = np.zeros(19, dtype=np.uint8)
    assert lzf_decompress(src, out) == 19
    assert out.tobytes() == b"abcd" * 4 + b"abc"
    assert lzf_decompress(np.frombuffer(bytes([(1 << 5), 40]), np.uint8), np.zeros(8, np.uint8)) == -1


def test_office_frame_counts_finite_points_and_colors():
    path = real_file("pcl__office1.pcd")
    summary = prism_stream.plan(str(path), ratio=0.01)
    # the data README: 307,200 points of which 254,456 finite, 52,182 distinct RGB over finite points
    assert summary.points == 254456
    assert summary.bins == 52182


def test_office_frame_sample_does_not_depend_on_chunk_size(tmp_path):
    path = real_file("pcl__office1.pcd")
    prism_stream.sample(str(path), str(tmp_path / "a.parquet"), ratio=0.02)
    prism_stream.sample(str(path), str(tmp_path / "b.parquet"), ratio=0.02, chunk_size=5000)
    a, b = pq.read_table(tmp_path / "a.parquet"), pq.read_table(tmp_path / "b.parquet")
    assert a.num_rows == int(0.02 * 254456 + 0.5)
    assert a.equals(b)
    assert not np.isnan(a.column("x").to_numpy()).any()


def test_pcd_without_header_is_refused(tmp_path):
    path = tmp_path / "bare.pcd"
    path.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(UnsupportedFormat, match="no PCD header"):
        prism_stream.sample(str(path), str(tmp_path / "o.parquet"), ratio=0.5)


@pytest.mark.parametrize("damage", ["truncate", "bad_lzf", "size_words"])
def test_damaged_pcd_is_refused(tmp_path, damage):
    rec, header = organized()
    kind = "binary" if damage == "truncate" else "binary_compressed"
    data = write_pcd(tmp_path / "ok.pcd", rec, header, kind).read_bytes()
    start = data.index(b"DATA") + len(f"DATA {kind}\n")
    if damage == "truncate":
        data = data[:-50]
    elif damage == "bad_lzf":
        data = data[:start + 8] + bytes([0xE0, 0xFF, 0xFF]) + data[start + 11:]
    else:
        data = data[:start + 4] + np.array([1 << 31], "<u4").tobytes() + data[start + 8:]
    path = tmp_path / "bad.pcd"
    path.write_bytes(data)
    with pytest.raises(CorruptInput):
        prism_stream.sample(str(path), str(tmp_path / "o.parquet"), ratio=0.5)
    assert not (tmp_path / "o.parquet").exists()


@pytest.mark.parametrize("color_type,field", [("F", "rgb"), ("U", "rgba")])
def test_a_pcd_sample_in_parquet_samples_again_and_queries_by_color_name(tmp_path, color_type, field):
    """PCL's packed word stayed packed in Parquet, so neither prism-stream nor a query by red/green/blue could
    read the output (issue 28, item 10)."""
    import duckdb

    rec, header = organized(color_type=color_type, field=field)
    src = write_pcd(tmp_path / "in.pcd", rec, header, "binary")
    first = tmp_path / "first.parquet"
    prism_stream.sample(str(src), str(first), ratio=1.0)
    again = tmp_path / "again.parquet"
    summary = prism_stream.sample(str(first), str(again), ratio=0.5, seed=3)
    kept_points = rec[finite(rec)]
    want = oracle.sample([unpack(kept_points[field])], ratio=0.5, seed=3).kept[0]
    assert summary.kept == len(want) and summary.bins == oracle.sample(
        [unpack(kept_points[field])], ratio=0.5, seed=3).bins
    got = duckdb.sql(f"SELECT red, green, blue FROM read_parquet('{again}')").fetchnumpy()
    channels = unpack(np.ascontiguousarray(kept_points[field]).view(np.uint32)[want])
    assert sorted(zip(*[got[c].tolist() for c in ("red", "green", "blue")])) == sorted(
        zip(*[c.tolist() for c in channels]))


def test_eval_denoises_a_pcd(tmp_path):
    """--denoise re-reads its cleaned Parquet copy by color name: a PCD was refused (its word stayed packed)."""
    from prism_stream.evaluate.run import evaluate

    rec, header = organized(width=60, height=40, seed=4)
    src = write_pcd(tmp_path / "in.pcd", rec, header, "binary")
    res = evaluate([str(src)], methods=("prism", "random"), preset="authors", metrics=False)
    facts = res.inputs["in.pcd"]["denoise"]
    assert facts["points_before"] == int(finite(rec).sum()) and facts["removed"] >= 0
    prism, rand = res.rows
    assert prism.count == rand.count > 0


def test_eval_denoises_a_parquet_whose_rgba_word_is_kept_whole(tmp_path):
    """An rgba word beside an alpha column of its own stays packed in --denoise's cleaned copy, which its reader
    reads as the input's (eval refused it, naming PCD fields; a reviewer's find)."""
    import pyarrow as pa

    from prism_stream.evaluate.run import evaluate

    rec, _ = organized(width=60, height=40, seed=4)
    rec = rec[finite(rec)]
    n = len(rec)
    src = tmp_path / "in.parquet"
    pq.write_table(pa.table({"x": rec["x"], "y": rec["y"], "z": rec["z"],
                             "rgba": np.ascontiguousarray(rec["rgb"]).view(np.uint32),
                             "alpha": np.linspace(0, 1, n)}), src)
    res = evaluate([str(src)], methods=("prism", "random"), preset="authors", metrics=False)
    facts = res.inputs["in.parquet"]["denoise"]
    assert facts["points_before"] == n and facts["removed"] >= 0
    prism, rand = res.rows
    assert prism.count == rand.count > 0


def packed_parquet(path, rec, field, kind):
    """A Parquet the way PCD converters write one: the packed word as one column (a float32's bits, a uint32,
    an int32 or an int64 holding the word), the rest as they are."""
    import pyarrow as pa

    word = np.ascontiguousarray(rec[field]).view(np.uint32)
    column = {"float32": word.view(np.float32), "uint32": word, "int32": word.view(np.int32),
              "int64": word.astype(np.int64)}[kind]
    table = pa.table({"x": rec["x"], "y": rec["y"], "z": rec["z"], field.upper() if kind == "int32" else field: column,
                      "ring": rec["ring"]})
    pq.write_table(table, path, row_group_size=97)
    return path


@pytest.mark.parametrize("field,kind", [("rgb", "float32"), ("rgb", "int32"), ("rgba", "uint32"), ("rgb", "int64")])
@pytest.mark.parametrize("memory", ["0", "1000000"])
def test_a_parquet_with_a_packed_color_word_samples_as_its_channels(tmp_path, monkeypatch, field, kind, memory):
    """A Parquet without red, green, blue whose colors are PCL's packed word (issue 28, item 10): the word is
    read as its three 8-bit channels, the oracle's kept rows come out, written as red, green, blue (and alpha)."""
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", memory)
    rec, _ = organized(width=40, height=25, seed=2, field=field)
    rec = rec[finite(rec)]
    src = packed_parquet(tmp_path / "in.parquet", rec, field, kind)
    out = tmp_path / "out.parquet"
    summary = prism_stream.sample(str(src), str(out), ratio=RATIO, seed=5, chunk_size=64)
    word = np.ascontiguousarray(rec[field]).view(np.uint32)
    want = oracle.sample([unpack(word)], ratio=RATIO, seed=5)
    assert (summary.kept, summary.bins) == (len(want.kept[0]), want.bins)
    table = pq.read_table(out)
    alpha = ["alpha"] if field == "rgba" else []
    assert table.column_names == ["x", "y", "z", "red", "green", "blue", *alpha, "ring"]
    assert table.column("x").to_numpy().tobytes() == rec["x"][want.kept[0]].tobytes()
    for name, channel in zip(("red", "green", "blue"), unpack(word[want.kept[0]])):
        assert table.column(name).to_numpy().tolist() == channel.tolist(), name
    if alpha:
        assert table.column("alpha").to_numpy().tolist() == (word[want.kept[0]] >> 24).tolist()
    # into LAS, the channels are the LAS colors (8-bit values * 256)
    import laspy

    las = laspy.read(prism_stream.sample(str(src), str(tmp_path / "out.las"), ratio=RATIO, seed=5).output)
    assert np.asarray(las.red).tolist() == (unpack(word[want.kept[0]])[0] * 256).tolist()


def test_a_packed_word_beside_named_channels_or_with_rgb_columns_is_not_unpacked(tmp_path):
    """red, green, blue present (or --rgb-columns given) take precedence: the word is an ordinary column."""
    import pyarrow as pa

    rec, _ = organized(width=10, height=10, seed=1)
    rec = rec[finite(rec)]
    n = len(rec)
    table = pa.table({"x": rec["x"], "rgb": np.ascontiguousarray(rec["rgb"]).view(np.float32),
                      "red": np.full(n, 7, np.uint8), "green": np.arange(n, dtype=np.uint8), "blue": np.zeros(n, np.uint8)})
    pq.write_table(table, tmp_path / "both.parquet")
    prism_stream.sample(str(tmp_path / "both.parquet"), str(tmp_path / "o.parquet"), ratio=1.0)
    assert pq.read_table(tmp_path / "o.parquet").column_names == ["x", "rgb", "red", "green", "blue"]
    only = tmp_path / "only.parquet"
    pq.write_table(table.select(["x", "rgb"]), only)
    with pytest.raises(prism_stream.errors.NoColorError, match="no color column 'r'"):
        prism_stream.sample(str(only), str(tmp_path / "o2.parquet"), ratio=1.0, rgb_columns=("r", "g", "b"))


def test_a_packed_word_that_is_not_a_32_bit_color_is_refused_naming_the_file(tmp_path):
    import pyarrow as pa

    for kind in (pa.float16(), pa.uint8(), pa.int16()):  # no 32-bit word: not a packed color (every point
        narrow = tmp_path / "narrow.parquet"  # came out black from a float16's bits; a hostile tester's find)
        pq.write_table(pa.table({"x": np.zeros(3, np.float32), "rgb": pa.array([1, 2, 3]).cast(kind)}), narrow)
        with pytest.raises(prism_stream.errors.NoColorError, match="no color column"):
            prism_stream.sample(str(narrow), str(tmp_path / "o.parquet"), ratio=1.0)

    bad = tmp_path / "bad.parquet"
    pq.write_table(pa.table({"x": np.zeros(3, np.float32), "rgb": np.array([1, 2, 1 << 40], np.int64)}), bad)
    with pytest.raises(CorruptInput, match="not a 32-bit color word") as e:
        prism_stream.sample(str(bad), str(tmp_path / "o.parquet"), ratio=1.0)
    assert "bad.parquet" in str(e.value)
    assert not (tmp_path / "o.parquet").exists()
