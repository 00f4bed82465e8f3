"""Shared fixtures: where the real clouds live, and writers for generated ones.

The test clouds are committed under ``tests/data`` (``real/`` and ``edge/``;
``tests/data/README.md`` gives each file's origin), so a fresh clone tests
itself with nothing beside it. A missing file is an error, never a skip. The
data is read-only: tests read it and write only under ``tmp_path``.

Under CI (``CI`` set in the environment) a skipped test fails the run: the
test environment installs every optional dependency and the data is in the
repository, so a skip can only hide something that no longer runs.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import warnings
from pathlib import Path

import hypothesis
import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from prism_stream import PrismWarning

# Provenance records when a run happened; with SOURCE_DATE_EPOCH fixed, two runs that must write the same bytes
# (one read against two, either input order...) do so even across a second's boundary. Subprocesses inherit it.
# tests/test_provenance.py checks the real clock with it removed.
os.environ.setdefault("SOURCE_DATE_EPOCH", "1767225600")

# A run of at most PRISM_STREAM_MEMORY_POINTS points (default about a million) is held in memory with numpy
# alone; the test clouds are all that small, so without this the suite would exercise that path instead of
# the streaming one (the candidate spill, the key cache) that large inputs take. tests/test_in_memory.py
# removes it and holds the in-memory path to the streaming one's bytes. Subprocesses inherit it.
os.environ["PRISM_STREAM_MEMORY_POINTS"] = "0"

# A suite started as a script's background job (`make test &`) inherits SIGINT ignored (sh's rule for `&`), and so
# would every command it starts, which keeps it ignored (tests/test_faults.py): the signal tests would then meet
# that convention instead of a Ctrl-C at a terminal. Commands started from here get SIGINT's default action.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

DATA = Path(__file__).resolve().parent / "data"

# The property tests run on a fixed set of examples, locally as in CI: a red run must mean a change broke
# something, not that the generator got lucky, and a local pass must mean CI passes (a mutant the fixed
# examples miss needs its own test, not a lucky local draw). PRISM_STREAM_EXPLORE=1 draws new examples.
hypothesis.settings.register_profile("fixed", derandomize=True, print_blob=True)
hypothesis.settings.register_profile("explore", derandomize=False, print_blob=True)
hypothesis.settings.load_profile("explore" if os.environ.get("PRISM_STREAM_EXPLORE") else "fixed")

REAL = DATA / "real"
EDGE = DATA / "edge"

# formats the engine reads today; PLY and PCD clouds in real/ are skipped until they are
LAS_EXTENSIONS = (".las", ".laz")


class MissingTestData(FileNotFoundError):
    """A file or folder of tests/data is not there: the checkout is incomplete (an error, not a skip)."""


def _require(folder: Path) -> Path:
    if not folder.is_dir():
        raise MissingTestData(f"test data folder not found: {folder} (it is part of the repository, "
                              "see tests/data/README.md)")
    return folder


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """The folder of real sensor clouds."""
    return _require(REAL)


@pytest.fixture(scope="session")
def edge_dir() -> Path:
    """The folder of edge-case files from other libraries' test suites."""
    return _require(EDGE)


def cli(capsys, *args):
    """Run the command line in this process: (exit code, stdout, stderr)."""
    from prism_stream_cli.main import run

    with pytest.raises(SystemExit) as exc:
        run([str(a) for a in args])
    out, err = capsys.readouterr()
    return exc.value.code or 0, out, err


def read_las(path) -> "laspy.LasData":
    """laspy.read, with every extra-bytes record's names (laspy names only the first record's dimensions; the
    writers name them all, as PDAL does: ``prism_stream.formats.extrabytes.merge_records``)."""
    import laspy

    from prism_stream.formats import extrabytes

    with laspy.open(str(path)) as reader:
        extrabytes.merge_records(reader.header)
        return reader.read()


def real_file(name: str) -> Path:
    """A file in real/; a missing one raises MissingTestData."""
    path = REAL / name
    if not path.is_file():
        raise MissingTestData(f"test data file not found: {path} (see tests/data/README.md)")
    return path


