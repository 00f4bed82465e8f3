"""Provenance: every output says how it was made, in its own metadata (SPEC 6).

Parquet carries a ``prism_stream`` key-value entry, LAS/LAZ a VLR, PLY a
header comment; each holds the options, the seed, each source's color-depth
decision, N, B, k (or k*), T and the count kept, and those values agree with
the run's summary and with the output itself. The metadata is read here from
the raw bytes as well as through the library's readers.
"""

from __future__ import annotations

import json
import math
import warnings

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.formats import las as las_format
from prism_stream.formats import parquet as parquet_format

from conftest import edge_file, real_file

SUMMARY_KEYS = ("points", "bins", "target", "k", "extra", "kept", "seed", "rule", "options")


def run(inputs, output, **options) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PrismWarning)
        return prism_stream.sample([str(p) for p in inputs], str(output), **options).as_dict()


def raw_parquet_provenance(path) -> dict:
    meta = pq.ParquetFile(path).schema_arrow.metadata
    return json.loads(meta[b"prism_stream"])


def raw_las_provenance(path) -> dict:
    with laspy.open(path) as reader:
        found = [v for v in reader.header.vlrs if v.user_id == las_format.PROVENANCE_USER_ID]
    assert len(found) == 1, "exactly one provenance VLR"
    return json.loads(bytes(found[0].record_data))


def rows_in(path) -> int:
    if str(path).endswith((".parquet", ".pq")):
        return pq.ParquetFile(path).metadata.num_rows
    return laspy.open(path).header.point_count


def distinct_rgb8(path) -> int:
    """B for an 8-bit LAS cloud, counted here from the colors: distinct (r, g, b) triples."""
    las = laspy.read(path)
    rgb = np.stack([las.red, las.green, las.blue], axis=1).astype(np.int64)
    assert rgb.max() <= 255
    return len(np.unique(rgb, axis=0))


def assert_agrees(prov: dict, summary: dict, output) -> None:
    for key in SUMMARY_KEYS:
        assert prov[key] == summary[key], key
    assert prov["kept"] == rows_in(output)
    assert [s["color_depth"] for s in prov["sources"]] == [s["color_depth"] for s in summary["sources"]]
    assert prov["inputs"] == summary["inputs"]


@pytest.mark.parametrize("out_name", ["out.parquet", "out.las", "out.laz"])
def test_output_metadata_holds_the_plan(tmp_path, out_name):
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / out_name
    summary = run([src], out, ratio=0.02, seed=11)
    prov = raw_parquet_provenance(out) if out_name.endswith(".parquet") else raw_las_provenance(out)
    reader = parquet_format if out_name.endswith(".parquet") else las_format
    assert reader.read_provenance(str(out)) == prov

    n = laspy.open(src).header.point_count
    assert prov["options"] == {"ratio": 0.02, "count": None, "k": None, "mode": "exact", "color_space": "rgb",
                               "quant_bits": 0, "color_depth": "auto", "seed": 11}
    assert prov["seed"] == 11
    assert prov["points"] == n
    assert prov["bins"] == distinct_rgb8(src)
    assert prov["target"] == math.floor(0.02 * n + 0.5)
    assert prov["kept"] == prov["target"]  # exact mode
    assert [(s["path"], s["color_depth"]) for s in prov["sources"]] == [(str(src), "8")]
    assert_agrees(prov, summary, out)


def test_paper_rule_records_k_star(tmp_path):
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "paper.parquet"
    summary = run([src], out, ratio=0.01, mode="paper")
    prov = raw_parquet_provenance(out)
    assert prov["rule"] == "paper" and prov["options"]["mode"] == "paper"
    assert prov["k_star"] == summary["k"] >= 1
    assert prov["kept"] == summary["kept"] == rows_in(out)


