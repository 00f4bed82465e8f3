"""SPEC 5: the output depends on input, options and seed only.

Not on chunk size, decoder threads, how a file is split into row groups,
the file format the same records come in, or how the same files are named
on the command line; a different seed gives a different sample with the
same per-bin counts.
"""

from __future__ import annotations

from collections import Counter

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import oracle
from conftest import random_colors, real_file, write_las, write_parquet
from prism_stream import sample
from prism_stream.core.passes import DEFAULT_CHUNK


def run(inputs, out, **opts) -> pa.Table:
    sample(inputs, str(out), overwrite=True, **opts)
    return pq.read_table(out).replace_schema_metadata(None)


def assert_same_table(a: pa.Table, b: pa.Table):
    assert a.num_rows == b.num_rows
    assert a.equals(b)


@pytest.fixture(scope="module")
def small_las(tmp_path_factory):
    """A 16-bit file with skewed bins, small enough for chunk_size=1."""
    return write_las(tmp_path_factory.mktemp("det") / "small.las", random_colors(400, seed=3, palette=40, depth=16))


@pytest.mark.parametrize("opts", [
    dict(ratio=0.1, mode="exact", seed=1),
    dict(ratio=0.1, mode="paper", color_space="chroma", quant_bits=2, seed=2),
    dict(k=3, seed=3),
], ids=["exact", "paper", "k"])
def test_chunk_size_does_not_matter_small(small_las, opts, tmp_path):
    base = run(str(small_las), tmp_path / "base.parquet", chunk_size=DEFAULT_CHUNK, **opts)
    assert base.num_rows > 0
    for chunk in (1, 7, 1000):
        assert_same_table(run(str(small_las), tmp_path / f"c{chunk}.parquet", chunk_size=chunk, **opts), base)


@pytest.mark.parametrize("name,chunks", [
    ("pdal__warsaw_small.las", (7, 1000)),
    ("laspy__fullwave.laz", (333, 4096)),
    ("pdal__autzen_trim.las", (1000, 65_536)),
])
def test_chunk_size_does_not_matter_real(name, chunks, tmp_path):
    path = str(real_file(name))
    opts = dict(ratio=0.05, mode="exact", color_space="rgb", seed=5)
    base = run(path, tmp_path / "base.parquet", **opts)
    for chunk in chunks:
        assert_same_table(run(path, tmp_path / f"c{chunk}.parquet", chunk_size=chunk, **opts), base)


@pytest.mark.parametrize("name", ["laspy__fullwave.laz", "potree__lion_takanawa.copc.laz"])
def test_threads_do_not_matter_laz(name, tmp_path):
    path = str(real_file(name))
    opts = dict(ratio=0.02, mode="exact", seed=8, chunk_size=50_000)
    assert_same_table(run(path, tmp_path / "t2.parquet", threads=2, **opts),
                      run(path, tmp_path / "t1.parquet", threads=1, **opts))


def test_threads_and_row_groups_do_not_matter_parquet(tmp_path):
    """The same rows in one row group or many, read with 1 or 2 threads: one output."""
    las = laspy.read(str(real_file("pdal__autzen_trim.las")))
    table = pa.table({"x": np.asarray(las.x), "y": np.asarray(las.y), "z": np.asarray(las.z),
                      "red": np.asarray(las.red), "green": np.asarray(las.green), "blue": np.asarray(las.blue)})
    one = write_parquet(tmp_path / "one.parquet", table)
    many = write_parquet(tmp_path / "many.parquet", table, row_group_size=7_777)
    assert pq.ParquetFile(many).metadata.num_row_groups > 10
    opts = dict(ratio=0.03, mode="exact", color_space="chroma", seed=12)
    base = run(str(one), tmp_path / "a.parquet", threads=1, **opts)
    assert_same_table(run(str(many), tmp_path / "b.parquet", threads=2, chunk_size=5_000, **opts), base)
    assert_same_table(run(str(one), tmp_path / "c.parquet", threads=2, **opts), base)


