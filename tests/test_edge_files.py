"""Every edge file from other libraries' test suites: a correct output or a one-line refusal.

For each of the files in ``tests/data/edge`` the table below says, from the
data README, what a robust tool must do with it:

- ``Ok(n)``: the file holds ``n`` colored points (the README's count); a run
  at ``--ratio 0.5`` writes exactly ``T = floor(0.5 n + 0.5)`` rows (SPEC 4,
  exact rule), and its provenance says ``points == n``;
- ``Refused(code, words)``: the command exits with ``code`` and one line on
  stderr that names the file and says ``words``.

Either way: no traceback, no hang (a timeout), no interpreter crash, memory
under a 3 GiB address-space limit, no partial output and no temporary file
left beside the output. Every file in the folder must have a row, so a file
added to the folder without a decision fails the suite.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from conftest import prism_stream_command

EDGE = Path(__file__).resolve().parent / "data" / "edge"
ADDRESS_SPACE = 3 << 30
RATIO = 0.5


@dataclass(frozen=True)
class Ok:
    points: int


@dataclass(frozen=True)
class Refused:
    code: int
    says: str


NO_RGB = Refused(5, "has no RGB")  # LAS point formats 0, 1, 4, 6, 9 carry no color: nothing to bin
PLY_NO_COLOR = Refused(5, "no red/green/blue")

EXPECTED = {
    # LAS 1.0-1.2 permutations: only formats 2 and 3 carry color
    "pdal__1.0_0.las": NO_RGB,
    "pdal__1.0_1.las": NO_RGB,
    "pdal__1.1_0.las": NO_RGB,
    "pdal__1.1_1.las": NO_RGB,
    "pdal__1.2_0.las": NO_RGB,
    "pdal__1.2_1.las": NO_RGB,
    "pdal__1.2_2.las": Ok(1),
    "pdal__1.2_3.las": Ok(1),
    # the header promises 1,065 points and the file ends after the header
    "pdal__1.2-no-points.las": Refused(6, "1065"),
    # a valid file with zero points: an empty (valid) output
    "pdal__no-points.las": Ok(0),
    # a VLR count of 1,069,128,089: refused from the header, without allocating
    "pdal__garbage_nVariableLength.las": Refused(6, "VLR"),
    "pdal__bad_vlr_count.las": Ok(10),  # all-zero colors: one bin, still a valid sample
    "pdal__spec_3.las": Ok(10),
    "pdal__extrabytes.las": Ok(1065),
    "pdal__gps-time-nan.las": NO_RGB,
    "pdal__lots_of_vlr.las": NO_RGB,
    # lazrs panics on LASzip 1.x point-wise compression (a BaseException): refused first
    "pdal__simple-laszip-compressor-version-1.2r0.laz": Refused(4, "compressor"),
    "pdal__1.2-with-color.copc.laz": Ok(1065),
    "pdal__1.2-with-color.parquet": Ok(1065),
    "pdal__1.2-with-color_wkb.parquet": Ok(1065),
    "laspy__simple1_3.las": NO_RGB,
    "laspy__test1_4.las": NO_RGB,
    "laspy__1_4_w_evlr.laz": NO_RGB,
    "laspy__unregistered_extra_bytes.las": NO_RGB,
    "lazperf__point-color.las": Ok(1065),
    "lazperf__no-points-1.3.laz": NO_RGB,
    "loadersgl__pdrf5-1.3.las": Ok(1024),
    "loadersgl__pdrf8-1.4.laz": Ok(1024),
    "loadersgl__pdrf9-1.4.las": NO_RGB,
    "loadersgl__pdrf10-1.4.las": Ok(1024),
    "loadersgl__pdrf9-1.5.las": NO_RGB,
    # LASzip item version 4, which the lazrs decoder does not read
    "loadersgl__pdrf7-v4-1.4.laz": Refused(4, "version"),
    "loadersgl__points-1.4.las": Ok(3),
    # PLY: a signed char blue, big-endian, bare-CR header lines, tabs, mixed type names
    "pdal__text_extradim.ply": Ok(1),
    "draco__test_pos_color_big_endian.ply": Ok(114),
    "draco__delim_test.ply": Ok(24),
    "draco__test_extra_whitespace.ply": Ok(3),
    "draco__test_more_datatypes.ply": Ok(3),
    # PLY without color (inf coordinates, splat SH coefficients, sized dims, lists on another element)
    "draco__float_inf_point_cloud.ply": PLY_NO_COLOR,
    "loadersgl__train-1000.ply": PLY_NO_COLOR,
    "pdal__sized_dims.ply": PLY_NO_COLOR,
    "open3d__test_sample_wrong_format.ply": PLY_NO_COLOR,
    "trimesh__points_ascii_with_lists.ply": PLY_NO_COLOR,
    "trimesh__ply_empty_bin.ply": PLY_NO_COLOR,
    # PLY with no elements at all ("ply " with a trailing space, or just the three lines)
    "pdal__no_vertex.ply": Refused(5, "no vertex element"),
    "trimesh__ply_empty_header.ply": Refused(5, "no vertex element"),
    # PCD
    "loadersgl__simple-ascii.pcd": Ok(213),
    "pcl__colored_cloud.pcd": Ok(1000),
    "pdal__missingheader.pcd": Refused(4, "no PCD header"),
    # E57: 16-bit colorLimits; a scan without color; a corrupt page checksum; a scan of zero points, no color
    "e57data__ColourRepresentation.e57": Ok(153),
    "pdal__A_B_different_dims.e57": Refused(5, "scan 0 has no colorRed"),
    "e57data__bad-crc.e57": Refused(6, "checksum"),
    "e57data__ZeroPoints.e57": Refused(5, "no colorRed"),
    # XYZRGB text
    "trimesh__points_agisoft.xyz": Ok(100),
}


def _limit():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def edge_files() -> list[str]:
    """Every file of the edge folder (a missing folder is an error at collection, not an empty list)."""
    return sorted(os.listdir(EDGE))


def test_every_edge_file_has_a_decision():
    assert sorted(EXPECTED) == edge_files()


def _streamed(path: Path, tmp_path: Path) -> int:
    """The same run in this process on the streaming path (conftest.py sets PRISM_STREAM_MEMORY_POINTS=0):
    its exit code (0, or the refusal's)."""
    import warnings

    import prism_stream

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prism_stream.sample(str(path), str(tmp_path / "streamed.parquet"), ratio=RATIO)
    except prism_stream.PrismError as exc:
        return exc.exit_code
    return 0


@pytest.mark.parametrize("name", edge_files())
def test_edge_file(tmp_path, name):
    assert name in EXPECTED, f"{name}: no decision in the table (see test_every_edge_file_has_a_decision)"
    source = EDGE / name
    work = tmp_path / "in"
    work.mkdir()
    local = work / name
    shutil.copyfile(source, local)
    before = local.read_bytes()
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    temp = tmp_path / "temp"
    temp.mkdir()
    output = out_dir / "sample.parquet"
    # the command as a user runs it: these small files take the default path (held in memory, no numba to
    # load: a second a file saved); the streaming path is held to the same outcome in this process, below
    env = {k: v for k, v in os.environ.items() if k not in ("PRISM_STREAM_DEBUG", "PRISM_STREAM_MEMORY_POINTS")}
    result = subprocess.run([*prism_stream_command(), str(local), str(output), "--ratio", str(RATIO), "--json",
                             "--temp-dir", str(temp)], capture_output=True, text=True, timeout=120, env=env,
                            preexec_fn=_limit)
    text = result.stdout + result.stderr
    assert "Traceback" not in text, text
    assert result.returncode >= 0, f"killed by signal {-result.returncode}: {text}"
    assert local.read_bytes() == before, "the input was modified"
    assert not os.listdir(temp), f"temporary files left: {os.listdir(temp)}"
    expected = EXPECTED[name]
    if isinstance(expected, Refused):
        errors = [ln for ln in result.stderr.splitlines() if ln.strip() and "warning:" not in ln]
        assert result.returncode == expected.code, text
        assert len(errors) == 1, text
        assert errors[0].startswith("prism-stream: error: ") and str(local) in errors[0], errors[0]
        assert expected.says in errors[0], errors[0]
        assert not os.listdir(out_dir), f"a refused run left {os.listdir(out_dir)}"
        assert _streamed(local, tmp_path) == expected.code
        return
    assert result.returncode == 0, text
    assert os.listdir(out_dir) == ["sample.parquet"], os.listdir(out_dir)
    target = int(RATIO * expected.points + 0.5)
    table = pq.read_table(output)
    assert table.num_rows == target
    summary = json.loads(result.stdout)
    assert summary["points"] == expected.points
    assert summary["kept"] == target
    provenance = json.loads(pq.read_schema(output).metadata[b"prism_stream"])
    assert provenance["points"] == expected.points
    assert _streamed(local, tmp_path) == 0
    streamed = pq.read_table(tmp_path / "streamed.parquet").replace_schema_metadata(None)
    assert streamed.equals(table.replace_schema_metadata(None))