def test_fixed_k_records_k_and_no_target(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    out = tmp_path / "k.las"
    summary = run([src], out, k=2)
    prov = las_format.read_provenance(str(out))
    assert prov["rule"] == "k" and prov["k"] == 2 and prov["options"]["k"] == 2
    assert prov["target"] is None
    assert_agrees(prov, summary, out)


def test_each_source_records_its_own_color_depth(tmp_path):
    """autzen stores 8-bit values, warsaw 8-bit values shifted left by 8: one decision each."""
    a, b = real_file("pdal__autzen_trim.las"), real_file("pdal__warsaw_small.las")
    out = tmp_path / "both.las"
    summary = run([a, b], out, count=5000, seed=2)
    prov = las_format.read_provenance(str(out))
    assert [(s["ordinal"], s["path"], s["color_depth"]) for s in prov["sources"]] == [
        (0, str(a), "8"), (1, str(b), "16")]
    assert [s["points"] for s in prov["sources"]] == [laspy.open(a).header.point_count,
                                                      laspy.open(b).header.point_count]
    assert prov["points"] == sum(s["points"] for s in prov["sources"])
    assert prov["target"] == 5000 == prov["kept"]
    assert_agrees(prov, summary, out)


def test_forced_color_depth_is_recorded(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    out = tmp_path / "forced.parquet"
    summary = run([src], out, ratio=0.5, color_depth="16", color_space="chroma", quant_bits=2)
    prov = parquet_format.read_provenance(str(out))
    assert prov["options"]["color_depth"] == "16"
    assert prov["options"]["color_space"] == "chroma" and prov["options"]["quant_bits"] == 2
    assert [s["color_depth"] for s in prov["sources"]] == ["16"]
    assert_agrees(prov, summary, out)


def test_parquet_input_keeps_its_metadata_beside_the_provenance(tmp_path):
    src = edge_file("pdal__1.2-with-color.parquet")
    out = tmp_path / "out.parquet"
    summary = run([src], out, ratio=0.3, seed=4)
    meta = pq.ParquetFile(out).schema_arrow.metadata
    for key, value in (pq.ParquetFile(src).schema_arrow.metadata or {}).items():
        assert meta[key] == value
    prov = raw_parquet_provenance(out)
    assert prov["points"] == pq.ParquetFile(src).metadata.num_rows
    assert_agrees(prov, summary, out)


def test_ply_output_carries_provenance_in_a_comment(tmp_path):
    from prism_stream.formats import ply

    src = real_file("open3d__frag_115.ply")
    out = tmp_path / "out.ply"
    summary = run([src], out, ratio=0.05, seed=1)
    prov = ply.read_provenance(str(out))
    assert prov is not None
    for key in SUMMARY_KEYS:
        assert prov[key] == summary[key], key
    with open(out, "rb") as f:
        head = f.read(1 << 16).split(b"end_header")[0].decode("ascii", "replace")
    assert "comment prism-stream {" in head


def test_provenance_records_when_and_the_command_line(tmp_path, monkeypatch):
    """`created` is the run's UTC time (SOURCE_DATE_EPOCH fixes it); `command` is the CLI's argv, absent from Python."""
    import datetime as dt
    import subprocess

    from conftest import prism_stream_command

    src = str(real_file("pdal__autzen_trim.las"))
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    before = dt.datetime.now(dt.timezone.utc).replace(microsecond=0)
    prism_stream.sample(src, str(tmp_path / "api.parquet"), ratio=0.01)
    prov = parquet_format.read_provenance(str(tmp_path / "api.parquet"))
    when = dt.datetime.fromisoformat(prov["created"].replace("Z", "+00:00"))
    assert before <= when <= dt.datetime.now(dt.timezone.utc) and "command" not in prov
    args = [src, str(tmp_path / "cli.laz"), "--count", "77", "--seed", "3"]
    assert subprocess.run([*prism_stream_command(), *args], capture_output=True).returncode == 0
    prov = las_format.read_provenance(str(tmp_path / "cli.laz"))
    assert prov["command"] == ["prism-stream", *args]
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")
    prism_stream.sample(src, str(tmp_path / "fixed.parquet"), ratio=0.01)
    assert parquet_format.read_provenance(str(tmp_path / "fixed.parquet"))["created"] == "1970-01-01T00:00:00Z"


def test_parquet_from_several_las_files_carries_the_first_ones_grid(tmp_path):
    """The source facts a Parquet keeps (to give the LAS integers back) are the first input's."""
    from conftest import random_colors, write_las

    a = write_las(tmp_path / "a.las", random_colors(500, seed=1), point_format=3)
    las = laspy.read(str(write_las(tmp_path / "b.las", random_colors(400, seed=2), point_format=3)))
    las.header.offsets = np.array([7.0, 8.0, 9.0])
    las.write(str(tmp_path / "b.las"))
    out = tmp_path / "out.parquet"
    run([a, tmp_path / "b.las"], out, ratio=0.5)
    facts = json.loads(pq.ParquetFile(out).schema_arrow.metadata[b"prism_stream_source"])
    assert facts["offsets"] == list(laspy.open(a).header.offsets) == [1000.0, 2000.0, 10.0]


def test_parquet_inputs_of_one_schema_keep_the_first_ones_metadata(tmp_path):
    import pyarrow as pa

    from conftest import random_colors

    paths = []
    for name, seed in (("a", 1), ("b", 2)):
        rgb = random_colors(300, seed=seed).astype(np.uint8)
        table = pa.table({"x": np.arange(300.0), "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
        paths.append(tmp_path / f"{name}.parquet")
        pq.write_table(table.replace_schema_metadata({b"origin": name.encode()}), paths[-1])
    out = tmp_path / "out.parquet"
    summary = run(paths, out, ratio=0.5)
    meta = pq.ParquetFile(out).schema_arrow.metadata
    assert meta[b"origin"] == b"a"
    assert b"prism_stream_source" not in meta  # Parquet in: nothing of another format to keep
    assert_agrees(raw_parquet_provenance(out), summary, out)


def test_an_input_without_points_records_zeros(tmp_path):
    src = edge_file("pdal__no-points.las")
    out = tmp_path / "out.parquet"
    summary = run([src], out, ratio=0.5)
    assert (summary["points"], summary["kept"], summary["ratio_achieved"]) == (0, 0, 0.0)
    prov = raw_parquet_provenance(out)
    assert (prov["points"], prov["kept"]) == (0, 0)
    assert summary["output"] == str(out.resolve()) and summary["outputs"] == [str(out.resolve())]