# The per-cloud tests (one read against two, in memory against streaming, rank prefixes, the streamed outlier
# removal) check what each real cloud holds: its point format, extra bytes, colors and geometry, not its size.
# The 697,721-point extra-bytes tile alone took a fifth of their time, so they read an excerpt of it: its first
# EXCERPT_POINTS points, its header and every VLR kept (laspy writes it back). bench/ runs the whole file.
EXCERPTED = {"pdal__las_with_several_extra_byte_bloc.laz"}
EXCERPT_POINTS = 120_000


@pytest.fixture(scope="session")
def real_cloud(tmp_path_factory):
    """``real_cloud(name)``: the path of a real cloud to run per-cloud tests on (an excerpt of a large one)."""
    made: dict = {}

    def get(name: str) -> Path:
        path = real_file(name)
        if name not in EXCERPTED:
            return path
        if name not in made:
            with laspy.open(path) as reader:
                points = reader.read_points(EXCERPT_POINTS)
                header = reader.header
            out = tmp_path_factory.mktemp("excerpt") / name
            with laspy.open(out, mode="w", header=header) as writer:
                writer.write_points(points)
            made[name] = out
        return made[name]

    return get


def covering(runs: list, name: str, names: list, ways: int = 3) -> list:
    """The runs a per-cloud test makes on cloud ``name``: every ``ways``-th of ``runs``, from an offset set by
    the cloud's place in ``names``.

    The per-cloud tests cross two things: what each real cloud holds (its format, extra bytes, colors) and
    what each run asks (a rule, a seed, quantization). The whole cross product decoded every cloud dozens of
    times; this covering keeps every cloud with a share of the runs and every run on several clouds (with
    eight clouds and ``ways`` 3, each run meets two or three of them), at a third of the decoding.
    """
    offset = sorted(names).index(name) % ways
    return [r for j, r in enumerate(runs) if j % ways == offset]


def edge_file(name: str) -> Path:
    """A file in edge/; a missing one raises MissingTestData."""
    path = EDGE / name
    if not path.is_file():
        raise MissingTestData(f"test data file not found: {path} (see tests/data/README.md)")
    return path


def real_las_files() -> list[Path]:
    """Every LAS/LAZ cloud in real/, sorted by name (MissingTestData if the folder is missing)."""
    return sorted(p for p in _require(REAL).iterdir() if p.name.lower().endswith(LAS_EXTENSIONS))


def write_las(path, rgb, point_format: int = 3, version: str = "1.2", extra: dict | None = None,
              xyz=None, seed: int = 0) -> Path:
    """Write a generated LAS/LAZ cloud (LAZ if ``path`` ends in .laz).

    ``rgb`` is an (n, 3) array (or three arrays) of the values to store in the
    16-bit red/green/blue fields, as is. ``extra`` maps extra-bytes dimension
    names to arrays of length n (their dtype is kept). Coordinates are random
    (seeded) unless ``xyz`` gives them; every record also gets a distinct
    ``intensity`` (its index mod 2^16) and ``gps_time`` where the format has
    one, so that kept records can be told apart.
    """
    path = Path(path)
    r, g, b = _channels(rgb)
    n = len(r)
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([1000.0, 2000.0, 10.0])
    for name, values in (extra or {}).items():
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.asarray(values).dtype))
    las = laspy.LasData(header)
    if xyz is None:
        rng = np.random.default_rng(seed)
        xyz = rng.uniform(0, 100, size=(n, 3))
    xyz = np.asarray(xyz, dtype=np.float64)
    las.x = xyz[:, 0] + header.offsets[0]
    las.y = xyz[:, 1] + header.offsets[1]
    las.z = xyz[:, 2] + header.offsets[2]
    las.red = r.astype(np.uint16)
    las.green = g.astype(np.uint16)
    las.blue = b.astype(np.uint16)
    las.intensity = (np.arange(n) % 65536).astype(np.uint16)
    if "gps_time" in las.point_format.dimension_names:
        las.gps_time = np.arange(n, dtype=np.float64) * 0.5
    for name, values in (extra or {}).items():
        las[name] = np.asarray(values)
    las.write(str(path))
    return path


