"""Size checks: the records a header declares must fill the file exactly where it says (issue 13).

Plausible garbage used to pass with exit 0: a LAS with its header written
twice at the start (every record read 227 bytes off) and a binary PCD with
a duplicated header (942 of 1,000 points read, from the wrong bytes). Each
file here is built in the test; each refusal is exit 6, one line, with the
numbers that disagree.
"""

from __future__ import annotations

import struct
import subprocess

import laspy
from laspy.vlrs.vlrlist import VLRList
import numpy as np
import pytest

import prism_stream
from prism_stream.errors import CorruptInput
from prism_stream.formats import las as las_format

from conftest import edge_file, prism_stream_command, write_las

N = 1000


def colors(n=N, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(n, 3))


def las_offset(raw: bytes) -> int:
    return struct.unpack_from("<I", raw, 96)[0]


def duplicate_header(src, dest):
    """The header (and VLRs) written twice at the start: the header's offset now points into the copy."""
    raw = src.read_bytes()
    dest.write_bytes(raw[:las_offset(raw)] + raw)
    return dest


def refused(tmp_path, src, *words):
    """Run the CLI on ``src``: exit 6, one line naming the file and every word, no output left."""
    out = tmp_path / "out.parquet"
    r = subprocess.run([*prism_stream_command(), str(src), str(out), "--ratio", "0.5", "--quiet"],
                       capture_output=True, text=True, timeout=300)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 6, r.stderr
    assert len(lines) == 1 and lines[0].startswith("prism-stream: error: "), r.stderr
    assert str(src) in lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not out.exists()
    with pytest.raises(CorruptInput) as info:
        prism_stream.sample(str(src), str(out), ratio=0.5)
    assert info.value.path == str(src) and "\n" not in str(info.value)
    return lines[0]


@pytest.mark.parametrize("version, fmt", [("1.2", 3), ("1.4", 7)])
def test_las_with_its_header_written_twice_is_refused(tmp_path, version, fmt):
    good = write_las(tmp_path / "good.las", colors(), point_format=fmt, version=version)
    bad = duplicate_header(good, tmp_path / "twice.las")
    off = las_offset(good.read_bytes())
    size = bad.stat().st_size
    # the numbers: records, where they end, where the file ends, how much is over
    line = refused(tmp_path, bad, f"{N} records", f"ending at byte {size - off}", f"ends at byte {size}",
                   f"{off} bytes left over")
    assert "misaligned" in line
    # the file it was made from is read as before
    assert prism_stream.sample(str(good), str(tmp_path / "g.parquet"), ratio=0.5).points == N


def test_las_with_one_stray_byte_after_the_records_is_refused(tmp_path):
    good = write_las(tmp_path / "good.las", colors())
    bad = tmp_path / "stray.las"
    bad.write_bytes(good.read_bytes() + b"\0")
    refused(tmp_path, bad, "1 bytes left over")


def test_las_one_byte_short_is_still_refused(tmp_path):
    good = write_las(tmp_path / "good.las", colors())
    bad = tmp_path / "short.las"
    bad.write_bytes(good.read_bytes()[:-1])
    refused(tmp_path, bad, f"{N} points", f"holds {N - 1}")


def test_las_14_records_end_where_the_evlrs_begin(tmp_path):
    """EVLRs after the records are not left-over bytes; a stray byte between records and EVLRs is."""
    src = write_las(tmp_path / "plain.las", colors(), point_format=7, version="1.4")
    las = laspy.read(str(src))
    las.evlrs = VLRList([laspy.VLR("prism-test", 7, "an EVLR", b"x" * 100)])
    good = tmp_path / "evlr.las"
    las.write(str(good))
    raw = good.read_bytes()
    evlr_start, nevlr = struct.unpack_from("<QI", raw, 235)
    assert nevlr == 1 and evlr_start < len(raw)
    assert prism_stream.sample(str(good), str(tmp_path / "g.parquet"), ratio=0.5).points == N
    # one byte slipped in before the EVLR (its start moved with it): the records no longer reach it
    bad = tmp_path / "gap.las"
    patched = bytearray(raw[:evlr_start] + b"\0" + raw[evlr_start:])
    struct.pack_into("<Q", patched, 235, evlr_start + 1)
    bad.write_bytes(bytes(patched))
    refused(tmp_path, bad, f"starts at byte {evlr_start + 1}", "1 bytes left over")


