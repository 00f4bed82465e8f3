"""Every output byte and summary field of the local and SQL engines, held to what the code wrote before the
engines shared one pipeline (tests/fingerprints.py; the Dask engine's cases are in test_dask_engine.py).

Each case runs on each way pass two gets its points: held in memory, from the candidate spill (one read),
and by reading the input again (two reads)."""

from __future__ import annotations

import warnings

import pytest

import prism_stream
from prism_stream.engines.sql import sample_query

from conftest import EDGE, real_file
from fingerprints import base_folder, check, copy_inputs, fingerprint

READS = {"memory": dict(env="1000000", reads="auto"), "one": dict(env="0", reads="auto"),
         "two": dict(env="0", reads="two")}

CASES = {
    # name: (inputs, output, options)
    "parquet": (["pdal__autzen_trim.las"], "out.parquet", dict(ratio=0.05, seed=3)),
    "laz_rank_order": (["pdal__autzen_trim.las"], "out.laz", dict(ratio=0.05, rank="prism_rank", order="rank")),
    "copc_extra_bytes": (["pdal__las_with_several_extra_byte_bloc.laz"], "out.copc.laz", dict(ratio=0.02)),
    "ply": (["open3d__frag_115.ply"], "out.ply", dict(k=3, quant_bits=2)),
    "pcd_to_las": (["pcl__office1.pcd"], "out.las", dict(ratio=0.05)),
    "las_two_tiles": (["pdal__autzen_trim.las", "pdal__warsaw_small.las"], "out.las",
                      dict(count=1500, color_space="chroma")),
    "folder": (["pdal__warsaw_small.las", "laspy__fullwave.laz"], "out/", dict(ratio=0.1, output_format="laz")),
    "per_file": (["pdal__warsaw_small.las", "potree__lion_takanawa.copc.laz"], "out/", dict(ratio=0.1, per_file=True)),
    "rank_all": (["potree__lion_takanawa.copc.laz"], "ranked.parquet", dict(rank="prism_rank")),
    "plan": (["pdal__autzen_trim.las", "laspy__fullwave.laz"], None, dict(ratio=0.01)),
}


def _run(base, case, how, monkeypatch):
    names, output, options = CASES[case]
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", READS[how]["env"])
    inputs = copy_inputs(base, *[real_file(n) for n in names])
    out = None if output is None else f"{base}/{output}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summary = prism_stream.sample(inputs, out, reads=READS[how]["reads"], **options)
    return [] if out is None else [out], summary


@pytest.mark.parametrize("how", sorted(READS))
@pytest.mark.parametrize("case", sorted(CASES))
def test_local_engine_writes_the_recorded_bytes(case, how, tmp_path, monkeypatch):
    base = base_folder(tmp_path)
    outputs, summary = _run(base, case, how, monkeypatch)
    check(f"local/{case}/{how}", fingerprint(base, outputs, summary))


@pytest.mark.parametrize("materialize", ["rerun", "spool"])
@pytest.mark.parametrize("reads", ["auto", "two"])
def test_sql_engine_writes_the_recorded_bytes(materialize, reads, tmp_path, monkeypatch):
    base = base_folder(tmp_path)
    [cloud] = copy_inputs(base, EDGE / "pdal__1.2-with-color.parquet")
    out = str(base / "query.parquet")
    query = f"SELECT * FROM read_parquet('{cloud}') WHERE Intensity > 50"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summary = sample_query(query, out, materialize=materialize, ratio=0.2, seed=9, reads=reads,
                               rank="prism_rank")
    check(f"sql/{materialize}/{reads}", fingerprint(base, [out], summary))
