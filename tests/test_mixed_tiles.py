"""Tiles whose attributes differ: the one-line error names the columns each file lacks or adds."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

import prism_stream

from conftest import prism_stream_command, random_colors, write_las


@pytest.fixture
def tiles(tmp_path):
    folder = tmp_path / "tiles"
    folder.mkdir()
    n = 500
    write_las(folder / "a.laz", random_colors(n, 1), extra={"height": np.zeros(n, np.float32)})
    write_las(folder / "b.laz", random_colors(n, 2), extra={"confidence": np.ones(n, np.uint8),
                                                            "height": np.zeros(n, np.float64)}, seed=1)
    return folder


def test_parquet_error_names_the_columns(tmp_path, tiles):
    with pytest.raises(prism_stream.PrismError) as info:
        prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "out.parquet"), ratio=0.1)
    msg = str(info.value)
    assert "b.laz" in msg and "a.laz's" in msg
    assert "extra confidence" in msg and "height (double, not float)" in msg
    assert "\n" not in msg
    assert not (tmp_path / "out.parquet").exists()


def test_cli_one_line(tmp_path, tiles):
    r = subprocess.run([*prism_stream_command(), str(tiles / "*.laz"), str(tmp_path / "out.parquet"),
                        "--ratio", "0.1"], capture_output=True, text=True)
    assert r.returncode != 0
    errors = [line for line in r.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "extra confidence" in errors[0], r.stderr
    assert "--columns union" in errors[0] and "or write an output folder: one output per input" in errors[0]


# -- --columns union | intersection -------------------------------------------------------------

def tile_columns(path) -> dict:
    import laspy

    las = laspy.read(str(path))
    out = {n: np.asarray(las[n]) for n in las.point_format.dimension_names if n not in ("X", "Y", "Z")}
    out.update(x=np.asarray(las.x), y=np.asarray(las.y), z=np.asarray(las.z))
    return out


@pytest.mark.parametrize("rule", ["union", "intersection"])
def test_columns_rule_keeps_every_value(tmp_path, tiles, rule):
    import pyarrow.parquet as pq

    out = tmp_path / "out.parquet"
    with pytest.warns(prism_stream.PrismWarning) as said:
        prism_stream.sample(str(tiles / "*.laz"), str(out), ratio=1.0, columns=rule)
    t = pq.read_table(out)
    a, b = tile_columns(tiles / "a.laz"), tile_columns(tiles / "b.laz")
    assert t.num_rows == 1000
    assert t.schema.field("height").type == pa_double()  # float in a, double in b: widened, said
    assert any("'height' has types double, float" in str(w.message) for w in said)
    if rule == "union":
        assert t.column_names[-1] == "confidence" and t.schema.field("confidence").nullable
        conf = t.column("confidence")
        assert conf.slice(0, 500).null_count == 500
        assert np.array_equal(conf.slice(500).to_numpy(), b["confidence"])
        assert any("'confidence' is missing from a.laz" in str(w.message) for w in said)
    else:
        assert "confidence" not in t.column_names
        assert any("confidence left out" in str(w.message) for w in said)
    for name in ("x", "intensity", "red", "height"):
        want = np.concatenate([a[name].astype(np.float64), b[name].astype(np.float64)])
        assert np.array_equal(t.column(name).to_numpy().astype(np.float64), want), name


def test_columns_rule_samples_the_same_points(tmp_path, tiles):
    """The rule changes columns, never which points are kept."""
    import pyarrow.parquet as pq

    prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "u.parquet"), ratio=0.2, seed=4, columns="union")
    prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "i.parquet"), ratio=0.2, seed=4, columns="intersection")
    u, i = pq.read_table(tmp_path / "u.parquet"), pq.read_table(tmp_path / "i.parquet")
    assert u.select(i.column_names).equals(i)


def test_columns_rule_needs_parquet_output(tmp_path, tiles):
    with pytest.raises(prism_stream.PrismError, match="needs Parquet output") as info:
        prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "out.laz"), ratio=0.1, columns="union")
    assert str(info.value).startswith(str(tmp_path / "out.laz"))  # the name the user gave, not a staging name
    assert not list(tmp_path.glob("out*"))


def test_columns_rule_on_dask(tmp_path, tiles):
    import pyarrow.parquet as pq

    from prism_stream.engines import dask as dask_engine

    prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "local.parquet"), ratio=0.3, columns="union")
    with dask_engine.connect("local:1") as client:
        dask_engine.sample(client, str(tiles / "*.laz"), str(tmp_path / "out"), ratio=0.3, columns="union",
                           unit_size=200)
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(pq.read_table(tmp_path / "local.parquet"))


def pa_double():
    import pyarrow as pa

    return pa.float64()
