"""A run imports what it uses: the format registry loads a format's module the first time its class is asked for
(``formats._Registry``), so a Parquet run never imports laspy (and the pyproj and requests laspy imports), a
tenth of a second of its start (bench/RESULTS_STARTUP.md); nor ``pyarrow.compute`` (30-50 ms), which a batch's
``filter`` and ``take`` load (``formats.arrow.rows_of`` takes numeric columns through numpy); and the registry still
gives every format's class."""

from __future__ import annotations

import json
import subprocess
import sys

from conftest import EDGE, real_file

RUN = """
import json, sys
from prism_stream_cli.main import run
try:
    run(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "loaded": [m for m in ("laspy", "lazrs", "requests", "pyarrow.compute")
                                          if m in sys.modules]}))
"""


def _loaded(*args) -> dict:
    done = subprocess.run([sys.executable, "-c", RUN, *map(str, args)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_parquet_run_does_not_import_laspy(tmp_path):
    got = _loaded(EDGE / "pdal__1.2-with-color.parquet", tmp_path / "out.parquet", "--ratio", "0.1", "--quiet")
    assert got == {"code": 0, "loaded": []}, got
    # the check itself sees laspy when a run does use it
    got = _loaded(real_file("pdal__autzen_trim.las"), tmp_path / "out.las", "--ratio", "0.1", "--quiet")
    assert got["code"] == 0 and "laspy" in got["loaded"], got


def test_the_registry_gives_every_formats_class():
    from prism_stream import formats
    from prism_stream.formats import base, copc, e57, las, parquet, pcd, ply, xyz, xyzout

    want_readers = {".las": las.LasSource, ".laz": las.LasSource, ".copc.laz": las.LasSource,
                    ".parquet": parquet.ParquetSource, ".pq": parquet.ParquetSource, ".ply": ply.PlySource,
                    ".pcd": pcd.PcdSource, ".e57": e57.E57Source, ".xyz": xyz.XyzSource}
    want_writers = {".las": las.LasSink, ".laz": las.LasSink, ".copc.laz": copc.CopcSink,
                    ".parquet": parquet.ParquetSink, ".pq": parquet.ParquetSink, ".ply": ply.PlySink,
                    ".xyz": xyzout.XyzSink}
    assert dict(formats.READERS) == want_readers and dict(formats.WRITERS) == want_writers
    assert all(issubclass(c, base.Source) for c in want_readers.values())
    assert all(issubclass(c, base.Sink) for c in want_writers.values())
    assert ".txt" not in formats.READERS and formats.READERS.get(".txt") is None
