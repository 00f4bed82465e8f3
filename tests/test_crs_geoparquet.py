"""CRS everywhere: GeoParquet 1.1 metadata, the WKB geometry column, and the CRS back into LAS.

The ``geo`` metadata is checked against the GeoParquet 1.1 JSON schema's
structure (written out below: version, primary_column, columns with
encoding, geometry_types, crs as a PROJJSON object or null, edges, bbox),
and the CRS itself by reading it back with pyproj.
"""

from __future__ import annotations

import json
import warnings

import jsonschema
import laspy
import numpy as np
import pyarrow.parquet as pq
import pyproj
import pytest

import prism_stream
from prism_stream.errors import UsageError
from prism_stream.formats.geo import wkb_xyz

from conftest import edge_file, real_file, write_parquet

# The GeoParquet 1.1.0 metadata schema (format-specs/schema.json of the 1.1.0 release), its constraints
# written out; the PROJJSON object is checked by pyproj instead of by the PROJ schema (not fetched here).
GEOPARQUET_1_1 = {
    "$schema": "http://json-schema.org/draft-07/schema#",
    "type": "object",
    "required": ["version", "primary_column", "columns"],
    "properties": {
        "version": {"type": "string", "const": "1.1.0"},
        "primary_column": {"type": "string", "minLength": 1},
        "columns": {
            "type": "object",
            "minProperties": 1,
            "patternProperties": {
                ".+": {
                    "type": "object",
                    "required": ["encoding", "geometry_types"],
                    "properties": {
                        "encoding": {"type": "string",
                                     "pattern": "^(WKB|point|linestring|polygon|multipoint|multilinestring"
                                                "|multipolygon)$"},
                        "geometry_types": {"type": "array", "uniqueItems": True,
                                           "items": {"type": "string", "pattern":
                                                     "^(GeometryCollection|(Multi)?(Point|LineString|Polygon))"
                                                     "( Z)?$"}},
                        "crs": {"oneOf": [{"type": "object"}, {"type": "null"}]},
                        "edges": {"type": "string", "enum": ["planar", "spherical"]},
                        "orientation": {"type": "string", "const": "counterclockwise"},
                        "bbox": {"type": "array", "items": {"type": "number"},
                                 "oneOf": [{"minItems": 4, "maxItems": 4}, {"minItems": 6, "maxItems": 6}]},
                        "epoch": {"type": "number"},
                        "covering": {"type": "object", "minProperties": 1},
                    },
                }
            },
            "additionalProperties": False,
        },
    },
}

CRS_CLOUDS = ["pdal__autzen_trim.las", "pdal__las_with_several_extra_byte_bloc.laz"]


def _geo(path) -> dict | None:
    raw = pq.ParquetFile(path).metadata.metadata.get(b"geo")
    return json.loads(raw) if raw else None