def test_format_of_the_same_records_does_not_matter(tmp_path):
    """One record set as LAS, LAZ and Parquet keeps the same records (the same x, y, z, colors)."""
    colors = random_colors(5000, seed=21, palette=300, depth=16)
    las_path = write_las(tmp_path / "same.las", colors, seed=21)
    laz_path = write_las(tmp_path / "same.laz", colors, seed=21)
    las = laspy.read(str(las_path))
    pq_path = write_parquet(tmp_path / "same.parquet", {
        "x": np.asarray(las.x), "y": np.asarray(las.y), "z": np.asarray(las.z),
        "red": np.asarray(las.red), "green": np.asarray(las.green), "blue": np.asarray(las.blue)})
    opts = dict(ratio=0.07, mode="exact", seed=77)
    cols = ["x", "y", "z", "red", "green", "blue"]
    tables = [run(str(p), tmp_path / f"out-{p.suffix[1:]}.parquet", **opts).select(cols)
              for p in (las_path, laz_path, pq_path)]
    assert tables[0].num_rows == 350
    assert_same_table(tables[1], tables[0])
    assert_same_table(tables[2], tables[0])


def test_same_files_named_differently_give_the_same_output(tmp_path):
    """A list of paths and a glob that expands to the same list, in the same order: one output."""
    folder = tmp_path / "parts"
    folder.mkdir()
    paths = [write_las(folder / f"p{i}.las", random_colors(600 + 100 * i, seed=i, palette=50), seed=i)
             for i in range(3)]
    opts = dict(ratio=0.1, mode="exact", seed=6)
    listed = run([str(p) for p in paths], tmp_path / "listed.parquet", **opts)
    globbed = run(str(folder / "p*.las"), tmp_path / "globbed.parquet", **opts)
    relative = run([str(folder / ".." / "parts" / p.name) for p in paths], tmp_path / "rel.parquet", **opts)
    assert_same_table(globbed, listed)
    assert_same_table(relative, listed)


def test_identical_files_in_either_order_give_the_same_output(tmp_path):
    """Ids come from (ordinal, record), not from names: two copies of one file swap freely."""
    colors = random_colors(800, seed=4, palette=60, depth=16)
    a = write_las(tmp_path / "a.las", colors, seed=4)
    b = write_las(tmp_path / "b.las", colors, seed=4)
    assert a.read_bytes() == b.read_bytes()
    opts = dict(ratio=0.1, mode="exact", seed=31)
    ab = run([str(a), str(b)], tmp_path / "ab.parquet", **opts)
    ba = run([str(b), str(a)], tmp_path / "ba.parquet", **opts)
    assert ab.num_rows == 160
    assert_same_table(ab, ba)


def test_running_twice_gives_the_same_output(small_las, tmp_path):
    opts = dict(ratio=0.2, mode="exact", seed=123)
    assert_same_table(run(str(small_las), tmp_path / "a.parquet", **opts),
                      run(str(small_las), tmp_path / "b.parquet", **opts))


def _per_bin(table: pa.Table) -> Counter:
    """Kept points per rgb bin (the files here are 16-bit: v >> 8)."""
    ch = [table.column(c).to_numpy().astype(np.int64) >> 8 for c in ("red", "green", "blue")]
    return Counter(oracle.bin_keys(*ch).tolist())


@pytest.mark.parametrize("opts", [dict(ratio=0.05, mode="paper"), dict(k=2)], ids=["paper", "k"])
def test_other_seed_other_sample_same_bin_counts(opts, tmp_path):
    path = str(real_file("pdal__warsaw_small.las"))
    a = run(path, tmp_path / "a.parquet", seed=0, **opts)
    b = run(path, tmp_path / "b.parquet", seed=1, **opts)
    assert a.num_rows == b.num_rows
    assert not a.equals(b)
    assert _per_bin(a) == _per_bin(b)


def test_other_seed_exact_mode_same_total_and_same_quota_multiset(tmp_path):
    """Exact mode: the seed also picks which bins get K + 1, but never how many, nor T."""
    path = str(real_file("pdal__warsaw_small.las"))
    a = run(path, tmp_path / "a.parquet", seed=0, ratio=0.5)
    b = run(path, tmp_path / "b.parquet", seed=1, ratio=0.5)
    assert a.num_rows == b.num_rows == 1500
    assert not a.equals(b)
    ca, cb = _per_bin(a), _per_bin(b)
    assert sorted(ca.values()) == sorted(cb.values())
    assert ca != cb  # with E > 0 extra bins, a new seed moves some of them
