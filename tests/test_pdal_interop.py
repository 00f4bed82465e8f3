"""PDAL interoperability and LAS -> Parquet -> LAS fidelity, on the real clouds.

PDAL's Parquet names dimensions Intensity, ReturnNumber, GpsTime... and may
carry the points only as WKB; its LAS output must fill the LAS standard
fields with them (not extra bytes, not zeros), keep the scales of the LAS
file PDAL read, and keep colors as they are.
"""

from __future__ import annotations

import warnings

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream

from conftest import edge_file, read_las, real_file

PDAL_PARQUET = ["pdal__1.2-with-color.parquet", "pdal__1.2-with-color_wkb.parquet"]
# the same 1065 points as LAS (PDAL's 1.2-with-color, as COPC)
PDAL_LAS = "pdal__1.2-with-color.copc.laz"
STANDARD = ["X", "Y", "Z", "intensity", "return_number", "number_of_returns", "scan_direction_flag",
            "edge_of_flight_line", "classification", "scan_angle_rank", "user_data", "point_source_id", "gps_time",
            "red", "green", "blue"]


def _run(inp, out, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return prism_stream.sample(str(inp), str(out), **options)


def _rows(las, dims) -> np.ndarray:
    """The records as sorted rows of the given dimensions (order-free comparison)."""
    cols = [np.asarray(las[d]).astype(np.float64) for d in dims]
    rows = np.stack(cols, axis=1)
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("name", PDAL_PARQUET)
def test_pdal_parquet_to_las_fills_the_standard_fields(tmp_path, name):
    out = tmp_path / "p.las"
    _run(edge_file(name), out, ratio=1.0)
    got, ref = laspy.read(str(out)), laspy.read(str(edge_file(PDAL_LAS)))
    assert got.header.point_format.id == 3  # the point format of the LAS file PDAL read
    np.testing.assert_array_equal(got.header.scales, [0.01, 0.01, 0.01])  # its scales, not a 2^-20 grid
    assert not {"Intensity", "GpsTime", "Classification", "ReturnNumber"} & set(got.point_format.dimension_names)
    assert "wkb" not in got.point_format.dimension_names
    dims = [d for d in STANDARD if d != "scan_angle_rank"] + ["scan_angle"]
    ref_scan = np.asarray(ref.scan_angle) * 0.006  # COPC (PF7) stores the angle in 0.006 degree steps
    def cm(las, axis):  # the COPC file has other offsets: compare coordinates in centimetres
        return np.round(np.asarray(las[axis.lower()]) * 100)

    ref_rows = _rows({**{d: ref[d] for d in dims if d not in ("scan_angle", "X", "Y", "Z")},
                      **{a: cm(ref, a) for a in "XYZ"}, "scan_angle": np.round(ref_scan)}, dims)
    got_rows = _rows({**{d: got[d] for d in dims if d not in ("scan_angle", "X", "Y", "Z")},
                      **{a: cm(got, a) for a in "XYZ"}, "scan_angle": got["scan_angle_rank"]}, dims)
    np.testing.assert_array_equal(got_rows, ref_rows)
    for d in ("intensity", "classification", "gps_time", "red", "return_number"):
        assert np.any(np.asarray(got[d]) != 0), f"{d} left zero"


@pytest.mark.parametrize("name", PDAL_PARQUET)
def test_pdal_parquet_sample_values_are_the_inputs(tmp_path, name):
    src = pq.read_table(edge_file(name))
    out = tmp_path / "p.laz"
    _run(edge_file(name), out, ratio=0.3)
    got = laspy.read(str(out))
    by_time = {t: i for i, t in enumerate(src.column("GpsTime").to_numpy())}
    idx = np.array([by_time[t] for t in np.asarray(got.gps_time)])
    for col, dim in (("Intensity", "intensity"), ("Classification", "classification"), ("Red", "red"),
                     ("Blue", "blue"), ("PointSourceId", "point_source_id"), ("UserData", "user_data"),
                     ("NumberOfReturns", "number_of_returns")):
        np.testing.assert_array_equal(np.asarray(got[dim]), src.column(col).to_numpy()[idx], err_msg=col)


# every real LAS cloud with RGB: PF3 (GeoTIFF keys), PF3 (WKT), PF8 LAZ with extra bytes, PF7 COPC
ROUND_TRIP = ["pdal__autzen_trim.las", "pdal__warsaw_small.las", "pdal__las_with_several_extra_byte_bloc.laz",
              "potree__lion_takanawa.copc.laz"]


@pytest.mark.parametrize("name", ROUND_TRIP)
def test_las_parquet_las_round_trips_every_value(tmp_path, name):
    """Colors included: 8-bit-valued 16-bit colors are not multiplied by 256 on the way back."""
    src = real_file(name)
    mid, back = tmp_path / "s.parquet", tmp_path / "back.las"
    _run(src, mid, ratio=1.0)
    _run(mid, back, ratio=1.0)
    a, b = read_las(src), laspy.read(str(back))
    assert b.header.point_format.id == a.header.point_format.id
    np.testing.assert_array_equal(b.header.scales, a.header.scales)
    np.testing.assert_array_equal(b.header.offsets, a.header.offsets)
    assert len(a.points) == len(b.points)
    for dim in a.point_format.standard_dimension_names:
        np.testing.assert_array_equal(np.asarray(b[dim]), np.asarray(a[dim]), err_msg=dim)
    for dim in a.point_format.extra_dimension_names:
        np.testing.assert_array_equal(np.asarray(b[dim]), np.asarray(a[dim]), err_msg=dim)
