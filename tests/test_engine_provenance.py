"""Every engine's every output says how it was made (SPEC 6, issue 13).

Engines: the local one (``prism-stream IN OUT``), DuckDB (``prism-stream
sql QUERY OUT``) and Dask (``--dask local:2``). Outputs: Parquet, LAS, LAZ,
PLY where the engine writes them; where it does not, the refusal is one line
and leaves nothing. The provenance is read back from each output's own
metadata by the format's library (pyarrow, laspy, plyfile), and its numbers
are checked against the oracle (tests/oracle.py): N, the points kept (and
the rows the output holds), the target, the bin count, the seed, the options
and each source's color-depth decision. The DuckDB table macro
(``prism_sample``) returns rows to the query that calls it and writes no
file, so it has no output metadata to check; its rows are
tests/test_duckdb_macro.py's.
"""

from __future__ import annotations

import glob
import json
import math
import os
import warnings

import laspy
import numpy as np
import plyfile
import pyarrow.parquet as pq
import pytest

from prism_stream.formats.ply import provenance_text
from prism_stream.formats.xyzout import read_provenance as xyz_provenance
from prism_stream_cli.main import run

import oracle
from conftest import random_colors, write_las, write_parquet

N = 3000
RATIO = 0.1
SEED = 17


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    """The same points as LAS (16-bit colors, v << 8) and as Parquet (8-bit colors), with their colors."""
    folder = tmp_path_factory.mktemp("cloud")
    rgb = random_colors(N, seed=9, palette=120)
    las = write_las(folder / "in.las", rgb << 8, point_format=3, extra={"ident": np.arange(N, dtype=np.uint32)})
    par = write_parquet(folder / "in.parquet", {"x": np.arange(N, dtype=np.float64), "y": np.zeros(N),
                                                "z": np.ones(N), "red": rgb[:, 0].astype(np.uint8),
                                                "green": rgb[:, 1].astype(np.uint8),
                                                "blue": rgb[:, 2].astype(np.uint8)})
    return {"las": las, "parquet": par, "rgb16": tuple(rgb[:, j] << 8 for j in range(3)),
            "rgb8": tuple(rgb[:, j].astype(np.uint8) for j in range(3))}


