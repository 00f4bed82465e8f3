"""SPEC 1-5 end to end: the engine's output equals the oracle's, row for row.

The oracle (tests/oracle.py) holds every point in memory and sorts; the
engine streams twice with cutoffs. For each case the kept records are read
back from the output and compared, every column and in order, with the
input records at the oracle's indices; the summary's numbers (N, B, T,
k*/K, E, kept, each file's color depth) must match the oracle's too.
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from conftest import REAL, random_colors, real_file, real_las_files, write_las, write_parquet
from conftest import read_las as read_las_named
from prism_stream import sample


@functools.lru_cache(maxsize=4)
def read_las(path: str) -> laspy.LasData:
    return read_las_named(path)  # every extra-bytes record's names, as the writers give them


def las_columns(las: laspy.LasData, names) -> dict:
    """Input columns by output name: x/y/z scaled to float64, every other dimension as stored."""
    out = {}
    for name in names:
        if name in ("x", "y", "z"):
            out[name] = np.asarray(getattr(las, name), dtype=np.float64)
        else:
            out[name] = np.asarray(las[name])
    return out


def expected_dimension_names(las: laspy.LasData) -> list[str]:
    return [n.lower() if n in ("X", "Y", "Z") else n for n in las.point_format.dimension_names]


def test_oracle_is_independent_of_the_engine():
    """The oracle may read files with laspy/pyarrow, but must not borrow the engine's logic."""
    import ast

    tree = ast.parse(Path(oracle.__file__).read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module or "")
    assert not any(m.startswith(("prism_stream", ".")) or m == "" for m in imported), imported


def assert_rows_equal(out_path, inputs: list[dict], kept: list[np.ndarray]):
    """The output holds inputs[s][column][kept[s]], source after source, for every column."""
    table = pq.read_table(out_path)
    assert table.num_rows == sum(len(k) for k in kept)
    for name in table.column_names:
        got = table.column(name).to_numpy(zero_copy_only=False)
        if got.dtype == object:  # fixed-size lists (multi-element extra bytes)
            got = np.stack(got) if len(got) else got
        want = np.concatenate([np.asarray(cols[name])[idx] for cols, idx in zip(inputs, kept)])
        np.testing.assert_array_equal(got, want, err_msg=f"column {name!r}")


def assert_summary_matches(summary, want: oracle.Result):
    assert summary.points == want.points
    assert summary.bins == want.bins
    assert summary.target == want.target
    assert summary.k == want.k
    assert summary.extra == want.extra
    assert summary.kept == want.kept_total
    assert [s["color_depth"] for s in summary.sources] == want.depths


def run_las_case(paths, inputs_arg, tmp_path, **opts):
    """Sample LAS/LAZ ``paths`` (given to the engine as ``inputs_arg``) and check against the oracle."""
    lases = [read_las(str(p)) for p in paths]
    want = oracle.sample([(l.red, l.green, l.blue) for l in lases], **_oracle_opts(opts))
    out = tmp_path / "out.parquet"
    summary = sample(inputs_arg, str(out), overwrite=True, **opts)
    assert_summary_matches(summary, want)
    names = expected_dimension_names(lases[0])
    assert pq.read_schema(out).names == names
    assert_rows_equal(out, [las_columns(l, names) for l in lases], want.kept)
    return summary, want


def _oracle_opts(opts: dict) -> dict:
    o = {k: v for k, v in opts.items() if k in ("ratio", "count", "k", "mode", "color_space", "color_depth", "seed")}
    if "quant_bits" in opts:
        o["bits"] = opts["quant_bits"]
    return o


# -- real clouds --------------------------------------------------------------------------

SMALL = 20_000  # points: below this a real cloud gets the full grid of options