def test_las_13_waveform_data_after_the_records_is_accepted(tmp_path):
    """laspy's LAS 1.3 sample keeps 160 bytes of waveform packets after its records (header field at 227).

    It has no RGB (so no run can bin it); the size check itself must pass it.
    """
    src = edge_file("laspy__simple1_3.las")
    raw = src.read_bytes()
    assert struct.unpack_from("<Q", raw, 227)[0] < len(raw)  # the file really has a tail
    facts = las_format.check_header(str(src))
    assert facts["count"] == laspy.open(str(src)).header.point_count
    bad = tmp_path / "stray13.las"  # a byte slipped in between the records and the waveform data
    patched = bytearray(raw[:-160] + b"\0" + raw[-160:])
    struct.pack_into("<Q", patched, 227, len(raw) - 160 + 1)
    bad.write_bytes(bytes(patched))
    with pytest.raises(CorruptInput, match="waveform/EVLR data starts at byte"):
        las_format.check_header(str(bad))


def test_laz_with_its_header_written_twice_is_refused(tmp_path):
    good = write_las(tmp_path / "good.laz", colors())
    bad = duplicate_header(good, tmp_path / "twice.laz")
    refused(tmp_path, bad, "chunk table offset", "outside the point data")


@pytest.mark.parametrize("keep", [0.5, 0.9])
def test_a_laz_file_cut_short_says_so(tmp_path, keep):
    """A LAZ copied or downloaded in part: its chunk table lies past the end. The message said 'a duplicated
    header or a wrong offset?' (hostile round 52); it now says the file is cut short."""
    good = write_las(tmp_path / "good.laz", colors())
    raw = good.read_bytes()
    cut = tmp_path / "cut.laz"
    cut.write_bytes(raw[:int(len(raw) * keep)])
    refused(tmp_path, cut, "before its LAZ chunk table", "cut short")


def test_laz_whose_chunk_table_does_not_cover_the_points_is_refused(tmp_path):
    """1,000 points in chunks of 50,000 is one chunk; a table listing two disagrees with the header."""
    good = write_las(tmp_path / "good.laz", colors())
    raw = bytearray(good.read_bytes())
    table = struct.unpack_from("<q", raw, las_offset(raw))[0]
    version, chunks = struct.unpack_from("<II", raw, table)
    assert (version, chunks) == (0, 1)
    struct.pack_into("<I", raw, table + 4, 2)
    bad = tmp_path / "chunks.laz"
    bad.write_bytes(bytes(raw))
    refused(tmp_path, bad, f"{N} points", "1 chunks", "lists 2 chunks")


# -- PCD -----------------------------------------------------------------

def pcd_cloud(n=N, seed=0):
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    for a in "xyz":
        rec[a] = rng.normal(size=n)
    c = colors(n, seed).astype(np.uint32)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    header = (f"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n").encode()
    return header, rec.tobytes()


def test_binary_pcd_with_a_duplicated_header_is_refused(tmp_path):
    header, body = pcd_cloud()
    good = tmp_path / "good.pcd"
    good.write_bytes(header + body)
    assert prism_stream.plan(str(good), ratio=0.5).points == N
    bad = tmp_path / "twice.pcd"
    bad.write_bytes(header + header + body)
    end = len(header) + N * 16
    refused(tmp_path, bad, f"{N} points of 16 bytes", f"ending at byte {end}",
            f"ends at byte {end + len(header)}", f"{len(header)} bytes left over")


def test_binary_pcd_with_a_stray_byte_is_refused(tmp_path):
    header, body = pcd_cloud()
    bad = tmp_path / "stray.pcd"
    bad.write_bytes(header + body + b"\n")
    refused(tmp_path, bad, "1 bytes left over")


def test_binary_pcd_one_record_short_is_refused(tmp_path):
    header, body = pcd_cloud()
    bad = tmp_path / "short.pcd"
    bad.write_bytes(header + body[:-16])
    refused(tmp_path, bad, f"declares {N} points", f"holds {N - 1}")
