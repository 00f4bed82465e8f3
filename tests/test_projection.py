"""--keep/--drop on a Parquet input: the run decodes only the columns the output keeps (with its coordinates and
colors), and writes what a run that decodes every column writes."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest
from conftest import EDGE

import prism_stream
from prism_stream.formats import parquet as parquet_format

# xyz as a fixed-size list, a WKB geometry column, colors named Red, Green, Blue: 15 columns
SOURCE = EDGE / "pdal__1.2-with-color.parquet"


def record_reads(monkeypatch) -> list:
    """The columns of every Parquet read from here on (None: every column), appended to the list returned."""
    asked = []
    real = parquet_format.ParquetSource._batches

    def recorded(self, chunk_size, start, stop, columns):
        asked.append(columns)
        yield from real(self, chunk_size, start, stop, columns)

    monkeypatch.setattr(parquet_format.ParquetSource, "_batches", recorded)
    return asked


@pytest.mark.parametrize("selection", [{"keep": ("Intensity",)}, {"drop": ("GpsTime", "UserData", "ScanAngleRank")}])
@pytest.mark.parametrize("space, reads", [(None, "held"), (None, "one"), (None, "two"), ("0.5", "held"),
                                          ("0.5", "one")])
def test_a_parquet_input_decodes_only_the_columns_the_output_keeps(tmp_path, monkeypatch, selection, space, reads):
    """Held in memory, streamed with a spill (restored from it) or read twice: the same output."""
    from prism_stream.engines import local

    if reads != "held":
        monkeypatch.setattr(local, "memory_points", lambda: 0)
    options = dict(ratio=0.1, seed=3, space=space, reads="auto" if reads == "held" else reads, **selection)
    whole = tmp_path / "whole.parquet"
    with monkeypatch.context() as m:
        m.setattr(parquet_format.ParquetSource, "read_only", lambda self, names: None)  # every column decoded
        prism_stream.sample(str(SOURCE), str(whole), **options)
    asked = record_reads(monkeypatch)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(SOURCE), str(out), **options)
    written = pq.read_table(out)
    assert written.equals(pq.read_table(whole))
    assert asked and None not in asked  # no read of every column
    assert {c for columns in asked for c in columns} == set(written.column_names)
    everything = pq.read_schema(SOURCE).names
    assert len(written.column_names) < len(everything)


def test_a_packed_color_word_is_decoded_whatever_the_selection(tmp_path, monkeypatch):
    """PCL's packed ``rgb`` stands in for red, green, blue (which the output is written with): the word is read
    whatever --keep says, and the output is the one a full decode writes."""
    import numpy as np
    import pyarrow as pa

    rng = np.random.default_rng(5)
    n = 5_000
    rgb = (rng.integers(0, 8, n) * 30 << 16 | rng.integers(0, 8, n) * 30 << 8 | rng.integers(0, 4, n) * 60)
    pq.write_table(pa.table({"x": rng.random(n), "y": rng.random(n), "z": rng.random(n),
                             "rgb": rgb.astype(np.uint32), "intensity": rng.integers(0, 9, n).astype(np.uint16),
                             "label": rng.integers(0, 3, n).astype(np.int32)}), tmp_path / "packed.parquet")
    options = dict(ratio=0.05, keep=("intensity",))
    with monkeypatch.context() as m:
        m.setattr(parquet_format.ParquetSource, "read_only", lambda self, names: None)
        prism_stream.sample(str(tmp_path / "packed.parquet"), str(tmp_path / "whole.parquet"), **options)
    prism_stream.sample(str(tmp_path / "packed.parquet"), str(tmp_path / "out.parquet"), **options)
    written = pq.read_table(tmp_path / "out.parquet")
    assert written.equals(pq.read_table(tmp_path / "whole.parquet"))
    assert "label" not in written.column_names and {"red", "green", "blue", "intensity"} <= set(written.column_names)


def _points(n: int, seed: int):
    import numpy as np

    rng = np.random.default_rng(seed)
    return rng, {"red": (rng.integers(0, 6, n) * 40).astype(np.uint16),
                 "green": (rng.integers(0, 6, n) * 40).astype(np.uint16),
                 "blue": rng.integers(0, 3, n).astype(np.uint16) * 90,
                 "intensity": rng.integers(0, 9, n).astype(np.uint16)}


@pytest.mark.parametrize("extra", [dict(space="0.5"), dict(denoise="sor:8,2.0")])
def test_coordinates_in_a_list_column_are_read_for_the_space_and_denoise(tmp_path, monkeypatch, extra):
    """Found by a reviewer: coordinates held in a ``position`` list column (which --space and --denoise read)
    were left out of the decode by --keep: the run failed with "no coordinates found"."""
    import numpy as np
    import pyarrow as pa

    n = 4_000
    rng, columns = _points(n, 6)
    xyz = rng.random((n, 3))
    position = pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3)
    pq.write_table(pa.table({"position": position, **columns}), tmp_path / "in.parquet")
    options = dict(ratio=0.1, keep=("intensity",), **extra)
    with monkeypatch.context() as m:
        m.setattr(parquet_format.ParquetSource, "read_only", lambda self, names: None)
        prism_stream.sample(str(tmp_path / "in.parquet"), str(tmp_path / "whole.parquet"), **options)
    prism_stream.sample(str(tmp_path / "in.parquet"), str(tmp_path / "out.parquet"), **options)
    assert pq.read_table(tmp_path / "out.parquet").equals(pq.read_table(tmp_path / "whole.parquet"))
    assert np.isfinite(xyz).all()


def test_a_geometry_one_input_declares_is_read_from_every_input(tmp_path, monkeypatch):
    """Found by a reviewer: of two inputs with the same columns, only the first declaring its WKB column a
    GeoParquet geometry, the second decoded it no more under --keep, and the writer (which takes the first
    input's geometry for all) failed."""
    import json
    import struct

    import pyarrow as pa

    inputs = []
    for i in range(2):
        n = 600
        rng, columns = _points(n, i)
        xs, ys = rng.random(n), rng.random(n)
        wkb = [struct.pack("<BIddd", 1, 1001, x, y, 1.0) for x, y in zip(xs, ys)]  # ISO WKB: Point Z
        table = pa.table({"geometry": pa.array(wkb, pa.binary()), **columns})
        if i == 0:
            geo = {"version": "1.0.0", "primary_column": "geometry",
                   "columns": {"geometry": {"encoding": "WKB", "geometry_types": ["Point Z"]}}}
            table = table.replace_schema_metadata({b"geo": json.dumps(geo).encode()})
        pq.write_table(table, tmp_path / f"in{i}.parquet")
        inputs.append(str(tmp_path / f"in{i}.parquet"))
    options = dict(ratio=0.2, keep=("intensity",))
    with monkeypatch.context() as m:
        m.setattr(parquet_format.ParquetSource, "read_only", lambda self, names: None)
        prism_stream.sample(inputs, str(tmp_path / "whole.parquet"), **options)
    prism_stream.sample(inputs, str(tmp_path / "out.parquet"), **options)
    written = pq.read_table(tmp_path / "out.parquet")
    assert written.equals(pq.read_table(tmp_path / "whole.parquet"))
    assert written.column("geometry").null_count == 0


@pytest.mark.parametrize("reads", ["one", "two"])
def test_the_dask_workers_decode_only_the_columns_the_output_keeps(tmp_path, monkeypatch, reads):
    """The units carry their source's columns to the workers: spilled or read again, every worker read
    decodes the kept columns alone, and the dataset is the local run's."""
    import distributed

    from prism_stream.engines import dask as dask_engine

    options = dict(ratio=0.1, seed=3, keep=("Intensity",))
    source = tmp_path / "groups.parquet"  # row groups of 200 points: units of their own
    pq.write_table(pq.read_table(SOURCE), source, row_group_size=200)
    local = tmp_path / "local.parquet"
    prism_stream.sample(str(source), str(local), **options)
    asked = record_reads(monkeypatch)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        summary = dask_engine.sample(client, str(source), str(tmp_path / "out"), unit_size=200, reads=reads,
                                     **options)
    assert summary.plan["dask"]["units"] > 1
    written = dask_engine.read_dataset(str(tmp_path / "out"))
    assert written.equals(pq.read_table(local))
    assert asked and None not in asked
    assert {c for columns in asked for c in columns} == set(written.column_names)


def test_the_temporary_disk_forecast_counts_only_the_decoded_columns(monkeypatch):
    """A spilled point holds the columns decoded: the forecast's bound is smaller by exactly the widths of the
    fixed-width columns --keep leaves out, for every point it bounds."""
    from prism_stream.engines import local

    monkeypatch.setattr(local, "memory_points", lambda: 0)
    temps = {}
    for name, selection in (("all", {}), ("kept", {"keep": ("Intensity",)})):
        summary = prism_stream.sample(str(SOURCE), None, ratio=0.1, reads="one", **selection)
        temps[name] = summary.plan["temp"]
    schema = pq.read_schema(SOURCE)
    kept = {"xyz", "wkb", "Red", "Green", "Blue", "Intensity"}  # the coordinates (both columns), colors, kept
    left_out = [f for f in schema if f.name not in kept]
    assert left_out and all(pa_fixed(f.type) for f in left_out)
    width = sum(f.type.bit_width // 8 for f in left_out)
    bound = temps["all"]["spill_points_bound"]
    assert temps["kept"]["spill_points_bound"] == bound
    assert temps["all"]["spill_bytes_bound"] - temps["kept"]["spill_bytes_bound"] == bound * width


def pa_fixed(kind) -> bool:
    try:
        return kind.bit_width > 0
    except ValueError:
        return False


@pytest.mark.parametrize("form", ["wkb", "list", "fixed"])
def test_the_forecast_sizes_list_and_wkb_coordinates_by_what_they_hold(tmp_path, form):
    """A spilled point's columns of no fixed width (WKB points, a list of three numbers) are sized by the
    file's own bytes a row, not a guess below what they hold: the forecast's bytes a point are at least the
    decoded columns' Arrow bytes, and within a third of them."""
    import numpy as np
    import pyarrow as pa

    from prism_stream.formats import open_source
    from prism_stream.run.tempspace import record_bytes

    rng = np.random.default_rng(2)
    n = 20_000
    xyz = rng.random((n, 3))
    column = {"wkb": pa.array([b"\x01" + np.array([1001], "<u4").tobytes() + p.astype("<f8").tobytes()
                               for p in xyz], pa.binary()),
              "list": pa.array(list(map(list, xyz)), pa.list_(pa.float64())),
              "fixed": pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3)}[form]
    name = {"wkb": "wkb", "list": "coords", "fixed": "position"}[form]
    table = pa.table({name: column, "red": np.zeros(n, np.uint8), "green": np.ones(n, np.uint8),
                      "blue": np.ones(n, np.uint8), "intensity": np.ones(n, np.uint16),
                      "label": np.ones(n, np.int64)})
    pq.write_table(table, tmp_path / "in.parquet")
    source = open_source(str(tmp_path / "in.parquet"), 0)
    source.read_only([name, "intensity"])
    held = sum(table.column(c).nbytes for c in source.read_columns) / n
    assert held <= record_bytes(source) <= held * 4 / 3