FULL_GRID = [
    dict(mode=mode, color_space=space, quant_bits=bits, seed=seed, **target)
    for mode, target in (("exact", {"ratio": 0.01}), ("exact", {"ratio": 0.3}), ("paper", {"ratio": 0.05}),
                         ("exact", {"k": 2}), ("exact", {"k": 1}))
    for space in ("rgb", "chroma")
    for bits in (0, 4)
    for seed in (0, 42)
]

# for the big clouds: every mode, color space, bit depth and seed appears at least once
SUBSET = [
    dict(mode="exact", color_space="rgb", quant_bits=0, seed=0, ratio=0.01),
    dict(mode="paper", color_space="chroma", quant_bits=4, seed=42, ratio=0.05),
    dict(mode="exact", color_space="chroma", quant_bits=0, seed=42, ratio=0.2),
    dict(mode="exact", color_space="rgb", quant_bits=4, seed=7, k=3),
]


def _real_cases():
    cases = []
    for path in real_las_files():
        n = laspy.open(str(path)).header.point_count
        grid = FULL_GRID if n <= SMALL else SUBSET
        for opts in grid:
            label = "-".join(f"{k}={v}" for k, v in opts.items())
            cases.append(pytest.param(path, opts, id=f"{path.name}-{label}"))
    return cases


@pytest.mark.parametrize("path,opts", _real_cases())
def test_real_cloud_matches_oracle(path, opts, tmp_path):
    run_las_case([path], str(path), tmp_path, **opts)


# -- real PLY clouds, read independently with plyfile --------------------------------------------

PLY_COLOR_NAMES = (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


@functools.lru_cache(maxsize=2)
def read_ply_vertices(path: str) -> dict:
    from plyfile import PlyData

    vertex = PlyData.read(path)["vertex"].data
    return {name: np.asarray(vertex[name]) for name in vertex.dtype.names}


def _real_ply_files():
    return sorted(p for p in REAL.iterdir() if p.suffix.lower() == ".ply")


@pytest.mark.parametrize("path", _real_ply_files(), ids=lambda p: p.name)
@pytest.mark.parametrize("opts", SUBSET, ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items()))
def test_real_ply_matches_oracle(path, opts, tmp_path):
    cols = read_ply_vertices(str(path))
    rgb = next(names for names in PLY_COLOR_NAMES if all(n in cols for n in names))
    want = oracle.sample([tuple(cols[n] for n in rgb)], **_oracle_opts(opts))
    out = tmp_path / "out.parquet"
    summary = sample(str(path), str(out), **opts)
    assert_summary_matches(summary, want)
    assert pq.read_schema(out).names == list(cols)
    assert_rows_equal(out, [cols], want.kept)


def test_real_clouds_cover_every_color_depth():
    """The real LAS/LAZ set holds both 8-bit and 16-bit files, so the grid above exercises both."""
    files = real_las_files()
    depths = {oracle.color_depth(oracle.read_las_colors(p)) for p in files}
    assert depths == {"8", "16"}


def test_las_output_keeps_the_oracle_records_byte_for_byte(tmp_path):
    path = real_file("pdal__warsaw_small.las")
    las = read_las(str(path))
    want = oracle.sample([(las.red, las.green, las.blue)], ratio=0.1, seed=3, color_space="chroma", bits=1)
    out = tmp_path / "out.las"
    sample(str(path), str(out), ratio=0.1, seed=3, color_space="chroma", quant_bits=1)
    got = laspy.read(str(out))
    assert got.header.point_format.id == las.header.point_format.id
    assert got.points.array.tobytes() == las.points.array[want.kept[0]].tobytes()


# -- generated clouds: several sources, skewed bins, mixed depths -------------------------------


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """Four LAS files of skewed colors: 8-bit and 16-bit (v << 8) ones, different sizes."""
    folder = tmp_path_factory.mktemp("generated")
    specs = [("c_part.las", 1500, 8), ("a_part.las", 700, 16), ("d_part.las", 2500, 16), ("b_part.las", 40, 8)]
    paths = []
    for i, (name, n, depth) in enumerate(specs):
        paths.append(write_las(folder / name, random_colors(n, seed=i, palette=120, depth=depth), seed=i))
    return folder, paths