def cli(capsys, *args) -> tuple[int, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(SystemExit) as exc:
            run([str(a) for a in args])
    _, err = capsys.readouterr()
    return exc.value.code or 0, err


def provenance_of(path) -> list[dict]:
    """Every provenance record in one output file, read by its format's own library."""
    s = str(path)
    if s.endswith(".parquet"):
        meta = pq.ParquetFile(s).schema_arrow.metadata or {}
        return [json.loads(meta[b"prism_stream"])] if b"prism_stream" in meta else []
    if s.endswith((".las", ".laz")):
        with laspy.open(s) as r:
            return [json.loads(bytes(v.record_data)) for v in r.header.vlrs
                    if v.user_id == "prism-stream" and v.record_id == 1]
    if s.endswith(".xyz"):
        found = xyz_provenance(s)
        return [] if found is None else [found]
    text = provenance_text(plyfile.PlyData.read(s).comments)
    return [] if text is None else [json.loads(text)]


def rows_of(path) -> int:
    s = str(path)
    if s.endswith(".parquet"):
        return pq.ParquetFile(s).metadata.num_rows
    if s.endswith((".las", ".laz")):
        return laspy.open(s).header.point_count
    if s.endswith(".xyz"):
        return len(np.loadtxt(s, comments="//", ndmin=2))
    return len(plyfile.PlyData.read(s)["vertex"].data)


def assert_right(prov: dict, stored) -> None:
    """The provenance says what the oracle says this run does."""
    want = oracle.sample([stored], ratio=RATIO, seed=SEED)
    (r8, g8, b8), _ = oracle.to_8bit(stored)
    assert prov["points"] == N
    assert prov["target"] == math.floor(RATIO * N + 0.5)
    assert prov["kept"] == len(want.kept[0]) == prov["target"]  # exact mode keeps the target
    assert prov["bins"] == len(np.unique(oracle.bin_keys(r8, g8, b8)))
    assert prov["seed"] == SEED and prov["rule"] == "exact"
    assert prov["options"] == {"ratio": RATIO, "count": None, "k": None, "mode": "exact", "color_space": "rgb",
                               "quant_bits": 0, "color_depth": "auto", "seed": SEED}
    assert [s["color_depth"] for s in prov["sources"]] == want.depths


# -- local ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("ext", ["parquet", "las", "laz", "ply", "xyz"])
@pytest.mark.parametrize("source", ["las", "parquet"])
def test_local_engine(capsys, tmp_path, cloud, source, ext):
    out = tmp_path / f"out.{ext}"
    code, err = cli(capsys, cloud[source], out, "--ratio", RATIO, "--seed", SEED, "--quiet")
    assert code == 0, err
    [prov] = provenance_of(out)
    assert_right(prov, cloud["rgb16" if source == "las" else "rgb8"])
    assert rows_of(out) == prov["kept"]
    assert prov["inputs"] == [os.path.abspath(cloud[source])]


# -- DuckDB: `prism-stream sql` ---------------------------------------------------------------------------

def test_sql_command_parquet(capsys, tmp_path, cloud):
    out = tmp_path / "out.parquet"
    query = f"SELECT * FROM read_parquet('{cloud['parquet']}')"
    code, err = cli(capsys, "sql", query, out, "--ratio", RATIO, "--seed", SEED, "--quiet")
    assert code == 0, err
    [prov] = provenance_of(out)
    assert_right(prov, cloud["rgb8"])
    assert rows_of(out) == prov["kept"]
    assert prov["query"] == query  # a query's sample names no input file: the query is its input


@pytest.mark.parametrize("ext", ["las", "laz", "ply"])
def test_sql_command_writes_only_parquet(capsys, tmp_path, cloud, ext):
    out = tmp_path / f"out.{ext}"
    code, err = cli(capsys, "sql", f"SELECT * FROM read_parquet('{cloud['parquet']}')", out, "--ratio", RATIO)
    assert code != 0 and err.count("\n") == 1 and "Parquet" in err, err
    assert os.listdir(tmp_path) == []


# -- Dask: `--dask local:2` -----------------------------------------------------------------------------

def test_dask_parquet_dataset(capsys, tmp_path, cloud):
    out = tmp_path / "out"
    code, err = cli(capsys, cloud["las"], out, "--ratio", RATIO, "--seed", SEED, "--dask", "local:2", "--quiet")
    assert code == 0, err
    parts = sorted(glob.glob(str(out / "*.parquet")))
    assert parts
    provs = [p for part in parts for p in provenance_of(part)]
    assert len(provs) == len(parts), "one provenance record in every part"
    assert all(p == provs[0] for p in provs)
    assert_right(provs[0], cloud["rgb16"])
    assert sum(rows_of(p) for p in parts) == provs[0]["kept"]


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_dask_las_tiles(capsys, tmp_path, cloud, ext):
    out = tmp_path / "out"
    code, err = cli(capsys, cloud["las"], out / f"*.{ext}", "--ratio", RATIO, "--seed", SEED, "--dask", "local:2",
                    "--quiet")
    assert code == 0, err
    assert sorted(os.listdir(out)) == [f"in.{ext}"]
    [prov] = provenance_of(out / f"in.{ext}")
    assert_right(prov, cloud["rgb16"])
    assert rows_of(out / f"in.{ext}") == prov["kept"]


def test_dask_refuses_ply(capsys, tmp_path, cloud):
    out = tmp_path / "out.ply"
    code, err = cli(capsys, cloud["las"], out, "--ratio", RATIO, "--dask", "local:2")
    assert code != 0 and err.count("\n") == 1 and "Parquet" in err, err
    assert os.listdir(tmp_path) == []