def _run(inp, out, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return prism_stream.sample(str(inp), str(out), **options)


def _las_crs(path):
    try:
        return laspy.read(str(path)).header.parse_crs()
    except pyproj.exceptions.CRSError:  # warsaw_small: an empty WKT VLR
        return None


def _check_geo(geo: dict, table) -> None:
    jsonschema.validate(geo, GEOPARQUET_1_1)
    assert geo["primary_column"] in geo["columns"]
    for name, col in geo["columns"].items():
        assert name in table.column_names, f"geo names {name!r}, which is not a column"
        if col.get("crs") is not None:
            pyproj.CRS.from_json_dict(col["crs"])  # a PROJJSON object pyproj reads


@pytest.mark.parametrize("name", CRS_CLOUDS)
def test_geometry_makes_geoparquet_with_the_las_crs(tmp_path, name):
    src = real_file(name)
    out = tmp_path / "s.parquet"
    _run(src, out, ratio=0.05, geometry=True)
    table = pq.read_table(out)
    geo = _geo(out)
    _check_geo(geo, table)
    assert geo["primary_column"] == "geometry"
    col = geo["columns"]["geometry"]
    assert col["encoding"] == "WKB" and col["geometry_types"] == ["Point Z"]
    assert pyproj.CRS.from_json_dict(col["crs"]) == _las_crs(src)
    x, y, z = wkb_xyz(table.column("geometry").combine_chunks(), "geometry", str(out))
    for axis, v in zip("xyz", (x, y, z)):
        np.testing.assert_array_equal(v, table.column(axis).to_numpy())
    # what pyarrow's reader sees as the schema's metadata carries it too
    assert b"geo" in pq.read_schema(out).metadata


def test_no_geometry_column_no_geo_key_but_the_crs_is_kept(tmp_path):
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "s.parquet"
    _run(src, out, ratio=0.05)
    assert _geo(out) is None  # GeoParquet needs a geometry column to name
    facts = json.loads(pq.read_schema(out).metadata[b"prism_stream_source"])
    assert pyproj.CRS.from_json_dict(facts["crs_projjson"]) == _las_crs(src)
    assert pyproj.CRS.from_wkt(facts["crs_wkt"]) == _las_crs(src)


def test_geometry_without_a_crs_says_unknown(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    assert _las_crs(src) is None
    out = tmp_path / "s.parquet"
    _run(src, out, ratio=0.05, geometry=True)
    geo = _geo(out)
    _check_geo(geo, pq.read_table(out))
    assert geo["columns"]["geometry"]["crs"] is None  # null: unknown (absent would mean OGC:CRS84)


@pytest.mark.parametrize("geometry", [False, True])
@pytest.mark.parametrize("name", CRS_CLOUDS)
def test_las_parquet_las_keeps_the_crs(tmp_path, name, geometry):
    src = real_file(name)
    mid, back = tmp_path / "s.parquet", tmp_path / "back.las"
    _run(src, mid, ratio=0.05, geometry=geometry)
    _run(mid, back, ratio=1.0)
    assert _las_crs(back) == _las_crs(src)


def test_geoparquet_input_keeps_its_geometry_and_crs(tmp_path):
    src = real_file("pdal__autzen_trim.las")
    mid, out = tmp_path / "g.parquet", tmp_path / "again.parquet"
    _run(src, mid, ratio=0.1, geometry=True)
    _run(mid, out, ratio=0.5)
    geo = _geo(out)
    _check_geo(geo, pq.read_table(out))
    assert pyproj.CRS.from_json_dict(geo["columns"]["geometry"]["crs"]) == _las_crs(src)


def test_pdal_geoparquet_crs_into_las(tmp_path):
    """PDAL's Parquet: its ``geo`` CRS becomes the LAS output's WKT VLR."""
    crs = _las_crs(edge_file("pdal__1.2-with-color.copc.laz"))  # the same points, with their CRS
    for name in ("pdal__1.2-with-color.parquet",):
        table = pq.read_table(edge_file(name))
        geo = json.loads(pq.ParquetFile(edge_file(name)).metadata.metadata[b"geo"])
        geo["columns"][geo["primary_column"]]["crs"] = crs.to_json_dict()
        fixed = tmp_path / name
        write_parquet(fixed, table.replace_schema_metadata({b"geo": json.dumps(geo).encode()}))
        out = tmp_path / (name + ".las")
        _run(fixed, out, ratio=0.5)
        assert _las_crs(out) == crs


def test_pdal_default_crs_that_cannot_fit_is_not_written(tmp_path):
    """PDAL labels a LAS file without a CRS EPSG:4326; on projected coordinates that is said and dropped."""
    out = tmp_path / "p.las"
    with pytest.warns(prism_stream.PrismWarning, match="geographic .* not written"):
        prism_stream.sample(str(edge_file("pdal__1.2-with-color.parquet")), str(out), ratio=0.5)
    assert _las_crs(out) is None


def test_geometry_needs_parquet_output(tmp_path):
    with pytest.raises(UsageError, match="--geometry .* Parquet output"):
        _run(real_file("pdal__autzen_trim.las"), tmp_path / "s.las", ratio=0.05, geometry=True)
    assert not list(tmp_path.iterdir())


def test_geometry_clash_is_refused(tmp_path):
    src = real_file("pdal__autzen_trim.las")
    mid = tmp_path / "g.parquet"
    _run(src, mid, ratio=0.1, geometry=True)
    with pytest.raises(UsageError, match="already has a column named 'geometry'"):
        _run(mid, tmp_path / "again.parquet", ratio=0.5, geometry=True)


def _points_z(column) -> np.ndarray:
    """(n, 3) of WKB Point Z values, decoded here (byte order, type 1001 or 0x80000001, three doubles)."""
    out = []
    for raw in column.to_pylist():
        order = "<" if raw[0] == 1 else ">"
        kind = int(np.frombuffer(raw[1:5], dtype=order + "u4")[0])
        assert kind in (1001, 0x80000001), kind
        out.append(np.frombuffer(raw[5:29], dtype=order + "f8"))
    return np.array(out)


def test_geometry_from_one_xyz_vector_column(tmp_path):
    import pyarrow as pa

    n = 200
    xyz = np.stack([np.arange(n) * 1.5, 100.0 - np.arange(n), np.arange(n) % 7 + 0.5], axis=1)
    rgb = np.random.default_rng(3).integers(0, 5, (n, 3)).astype(np.uint8)
    table = pa.table({"xyz": pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3),
                      "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2], "ident": np.arange(n)})
    src = write_parquet(tmp_path / "in.parquet", table)
    out = tmp_path / "out.parquet"
    _run(src, out, ratio=0.5, seed=1, geometry=True)
    got = pq.read_table(out)
    _check_geo(_geo(out), got)
    rows = got.column("ident").to_numpy()
    assert len(rows) == round(0.5 * n)
    assert np.array_equal(_points_z(got.column("geometry")), xyz[rows])
    quad = pa.table({"xyz": pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(4 * n)), 4),
                     "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
    with pytest.raises(UsageError, match="--geometry needs the points. coordinates: x, y and z columns"):
        _run(write_parquet(tmp_path / "quad.parquet", quad), tmp_path / "quad-out.parquet", ratio=0.5, geometry=True)