GEN_GRID = [
    dict(mode=mode, color_space=space, quant_bits=bits, seed=seed, **target)
    for mode, target in (("exact", {"ratio": 0.02}), ("exact", {"ratio": 0.5}), ("paper", {"ratio": 0.1}),
                         ("exact", {"count": 7}), ("exact", {"k": 4}))
    for space in ("rgb", "chroma")
    for bits in (0, 4)
    for seed in (0, 99)
]


@pytest.mark.parametrize("opts", GEN_GRID, ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items()))
def test_list_of_sources_matches_oracle(generated, opts, tmp_path):
    """Sources in argument order (not sorted): ordinal i is the i-th argument."""
    _, paths = generated
    summary, want = run_las_case(paths, [str(p) for p in paths], tmp_path, **opts)
    assert [Path(s["path"]).name for s in summary.sources] == [p.name for p in paths]


@pytest.mark.parametrize("opts", GEN_GRID[::5], ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items()))
def test_glob_of_sources_matches_oracle(generated, opts, tmp_path):
    """A glob expands in sorted path order, which fixes the source ordinals."""
    folder, paths = generated
    ordered = sorted(paths)
    summary, _ = run_las_case(ordered, str(folder / "*_part.las"), tmp_path, **opts)
    assert [Path(s["path"]).name for s in summary.sources] == [p.name for p in ordered]


def test_source_order_changes_ids_hence_the_sample(generated, tmp_path):
    """Ids carry the source ordinal: the same files in another order are another cloud."""
    _, paths = generated
    a = run_las_case(paths, [str(p) for p in paths], tmp_path, ratio=0.3, seed=1)[1]
    b = run_las_case(paths[::-1], [str(p) for p in paths[::-1]], tmp_path, ratio=0.3, seed=1)[1]
    assert [x.tolist() for x in a.kept] != [x.tolist() for x in b.kept[::-1]]


def test_empty_source_keeps_its_ordinal(generated, tmp_path):
    """An empty file still takes an ordinal: the sources after it get the next ones."""
    _, paths = generated
    empty = write_las(tmp_path / "empty.las", np.zeros((0, 3), dtype=np.int64))
    order = [paths[0], empty, paths[1]]
    summary, want = run_las_case(order, [str(p) for p in order], tmp_path, ratio=0.2, seed=13)
    assert [s["ordinal"] for s in summary.sources] == [0, 1, 2]
    assert summary.sources[1]["points"] == 0
    # the same two files without the empty one between them are another cloud (ids differ)
    other = oracle.sample([oracle.read_las_colors(p) for p in (paths[0], paths[1])], ratio=0.2, seed=13)
    assert [k.tolist() for k in other.kept] != [want.kept[0].tolist(), want.kept[2].tolist()]


def test_keep_flag_column_is_the_oracle_mask(generated, tmp_path):
    """With a keep flag every point is written, flagged exactly where the oracle keeps it."""
    _, paths = generated
    lases = [read_las(str(p)) for p in paths]
    want = oracle.sample([(l.red, l.green, l.blue) for l in lases], ratio=0.05, seed=21, color_space="chroma")
    out = tmp_path / "flagged.parquet"
    sample([str(p) for p in paths], str(out), ratio=0.05, seed=21, color_space="chroma", flag="keep")
    table = pq.read_table(out)
    assert table.num_rows == sum(len(l.points) for l in lases)
    mask = []
    for l, kept in zip(lases, want.kept):
        m = np.zeros(len(l.points), dtype=bool)
        m[kept] = True
        mask.append(m)
    np.testing.assert_array_equal(table.column("keep").to_numpy(), np.concatenate(mask))
    np.testing.assert_array_equal(table.column("gps_time").to_numpy(), np.concatenate([l.gps_time for l in lases]))


