"""Bad input: one line naming the file and the cause, a known exit code, nothing left behind.

Every case runs twice: through the ``prism-stream`` command (exit code,
stderr, no traceback) and through the Python API (the exception type and
its ``exit_code``). Either way the output path must not appear (or must be
unchanged when it existed before), no ``*.prism-tmp`` file may be left in
the output folder, no ``prism-stream-*`` folder in the temp folder, and the
input's bytes must be unchanged.
"""

from __future__ import annotations

import hashlib
import os
import resource
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.errors import (CorruptInput, InputNotFound, NoColorError, OutputError, OutputExists,
                                 UnsupportedFormat, UsageError)

from conftest import edge_file, prism_stream_command, real_file

GIB = 1 << 30


def _limit_address_space(limit: int):
    def apply():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return apply


def run_cli(args, cwd, memory_limit: int | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PRISM_STREAM_DEBUG"}
    return subprocess.run([*prism_stream_command(), *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120,
                          preexec_fn=_limit_address_space(memory_limit) if memory_limit else None)


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@dataclass
class Scene:
    """The files of one case, fingerprinted before the run so the test can say what changed."""

    inputs: list[Path]
    output: Path
    temp_dir: Path
    before: dict = field(default_factory=dict)

    def __post_init__(self):
        self.temp_dir.mkdir(exist_ok=True)
        self.before = {p: sha256(p) for p in self._existing()}

    def _existing(self):
        return [p for p in [*self.inputs, self.output] if p.is_file()]

    def assert_nothing_left(self, output_existed: bool = False):
        for p, digest in self.before.items():
            assert sha256(p) == digest, f"{p} was modified"
        if not output_existed:
            assert not self.output.exists(), "a failed run left its output behind"
        folder = self.output.parent
        leftovers = [n for n in os.listdir(folder) if n.endswith(".prism-tmp")]
        assert not leftovers, f"temporary output files left in {folder}: {leftovers}"
        stale = [n for n in os.listdir(self.temp_dir) if n.startswith("prism-stream-")]
        assert not stale, f"temporary folders left in {self.temp_dir}: {stale}"


def assert_one_line(result: subprocess.CompletedProcess, kind: str = "error") -> str:
    assert "Traceback" not in result.stderr + result.stdout
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got:\n{result.stderr}"
    assert lines[0].startswith(f"prism-stream: {kind}:"), lines[0]
    return lines[0]


def copy_into(tmp_path: Path, source: Path) -> Path:
    """A private copy of a shared file, so the test may fingerprint it and name outputs beside it."""
    dest = tmp_path / source.name
    shutil.copyfile(source, dest)
    return dest


# --- the cases: (input file, extra CLI options, exit code, exception, what the message must say) -------------

CORRUPT = [
    # a VLR count of 1,069,128,089: must be refused from the header, not by allocating gigabytes
    ("pdal__garbage_nVariableLength.las", "VLR"),
    # the header promises 1,065 points, the file ends after the header
    ("pdal__1.2-no-points.las", "1065"),
]

# valid LAZ in encodings the lazrs decoder does not read: refused from the header, exit 4 (not corrupt), with the way
# out (LASzip's own decompressor)
UNDECODABLE = [
    ("pdal__simple-laszip-compressor-version-1.2r0.laz", "compressor 1 (point-wise"),  # lazrs panics on it
    ("loadersgl__pdrf7-v4-1.4.laz", "Point14 of compression version 4"),
]


@pytest.mark.parametrize("name, says", UNDECODABLE)
def test_a_laz_encoding_the_decoder_cannot_read_is_exit_4_before_pass_one(tmp_path, name, says):
    src = copy_into(tmp_path, edge_file(name))
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UnsupportedFormat.exit_code == 4, result.stderr
    assert name in line and says in line and "does not read" in line and "laszip -i" in line, line
    with pytest.raises(UnsupportedFormat):
        prism_stream.sample(str(src), str(scene.output), ratio=0.5, temp_dir=str(scene.temp_dir))
    scene.assert_nothing_left()

NO_COLOR = ["pdal__1.2_1.las", "lazperf__no-points-1.3.laz"]


@pytest.mark.parametrize("name, says", CORRUPT)
def test_corrupt_file_is_one_line_exit_6(tmp_path, name, says):
    src = copy_into(tmp_path, edge_file(name))
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5", "--temp-dir", scene.temp_dir], tmp_path,
                     memory_limit=2 * GIB)
    line = assert_one_line(result)
    assert result.returncode == CorruptInput.exit_code == 6, result.stderr
    assert name in line and says.lower() in line.lower()
    scene.assert_nothing_left()


@pytest.mark.parametrize("name, says", CORRUPT)
def test_corrupt_file_raises_corrupt_input(tmp_path, name, says):
    src = copy_into(tmp_path, edge_file(name))
    scene = Scene([src], tmp_path / "out.las", tmp_path / "tmp")
    with pytest.raises(CorruptInput) as info:
        prism_stream.sample(str(src), str(scene.output), ratio=0.5, temp_dir=str(scene.temp_dir))
    assert info.value.path == str(src) and "\n" not in str(info.value)
    scene.assert_nothing_left()


@pytest.mark.parametrize("name", NO_COLOR)
def test_cloud_without_color_is_exit_5(tmp_path, name):
    src = copy_into(tmp_path, edge_file(name))
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == NoColorError.exit_code == 5
    assert name in line and "RGB" in line
    with pytest.raises(NoColorError):
        prism_stream.sample(str(src), str(scene.output), ratio=0.5, temp_dir=str(scene.temp_dir))
    scene.assert_nothing_left()


def test_missing_file_is_exit_3(tmp_path):
    scene = Scene([], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli(["no-such-cloud.las", scene.output, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == InputNotFound.exit_code == 3
    assert "no-such-cloud.las" in line
    with pytest.raises(InputNotFound):
        prism_stream.sample(str(tmp_path / "no-such-cloud.las"), str(scene.output), ratio=0.5)
    scene.assert_nothing_left()


def test_glob_matching_nothing_is_exit_3(tmp_path):
    scene = Scene([], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([str(tmp_path / "*.laz"), scene.output, "--ratio", "0.5"], tmp_path)
    assert_one_line(result)
    assert result.returncode == 3
    scene.assert_nothing_left()


def test_unknown_input_extension_is_exit_4(tmp_path):
    """Points in a file whose extension no reader claims: refused by name, not sniffed."""
    src = tmp_path / "cloud.lidar"
    shutil.copyfile(edge_file("lazperf__point-color.las"), src)
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UnsupportedFormat.exit_code == 4
    assert src.name in line and ".lidar" in line
    with pytest.raises(UnsupportedFormat):
        prism_stream.sample(str(src), str(scene.output), ratio=0.5)
    scene.assert_nothing_left()


def test_unknown_output_extension_is_exit_4(tmp_path):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    scene = Scene([src], tmp_path / "out.csv", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == 4 and "out.csv" in line
    scene.assert_nothing_left()


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="a /proc file system")
def test_a_folder_that_takes_no_files_says_so(tmp_path):
    """/proc is there, yet creating a file in it fails with "No such file or directory": said as what it means."""
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    result = run_cli([src, "/proc/prism-stream-out.parquet", "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == OutputError.exit_code == 8, line
    assert "/proc: cannot write here: the folder takes no new files" in line, line
    assert [p.name for p in tmp_path.iterdir()] == [src.name]


def test_missing_output_folder_is_an_output_error(tmp_path):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    out = tmp_path / "no-such-folder" / "out.las"
    result = run_cli([src, out, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == OutputError.exit_code == 8 and "out.las" in line
    with pytest.raises(OutputError):
        prism_stream.sample(str(src), str(out), ratio=0.5)
    assert not out.parent.exists()
    assert [p.name for p in tmp_path.iterdir()] == [src.name]
    inside_a_file = src / "out.las"  # a file where the output's folder should be: said as such
    line = assert_one_line(run_cli([src, inside_a_file, "--ratio", "0.5"], tmp_path))
    assert f"{src.name} is not a folder" in line and sha256(src) == sha256(edge_file("lazperf__point-color.las"))


def test_not_a_las_file_is_refused(tmp_path):
    """A .las name on bytes that are not LAS: refused from the signature, one line."""
    src = tmp_path / "notes.las"
    src.write_bytes(b"these are not the points you are looking for\n" * 20)
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UnsupportedFormat.exit_code and "notes.las" in line
    scene.assert_nothing_left()


@pytest.mark.parametrize("content", [b"# notes\n" * 40, b""])
def test_not_a_parquet_file_is_refused_as_no_parquet(tmp_path, content):
    """A .parquet name on bytes that do not begin with Parquet's PAR1 (text, an empty file): not a Parquet file,
    exit 4 as for a .las that is no LAS (a Parquet file cut short stays corrupt, exit 6: the truncation test)."""
    src = tmp_path / "notes.parquet"
    src.write_bytes(content)
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UnsupportedFormat.exit_code and "notes.parquet" in line and "PAR1" in line
    with pytest.raises(UnsupportedFormat):
        prism_stream.sample(str(src), str(scene.output), ratio=0.5)
    scene.assert_nothing_left()


def test_a_glob_without_an_output_never_replaces_a_tile(tmp_path):
    """``prism-stream tiles/*.laz --ratio 0.01 --overwrite``: the shell makes the last tile the output. A file
    beside the inputs, in their format, that prism-stream did not write is refused (exit 2) and kept; an output
    prism-stream wrote there is replaced as --overwrite says."""
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    a, b = copy_into(tiles, real_file("pdal__autzen_trim.las")), tiles / "b.las"
    shutil.copyfile(a, b)
    scene = Scene([a, b], b, tmp_path / "tmp")
    result = run_cli([a, b, "--ratio", "0.01", "--overwrite", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UsageError.exit_code and "b.las" in line and "tile" in line
    # without --overwrite the same reason, not "use --overwrite", which the next try would refuse
    result = run_cli([a, b, "--ratio", "0.01", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UsageError.exit_code and "tile" in line and "--overwrite" not in line, line
    with pytest.raises(UsageError):
        prism_stream.sample(str(a), str(b), ratio=0.01, overwrite=True)
    scene.assert_nothing_left(output_existed=True)
    ours = tiles / "sample.las"
    for ratio in ("0.01", "0.02"):  # written, then replaced: it carries prism-stream's provenance
        result = run_cli([a, ours, "--ratio", ratio, "--overwrite", "--quiet"], tmp_path)
        assert result.returncode == 0, result.stderr
    assert laspy.read(ours).header.point_count == round(0.02 * laspy.read(a).header.point_count)
    # a tile prism-stream wrote as a per-file output (directory mode's, named after its input) is a tile too;
    # a glob of *.las or *.laz matches a COPC tile and a.las beside d.laz is one family
    originals = tmp_path / "originals"
    originals.mkdir()
    shutil.copyfile(a, originals / "c.las")
    assert prism_stream.sample(str(originals), str(tiles) + os.sep, ratio=0.5)  # tiles/c.las, by directory mode
    shutil.copyfile(edge_file("pdal__1.2-with-color.copc.laz"), tiles / "e.copc.laz")
    shutil.copyfile(edge_file("loadersgl__pdrf8-1.4.laz"), tiles / "d.laz")
    for last in ("c.las", "d.laz", "e.copc.laz"):
        before = sha256(tiles / last)
        result = run_cli([a, b, tiles / last, "--ratio", "0.01", "--overwrite"], tmp_path)
        assert result.returncode == UsageError.exit_code and last in assert_one_line(result), last
        assert sha256(tiles / last) == before, last


def test_a_tile_guard_for_links(tmp_path):
    """Links among the tiles are where the glob found them (a folder of links into other folders is guarded);
    an output that is a link to a tile elsewhere is replaced as a link, the tile untouched."""
    for folder in ("links", "r1", "r2", "x"):
        (tmp_path / folder).mkdir()
    shutil.copyfile(real_file("pdal__autzen_trim.las"), tmp_path / "r1" / "a.las")
    shutil.copyfile(real_file("pdal__autzen_trim.las"), tmp_path / "r2" / "c.las")
    (tmp_path / "links" / "a.las").symlink_to(tmp_path / "r1" / "a.las")
    (tmp_path / "links" / "c.las").symlink_to(tmp_path / "r2" / "c.las")
    before = sha256(tmp_path / "r2" / "c.las")
    result = run_cli([tmp_path / "links" / "a.las", tmp_path / "links" / "c.las", "--ratio", "0.5", "--overwrite"],
                     tmp_path)
    assert result.returncode == UsageError.exit_code and "c.las" in assert_one_line(result)
    assert (tmp_path / "links" / "c.las").is_symlink() and sha256(tmp_path / "r2" / "c.las") == before
    (tmp_path / "x" / "out.las").symlink_to(tmp_path / "r2" / "c.las")
    result = run_cli([tmp_path / "r1" / "a.las", tmp_path / "x" / "out.las", "--ratio", "0.5", "--overwrite"],
                     tmp_path)
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "x" / "out.las").is_symlink() and sha256(tmp_path / "r2" / "c.las") == before


def test_directory_mode_overwrites_only_its_own_outputs(tmp_path):
    """``prism-stream dm/* --overwrite`` with a folder among the tiles: the folder is the output and holds the
    originals under the inputs' names; --overwrite replaces a file there only when it is this command's earlier
    output (its provenance names the same inputs), so the originals are kept and a re-run still replaces."""
    dm = tmp_path / "dm"
    (dm / "orig").mkdir(parents=True)
    for name in ("a.las", "b.las"):
        shutil.copyfile(real_file("pdal__autzen_trim.las"), dm / name)
        shutil.copyfile(real_file("pdal__autzen_trim.las"), dm / "orig" / name)
    before = {p: sha256(p) for p in (dm / "orig").iterdir()}
    result = run_cli([dm / "a.las", dm / "b.las", dm / "orig", "--ratio", "0.5", "--overwrite"], tmp_path)
    assert result.returncode == UsageError.exit_code and "orig" in assert_one_line(result)
    assert {p: sha256(p) for p in (dm / "orig").iterdir()} == before
    out = tmp_path / "out"
    for ratio in ("0.5", "0.25"):
        result = run_cli([dm / "a.las", dm / "b.las", str(out) + os.sep, "--ratio", ratio, "--overwrite", "--quiet"],
                         tmp_path)
        assert result.returncode == 0, result.stderr
    kept = sum(laspy.read(out / n).header.point_count for n in ("a.las", "b.las"))  # one cloud, two files
    assert kept == round(0.25 * 2 * laspy.read(dm / "a.las").header.point_count)


def test_a_glob_without_an_output_never_replaces_a_tile_on_dask(tmp_path):
    """The same on the Dask engine, whose output is a folder: the last Parquet tile would have become one."""
    pytest.importorskip("distributed")
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    for name in ("a.parquet", "b.parquet"):
        assert prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(tiles / name), ratio=0.2)
    table = pq.read_table(tiles / "a.parquet")
    pq.write_table(table.replace_schema_metadata({}), tiles / "c.parquet")  # a tile no prism-stream run wrote
    before = sha256(tiles / "c.parquet")
    result = run_cli([tiles / "a.parquet", tiles / "b.parquet", tiles / "c.parquet", "--ratio", "0.5",
                      "--overwrite", "--dask", "local:1"], tmp_path)
    assert result.returncode == UsageError.exit_code and "c.parquet" in assert_one_line(result)
    assert (tiles / "c.parquet").is_file() and sha256(tiles / "c.parquet") == before


@pytest.mark.parametrize("ext", [".las", ".laz", ".copc.laz", ".parquet", ".ply", ".xyz"])
def test_a_run_again_into_its_own_output_beside_the_inputs(tmp_path, ext):
    """Every format prism-stream writes carries its provenance, so an output of it beside inputs in its format
    is replaced by --overwrite (the tile guard reads the provenance back), for each format."""
    src = tmp_path / f"in{ext}"
    assert prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(src), ratio=0.5)
    ours = tmp_path / f"sample{ext}"
    for ratio in (0.2, 0.1):
        result = run_cli([src, ours, "--ratio", ratio, "--overwrite", "--quiet"], tmp_path)
        assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("ratio", ["0", "-0.1", "1.5", "nan"])
def test_ratio_outside_0_1_is_a_usage_error(tmp_path, ratio):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, f"--ratio={ratio}", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == UsageError.exit_code == 2
    assert "--ratio" in line
    with pytest.raises(UsageError):
        prism_stream.sample(str(src), str(scene.output), ratio=float(ratio))
    scene.assert_nothing_left()


def test_count_above_n_is_a_usage_error(tmp_path):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    n = laspy.open(src).header.point_count
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--count", n + 1, "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == 2 and f"{n + 1:,}" in line and f"the {n:,} points" in line
    with pytest.raises(UsageError):
        prism_stream.sample(str(src), str(scene.output), count=n + 1, temp_dir=str(scene.temp_dir))
    scene.assert_nothing_left()


def test_two_targets_are_a_usage_error(tmp_path):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    scene = Scene([src], tmp_path / "out.parquet", tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.5", "--count", "10"], tmp_path)
    assert_one_line(result)
    assert result.returncode == 2
    scene.assert_nothing_left()


def test_existing_output_is_kept_without_overwrite(tmp_path):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    out = tmp_path / "out.parquet"
    out.write_bytes(b"an older result the user wants to keep")
    scene = Scene([src], out, tmp_path / "tmp")
    result = run_cli([src, out, "--ratio", "0.5", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == OutputExists.exit_code == 7 and "out.parquet" in line
    with pytest.raises(OutputExists):
        prism_stream.sample(str(src), str(out), ratio=0.5)
    scene.assert_nothing_left(output_existed=True)


@pytest.mark.parametrize("spelling", ["same", "relative"])
def test_output_equal_to_an_input_is_refused(tmp_path, spelling):
    src = copy_into(tmp_path, edge_file("lazperf__point-color.las"))
    out = src if spelling == "same" else Path("..") / tmp_path.name / src.name
    scene = Scene([src], src, tmp_path / "tmp")
    result = run_cli([src, out, "--ratio", "0.5", "--overwrite"], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == 2 and src.name in line
    with pytest.raises(UsageError):
        prism_stream.sample(str(src), str(src), ratio=0.5, overwrite=True)
    scene.assert_nothing_left(output_existed=True)


@pytest.mark.parametrize("name, keep, out_name", [
    ("pdal__autzen_trim.las", 0.5, "out.las"),  # LAS cut mid-points
    ("pdal__autzen_trim.las", 0.999, "out.parquet"),  # LAS missing its last few records
    ("pdal__las_with_several_extra_byte_bloc.laz", 0.5, "out.laz"),  # LAZ cut mid-chunks
    ("laspy__fullwave.laz", 0.98, "out.parquet"),  # LAZ missing its tail (and chunk table)
])
def test_truncated_file_is_one_line_and_no_output(tmp_path, name, keep, out_name):
    """A copy of a real cloud, cut inside its point records."""
    data = real_file(name).read_bytes()
    src = tmp_path / f"cut_{name}"
    src.write_bytes(data[: int(len(data) * keep)])
    scene = Scene([src], tmp_path / out_name, tmp_path / "tmp")
    result = run_cli([src, scene.output, "--ratio", "0.3", "--temp-dir", scene.temp_dir], tmp_path)
    line = assert_one_line(result)
    assert result.returncode == 6 and src.name in line
    with pytest.raises(CorruptInput):
        prism_stream.sample(str(src), str(scene.output), ratio=0.3, temp_dir=str(scene.temp_dir))
    scene.assert_nothing_left()


# --- things that are not errors: a warning line, exit 0, a valid output ---------------------------------------

def test_all_zero_color_warns_and_writes_a_valid_output(tmp_path):
    src = copy_into(tmp_path, edge_file("pdal__spec_3.las"))
    n = laspy.open(src).header.point_count
    out = tmp_path / "out.las"
    scene = Scene([src], out, tmp_path / "tmp")
    result = run_cli([src, out, "--ratio", "0.5", "--quiet", "--temp-dir", scene.temp_dir], tmp_path)
    assert result.returncode == 0, result.stderr
    line = assert_one_line(result, "warning")
    assert "same color" in line or "one bin" in line
    kept = laspy.read(out)
    assert len(kept.points) == int(np.floor(0.5 * n + 0.5))
    assert not (kept.red.any() or kept.green.any() or kept.blue.any())
    with pytest.warns(PrismWarning):
        prism_stream.sample(str(src), str(tmp_path / "again.las"), ratio=0.5)
    scene.before.pop(out, None)
    for p, digest in scene.before.items():
        assert sha256(p) == digest


@pytest.mark.parametrize("out_name", ["out.las", "out.parquet"])
def test_zero_points_gives_a_valid_empty_output(tmp_path, out_name):
    src = copy_into(tmp_path, edge_file("pdal__no-points.las"))
    digest = sha256(src)
    out = tmp_path / out_name
    result = run_cli([src, out, "--ratio", "0.5", "--quiet"], tmp_path)
    assert result.returncode == 0, result.stderr
    line = assert_one_line(result, "warning")
    assert "no points" in line
    assert_valid_empty(out, src)
    assert sha256(src) == digest


@pytest.mark.parametrize("out_name", ["out.las", "out.laz", "out.parquet"])
def test_zero_points_through_the_api_warns(tmp_path, out_name):
    src = edge_file("pdal__no-points.las")
    out = tmp_path / out_name
    with pytest.warns(PrismWarning, match="no points"):
        summary = prism_stream.sample(str(src), str(out), ratio=0.5)
    assert summary.points == 0 and summary.kept == 0
    assert_valid_empty(out, src)


def assert_valid_empty(out: Path, src: Path) -> None:
    if out.suffix == ".parquet":
        assert pq.ParquetFile(out).metadata.num_rows == 0
    else:
        empty = laspy.read(out)
        assert len(empty.points) == 0 and empty.header.point_count == 0
        assert empty.header.point_format.id == laspy.open(src).header.point_format.id
