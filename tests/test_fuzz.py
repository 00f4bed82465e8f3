"""Mutated LAS, PLY and PCD files: a correct output or a one-line refusal, never anything else.

Hypothesis starts from small valid files (generated here) and changes their
header words, flips and inserts bytes, or cuts them short. Whatever it
makes, ``prism_stream.sample`` must either return a summary whose output
holds exactly ``kept`` rows, or raise a ``PrismError`` naming the file,
leaving no output and no temporary file. Any other exception is a bug. A
few mutants also go through the command, in a child process, so that a
crash of the interpreter (a panic, a segfault) would show as a signal.

Budget: a few hundred examples in all, well under two minutes.
"""

from __future__ import annotations

import functools
import os
import resource
import subprocess
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import prism_stream
from prism_stream.errors import PrismError

from conftest import lzf_literals, prism_stream_command, write_las

N = 40
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


def mutate(data: bytes, draw) -> bytes:
    """One mutation: a header word replaced, bytes flipped or inserted, or the file cut short."""
    kind = draw(st.sampled_from(["word", "flip", "insert", "truncate"]))
    end = data.find(b"end_header")
    end = data.find(b"DATA") if end < 0 else end
    end = 375 if end < 0 else end  # LAS: the header block
    if kind == "word":
        header = data[:end]
        words = [i for i, w in enumerate(header.split(b" ")) if w]
        if not words:
            return data
        parts = header.split(b" ")
        i = draw(st.sampled_from(words))
        parts[i] = draw(st.sampled_from([b"0", b"-1", b"1", b"4294967295", b"99999999999", b"nan", b"x", b"",
                                         b"list", b"double", b"binary", b"ascii", b"1e9", b"\xff"]))
        return b" ".join(parts) + data[end:]
    if kind == "flip":
        out = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            at = draw(st.integers(0, len(out) - 1))
            out[at] = draw(st.integers(0, 255))
        return bytes(out)
    if kind == "insert":
        at = draw(st.integers(0, len(data)))
        return data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:]
    return data[:draw(st.integers(0, len(data) - 1))]


def check_one(folder: Path, name: str, data: bytes) -> str:
    """Run the API on one mutant and assert one of the two allowed outcomes; says which it was."""
    path = folder / name
    path.write_bytes(data)
    output = folder / "out.parquet"
    if output.exists():
        output.unlink()
    temp = folder / "temp"
    temp.mkdir(exist_ok=True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            summary = prism_stream.sample(str(path), str(output), ratio=0.5, chunk_size=16, temp_dir=str(temp))
    except PrismError as exc:
        assert "\n" not in str(exc), str(exc)
        assert exc.path in (str(path), str(output)), str(exc)
        assert not output.exists(), "a refused run left its output"
        outcome = "refused"
    else:
        assert pq.read_metadata(output).num_rows == summary.kept
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
    mutant = mutate(_seeds()[seed_name], data.draw)
    check_one(tmp_path, seed_name.replace("seed", "mutant"), mutant)


def _limit():
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


@pytest.mark.parametrize("seed_name", ["seed.las", "seed_binary_little_endian.ply", "seed_binary_compressed.pcd"])
def test_mutants_through_the_command(tmp_path, seeds, seed_name):
    """A handful of mutants in a child process: an interpreter crash would be a signal here."""
    rng = np.random.default_rng(7)
    base = bytearray(seeds[seed_name])
    cmd = prism_stream_command()
    for i in range(4):
        data = bytearray(base)
        for at in rng.integers(0, len(data), size=6):
            data[at] = int(rng.integers(0, 256))
        path = tmp_path / f"m{i}{Path(seed_name).suffix}"
        path.write_bytes(bytes(data))
        output = tmp_path / f"m{i}.parquet"
        r = subprocess.run([*cmd, str(path), str(output), "--ratio", "0.5", "-q"], capture_output=True, text=True,
                           timeout=120, preexec_fn=_limit)
        assert r.returncode >= 0, f"killed by signal {-r.returncode}"
        assert "Traceback" not in r.stderr
        if r.returncode == 0:
            assert output.is_file()
        else:
            lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
            assert len(lines) == 1 and lines[0].startswith("prism-stream: error: "), r.stderr
            assert not output.exists()