@pytest.fixture
def tree(tmp_path):
    """An input folder with a subfolder: three LAS files, one 16-bit."""
    root = tmp_path / "in"
    (root / "sub").mkdir(parents=True)
    specs = [("f0.las", 900, 8), ("f1.las", 1400, 16), ("sub/f2.las", 600, 8)]
    paths = [write_las(root / name, random_colors(n, seed=i, palette=70, depth=d), seed=i)
             for i, (name, n, d) in enumerate(specs)]
    return root, paths


@pytest.mark.parametrize("per_file", [False, True], ids=["global-solve", "per-file"])
def test_directory_mode_matches_oracle(tree, per_file, tmp_path):
    """One output per input file: a global solve over all files, or each file solved alone."""
    root, paths = tree
    opts = dict(ratio=0.05, mode="exact", color_space="chroma", seed=17)
    lases = [read_las(str(p)) for p in paths]
    rgb = [(l.red, l.green, l.blue) for l in lases]
    if per_file:
        kept = [oracle.sample([c], **_oracle_opts(opts)).kept[0] for c in rgb]
    else:
        kept = oracle.sample(rgb, **_oracle_opts(opts)).kept
    out = tmp_path / "out"
    summary = sample(str(root), str(out) + "/", per_file=per_file, **opts)
    assert summary.kept == sum(len(k) for k in kept)
    for path, las, idx in zip(paths, lases, kept):
        got = laspy.read(str(out / path.relative_to(root)))
        assert got.points.array.tobytes() == las.points.array[idx].tobytes(), path.name


def test_one_bin_is_a_plain_random_sample(tmp_path, quiet):
    colors = np.tile([[10, 20, 30]], (500, 1))
    path = write_las(tmp_path / "flat.las", colors)
    summary, want = run_las_case([path], str(path), tmp_path, ratio=0.1, seed=5)
    assert summary.bins == 1 and summary.kept == 50


def test_every_point_its_own_bin(tmp_path):
    """B = N: exact keeps T bins of one point (K = 0), paper keeps all (k* = 1)."""
    rng = np.random.default_rng(0)
    codes = rng.choice(1 << 24, size=3000, replace=False)
    colors = np.stack([(codes >> 16) & 255, (codes >> 8) & 255, codes & 255], axis=1)
    path = write_las(tmp_path / "distinct.las", colors)
    s, _ = run_las_case([path], str(path), tmp_path, ratio=0.05, seed=11)
    assert (s.k, s.kept) == (0, 150)
    s, _ = run_las_case([path], str(path), tmp_path, ratio=0.05, seed=11, mode="paper")
    assert (s.k, s.kept) == (1, 3000)


# -- Parquet input ----------------------------------------------------------------------


def las_to_table(las: laspy.LasData) -> pa.Table:
    names = expected_dimension_names(las)
    return pa.table(las_columns(las, names))


@pytest.fixture(scope="module")
def autzen_parquet(tmp_path_factory):
    las = read_las(str(real_file("pdal__autzen_trim.las")))
    path = tmp_path_factory.mktemp("pq") / "autzen.parquet"
    table = las_to_table(las)
    write_parquet(path, table, row_group_size=30_000)
    return path, table


@pytest.mark.parametrize("opts", [
    dict(ratio=0.01, mode="exact", seed=0),
    dict(ratio=0.05, mode="paper", color_space="chroma", quant_bits=4, seed=42),
    dict(k=2, color_space="rgb", quant_bits=4, seed=9),
], ids=["exact", "paper-chroma-4", "k2"])
def test_parquet_input_matches_oracle(autzen_parquet, opts, tmp_path):
    path, table = autzen_parquet
    want = oracle.sample([oracle.read_parquet_colors(path)], **_oracle_opts(opts))
    out = tmp_path / "out.parquet"
    summary = sample(str(path), str(out), **opts)
    assert_summary_matches(summary, want)
    assert pq.read_schema(out).names == table.column_names
    cols = {n: table.column(n).to_numpy() for n in table.column_names}
    assert_rows_equal(out, [cols], want.kept)