def write_parquet(path, table, row_group_size: int | None = None) -> Path:
    """Write a generated cloud to Parquet.

    ``table`` is a ``pyarrow.Table`` or a dict of column name to array;
    ``row_group_size`` splits it into several row groups.
    """
    path = Path(path)
    if not isinstance(table, pa.Table):
        table = pa.table({k: np.asarray(v) for k, v in table.items()})
    pq.write_table(table, str(path), row_group_size=row_group_size)
    return path


def random_colors(n: int, seed: int = 0, palette: int = 200, skew: float = 1.3, depth: int = 8) -> np.ndarray:
    """(n, 3) colors drawn from a palette with Zipf-like skewed bin sizes.

    ``depth=16`` returns the 8-bit values scaled by 256 (v << 8), as many LAS
    writers store them.
    """
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, size=(palette, 3))
    weights = 1.0 / np.arange(1, palette + 1) ** skew
    pick = rng.choice(palette, size=n, p=weights / weights.sum())
    out = colors[pick].astype(np.int64)
    return out << 8 if depth == 16 else out


def _channels(rgb):
    if isinstance(rgb, (tuple, list)) and len(rgb) == 3 and np.ndim(rgb[0]) == 1:
        return tuple(np.asarray(c) for c in rgb)
    a = np.asarray(rgb)
    return a[:, 0], a[:, 1], a[:, 2]


@pytest.fixture
def quiet():
    """Silence PrismWarning (one bin, empty output) inside a test that expects it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PrismWarning)
        yield


def lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream of literal runs only (32 bytes a run): a PCD binary_compressed body."""
    out = bytearray()
    for i in range(0, len(data), 32):
        run = data[i:i + 32]
        out.append(len(run) - 1)
        out += run
    return bytes(out)


def user_env(**extra) -> dict:
    """The environment a user's command line runs in: this one without the suite's streaming switch (a small
    input is then held in memory, as it is for a user), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k != "PRISM_STREAM_MEMORY_POINTS"}
    env.update(extra)
    return env


def prism_stream_command() -> list[str]:
    """The installed console script (beside this interpreter first), else the module."""
    script = Path(sys.executable).with_name("prism-stream")
    if script.is_file():
        return [str(script)]
    found = shutil.which("prism-stream")
    return [found] if found else [sys.executable, "-m", "prism_stream_cli.main"]


# -- no silent skips under CI ---------------------------------------------------------------
# `make test` installs every optional dependency and the data is committed, so under CI a skipped
# test is something that silently stopped running: the run fails and names it. Skips, not xfails:
# an xfail states an expectation and is reported as such. Collection-time skips count too (a module
# that skips itself at import). With pytest-xdist the controller sees every worker's reports, so the
# decision is taken there.

_SKIPPED: list[tuple[str, str]] = []


def skips_fail_the_run() -> bool:
    """True under CI: the environment variable CI set to anything but empty, 0, false or no."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def _reason(report) -> str:
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:  # (path, line, "Skipped: reason")
        return str(longrepr[2])
    return str(longrepr)


def pytest_runtest_logreport(report):
    if report.skipped and not hasattr(report, "wasxfail"):
        _SKIPPED.append((report.nodeid, _reason(report)))


def pytest_collectreport(report):
    if report.skipped:
        _SKIPPED.append((report.nodeid or "<collection>", _reason(report)))


def _is_xdist_worker(config) -> bool:
    return hasattr(config, "workerinput")


def pytest_sessionfinish(session, exitstatus):
    if _SKIPPED and skips_fail_the_run() and not _is_xdist_worker(session.config) \
            and exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if not _SKIPPED or not skips_fail_the_run() or _is_xdist_worker(config):
        return
    terminalreporter.section(f"{len(_SKIPPED)} skipped under CI: the run fails", sep="=", red=True, bold=True)
    for nodeid, reason in _SKIPPED:
        terminalreporter.line(f"SKIPPED {nodeid} - {reason}", red=True)
    terminalreporter.line("A skip under CI hides a test that no longer runs: every optional dependency is "
                          "installed by `make test` and the data is in tests/data. Make it run, or make it fail.")