def test_parquet_folder_is_one_source_per_file(autzen_parquet, tmp_path):
    """A directory dataset expands to its files in sorted order; ids follow that order."""
    _, table = autzen_parquet
    folder = tmp_path / "dataset"
    folder.mkdir()
    parts = [table.slice(0, 40_000), table.slice(40_000, 50_000), table.slice(90_000)]
    for i, part in enumerate(parts):
        write_parquet(folder / f"part-{i}.parquet", part, row_group_size=16_384)
    opts = dict(ratio=0.02, mode="exact", color_space="chroma", seed=4)
    want = oracle.sample([oracle.read_parquet_colors(folder / f"part-{i}.parquet") for i in range(3)],
                         **_oracle_opts(opts))
    out = tmp_path / "out.parquet"
    summary = sample(str(folder), str(out), **opts)
    assert_summary_matches(summary, want)
    assert len(summary.sources) == 3
    cols = [{n: p.column(n).to_numpy() for n in p.column_names} for p in parts]
    assert_rows_equal(out, cols, want.kept)


# -- random small clouds: any options, any chunk size ---------------------------------------

@st.composite
def small_clouds(draw):
    """1-3 sources of 1-400 points, each 8-bit or 16-bit, colors from a small palette (big bins)."""
    sources = []
    for _ in range(draw(st.integers(1, 3))):
        n = draw(st.integers(1, 400))
        palette = draw(st.integers(1, 30))
        depth = draw(st.sampled_from([8, 16]))
        sources.append(random_colors(n, seed=draw(st.integers(0, 2**32 - 1)), palette=palette, depth=depth))
    return sources


@st.composite
def any_options(draw, n):
    rule = draw(st.sampled_from(["exact", "paper", "k", "count"]))
    opts = dict(color_space=draw(st.sampled_from(["rgb", "chroma"])), quant_bits=draw(st.sampled_from([2, 4, 7])),
                seed=draw(st.integers(0, (1 << 64) - 1)), chunk_size=draw(st.sampled_from([7, 100, 1 << 20])))
    if rule == "k":
        opts["k"] = draw(st.integers(1, 50))
    elif rule == "count":
        opts["count"] = draw(st.integers(1, n))
    else:
        opts.update(mode=rule, ratio=draw(st.floats(0.001, 1.0)))
    return opts


def random_run(tmp_path_factory, data):
    """A drawn cloud of LAS files and drawn options, sampled: (sources, the oracle's result, the summary, the
    output), the summary already checked against the oracle's."""
    sources = data.draw(small_clouds())
    opts = data.draw(any_options(sum(len(s) for s in sources)))
    folder = tmp_path_factory.mktemp("h")
    paths = [write_las(folder / f"s{i}.las", c, seed=i) for i, c in enumerate(sources)]
    want = oracle.sample([(c[:, 0], c[:, 1], c[:, 2]) for c in sources], **_oracle_opts(opts))
    out = folder / "out.parquet"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one bin / empty target warnings are expected here
        summary = sample([str(p) for p in paths], str(out), **opts)
    assert_summary_matches(summary, want)
    return sources, want, summary, out


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_random_clouds_match_oracle(tmp_path_factory, data):
    sources, want, summary, out = random_run(tmp_path_factory, data)
    t = pq.read_table(out, columns=["intensity", "red", "green", "blue"])
    np.testing.assert_array_equal(t.column("intensity").to_numpy(), np.concatenate(want.kept) % 65536)
    got = np.stack([t.column(c).to_numpy() for c in ("red", "green", "blue")], axis=1)
    np.testing.assert_array_equal(got, np.concatenate([c[k] for c, k in zip(sources, want.kept)]))
